"""The 2-D map of a whole cavity (reference ch. 2: the urologist's map of what the scope covered; issue 37).

A closed organ cannot be flattened onto one plane (docs/panorama.md: the planar mosaic of the bladder
leaves an 11 px residual), so the map is drawn on the cavity's own surface and unwrapped by that surface's
parameterisation:

1. **Surface** (:func:`fit_cavity_surface`): the ellipsoid the map's points describe, by algebraic least
   squares (:func:`scope3d.geometry.ellipsoid.fit_ellipsoid`), with a smooth radial correction (a polynomial
   of the unit direction in the ellipsoid's normalised frame, degree ``radial_degree``: the span of the
   spherical harmonics up to that degree) so that the surface follows the wall and a frame's pixel lands
   where the wall is, not where an ellipsoid would be. When the points do not determine the ellipsoid (a
   semi-axis' standard error above ``max_axis_error_fraction`` of it, e.g. a cap of the wall, or no
   ellipsoid fits), a sphere about the cameras' centroid is used instead (radius: the points' median
   distance to it) with the same radial correction; which one and why is the surface's ``reason``.
2. **Unwrapping**: equirectangular in the normalised frame, ``(X - c) @ axes / semi_axes = r(u) u`` with
   ``u = (cos lat cos lon, cos lat sin lon, sin lat)``: longitude about the shortest axis (the pole), 0 along
   the longest. The north pole is the side of the first frame's view (the scope's entry in the planned scans).
3. **Rendering**: each texel's wall point is projected into every registered frame that sees it (in front,
   facing it, inside the circular field; the frames' pixels projected onto the surface through the camera
   model, read backwards so that no texel is left between two pixels), and the views are blended with
   weights ``(cos(view angle) x focal / distance x feather) ^ blend_power``, the tip light's ``cos i / d^2``
   divided out as in :mod:`scope3d.mvs.texturing`. Occlusion is not tested: a wall about star-shaped around
   its centre, seen from inside, hides little of itself from a scope near its middle.
4. **Coverage**: a texel is covered when some frame sees it (the rule of
   :func:`scope3d.sfm.scan_planning.coverage`: in front, inside the image and its circular field);
   ``coverage_fraction`` is area-weighted on the surface. Uncovered regions are the connected uncovered
   texels (joined across the map's left/right seam and at the poles), with their area and centre.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import cv2
import numpy as np
from scipy import ndimage

from scope3d.geometry.ellipsoid import fit_ellipsoid
from scope3d.geometry.pose import Pose
from scope3d.mvs.texturing import field_margin, sample_image
from scope3d.sensor.camera import Camera
from scope3d.utils.robust import robust_sigma


@dataclass(frozen=True)
class OrganMapOptions:
    """texel_mm : texel size on the surface at the equator (map units: mm when scaled); None: the frames'
        median pixel footprint on the wall (distance / focal along their optical axes).
    max_width_px : the atlas's width at most (its height is half of it; memory grows with the texels).
    radial_degree : degree of the radial correction of the fitted ellipsoid (0: the bare ellipsoid).
    max_axis_error_fraction : the ellipsoid is used when each semi-axis' standard error is below this
        fraction of it, else the cameras' centroid sphere.
    feather_px, blend_power, min_cos, compensate_light, white_level : the blend (see
        :class:`scope3d.mvs.texturing.TextureOptions`).
    min_region_fraction : uncovered regions below this fraction of the wall's area are counted, not listed."""

    texel_mm: float | None = None
    max_width_px: int = 3072
    radial_degree: int = 4
    max_axis_error_fraction: float = 0.05
    feather_px: float = 12.0
    blend_power: float = 4.0
    min_cos: float = 0.25
    compensate_light: bool = True
    white_level: float = 235.0
    min_region_fraction: float = 0.001

    def __post_init__(self) -> None:
        if self.max_width_px < 16 or self.radial_degree < 0 or not 0 < self.max_axis_error_fraction:
            raise ValueError("max_width_px >= 16, radial_degree >= 0 and max_axis_error_fraction > 0 required")
        if self.texel_mm is not None and not self.texel_mm > 0:
            raise ValueError("texel_mm must be > 0")


