"""Axial-stereo geometry: two views taken along the viewing direction (reference ch. 7).

When a forward-looking scope steps along its optical axis, every epipolar line is a ray from the epipole
(the image of the other camera centre, near the image centre), and a scene point slides *outward* along
its ray as the camera advances. This module turns that into ordinary one-dimensional stereo:

1. A *virtual camera* is put at each camera centre with the same orientation for both, its +z axis along
   the baseline (rear centre -> front centre). Rotating a camera about its centre is an exact image warp,
   so any relative rotation and any tilt between the motion and the optical axis (axis misalignment) is
   absorbed here; the epipole of both virtual cameras is their principal point ``(0, 0)``.
2. Both images are resampled on a *log-polar grid* around that epipole: row = polar angle ``theta``,
   column = ``log(rho)`` with ``rho`` the normalised radius (tan of the angle to the baseline). Epipolar
   lines become rows, and the axial motion (locally a zoom about the epipole) becomes a pure shift along
   the row, so a matcher's square window sees the same patch in both images, with disparity
   ``d = (log rho_front - log rho_rear) / step`` independent of where on the ray the point lies.
3. Triangulation is then closed-form: the point's coordinate along the baseline in the front virtual
   camera is ``Z = b / (exp(d * step) - 1)`` with ``b`` the baseline (mm), and the point is
   ``Z * (x, y, 1)`` in that camera. This is the general-case form of the reference's eq. 7.3.

:func:`aligned_triangulate` is the reference's own model (eqs. 7.3-7.4: optical axes coincide, image axes
parallel, pure translation), kept as a check; :func:`aligned_poses` builds the poses that model assumes.
:func:`triangulate_rays` triangulates matched pixels of any two posed cameras (midpoint of the common
perpendicular) and is used to verify the closed form.

Frames and units: poses are ``cam_from_world`` (:class:`~scope3d.geometry.pose.Pose`), lengths in mm, angles in
rad; pixels have their origin at the centre of the top-left pixel. "Rear" is the camera farther back
along the motion, "front" the one that has advanced (deeper in the hole).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.triangulation import triangulate_midpoint
from scope3d.sensor.camera import Camera
from scope3d.utils.aot import load_kernels
from scope3d.utils.row_blocks import run_by_row_blocks

_kernels = load_kernels("scope3d.mvs.axial_kernels")


@dataclass(frozen=True)
class PolarGridOptions:
    """How the log-polar grid around the epipole is sampled.

    radial_step_px : float
        Column spacing at the outer edge of the image, in image pixels. Log sampling makes the spacing
        proportional to the radius, so inside it is finer; 1.0 keeps the rim at native resolution.
    angular_step_px : float
        Row spacing, as arc length in pixels at the outer edge. Above 1 undersamples the rim slightly
        to save time (the rim is dim and noisy anyway); every row is one epipolar line.
    min_radius_px : float
        Inner radius of the grid, pixels from the epipole. Nearer the epipole the disparity tends to 0
        and depth is ill-conditioned (eq. 7.3 divides by it), and log sampling would explode the few
        pixels there into many columns.
    """

    radial_step_px: float = 1.0
    angular_step_px: float = 1.5
    min_radius_px: float = 6.0

    def __post_init__(self) -> None:
        for name in ("radial_step_px", "angular_step_px", "min_radius_px"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"PolarGridOptions.{name} must be positive, got {value}")


@dataclass(frozen=True)
class PolarGrid:
    """A log-polar sampling of the virtual image plane around the epipole.

    Row ``a`` is the polar angle ``theta_a = 2 pi a / n_angles`` (rad, from the virtual x axis toward
    +y); column ``c`` is the normalised radius ``rho_c = exp(log_rho_min + c * log_rho_step)``.
    """

    n_angles: int
    n_radii: int
    log_rho_min: float
    log_rho_step: float

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_angles, self.n_radii)

    def angles(self) -> np.ndarray:
        """(n_angles,) rad."""
        return np.arange(self.n_angles) * (2.0 * np.pi / self.n_angles)

    def radii(self) -> np.ndarray:
        """(n_radii,) normalised radii (unitless)."""
        return np.exp(self.log_rho_min + self.log_rho_step * np.arange(self.n_radii))

    def virtual_points(self) -> np.ndarray:
        """(n_angles, n_radii, 3) points ``(x, y, 1)`` on the virtual image plane z = 1."""
        theta = self.angles()[:, None]
        rho = self.radii()[None, :]
        out = np.empty(self.shape + (3,))
        out[..., 0] = rho * np.cos(theta)
        out[..., 1] = rho * np.sin(theta)
        out[..., 2] = 1.0
        return out

    def coordinates_of(self, points_virtual: np.ndarray) -> np.ndarray:
        """Fractional (row, column) of directions in the virtual frame; NaN for z <= 0.

        points_virtual : (..., 3) any points or directions in the virtual camera frame.
        Returns (..., 2) float: row in [0, n_angles) (wraps), column (may be outside [0, n_radii)).
        """
        p = np.asarray(points_virtual, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(p[..., 2] > 0, p[..., 2], np.nan)
            x, y = p[..., 0] / z, p[..., 1] / z
            rho = np.hypot(x, y)
            col = (np.log(rho) - self.log_rho_min) / self.log_rho_step
        row = np.mod(np.arctan2(y, x), 2.0 * np.pi) * (self.n_angles / (2.0 * np.pi))
        return np.stack([row, col], axis=-1)


def epipole_px(camera: Camera, pose: Pose, other_centre_mm: np.ndarray) -> tuple[np.ndarray, bool]:
    """Epipole in ``camera`` at ``pose``: the image of the other camera's centre.

    other_centre_mm : (3,) world, mm. Returns ``(pixel (2,), in_front)``; ``in_front`` is True when the
    other centre is ahead of this camera (focus of expansion of the rear camera), False when behind
    (the front camera: the epipole is then the image of the point diametrically opposite). Distortion is
    applied. Raises InputError when the centres coincide or the epipole is at infinity (lateral motion).
    """
    c = pose.transform(np.asarray(other_centre_mm, dtype=float).reshape(1, 3))[0]
    if np.linalg.norm(c) < 1e-12:
        raise InputError("the two camera centres coincide (zero step): axial stereo needs a baseline")
    if abs(c[2]) < 1e-9 * np.linalg.norm(c):
        raise InputError("the epipole is at infinity: the motion is perpendicular to the optical axis")
    xy = camera.distort(c[None, :2] / c[2])[0]
    return np.array([camera.fx * xy[0] + camera.cx, camera.fy * xy[1] + camera.cy]), bool(c[2] > 0)


@dataclass(frozen=True)
class AxialPair:
    """Geometry of one axial-stereo pair, ready for resampling and triangulation.

    camera : Camera shared by both frames.
    pose_rear, pose_front : Pose ``cam_from_world`` of the camera farther back and farther along the motion.
    virtual_from_world : (3, 3) rotation of the two virtual cameras (z along the baseline).
    baseline_mm : float, distance between the camera centres.
    axis_angle_rad : float, the larger angle between the baseline and either optical axis.
    grid : PolarGrid shared by both resampled images.
    swapped : True when the caller's first frame was the front one.
    """

    camera: Camera
    pose_rear: Pose
    pose_front: Pose
    virtual_from_world: np.ndarray
    baseline_mm: float
    axis_angle_rad: float
    grid: PolarGrid
    swapped: bool = False
    _maps: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def front_centre(self) -> np.ndarray:
        return self.pose_front.centre

    def virtual_from_camera(self, pose: Pose) -> np.ndarray:
        """(3, 3) rotation taking directions of the camera at ``pose`` into the virtual frame."""
        return self.virtual_from_world @ pose.rotation.T

    def polar_maps(self, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """cv2.remap maps sampling the image of the camera at ``pose`` on the polar grid.

        Returns map_u, map_v : (n_angles, n_radii) float32 pixels; -1 where the grid point is behind the
        camera or outside its image disc (so remap gives 0 there). The maps depend only on the camera's
        orientation (the grid is a set of directions), so they are cached per rotation: the two frames of a
        pure axial step share one pair of maps.
        """
        key = ("polar", self.virtual_from_camera(pose).tobytes())
        if key not in self._maps:
            self._maps[key] = self._compute_polar_maps(pose)
        return self._maps[key]

    def _compute_polar_maps(self, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        # One compiled pass over the grid (mvs/axial_kernels.py): the NumPy expression of the same
        # projection made ten (A R, 3) float64 temporaries and took ~130 ms of a ~450 ms pair at 608 px.
        cam = self.camera
        theta = self.grid.angles()
        cos_sin = np.ascontiguousarray(np.stack([np.cos(theta), np.sin(theta)], axis=1).reshape(-1))
        mask = -1.0 if cam.mask_radius_px is None else float(cam.mask_radius_px)
        image = np.array([cam.width, cam.height, mask, (cam.width - 1) / 2.0, (cam.height - 1) / 2.0])
        intrinsics = np.array([cam.fx, cam.fy, cam.cx, cam.cy, cam.k1, cam.k2], dtype=float)
        map_u = np.empty(self.grid.shape, np.float32)
        map_v = np.empty(self.grid.shape, np.float32)
        inputs = (cos_sin, np.ascontiguousarray(self.grid.radii()), np.ascontiguousarray(self.virtual_from_camera(pose).T),
                  intrinsics, image)
        run_by_row_blocks(_kernels.polar_maps, self.grid.n_angles, inputs, (map_u, map_v))  # on the cores
        return map_u, map_v

    def to_polar(self, image: np.ndarray, pose: Pose, *, interpolation: int = cv2.INTER_CUBIC) -> np.ndarray:
        """Resample ``image`` (H, W) or (H, W, C) taken at ``pose`` onto the grid: (n_angles, n_radii[, C])."""
        map_u, map_v = self.polar_maps(pose)
        return cv2.remap(image, map_u, map_v, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def valid_polar(self, pose: Pose) -> np.ndarray:
        """(n_angles, n_radii) bool: grid point lands inside the image disc of the camera at ``pose``."""
        map_u, _ = self.polar_maps(pose)
        return map_u >= 0

    def image_to_grid(self, pose: Pose) -> np.ndarray:
        """(H, W, 2) float32 fractional (row, column) on the grid of every pixel of the camera at ``pose``.

        Cached per rotation, like :meth:`polar_maps` (a depth map and its confidence share it)."""
        key = ("image", self.virtual_from_camera(pose).tobytes())
        if key not in self._maps:
            coords = self.grid.coordinates_of(self.camera_rays() @ self.virtual_from_camera(pose).T)
            self._maps[key] = coords.reshape(self.camera.height, self.camera.width, 2).astype(np.float32)
        return self._maps[key]

    def camera_rays(self) -> np.ndarray:
        """(H * W, 3) unit rays of every pixel in the camera frame (cached)."""
        if "rays" not in self._maps:
            self._maps["rays"] = self.camera.unproject(self.camera.pixel_grid().reshape(-1, 2))
        return self._maps["rays"]

    def from_polar(self, values: np.ndarray, pose: Pose) -> np.ndarray:
        """Resample a polar map (n_angles, n_radii) float, NaN = no value, back to the image at ``pose``.

        Bilinear where all four neighbours have values, NaN elsewhere (no blending across holes).
        Returns (H, W) float32.
        """
        coords = self.image_to_grid(pose)
        # Pad one wrapped row so that bilinear interpolation across theta = 2 pi sees row 0.
        vals = np.asarray(values, dtype=np.float32)
        vals = np.concatenate([vals, vals[:1]], axis=0)
        known = np.isfinite(vals)
        filled = np.where(known, vals, 0.0).astype(np.float32)
        map_x = np.nan_to_num(coords[..., 1], nan=-10.0)
        map_y = np.nan_to_num(coords[..., 0], nan=-10.0)
        out = cv2.remap(filled, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        weight = cv2.remap(known.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return np.where(weight > 0.999, out, np.nan).astype(np.float32)

    # --- triangulation ----------------------------------------------------------------------
    def depth_along_baseline(self, disparity: np.ndarray) -> np.ndarray:
        """Closed-form triangulation on the grid (general form of eq. 7.3).

        disparity : (n_angles, n_radii) float, columns, ``col_front - col_rear`` (> 0 for a point in front).
        Returns (n_angles, n_radii) float, mm: coordinate ``Z`` of the point along the baseline in the
        front virtual camera, ``Z = b / (exp(d * step) - 1)``; NaN where ``d <= 0`` or NaN.
        """
        d = np.asarray(disparity, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            z = self.baseline_mm / np.expm1(d * self.grid.log_rho_step)
        return np.where(d > 0, z, np.nan)

    def range_from_disparity(self, disparity: np.ndarray, where: np.ndarray | None = None) -> np.ndarray:
        """(n_angles, n_radii) mm: distance from the front camera centre to the point along its grid ray.

        where : (n_angles, n_radii) bool or None; when given, only those cells are computed (NaN elsewhere).
        """
        rho = self.grid.radii()[None, :]
        if where is None:
            return self.depth_along_baseline(disparity) * np.sqrt(1.0 + rho * rho)
        d = np.asarray(disparity, dtype=float)
        out = np.full(d.shape, np.nan)
        rho = np.broadcast_to(rho, d.shape)[where]
        out[where] = self.depth_along_baseline(d[where]) * np.sqrt(1.0 + rho * rho)
        return out

    def range_sigma(self, disparity: np.ndarray, disparity_sigma: np.ndarray | float) -> np.ndarray:
        """First-order standard deviation (mm) of the range given that of the disparity (columns).

        ``dZ/dd = -b step exp(d step) / (exp(d step) - 1)^2``; near the epipole ``d -> 0`` and this blows up
        as ``Z^2 step / b``: the conditioning that the confidence mask uses. NaN where ``d <= 0`` or NaN.
        """
        d = np.asarray(disparity, dtype=float)
        s = self.grid.log_rho_step
        rho = self.grid.radii()[None, :]
        # In place, in the order of ``b s exp(d s) / expm1(d s)^2 sqrt(1 + rho^2) sigma``: the same
        # bits without a frame-sized float64 temporary per operation.
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            x = d * s
            out = np.exp(x)
            out *= self.baseline_mm * s
            denominator = np.expm1(x, out=x)
            np.square(denominator, out=denominator)
            out /= denominator
            out *= np.sqrt(1.0 + rho * rho)
            out *= np.asarray(disparity_sigma)
        out[~(d > 0)] = np.nan
        return out

    def points_world(self, depth_along_baseline_mm: np.ndarray) -> np.ndarray:
        """(n_angles, n_radii, 3) world points (mm) from :meth:`depth_along_baseline` (NaN propagates)."""
        local = self.grid.virtual_points() * np.asarray(depth_along_baseline_mm)[..., None]
        return local @ self.virtual_from_world + self.front_centre

    def triangulate_grid(self, coords_front: np.ndarray, disparity: np.ndarray) -> np.ndarray:
        """World points (N, 3) mm of matches given by fractional front-grid coordinates.

        coords_front : (N, 2) (row, column) on the grid of the front image; disparity : (N,) columns,
        ``col_front - col_rear``. Closed form of eq. 7.3 in the virtual frame, then to the world.
        """
        c = np.asarray(coords_front, dtype=float).reshape(-1, 2)
        theta = c[:, 0] * (2.0 * np.pi / self.grid.n_angles)
        rho = np.exp(self.grid.log_rho_min + self.grid.log_rho_step * c[:, 1])
        z = self.depth_along_baseline(np.asarray(disparity, dtype=float).reshape(-1))
        local = np.stack([rho * np.cos(theta) * z, rho * np.sin(theta) * z, z], axis=1)
        return local @ self.virtual_from_world + self.front_centre


def make_axial_pair(
    camera: Camera,
    pose_a: Pose,
    pose_b: Pose,
    *,
    grid_options: PolarGridOptions = PolarGridOptions(),
    min_step_mm: float = 1e-3,
    max_axis_angle_deg: float = 15.0,
) -> AxialPair:
    """Set up the virtual cameras and the polar grid for the frames at ``pose_a`` and ``pose_b``.

    The frame farther along the common viewing direction becomes the front one, whichever order they
    come in. Raises InputError when the step is below ``min_step_mm`` (no baseline, depth undefined) or
    the baseline makes more than ``max_axis_angle_deg`` with either optical axis (the epipole then
    leaves the centre of the image and the radial-epipolar model no longer covers the view).
    """
    c_a, c_b = pose_a.centre, pose_b.centre
    step = float(np.linalg.norm(c_b - c_a))
    if not step >= min_step_mm:
        raise InputError(
            f"the two frames are {step:.3g} mm apart (minimum {min_step_mm:g} mm): "
            "axial stereo needs the scope to move between them"
        )
    direction = (c_b - c_a) / step
    view = pose_a.optical_axis + pose_b.optical_axis
    swapped = bool(np.dot(direction, view) < 0)
    if swapped:
        direction = -direction
    angles = [np.arccos(np.clip(np.dot(direction, p.optical_axis), -1, 1)) for p in (pose_a, pose_b)]
    axis_angle = float(max(angles))
    if np.rad2deg(axis_angle) > max_axis_angle_deg:
        raise InputError(
            f"the poses are not axial: the step makes {np.rad2deg(axis_angle):.1f} deg with the optical axis "
            f"(limit {max_axis_angle_deg:g} deg); use lateral stereo or frames taken along the viewing direction"
        )
    pose_rear, pose_front = (pose_b, pose_a) if swapped else (pose_a, pose_b)
    # Virtual x, y as close as possible to the front camera's, so that the polar angle 0 is image +x.
    x_hint = pose_front.rotation[0]
    y = np.cross(direction, x_hint)
    y /= np.linalg.norm(y)
    x = np.cross(y, direction)
    virtual_from_world = np.stack([x, y, direction])
    grid = _make_grid(camera, [pose_rear, pose_front], virtual_from_world, grid_options)
    return AxialPair(camera, pose_rear, pose_front, virtual_from_world, step, axis_angle, grid, swapped)


def _make_grid(camera: Camera, poses: list[Pose], virtual_from_world: np.ndarray, opts: PolarGridOptions) -> PolarGrid:
    """Polar grid covering the image discs of both cameras as seen from the virtual frame."""
    focal = 0.5 * (camera.fx + camera.fy)
    # Sample the outline of the valid image (mask circle or frame border) to find the largest radius.
    n = 720
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    if camera.mask_radius_px is not None:
        centre = np.array([(camera.width - 1) / 2.0, (camera.height - 1) / 2.0])
        outline = centre + camera.mask_radius_px * np.stack([np.cos(t), np.sin(t)], axis=1)
    else:
        s = np.linspace(0, 1, n // 4, endpoint=False)
        w, h = camera.width - 1.0, camera.height - 1.0
        outline = np.concatenate([
            np.stack([s * w, 0 * s], 1), np.stack([w + 0 * s, s * h], 1),
            np.stack([w - s * w, h + 0 * s], 1), np.stack([0 * s, h - s * h], 1),
        ])
    rho_max = 0.0
    for pose in poses:
        rays = camera.unproject(outline) @ pose.rotation @ virtual_from_world.T
        ok = rays[:, 2] > 1e-6
        if np.any(ok):
            rho_max = max(rho_max, float(np.max(np.hypot(rays[ok, 0], rays[ok, 1]) / rays[ok, 2])))
    if rho_max <= 0:
        raise InputError("the image does not see along the baseline: no axial-stereo overlap")
    rho_min = opts.min_radius_px / focal
    if rho_min >= rho_max:
        raise InputError("PolarGridOptions.min_radius_px is larger than the image")
    log_step = opts.radial_step_px / (focal * rho_max)
    n_radii = int(np.ceil(np.log(rho_max / rho_min) / log_step)) + 1
    n_angles = int(np.ceil(2 * np.pi * focal * rho_max / opts.angular_step_px))
    n_angles += (-n_angles) % 4  # a multiple of 4 keeps the image axes on grid rows
    return PolarGrid(n_angles, n_radii, float(np.log(rho_min)), float(log_step))


def aligned_poses(pose_rear: Pose, pose_front: Pose) -> tuple[Pose, Pose]:
    """The poses the reference's aligned model (Fig. 7.1) assumes.

    Keeps the front pose, and puts the rear camera with the same orientation at the same distance
    straight behind it along the front optical axis. Feeding these to :func:`make_axial_pair` reproduces
    eqs. 7.3-7.4 exactly, so the benchmarks can measure what assuming alignment costs.
    """
    step = float(np.linalg.norm(pose_front.centre - pose_rear.centre))
    centre = pose_front.centre - step * pose_front.optical_axis
    return Pose.from_centre(pose_front.rotation, centre), pose_front


def aligned_triangulate(
    camera: Camera, pixels_rear: np.ndarray, pixels_front: np.ndarray, step_mm: float
) -> np.ndarray:
    """The reference's eqs. 7.3-7.4 for perfectly aligned axial stereo.

    pixels_rear, pixels_front : (N, 2) float, matched pixels p1 (rear image 1) and p2 (front image 2).
    step_mm : float, C1 -> C2 distance along the common optical axis.
    Returns (N, 3) float, mm, the point in the front camera frame.

    With normalised (undistorted) radii ``r1 = |p1 - O1| / f`` and ``r2 = |p2' - O1| / f``, eq. 7.3 gives the
    depth from the front camera ``Z = r1 / (r2 - r1) * step`` and eq. 7.4 ``(X, Y) = p2 / f * Z``. The
    radii are normalised with the calibrated focal length, i.e. the equations are applied to
    distortion-corrected pixels, as sec. 9.2 prescribes.
    """
    if not step_mm > 0:
        raise InputError(f"axial step must be positive, got {step_mm} mm")
    n1 = camera.pixel_to_normalised(np.asarray(pixels_rear, dtype=float).reshape(-1, 2))
    n2 = camera.pixel_to_normalised(np.asarray(pixels_front, dtype=float).reshape(-1, 2))
    r1 = np.linalg.norm(n1, axis=1)
    r2 = np.linalg.norm(n2, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = r1 / (r2 - r1) * step_mm  # eq. 7.3
    return np.concatenate([n2 * z[:, None], z[:, None]], axis=1)  # eq. 7.4


def triangulate_rays(
    camera: Camera, pose_1: Pose, pose_2: Pose, pixels_1: np.ndarray, pixels_2: np.ndarray
) -> np.ndarray:
    """General two-view triangulation: midpoint of the shortest segment between the two pixel rays
    (:func:`scope3d.geometry.triangulation.triangulate_midpoint`).

    pixels_1, pixels_2 : (N, 2) matched pixels in the cameras at ``pose_1`` and ``pose_2``.
    Returns (N, 3) world points, mm; NaN for (nearly) parallel rays.
    """
    o1, d1 = camera.pixel_rays_world(pose_1, np.asarray(pixels_1, dtype=float).reshape(-1, 2))
    o2, d2 = camera.pixel_rays_world(pose_2, np.asarray(pixels_2, dtype=float).reshape(-1, 2))
    n = len(o1)
    return triangulate_midpoint(np.concatenate([o1, o2]), np.concatenate([d1, d2]), np.tile(np.arange(n), 2), n)
