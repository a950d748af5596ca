"""A smooth surface through the triangulated points, its texture mosaic and its depth map (reference
sec. 3.2: "a thin plate spline algorithm was applied to generate a smooth 3D surface by fitting these
feature points"; Fig. 4.6(b, c)).

Why a thin-plate-spline height field over the best-fit plane
------------------------------------------------------------
A scope above a surgical cavity sees the surface from one side: every point of the field is a
function ``h(s, t)`` of its position in the plane the cameras look down on. Writing the surface as a
height field over the points' best-fit plane (PCA) makes it a 2-D scattered-data fit, and the
thin-plate spline is the smoothest interpolant of such data: it minimises the bending energy
``∫∫ h_ss² + 2 h_st² + h_tt²`` (no tuning of a length scale, unlike Gaussian RBFs), reproduces planes
exactly (a flat sheet stays flat whatever the smoothing) and, with ``smoothing > 0``, becomes the
smoothing spline that averages out triangulation noise instead of threading through it. It is what the
reference used; :class:`scope3d.scene.thin_plate.ThinPlateSpline` solves it exactly (the system of
``scipy.interpolate.RBFInterpolator(kernel="thin_plate_spline")``) and evaluates it on the grid by tiles.
Poisson or ball-pivoting reconstruction would handle closed or overhanging shapes, which a
single-sided endoscopic survey never sees, at the price of normals and far more points.

The spline is fitted to cell medians of a coarse bin grid (``control_cell_mm``), not to every point:
this bounds the dense solve (its cost grows as the cube of the number of centres) and makes the fit
robust to the occasional wrong track. The mesh is then the spline sampled on a regular grid of the
plane (``grid_step_mm``), kept only where data are near (``max_extrapolation_mm``): the grid *is* a
raster image of the surface, which the texture, fluorescence and depth-map stages reuse.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from scope3d.geometry.grid import grid_faces
from scope3d.geometry.plane import fit_plane
from scope3d.geometry.pose import Pose
from scope3d.scene.mesh import Mesh
from scope3d.scene.thin_plate import ThinPlateSpline
from scope3d.sensor.camera import Camera
from scope3d.sensor.camera_models import DEFAULT_MODEL, PINHOLE_HALF_ANGLE_LIMIT
from scope3d.utils.robust import MAD_TO_SIGMA, robust_sigma
from scope3d.utils.sample_image import sample_image

#: Passes of :func:`off_surface_points`: gross errors (2 mm) first, then ~3 sigma of a two-view point's depth.
OFF_SURFACE_FLOORS_MM = (2.0, 0.5)


@dataclass(frozen=True)
class SurfaceOptions:
    """Thin-plate-spline surface fitting.

    grid_step_mm : float, spacing of the output mesh grid (default 0.2 mm: finer than the
        fluorescence targets' ~1 mm features, 40k vertices for a 40 mm field).
    control_cell_mm : float, points are reduced to one median per cell of this size before the fit
        (default 0.6 mm, about the point spacing of a 30-frame survey); raised automatically so that
        at most ``max_control_points`` remain.
    max_control_points : int, bound on the spline's centres (default 2500; ~1 s dense solve).
    smoothing : float, the spline's smoothing (scipy's ``smoothing``, in mm² per centre; default 0.5,
        about the variance of single-point depth errors times the few points merged per cell).
    outlier_mad : float, points farther than this many median absolute deviations from their cell's
        median height are ignored (default 4).
    max_extrapolation_mm : float, grid vertices farther than this from every point are left out of
        the mesh (default 1.5 mm).
    robust_passes : int, refits after dropping control points far from the spline (default 2).
    max_grid_vertices : int, memory budget of the grid (default 2,000,000 vertices, a 280 mm square at
        0.2 mm: fitting and texturing a 300 mm field of 400k points peaked at 160 B per grid vertex, so
        ~0.3 GB): a larger field is sampled at the coarser step that fits it (``Surface.step_mm`` says which).
    min_neighbours : int, support_radius_mm : float, points with fewer than ``min_neighbours`` other
        points within ``support_radius_mm`` in the plane are ignored (default 3 within 1 mm).
    local_neighbours : int, control points are checked against the plane of this many neighbours
        (default 8), ``local_passes`` times (default 2); outlier_floor_mm : float, least deviation
        called an outlier (default 0.15 mm).
    """

    grid_step_mm: float = 0.2
    control_cell_mm: float = 0.6
    max_control_points: int = 2500
    smoothing: float = 0.5
    outlier_mad: float = 4.0
    max_extrapolation_mm: float = 1.5
    robust_passes: int = 2
    min_neighbours: int = 3
    local_neighbours: int = 8
    local_passes: int = 2
    outlier_floor_mm: float = 0.15
    support_radius_mm: float = 1.0
    max_grid_vertices: int = 2_000_000

    def __post_init__(self) -> None:
        for name in ("grid_step_mm", "control_cell_mm", "outlier_mad", "max_extrapolation_mm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.smoothing < 0 or self.max_control_points < 10:
            raise ValueError("smoothing must be >= 0 and max_control_points >= 10")
        if self.max_grid_vertices < 4:
            raise ValueError(f"max_grid_vertices must be >= 4, got {self.max_grid_vertices}")


@dataclass
class Surface:
    """A height field over a plane, sampled on a grid.

    origin : (3,) mm world, the plane's origin. axes : (3, 3), rows e_s, e_t, n (orthonormal, world);
    ``n`` points towards the cameras. A grid vertex (r, c) is
    ``origin + s[c] e_s + t[r] e_t + height[r, c] n``.
    s : (W,) mm; t : (H,) mm; height : (H, W) mm, NaN outside the surveyed region.
    """

    origin: np.ndarray
    axes: np.ndarray
    s: np.ndarray
    t: np.ndarray
    height: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool, grid vertices that are part of the surface."""
        return np.isfinite(self.height)

    @property
    def step_mm(self) -> float:
        return float(self.s[1] - self.s[0]) if len(self.s) > 1 else 0.0

    def vertices(self) -> np.ndarray:
        """(H, W, 3) mm world; NaN outside the surface."""
        ss, tt = np.meshgrid(self.s, self.t)
        return self.origin + ss[..., None] * self.axes[0] + tt[..., None] * self.axes[1] + self.height[..., None] * self.axes[2]

    def to_plane(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 3) world mm -> (N, 3) plane coordinates (s, t, h) mm."""
        return (np.asarray(points_world, float) - self.origin) @ self.axes.T

    def normals(self) -> np.ndarray:
        """(H, W, 3) unit normals (world) from central differences of the height field."""
        hs = np.gradient(self.height, self.step_mm, axis=1)
        ht = np.gradient(self.height, self.step_mm, axis=0)
        n = self.axes[2] - hs[..., None] * self.axes[0] - ht[..., None] * self.axes[1]
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def cell_areas_mm2(self) -> np.ndarray:
        """(H, W) surface area (mm²) each grid vertex stands for (plane cell area / cos of the slope)."""
        hs = np.gradient(self.height, self.step_mm, axis=1)
        ht = np.gradient(self.height, self.step_mm, axis=0)
        return self.step_mm**2 * np.sqrt(1.0 + hs * hs + ht * ht)

    def height_at(self, st: np.ndarray) -> np.ndarray:
        """(N, 2) plane coordinates (s, t) mm -> (N,) height (mm) by bilinear interpolation; NaN
        outside the surveyed region."""
        from scipy.ndimage import map_coordinates

        st = np.asarray(st, float)
        col = (st[:, 0] - self.s[0]) / self.step_mm
        row = (st[:, 1] - self.t[0]) / self.step_mm
        return map_coordinates(self.height, [row, col], order=1, mode="constant", cval=np.nan)

    def ray_depths(self, pose: Pose, rays_cam: np.ndarray, *, iterations: int = 6) -> np.ndarray:
        """z-depth (mm, camera frame) at which each ray meets the surface; NaN where it misses.

        rays_cam : (N, 3) camera-frame directions with z = 1 (so the ray parameter is the z-depth).
        Fixed-point iteration on the height field (converges while the surface's slope times the ray's
        obliquity stays below 1, true for a scope looking down into a cavity)."""
        d = np.asarray(rays_cam, float) @ pose.rotation  # world direction per unit z-depth
        c = self.to_plane(pose.centre[None])[0]
        dp = d @ self.axes.T
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (np.nanmedian(self.height) - c[2]) / dp[:, 2]
            for _ in range(iterations):
                h = self.height_at(c[:2] + z[:, None] * dp[:, :2])
                z = (h - c[2]) / dp[:, 2]
        z[~(z > 0)] = np.nan
        return z

    def refined(self, rows: slice, cols: slice, factor: int) -> "Surface":
        """The part ``[rows, cols]`` of the grid resampled ``factor`` times finer (bicubic on the
        height; cells next to missing heights stay missing). For measuring small targets."""
        if factor < 1:
            raise ValueError(f"factor must be >= 1, got {factor}")
        h = self.height[rows, cols]
        s, t = self.s[cols], self.t[rows]
        if factor == 1 or h.size == 0:
            return Surface(self.origin, self.axes, s, t, h.copy())
        valid = np.isfinite(h).astype(np.float32)
        filled = np.where(np.isfinite(h), h, np.nanmean(h) if np.isfinite(h).any() else 0.0).astype(np.float64)
        n_s, n_t = (len(s) - 1) * factor + 1, (len(t) - 1) * factor + 1
        s_new = s[0] + np.arange(n_s) * (self.step_mm / factor)
        t_new = t[0] + np.arange(n_t) * (self.step_mm / factor)
        # align grid nodes exactly (resize maps pixel centres; use remap on node coordinates instead)
        mc, mr = np.meshgrid(np.arange(n_s) / factor, np.arange(n_t) / factor)
        h_new = cv2.remap(filled.astype(np.float32), mc.astype(np.float32), mr.astype(np.float32), cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REPLICATE).astype(float)
        v_new = cv2.remap(valid, mc.astype(np.float32), mr.astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        h_new[v_new < 0.999] = np.nan
        return Surface(self.origin, self.axes, s_new, t_new, h_new)

    def mesh(self, colors: np.ndarray | None = None) -> Mesh:
        """Triangle mesh of the valid grid (two triangles per cell whose 4 corners are valid).

        colors : optional (H, W, 3) uint8 per-vertex colours. Faces wind counter-clockwise seen from
        ``n`` (the camera side).
        """
        valid = self.valid
        index = np.full(valid.shape, -1, dtype=np.int64)
        index[valid] = np.arange(int(valid.sum()))
        cell = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
        # columns run along s and rows along t, and (s, t, n) is right-handed: the grid's
        # counter-clockwise (column, row) winding is counter-clockwise about n
        faces = index.reshape(-1)[grid_faces(*valid.shape, keep=cell)]
        verts = self.vertices()[valid]
        normals = self._edge_normals()[valid]
        vc = None if colors is None else np.asarray(colors, np.uint8)[valid]
        return Mesh(verts, faces, vc, normals)

    def _edge_normals(self) -> np.ndarray:
        """:meth:`normals` where they are defined, and at the surveyed region's edge (where a central
        difference reaches outside it and gives NaN) from the one-sided difference into the region, or the
        plane's normal where a vertex has no valid neighbour along an axis: a mesh file must hold no NaN."""
        gradients = []
        for axis in (1, 0):
            h = np.moveaxis(self.height, axis, 0)
            forward = np.full_like(h, np.nan)
            forward[:-1] = h[1:] - h[:-1]
            backward = np.full_like(h, np.nan)
            backward[1:] = h[1:] - h[:-1]
            central = np.where(np.isnan(forward), backward, np.where(np.isnan(backward), forward,
                                                                      0.5 * (forward + backward)))
            gradients.append(np.moveaxis(np.nan_to_num(central) / self.step_mm, 0, axis))
        hs, ht = gradients
        n = self.axes[2] - hs[..., None] * self.axes[0] - ht[..., None] * self.axes[1]
        return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _control_points(stn: np.ndarray, cell: float, mad_k: float) -> np.ndarray:
    """Cell medians of (s, t, h) after rejecting points far from their cell's median height."""
    key = np.floor(stn[:, :2] / cell).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    inv_s, stn_s = inv[order], stn[order]
    starts = np.flatnonzero(np.r_[True, inv_s[1:] != inv_s[:-1]])
    counts = np.diff(np.r_[starts, len(inv_s)])
    # median height per cell via sorting heights within groups
    o2 = np.lexsort((stn_s[:, 2], inv_s))
    h_sorted = stn_s[o2, 2]
    med_h = 0.5 * (h_sorted[starts + (counts - 1) // 2] + h_sorted[starts + counts // 2])
    dev = np.abs(stn_s[:, 2] - med_h[inv_s])
    # global MAD: robust spread of the whole cloud about the local medians (dev are absolute deviations)
    sigma = max(robust_sigma(dev, about=0.0), MAD_TO_SIGMA * 1e-3)
    keep = dev <= mad_k * sigma
    n_keep = np.bincount(inv_s[keep], minlength=len(starts))
    ok = n_keep > 0
    sums = np.stack([np.bincount(inv_s[keep], stn_s[keep, c], len(starts)) for c in range(2)], 1)
    st = sums[ok] / n_keep[ok, None]
    return np.column_stack([st, med_h[ok]])


def _local_plane_residuals(stn: np.ndarray, k: int, usable: np.ndarray | None = None) -> np.ndarray:
    """Height (M,) of each point (M, 3) (s, t, h) above the least-squares plane of its ``k`` nearest
    neighbours in (s, t) among the ``usable`` points (boolean (M,), default all), the point itself excluded."""
    src = np.arange(len(stn)) if usable is None else np.flatnonzero(usable)
    _, idx = cKDTree(stn[src, :2]).query(stn[:, :2], k=k + 1)
    idx = src[idx]
    # the point itself is its own nearest usable neighbour when usable: move it last, keep the first k
    order = np.argsort(idx == np.arange(len(stn))[:, None], axis=1, kind="stable")
    nb = stn[np.take_along_axis(idx, order, axis=1)[:, :k]]  # (M, k, 3)
    A = np.concatenate([nb[:, :, :2] - stn[:, None, :2], np.ones(nb.shape[:2] + (1,))], axis=2)
    AtA = np.einsum("mki,mkj->mij", A, A) + 1e-9 * np.eye(3)
    coef = np.linalg.solve(AtA, np.einsum("mki,mk->mi", A, nb[:, :, 2])[..., None])[..., 0]
    return stn[:, 2] - coef[:, 2]  # plane value at the point itself (offset term)


def _reject_local_outliers(ctrl: np.ndarray, k: int, mad_k: float, floor_mm: float) -> np.ndarray:
    """Drop control points (M, 3) (s, t, h) far from the least-squares plane of their ``k`` nearest
    neighbours: the spline would otherwise bend towards a wrong track (smoothing only damps it).
    Threshold: ``mad_k`` robust sigmas of those residuals, at least ``floor_mm`` (above the sag of a
    curved field over a neighbourhood, d^2 / 2R = 0.06 mm for 1.5 mm on the 17.5 mm dome)."""
    if k < 3 or len(ctrl) <= k + 3:
        return ctrl
    resid = _local_plane_residuals(ctrl, k)
    sigma = robust_sigma(resid)
    keep = np.abs(resid) <= max(mad_k * sigma, floor_mm)
    return ctrl[keep] if keep.sum() >= 10 else ctrl


def off_surface_points(points: np.ndarray, *, towards: np.ndarray | None = None, neighbours: int = 10,
                       mad_k: float = 6.0, floors_mm: tuple[float, ...] = OFF_SURFACE_FLOORS_MM) -> np.ndarray:
    """Boolean mask (N,) of points (N, 3) mm that stand off the local surface of their neighbours.

    Each point is compared with the least-squares plane of its ``neighbours`` nearest points in the
    best-fit plane of the cloud (a height field seen from one side, as :func:`fit_surface` assumes).
    A wrong two-view match that satisfies the epipolar constraint triangulates at the wrong depth
    along its ray — millimetres above or below a dense, consistent neighbourhood — which is what this
    catches. One pass per floor, on the points the previous passes kept: gross errors go first. Within a
    pass, the points flagged are set aside and every point is checked again against planes through the
    others only: a wrong point tilts its neighbours' planes and would otherwise take correct neighbours
    with it (on the dome, two correct points lost per wrong one). Threshold: ``mad_k`` robust sigmas of
    the residuals, at least the pass's floor (the last, default 0.5 mm, about 3 sigma of a two-view
    point's depth at the dome's 400 px).
    """
    pts = np.asarray(points, float)
    off = ~np.all(np.isfinite(pts), axis=1)
    if (~off).sum() <= 2 * neighbours + 3:
        return off
    origin, axes = fit_plane(pts[~off], towards)
    stn = (pts - origin) @ axes.T
    stn[off] = 0.0  # never used: not usable as neighbours, never unflagged
    for floor_mm in floors_mm:
        usable = ~off
        if usable.sum() <= 2 * neighbours + 3:
            break
        resid = _local_plane_residuals(stn, neighbours, usable)
        threshold = max(mad_k * robust_sigma(resid[usable]), floor_mm)
        suspect = usable & (np.abs(resid) > threshold)
        if suspect.any() and (usable & ~suspect).sum() > neighbours + 3:
            resid = _local_plane_residuals(stn, neighbours, usable & ~suspect)
        off |= usable & (np.abs(resid) > threshold)
    return off


def fit_surface(points: np.ndarray, *, options: SurfaceOptions = SurfaceOptions(),
                towards: np.ndarray | None = None) -> Surface:
    """Fit the thin-plate-spline height field.

    points : (N, 3) mm world, N >= 10 (the triangulated features). towards : (3,) direction the
    surface's normal should face (towards the cameras). Raises ``ValueError`` for too few points.
    """
    pts = np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < 10:
        raise ValueError(f"need at least 10 points to fit a surface, got {len(pts)}")
    # a few far wrong points (a ring's background, a bad track) would tilt the plane and stretch the grid
    # over metres of nothing: the plane and the grid are fitted to the extent the bulk of the points fill
    inside = _within_robust_extent(pts)
    if inside.sum() >= 10:
        pts = pts[inside]
    origin, axes = fit_plane(pts, towards)
    stn = (pts - origin) @ axes.T
    inside = _within_robust_extent(stn[:, :2])
    if inside.sum() >= 10:
        stn = stn[inside]
    # an isolated point cannot be checked against neighbours (the spline would bend to it): keep points
    # with at least ``min_neighbours`` others within ``support_radius_mm`` in the plane
    if options.min_neighbours > 0:
        count = cKDTree(stn[:, :2]).query_ball_point(stn[:, :2], options.support_radius_mm, return_length=True) - 1
        supported = count >= options.min_neighbours
        if supported.sum() >= 10:
            stn = stn[supported]
    cell = options.control_cell_mm
    extent = np.ptp(stn[:, 0]) * np.ptp(stn[:, 1])
    cell = max(cell, np.sqrt(extent / options.max_control_points))
    ctrl = _control_points(stn, cell, options.outlier_mad)
    while len(ctrl) > options.max_control_points:
        cell *= 1.25
        ctrl = _control_points(stn, cell, options.outlier_mad)
    # twice: a cluster of two or three wrong points shields itself in its neighbours' plane until the
    # worst of it is gone (a wrong cell left a 1.4 mm sag in a hole of the flat sheet otherwise)
    for _ in range(options.local_passes):
        ctrl = _reject_local_outliers(ctrl, options.local_neighbours, options.outlier_mad, options.outlier_floor_mm)
    tps = ThinPlateSpline.fit(ctrl[:, :2], ctrl[:, 2], options.smoothing)
    # A cell holding a single wrong track is its own median; catch those against the spline fitted
    # through their neighbours: drop control points far from the fit (robust MAD, floor 0.3 mm) and refit.
    for _ in range(options.robust_passes):
        resid = ctrl[:, 2] - tps(ctrl[:, :2])
        keep = np.abs(resid) <= max(options.outlier_mad * robust_sigma(resid), 2.0 * options.outlier_floor_mm)
        if keep.all() or keep.sum() < 10:
            break
        ctrl = ctrl[keep]
        tps = ThinPlateSpline.fit(ctrl[:, :2], ctrl[:, 2], options.smoothing)
    lo = stn[:, :2].min(axis=0)
    hi = stn[:, :2].max(axis=0)
    step = _grid_step(hi - lo, options.grid_step_mm, options.max_grid_vertices)
    s = np.arange(lo[0], hi[0] + step, step)
    t = np.arange(lo[1], hi[1] + step, step)
    ss, tt = np.meshgrid(s, t)
    grid = np.column_stack([ss.ravel(), tt.ravel()])
    # a grid coarsened for memory reaches at least one step from the points (else few vertices, if any,
    # would lie within the extrapolation distance of a point)
    reach = max(options.max_extrapolation_mm, step)
    near = cKDTree(stn[:, :2]).query(grid, distance_upper_bound=reach)[0] < np.inf
    # fill holes smaller than the extrapolation distance (closing), so the mesh has no pin-holes
    near = near.reshape(ss.shape)
    k = max(1, int(round(reach / step)))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))
    near = cv2.morphologyEx(near.astype(np.uint8), cv2.MORPH_CLOSE, kernel).astype(bool)
    # and fill every hole enclosed by the surveyed region: a fluorescent film or a specular patch has
    # no features, but the spline interpolates across it (what is not reachable from the border
    # through unsurveyed cells is inside)
    outside = np.pad(~near, 1, constant_values=True).astype(np.uint8)
    cv2.floodFill(outside, None, (0, 0), 2)
    near |= outside[1:-1, 1:-1] != 2
    height = np.full(ss.shape, np.nan)
    # near centres exactly, the far ones' smooth sum on a 0.8 mm lattice (ThinPlateSpline.tiled: ~0.2 um)
    height[near] = tps.tiled(grid[near.ravel()])
    return Surface(origin, axes, s, t, height)