def _monomials(degree: int) -> list[tuple[int, int, int]]:
    return [(i, j, n - i - j) for n in range(degree + 1) for i in range(n + 1) for j in range(n + 1 - i)]


def _radial_basis(unit: np.ndarray, degree: int) -> np.ndarray:
    """(N, K) monomials x^i y^j z^k (i + j + k <= degree) of unit directions (N, 3)."""
    cols = []
    px = [np.ones(len(unit)), unit[:, 0]]
    py = [np.ones(len(unit)), unit[:, 1]]
    pz = [np.ones(len(unit)), unit[:, 2]]
    for _ in range(2, degree + 1):
        px.append(px[-1] * unit[:, 0])
        py.append(py[-1] * unit[:, 1])
        pz.append(pz[-1] * unit[:, 2])
    for i, j, k in _monomials(degree):
        cols.append(px[i] * py[j] * pz[k])
    return np.stack(cols, axis=1)


@dataclass(frozen=True)
class CavitySurface:
    """The cavity's surface and its map parameterisation: ``X = centre + axes @ (semi_axes * r(u) * u)``.

    centre : (3,); axes : (3, 3) rotation, columns the map's x (longitude 0), y and pole; semi_axes : (3,);
    radial : the radial correction's coefficients over :func:`_radial_basis` (r(u) = 1 + basis @ radial);
    kind : "ellipsoid" or "sphere about the cameras' centroid"; reason : why that one."""

    centre: np.ndarray
    axes: np.ndarray
    semi_axes: np.ndarray
    radial: np.ndarray
    radial_degree: int
    kind: str
    reason: str
    radial_rms: float = 0.0

    def normalised(self, points: np.ndarray) -> np.ndarray:
        return ((np.asarray(points, float) - self.centre) @ self.axes) / self.semi_axes

    def radius(self, unit: np.ndarray) -> np.ndarray:
        """r(u) for unit directions (N, 3) of the normalised frame."""
        if self.radial_degree == 0 and not len(self.radial):
            return np.ones(len(unit))
        return 1.0 + _radial_basis(unit, self.radial_degree) @ self.radial

    def angles(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(longitude, latitude) rad of points (N, 3): their direction in the normalised frame."""
        p = self.normalised(points)
        return np.arctan2(p[:, 1], p[:, 0]), np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))

    def points(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        """Surface points (N, 3) at (longitude, latitude) rad."""
        cl = np.cos(lat)
        unit = np.stack([cl * np.cos(lon), cl * np.sin(lon), np.sin(lat)], axis=1)
        return self.centre + (unit * self.radius(unit)[:, None] * self.semi_axes) @ self.axes.T

    def intersect(self, origins: np.ndarray, directions: np.ndarray, *, iterations: int = 12) -> np.ndarray:
        """Where rays from inside the surface meet it: (N, 3), NaN where a ray starts outside. In the normalised
        frame the ray is ``o + t d``; t solves ``|o + t d| = r`` with r the radial correction at the current
        hit's direction, repeated (the correction changes slowly with direction: a few rounds converge)."""
        o = self.normalised(origins)
        d = (np.asarray(directions, float) @ self.axes) / self.semi_axes
        a = np.einsum("ij,ij->i", d, d)
        b = np.einsum("ij,ij->i", o, d)
        oo = np.einsum("ij,ij->i", o, o)
        r = np.ones(len(o))
        t = np.full(len(o), np.nan)
        for _ in range(iterations if len(self.radial) else 1):
            with np.errstate(invalid="ignore"):
                t = (-b + np.sqrt(b * b - a * (oo - r * r))) / a
            p = o + t[:, None] * d
            if not len(self.radial):
                break
            r = self.radius(p / np.linalg.norm(p, axis=1, keepdims=True))
        t = np.where(t > 0, t, np.nan)
        return np.asarray(origins, float) + t[:, None] * np.asarray(directions, float)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "reason": self.reason, "centre": self.centre.tolist(),
                "semi_axes": self.semi_axes.tolist(), "axes_columns": self.axes.tolist(),
                "radial_degree": self.radial_degree, "radial_rms_fraction": self.radial_rms}


def fit_cavity_surface(points: np.ndarray, camera_centres: np.ndarray, first_view: np.ndarray | None = None, *,
                       options: OrganMapOptions = OrganMapOptions()) -> CavitySurface:
    """The surface of a cavity whose wall holds ``points`` (N, 3), seen from ``camera_centres`` (M, 3) inside it
    (see the module's docstring). first_view : a point the first frame looks at, put on the northern side."""
    X = np.asarray(points, float)
    inside = np.mean(camera_centres, axis=0)
    fit = fit_ellipsoid(X, inside=inside)
    if fit is None:
        use, reason = False, "no ellipsoid fits the points (their quadric is not definite)"
    else:
        rel = fit.semi_axes_sigma / fit.semi_axes
        use = bool(np.all(rel <= options.max_axis_error_fraction))
        if use:
            reason = (f"the points determine the ellipsoid: semi-axes' standard errors {np.max(rel):.2%} of "
                      f"them at most (limit {options.max_axis_error_fraction:.0%})")
        else:
            reason = (f"the ellipsoid is ill-conditioned: a semi-axis' standard error is {np.max(rel):.0%} of it "
                      f"(limit {options.max_axis_error_fraction:.0%}), the points do not surround the cavity")
    if use:
        centre, axes, semi = fit.centre, fit.axes.copy(), fit.semi_axes.copy()
        kind = "ellipsoid"
    else:
        centre = inside
        radius = float(np.median(np.linalg.norm(X - centre, axis=1)))
        axes, semi = np.eye(3), np.full(3, radius)
        kind = "sphere about the cameras' centroid"
    # orientation: the pole (third column, the shortest axis) towards the first view's wall, x towards the
    # cameras' side (signs are the only freedom left; a right-handed frame)
    if first_view is not None and (np.asarray(first_view) - centre) @ axes[:, 2] < 0:
        axes[:, 2] = -axes[:, 2]
        axes[:, 1] = -axes[:, 1]
    surface = CavitySurface(centre, axes, semi, np.zeros(0), 0, kind, reason)
    if options.radial_degree == 0 or len(X) < 3 * len(_monomials(options.radial_degree)):
        return surface
    p = surface.normalised(X)
    r = np.linalg.norm(p, axis=1)
    unit = p / r[:, None]
    basis = _radial_basis(unit, options.radial_degree)
    keep = np.ones(len(X), bool)
    ridge = 1e-6 * len(X)  # the monomials are redundant on the sphere (x² + y² + z² = 1): the smallest norm
    coef = np.zeros(basis.shape[1])
    for _ in range(3):
        bk = basis[keep]
        coef = np.linalg.solve(bk.T @ bk + ridge * np.eye(basis.shape[1]), bk.T @ (r[keep] - 1.0))
        res = r - 1.0 - basis @ coef
        keep = np.abs(res) <= 3.0 * max(robust_sigma(res[keep], about=0.0), 1e-9)
    rms = float(np.sqrt(np.mean((r[keep] - 1.0 - basis[keep] @ coef) ** 2)))
    return CavitySurface(centre, axes, semi, coef, options.radial_degree, kind, reason, rms)