#: :func:`_within_robust_extent`: the percentiles that bound the bulk of the points, and how far beyond
#: them (a fraction of their span) the grid still reaches.
_EXTENT_QUANTILES = (0.01, 0.99)
_EXTENT_MARGIN = 0.25


def _within_robust_extent(x: np.ndarray) -> np.ndarray:
    """(N,) bool: the points (N, D) inside the box the data supports, per coordinate its 1st to 99th
    percentile widened on each side by a quarter of that span. A surveyed field's points fill it whole
    (a uniform field's edge lies 1 % of the span beyond its percentile, a uniform disc's 3.5 %, a Gaussian
    cloud's 3.5 sigma past its centre), so only points far outside the bulk are left out, and however far
    they lie they cannot set the box: the percentiles ignore the farthest 1 % on each side."""
    lo, hi = np.quantile(x, _EXTENT_QUANTILES, axis=0)
    pad = _EXTENT_MARGIN * (hi - lo)
    return np.all((x >= lo - pad) & (x <= hi + pad), axis=1)


def _grid_step(span: np.ndarray, step: float, max_vertices: int) -> float:
    """The grid step (mm): ``step``, or the least coarser one whose grid over ``span`` (2,) mm has at most
    ``max_vertices`` vertices (np.arange over [lo, hi + step) holds at most span / step + 2 values)."""
    def count(h):
        return (np.floor(span[0] / h) + 2) * (np.floor(span[1] / h) + 2)

    if count(step) <= max_vertices:
        return step
    step = max(step, float(np.sqrt(span[0] * span[1] / max_vertices)))
    while count(step) > max_vertices:
        step *= 1.01
    return step