@dataclass
class OrganMap:
    """image : (H, W, 3) uint8 RGB atlas (uncovered texels grey); covered : (H, W) bool; area : (H, W) float32
    each texel's area on the surface (map units²); path_px : (m, 2) where each frame's optical axis meets the
    wall on the atlas (NaN: frame not registered); regions : the uncovered regions (dicts, largest first);
    coverage_fraction; texel_mm; surface; n_views : (H, W) how many frames see each texel; group_coverage : each
    video's own covered fraction; group : each frame's video; video_gains : each video's brightness over the
    first's (see :func:`_blend_videos`)."""

    image: np.ndarray
    covered: np.ndarray
    area: np.ndarray
    path_px: np.ndarray
    regions: list[dict]
    n_small_regions: int
    small_regions_fraction: float
    coverage_fraction: float
    texel_mm: float
    surface: CavitySurface
    n_views: np.ndarray = field(repr=False)
    group_coverage: list[float] = field(default_factory=list)
    group: np.ndarray = field(default_factory=lambda: np.zeros(0, int), repr=False)
    video_gains: list[float] = field(default_factory=list)

    @property
    def width(self) -> int:
        return self.image.shape[1]

    @property
    def height(self) -> int:
        return self.image.shape[0]

    def summary(self) -> dict:
        return {"surface": self.surface.to_dict(), "atlas_px": [self.width, self.height],
                "texel_mm": self.texel_mm, "coverage_fraction": self.coverage_fraction,
                "wall_area_mm2": float(self.area.sum()),
                "uncovered_regions": self.regions, "n_small_uncovered_regions": self.n_small_regions,
                "small_uncovered_fraction": self.small_regions_fraction,
                "n_frames_on_map": int(np.isfinite(self.path_px[:, 0]).sum()),
                **({"video_gains": self.video_gains} if len(self.video_gains) > 1 else {})}


def atlas_px(surface: CavitySurface, points: np.ndarray, width: int, height: int) -> np.ndarray:
    """Atlas pixel coordinates (N, 2) (column, row; texel centres at integers) of points (N, 3)."""
    lon, lat = surface.angles(points)
    return np.stack([(lon + np.pi) / (2 * np.pi) * width - 0.5, (np.pi / 2 - lat) / np.pi * height - 0.5], axis=1)


def _texel_geometry(surface: CavitySurface, width: int, height: int):
    """Texel points (H*W, 3) float32, inward unit normals (H*W, 3) float32 and areas (H, W) float32."""
    lon = -np.pi + (np.arange(width) + 0.5) * 2 * np.pi / width
    lat = np.pi / 2 - (np.arange(height) + 0.5) * np.pi / height
    pts = np.empty((height, width, 3), np.float32)
    for r0 in range(0, height, 64):  # the radial basis of every texel at once would be K times the atlas
        rows = slice(r0, min(r0 + 64, height))
        lo, la = np.meshgrid(lon, lat[rows])
        pts[rows] = surface.points(lo.ravel(), la.ravel()).reshape(-1, width, 3)
    normals = np.empty_like(pts)
    area = np.empty((height, width), np.float32)
    step_lon, step_lat = np.float32(2 * np.pi / width), np.float32(np.pi / height)
    centre = surface.centre.astype(np.float32)
    for r0 in range(0, height, 64):  # central differences, a band of rows at a time (whole-atlas temporaries
        r1 = min(r0 + 64, height)     # of a 3072-px atlas took 570 MB)
        band = pts[r0:r1]
        d_lon = (np.roll(band, -1, axis=1) - np.roll(band, 1, axis=1)) / (2 * step_lon)
        above, below = pts[max(r0 - 1, 0):r1 - 1 if r0 == 0 else r1 - 1], pts[r0 + 1:min(r1 + 1, height)]
        north = np.concatenate([band[:1], above]) if r0 == 0 else above  # rows go south: latitude decreases
        south = np.concatenate([below, band[-1:]]) if r1 == height else below
        spans = np.full(r1 - r0, 2.0, np.float32)
        spans[0] -= r0 == 0
        spans[-1] -= r1 == height
        d_lat = (north - south) / (spans[:, None, None] * step_lat)
        cross = np.cross(d_lon, d_lat)
        norm = np.linalg.norm(cross, axis=2)
        area[r0:r1] = norm * (step_lon * step_lat)
        n = cross / np.maximum(norm, 1e-30)[..., None]
        outward = np.einsum("hwk,hwk->hw", n, centre - band) < 0
        n[outward] *= -1
        normals[r0:r1] = n
    return pts.reshape(-1, 3), normals.reshape(-1, 3), area


def _dilate_wrapped(mask: np.ndarray) -> np.ndarray:
    out = mask.copy()
    out |= np.roll(mask, 1, axis=1) | np.roll(mask, -1, axis=1)
    grown = out.copy()
    grown[1:] |= out[:-1]
    grown[:-1] |= out[1:]
    return grown


def _candidate_texels(points: np.ndarray, width: int, height: int, camera: Camera, pose: Pose,
                      stride: int) -> np.ndarray:
    """Indices of the texels near the frame's field: a sub-grid of every ``stride``-th texel projected, its
    cells inside the field grown by one cell."""
    grid = points.reshape(height, width, 3)[::stride, ::stride]
    hc, wc = grid.shape[:2]
    local = pose.transform(grid.reshape(-1, 3).astype(float))
    inside = np.zeros(len(local), bool)
    front = local[:, 2] > 0
    # a texel in the field is within a cell of a sub-grid point in it (the field spans many cells): one cell's
    # growth, and a margin of a cell's width in pixels (texels are about the frames' pixel footprint)
    inside[front] = camera.in_image(camera.project(local[front]), margin_px=-float(stride))
    cells = _dilate_wrapped(inside.reshape(hc, wc))
    full = np.repeat(np.repeat(cells, stride, axis=0), stride, axis=1)[:height, :width]
    return np.flatnonzero(full)


def _frame_footprint_mm(surface: CavitySurface, cameras: Sequence[Camera], poses: Sequence[Pose | None]) -> float:
    """The frames' median pixel footprint on the wall along their optical axes (distance / focal)."""
    d = []
    for camera, pose in zip(cameras, poses):
        if pose is not None:
            hit = surface.intersect(pose.centre[None], pose.optical_axis[None])[0]
            if np.all(np.isfinite(hit)):
                d.append(np.linalg.norm(hit - pose.centre) / math.sqrt(camera.fx * camera.fy))
    return float(np.median(d)) if d else 1.0