def best_views(
    camera: Camera, poses: list[Pose], points: np.ndarray, normals: np.ndarray, *, edge_weight: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """For each surface point choose the frame that sees it best.

    points, normals : (V, 3) world mm and unit normals. Score = cos(angle between normal and the ray
    to the camera) - ``edge_weight`` * (radial image position / image radius)² — facing views near the
    image centre are sharpest and least distorted. Occlusion is not modelled: a single-sided surgical
    field seen from above does not hide itself.
    Returns view (V,) int64 (-1 when no frame sees the point) and pixels (V, 2) in that view.

    Each frame scores only the points of the cells (:func:`_point_cells`) that can meet its viewing cone
    (:func:`_viewing_cone_tangent`): the others project outside its image whatever their exact position,
    so the result is the same as scoring every point in every frame, at a cost that grows with the points
    times the frames that see them, not with points times frames.
    """
    V = len(points)
    best = np.full(V, -np.inf)
    view = np.full(V, -1, dtype=np.int64)
    pix = np.full((V, 2), np.nan)
    centre_px = np.array([(camera.width - 1) / 2.0, (camera.height - 1) / 2.0])
    r_img = camera.mask_radius_px or 0.5 * np.hypot(camera.width, camera.height)
    order, starts, cell_centres, cell_radii = _point_cells(points)
    half_angle = _viewing_cone_half_angle(camera)
    for k, pose in enumerate(poses):  # per-frame loop
        sel = order[_cone_cells(pose, cell_centres, cell_radii, half_angle, starts)]
        if len(sel) == 0:
            continue
        p = points[sel]
        uv = camera.project_world(pose, p)
        ok = camera.in_image(uv, margin_px=2.0)
        to_cam = pose.centre - p
        cosang = np.einsum("vi,vi->v", normals[sel], to_cam) / np.linalg.norm(to_cam, axis=1)
        rad = np.linalg.norm(uv - centre_px, axis=1) / r_img
        score = np.where(ok & (cosang > 0.1), cosang - edge_weight * rad * rad, -np.inf)
        better = score > best[sel]
        upd = sel[better]
        best[upd] = score[better]
        view[upd] = k
        pix[upd] = uv[better]
    return view, pix


#: Points per cell of :func:`_point_cells` (about): fewer cells make the per-frame cone test cheaper,
#: smaller ones hug a frame's footprint more tightly; any size gives the same views.
_CELL_POINTS = 1024


def _point_cells(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points (V, 3) grouped into cubic cells of ~``_CELL_POINTS`` points each (side from the area the
    cloud's two longest extents span: a surface's points). Returns the point order (V,) int64 sorting
    them by cell, each cell's first position in that order (C + 1,) (the last = V), and each cell's
    bounding sphere: centres (C, 3) mm and radii (C,) mm."""
    V = len(points)
    if V == 0:
        return np.zeros(0, np.int64), np.zeros(1, np.int64), np.zeros((0, 3)), np.zeros(0)
    lo = points.min(axis=0)
    extent = np.sort(np.ptp(points, axis=0))[::-1]
    side = max(float(np.sqrt(extent[0] * extent[1] * _CELL_POINTS / V)), 1e-6)
    cell = np.floor((points - lo) / side).astype(np.int64)
    _, key = np.unique(cell, axis=0, return_inverse=True)
    order = np.argsort(key.ravel(), kind="stable")
    counts = np.bincount(key.ravel())
    starts = np.r_[0, np.cumsum(counts)]
    centres = np.stack([np.bincount(key.ravel(), points[:, c]) for c in range(3)], axis=1) / counts[:, None]
    dist = np.linalg.norm(points - centres[key.ravel()], axis=1)
    radii = np.zeros(len(counts))
    np.maximum.at(radii, key.ravel(), dist)
    return order, starts, centres, radii


def _viewing_cone_half_angle(camera: Camera) -> float:
    """Half-angle (rad) about the optical axis of a cone holding every point that :meth:`Camera.project` can
    put inside the image. scope3d's radial model: :func:`_viewing_cone_tangent`. Another model whose radial
    map increases over its whole field (a fisheye up to its fold, beyond which it projects nothing; a
    pinhole family without a fold): the ray of the image's farthest corner. A pinhole family that folds
    back: every point in front of the camera."""
    if camera.model == DEFAULT_MODEL:
        return float(np.arctan(_viewing_cone_tangent(camera)))
    # no fold: the field reaches the pinhole's limit (to the bisection's 1e-12 rad)
    if camera.lens.is_fisheye or camera.max_half_angle_rad >= PINHOLE_HALF_ANGLE_LIMIT - 1e-9:
        corners = np.array([[-0.5, -0.5], [camera.width - 0.5, camera.height - 0.5],
                            [-0.5, camera.height - 0.5], [camera.width - 0.5, -0.5]])
        rays = camera.unproject(corners)
        return float(np.max(np.arccos(np.clip(rays[:, 2], -1.0, 1.0)))) * (1.0 + 1e-9)  # the ray's own rounding
    return np.pi / 2


def _viewing_cone_tangent(camera: Camera) -> float:
    """Tangent of the half-angle, about the optical axis, of a cone holding every point in front of the
    camera that :meth:`Camera.project` can put inside the image.

    A point at undistorted normalised radius r lands at distorted radius |r (1 + k1 r² + k2 r⁴)|; the
    image's farthest corner bounds the distorted radius of anything inside it, and beyond the largest r at
    which the odd polynomial reaches that bound it stays above it (its leading term dominates). A barrel
    lens folds points from far outside its field back into the image: the cone then is that much wider."""
    corners = np.array([[-0.5, -0.5], [camera.width - 0.5, camera.height - 0.5],
                        [-0.5, camera.height - 0.5], [camera.width - 0.5, -0.5]])
    limit = float(np.max(np.hypot((corners[:, 0] - camera.cx) / camera.fx, (corners[:, 1] - camera.cy) / camera.fy)))
    radius = limit
    for sign in (1.0, -1.0):  # r (1 + k1 r² + k2 r⁴) = ±limit
        roots = np.roots([camera.k2, 0.0, camera.k1, 0.0, 1.0, -sign * limit])
        real = roots[np.abs(roots.imag) <= 1e-9 * np.maximum(1.0, np.abs(roots))].real
        if len(real):
            radius = max(radius, float(real.max()))
    return radius * (1.0 + 1e-9)  # the root's own rounding


def _cone_cells(pose: Pose, centres: np.ndarray, radii: np.ndarray, half_angle: float, starts: np.ndarray) -> np.ndarray:
    """Positions (into the cell-sorted order) of the points of every cell whose bounding sphere can meet
    the camera's viewing cone of ``half_angle`` (rad) about its optical axis (conservative: a sphere
    holding the camera centre always can)."""
    to_cell = centres - pose.centre
    dist = np.linalg.norm(to_cell, axis=1)
    cos_axis = (to_cell @ pose.optical_axis) / np.maximum(dist, 1e-300)
    angle = np.arccos(np.clip(cos_axis, -1.0, 1.0))
    with np.errstate(invalid="ignore"):
        spread = np.arcsin(np.minimum(radii / np.maximum(dist, 1e-300), 1.0))
    hit = (dist <= radii) | (angle - spread <= half_angle + 1e-9)
    cells = np.flatnonzero(hit)
    if len(cells) == 0:
        return np.zeros(0, np.int64)
    counts = starts[cells + 1] - starts[cells]
    return np.repeat(starts[cells] - np.cumsum(np.r_[0, counts[:-1]]), counts) + np.arange(int(counts.sum()))


def sample_images(images, view: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Bilinear samples: images : sequence or callable ``images(k)`` -> (H, W[, C]) array; view (V,),
    pixels (V, 2). Returns (V, C) float (0 where view is -1)."""
    get = images if callable(images) else (lambda k: images[k])
    out = None
    for k in np.unique(view[view >= 0]):
        sel = view == k
        img = np.asarray(get(int(k)))
        if img.ndim == 2:
            img = img[..., None]
        if out is None:
            out = np.zeros((len(view), img.shape[2]), dtype=float)
        src = img.astype(np.float32)
        xy = pixels[sel].astype(np.float32)
        out[sel] = sample_image(src, xy, border=cv2.BORDER_REPLICATE).reshape(len(xy), -1)
    return out if out is not None else np.zeros((len(view), 1))


def texture(surface: Surface, camera: Camera, poses: list[Pose], images) -> tuple[np.ndarray, np.ndarray]:
    """Texture mosaic: every grid vertex coloured from its best view (:func:`best_views`).

    images : sequence or callable ``images(k)`` -> (H, W, 3) uint8 RGB. Returns colours (H, W, 3)
    uint8 (black outside the surface or where no frame sees it) and the view index map (H, W) int.
    """
    valid = surface.valid
    verts = surface.vertices()[valid]
    normals = surface.normals()[valid]
    view, pix = best_views(camera, poses, verts, normals)
    rgb = sample_images(images, view, pix)
    if rgb.shape[1] == 1:
        rgb = np.repeat(rgb, 3, axis=1)
    colors = np.zeros(valid.shape + (3,), np.uint8)
    colors[valid] = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    view_map = np.full(valid.shape, -1, dtype=np.int64)
    view_map[valid] = view
    return colors, view_map


def depth_map(surface: Surface) -> np.ndarray:
    """(H, W) depth (mm) of the surface below its top along the normal (the cameras' side): the
    reference's pseudo-colour depth map (Fig. 4.6(c)). The top is the 99.5th percentile of the
    heights, so that a spline overshoot at the unsurveyed edge does not set the scale; depths are
    clipped at 0. NaN outside the surface."""
    top = np.nanpercentile(surface.height, 99.5)
    return np.maximum(top - surface.height, 0.0)


def save_depth_map_png(path, surface: Surface, *, title: str = "depth map") -> None:
    """Depth map with a colour scale (mm) as a PNG (written atomically)."""
    from scope3d.utils.figures import new_figure, save_figure

    d = depth_map(surface)
    extent = (surface.s[0], surface.s[-1], surface.t[-1], surface.t[0])
    fig = new_figure((5.5, 4.5), dpi=110)
    ax = fig.add_subplot()
    im = ax.imshow(d, cmap="turbo", extent=extent)
    fig.colorbar(im, ax=ax, label="depth below the highest point (mm)")
    ax.set_xlabel("s (mm)")
    ax.set_ylabel("t (mm)")
    ax.set_title(title)
    fig.tight_layout()
    save_figure(fig, path)


def enlarge_raster(img: np.ndarray, factor: int = 3) -> np.ndarray:
    """Surface rasters (one pixel per 0.2 mm grid vertex) enlarged for viewing: colours bilinear,
    masks and labels nearest."""
    a = np.asarray(img)
    size = (a.shape[1] * factor, a.shape[0] * factor)
    if a.dtype == bool:
        return cv2.resize(a.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
    if a.dtype != np.uint8:
        return cv2.resize(a.astype(np.int32), size, interpolation=cv2.INTER_NEAREST)
    return cv2.resize(a, size, interpolation=cv2.INTER_LINEAR)