def _label_wrapped(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """Connected components (4-neighbours) of a (H, W) mask on the sphere: joined across the left/right seam
    and, at the top and bottom rows (one point each, a pole), all together."""
    labels, n = ndimage.label(mask)
    parent = np.arange(n + 1)

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    def union(a, b):
        if a and b:
            ra, rb = find(a), find(b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)

    for a, b in zip(labels[:, 0], labels[:, -1]):
        union(a, b)
    for row in (labels[0], labels[-1]):
        present = np.unique(row[row > 0])
        for b in present[1:]:
            union(present[0], b)
    roots = np.array([find(a) for a in range(n + 1)])
    _, compact = np.unique(roots, return_inverse=True)
    return compact[labels], int(compact.max())


def organ_map(surface: CavitySurface, camera: Camera | Sequence[Camera], poses: Sequence[Pose | None],
              frame: Callable[[int], np.ndarray], *, options: OrganMapOptions = OrganMapOptions(),
              groups: Sequence[int] | None = None) -> OrganMap:
    """The 2-D map of the cavity from the frames taken at ``poses`` (``cam_from_world``, None: not registered;
    frame(k) the k-th image, RGB or grey). camera : every frame's, or one per frame (several videos on one
    map). groups : each frame's video (0, 1, ...): the map also gives each video's own covered fraction
    (``group_coverage``)."""
    cameras = [camera] * len(poses) if isinstance(camera, Camera) else list(camera)
    group = np.zeros(len(poses), int) if groups is None else np.asarray(groups, int)
    equator = 2 * np.pi * float(np.mean(surface.semi_axes[:2]))
    texel = options.texel_mm or _frame_footprint_mm(surface, cameras, poses)
    width = int(min(options.max_width_px, max(16, 2 * round(equator / texel / 2))))
    height = width // 2
    texel = equator / width
    points, normals, area = _texel_geometry(surface, width, height)
    n_tex = width * height
    n_groups = int(group.max(initial=0)) + 1
    acc = np.zeros((n_groups, n_tex, 3), np.float32)  # per video: each its own gain (exposure, light)
    weight = np.zeros((n_groups, n_tex), np.float32)
    n_views = np.zeros(n_tex, np.uint16)
    seen_by = np.zeros((n_groups, n_tex), bool)
    stride = max(1, min(16, width // 256))
    for k, pose in enumerate(poses):
        if pose is None:
            continue
        camera = cameras[k]
        focal = math.sqrt(camera.fx * camera.fy)
        idx = _candidate_texels(points, width, height, camera, pose, stride)
        if not len(idx):
            continue
        p = points[idx].astype(float)
        to_cam = pose.centre - p
        dist = np.linalg.norm(to_cam, axis=1)
        cos = np.einsum("ij,ij->i", normals[idx], to_cam) / np.maximum(dist, 1e-300)
        local = np.einsum("ij,kj->ik", -to_cam, pose.rotation)
        uv = np.full((len(idx), 2), np.nan)
        front = local[:, 2] > 0
        uv[front] = camera.project(local[front])
        seen = front & camera.in_image(uv) & (cos > 0)
        n_views[idx[seen]] += 1
        seen_by[group[k], idx[seen]] = True
        margin = field_margin(camera, uv) - 1.5  # a bilinear read reaches one pixel out
        use = seen & (cos >= options.min_cos) & (margin > 0)
        if not use.any():
            continue
        feather = np.clip(margin[use] / options.feather_px, 0.0, 1.0) if options.feather_px > 0 else 1.0
        w = (cos[use] * focal / dist[use] * feather) ** options.blend_power
        image = frame(k)
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        colour = sample_image(image, uv[use])
        if options.compensate_light:
            colour /= (cos[use] / dist[use] ** 2)[:, None].astype(np.float32)
        acc[group[k], idx[use]] += colour * w[:, None].astype(np.float32)
        weight[group[k], idx[use]] += w.astype(np.float32)
    rgb, total_weight, gains = _blend_videos(acc, weight)
    coloured = total_weight > 0
    if coloured.any():
        level = float(np.percentile(rgb[coloured], 99.5)) or 1.0
        rgb *= options.white_level / level
    atlas = np.full((n_tex, 3), 96, np.uint8)
    atlas[coloured] = np.clip(np.rint(rgb[coloured]), 0, 255).astype(np.uint8)
    covered = (n_views > 0).reshape(height, width)
    total = float(area.sum())
    coverage = float(area[covered].sum() / total)
    group_coverage = [float(area.ravel()[g].sum() / total) for g in seen_by]
    regions, n_small, small = _uncovered_regions(~covered, area, points.reshape(height, width, 3), surface,
                                                 width, height, options.min_region_fraction)
    path = np.full((len(poses), 2), np.nan)
    for k, pose in enumerate(poses):
        if pose is not None:
            hit = surface.intersect(pose.centre[None], pose.optical_axis[None])
            if np.all(np.isfinite(hit)):
                path[k] = atlas_px(surface, hit, width, height)[0]
    return OrganMap(atlas.reshape(height, width, 3), covered, area, path, regions, n_small, small, coverage,
                    float(texel), surface, n_views.reshape(height, width), group_coverage, group,
                    [float(g) for g in gains])


def _blend_videos(acc: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The videos' blended colours (n_tex, 3), summed weights and gains (``acc`` is overwritten): each video's colours
    divided by its gain, the median ratio of its colours to the first video's on the texels both see (videos of
    one wall differ by their exposure and light: the phantom's 15 mm and 30 mm scans, true poses, light divided
    out, are 3.9 times apart, and without the gain the 30 mm scan's texels outshone the rest of the map), or,
    without 100 common texels, the ratio of their medians."""
    for g in range(len(weight)):  # each video's weighted mean, in place (a 3072-px atlas: 56 MB per copy)
        has = weight[g] > 0
        acc[g, has] /= weight[g, has, None]
    gains = np.ones(len(weight), np.float32)
    if len(weight) == 1:
        return acc[0], weight[0], gains
    base = weight[0] > 0
    for g in range(1, len(weight)):
        has = weight[g] > 0
        both = np.flatnonzero(has & base)
        first = acc[0, both].mean(axis=1)
        both, first = both[first > 0], first[first > 0]
        if len(both) >= 100:
            gains[g] = float(np.median(acc[g, both].mean(axis=1) / first))
        elif has.any() and base.any():
            gains[g] = float(np.median(acc[g, has].mean(axis=1)) / max(np.median(acc[0, base].mean(axis=1)), 1e-12))
    total = weight.sum(axis=0)
    rgb = np.zeros(acc.shape[1:], np.float32)
    for g in range(len(weight)):
        rgb += acc[g] * (weight[g] / max(gains[g], 1e-12))[:, None]
    coloured = total > 0
    rgb[coloured] /= total[coloured, None]
    return rgb, total, gains


def _uncovered_regions(uncovered: np.ndarray, area: np.ndarray, points: np.ndarray, surface: CavitySurface,
                       width: int, height: int, min_fraction: float) -> tuple[list[dict], int, float]:
    labels, n = _label_wrapped(uncovered)
    total = float(area.sum())
    if n == 0:
        return [], 0, 0.0
    flat = labels.ravel()
    region_area = np.bincount(flat, weights=area.ravel().astype(float), minlength=n + 1)
    centroid = np.stack([np.bincount(flat, weights=(area * points[..., c]).ravel().astype(float), minlength=n + 1)
                         for c in range(3)], axis=1) / np.maximum(region_area, 1e-300)[:, None]
    regions, n_small, small = [], 0, 0.0
    for lab in np.argsort(-region_area[1:]) + 1:
        fraction = region_area[lab] / total
        if fraction < min_fraction:
            n_small += 1
            small += fraction
            continue
        rows, cols = np.nonzero(labels == lab)
        # the centre: the region's area-weighted mean point, pulled onto the surface along its direction
        lon, lat = surface.angles(centroid[lab][None])
        regions.append({"area_mm2": float(region_area[lab]), "fraction": float(fraction),
                        "centre_lon_deg": float(np.degrees(lon[0])), "centre_lat_deg": float(np.degrees(lat[0])),
                        "centre_px": atlas_px(surface, centroid[lab][None], width, height)[0].tolist(),
                        "rows_px": [int(rows.min()), int(rows.max())],
                        "touches_pole": bool(rows.min() == 0 or rows.max() == height - 1),
                        "label": int(lab)})
    return regions, n_small, float(small)


# The scope's path per video: red, then orange, magenta, white.
PATH_COLOURS = ((230, 30, 30), (255, 150, 0), (230, 0, 230), (255, 255, 255))


def draw_organ_map(organ: OrganMap) -> tuple[np.ndarray, np.ndarray]:
    """(organ_map RGB image, coverage mask uint8 0/255): the atlas with a 30° graticule, the uncovered regions
    hatched and outlined, the scope's path (frame centres of view joined in capture order, green start,
    every fifth frame numbered; one path per video, :data:`PATH_COLOURS`)."""
    img = organ.image.copy()
    h, w = img.shape[:2]
    s = max(1, round(w / 1000))
    for deg in range(-60, 90, 30):  # graticule: the atlas lightened along every 30° of latitude and longitude
        rows = slice(max(0, round((90 - deg) / 180 * h) - s // 2), round((90 - deg) / 180 * h) + (s + 1) // 2)
        img[rows] = (img[rows] * 0.6 + 102).astype(np.uint8)
    for deg in range(-150, 180, 30):
        cols = slice(max(0, round((deg + 180) / 360 * w) - s // 2), round((deg + 180) / 360 * w) + (s + 1) // 2)
        img[:, cols] = (img[:, cols] * 0.6 + 102).astype(np.uint8)
    uncovered = ~organ.covered
    yy, xx = np.mgrid[0:h, 0:w]
    stripes = ((xx + yy) // (4 * s)) % 2 == 0
    img[uncovered & stripes] = (40, 70, 160)
    img[uncovered & ~stripes] = (20, 30, 70)
    listed = np.zeros((h, w), np.uint8)
    labels, _ = _label_wrapped(uncovered)
    for region in organ.regions:
        listed[labels == region["label"]] = 255
    contours, _ = cv2.findContours(listed, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(img, contours, -1, (255, 220, 0), s, lineType=cv2.LINE_AA)
    group = organ.group if len(organ.group) == len(organ.path_px) else np.zeros(len(organ.path_px), int)
    for g in np.unique(group):  # one path per video, its frames numbered from 0
        members = np.flatnonzero(group == g)
        path = organ.path_px[members]
        colour = PATH_COLOURS[int(g) % len(PATH_COLOURS)]
        ok = np.flatnonzero(np.isfinite(path[:, 0]))
        for a, b in zip(ok[:-1], ok[1:]):
            if abs(path[a, 0] - path[b, 0]) > w / 2:  # across the seam: no line over the whole map
                continue
            cv2.line(img, tuple(np.rint(path[a]).astype(int)), tuple(np.rint(path[b]).astype(int)), colour,
                     s, lineType=cv2.LINE_AA)
        for i, k in enumerate(ok):
            c = tuple(np.rint(path[k]).astype(int))
            cv2.circle(img, c, 2 * s + 1, (40, 200, 40) if i == 0 else colour, -1, lineType=cv2.LINE_AA)
            if k % 5 == 0:
                cv2.putText(img, str(k), (c[0] + 3 * s, c[1] - 3 * s), cv2.FONT_HERSHEY_SIMPLEX, 0.35 * s,
                            (255, 255, 255), max(1, s // 2), cv2.LINE_AA)
    return img, (organ.covered * 255).astype(np.uint8)


def alignment_error(surface: CavitySurface, camera: Camera, poses: Sequence[Pose | None],
                    true_poses: Sequence[Pose], depth: Callable[[int], np.ndarray], truth_from_map,
                    width: int, height: int, *, step_px: int = 4) -> dict:
    """How far the map puts each frame's pixels from where they belong: for pixels on a ``step_px`` grid inside
    each registered frame's field (with a true depth), the atlas position of the map's mapping (the ray from the
    map's pose meeting the fitted surface) against the atlas position of the pixel's true wall point (true pose
    and depth) carried into the map's frame by the inverse of ``truth_from_map`` (a
    :class:`scope3d.geometry.similarity.Similarity`: the gauge of a map known up to a similarity, fitted on the
    tracks, not on the atlas). Returns atlas px: mean, median, p95, max, n; per frame p95 (None: not
    registered); and the same
    displacement measured on the wall (``on_wall_mean``, ``on_wall_p95``, map units: the equirectangular atlas
    stretches longitude near its poles, where an atlas px is a fraction of a texel on the wall)."""
    grid = camera.pixel_grid()[::step_px, ::step_px].reshape(-1, 2)
    grid = grid[camera.in_image(grid)]
    errors, walls, per_frame = [], [], [None] * len(poses)
    for k, pose in enumerate(poses):
        if pose is None:
            continue
        z = depth(k)[grid[:, 1].astype(int), grid[:, 0].astype(int)].astype(float)
        ok = np.isfinite(z) & (z > 0)
        if not ok.any():
            continue
        px = grid[ok]
        true_world = true_poses[k].inverse().transform(camera.unproject(px, z[ok]))
        # the similarity's inverse: X = (X' - target) @ rotation / scale + origin
        true_in_map = ((true_world - truth_from_map.target) @ truth_from_map.rotation) / truth_from_map.scale \
            + truth_from_map.origin
        origins, dirs = camera.pixel_rays_world(pose, px)
        hit = surface.intersect(origins, dirs)
        a = atlas_px(surface, hit, width, height)
        b = atlas_px(surface, true_in_map, width, height)
        d = a - b
        d[:, 0] = (d[:, 0] + width / 2) % width - width / 2  # across the seam
        e = np.linalg.norm(d, axis=1)
        lon, lat = surface.angles(true_in_map)
        # on the wall: from the map's point to the surface's point where the truth puts the pixel
        on_wall = np.linalg.norm(hit - surface.points(lon, lat), axis=1)
        ok = np.isfinite(e) & np.isfinite(on_wall)
        if ok.any():
            errors.append(e[ok])
            walls.append(on_wall[ok])
            per_frame[k] = float(np.percentile(e[ok], 95))
    if not errors:
        return {}
    e, m = np.concatenate(errors), np.concatenate(walls)
    return {"mean_px": float(e.mean()), "median_px": float(np.median(e)), "p95_px": float(np.percentile(e, 95)),
            "max_px": float(e.max()), "on_wall_mean": float(m.mean()), "on_wall_p95": float(np.percentile(m, 95)),
            "n_pixels": int(len(e)), "step_px": step_px, "per_frame_p95_px": per_frame}
