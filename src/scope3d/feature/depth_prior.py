"""Where the scene may lie along each ray, and where a feature may appear in another frame."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.scene.surface import Surface
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import PoseTolerance


@dataclass(frozen=True)
class DepthPrior:
    """Range of z-depths (mm, camera frame, along the optical axis) at which the scene may lie.

    Plain data (it pickles, so cluster workers can receive it).

    near_mm, far_mm : float, 0 < near <= far. The overlap and the matcher's prediction use the
        geometric mean as the "expected" depth (the depth of the plane in the homography case).
    box_min_mm, box_max_mm : optional (3,) float, world mm: the scene lies in this box (a calibrated
        object's); each ray's range is where it crosses the box.
    band_surface, band_mm : optional :class:`~scope3d.scene.surface.Surface` and float mm: the scene lies
        within ``band_mm`` of this surface (a coarse one already reconstructed), measured along its normal.
    Per-ray ranges (:meth:`ray_ranges`) are NaN where the box or the surface says nothing (the global
    range is used there) and are clipped to [near_mm, far_mm] by the matcher.
    """

    near_mm: float
    far_mm: float
    box_min_mm: np.ndarray | None = field(default=None, compare=False)
    box_max_mm: np.ndarray | None = field(default=None, compare=False)
    band_surface: Surface | None = field(default=None, compare=False, repr=False)
    band_mm: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.near_mm) and np.isfinite(self.far_mm)) or not 0 < self.near_mm <= self.far_mm:
            raise ValueError(f"depth prior must satisfy 0 < near <= far, got [{self.near_mm}, {self.far_mm}] mm")
        if (self.box_min_mm is None) != (self.box_max_mm is None):
            raise ValueError("a depth prior's box needs both corners")
        if self.box_min_mm is not None and self.band_surface is not None:
            raise ValueError("a depth prior has a box or a surface band, not both")
        if not (np.isfinite(self.band_mm) and self.band_mm >= 0):
            raise ValueError(f"band_mm must be finite and >= 0, got {self.band_mm}")

    @property
    def mid_mm(self) -> float:
        return float(np.sqrt(self.near_mm * self.far_mm))

    @property
    def per_ray(self) -> bool:
        """True when :meth:`ray_ranges` knows more than the global range."""
        return self.box_min_mm is not None or self.band_surface is not None

    def with_band(self, surface: Surface, band_mm: float) -> "DepthPrior":
        """The same global range, each ray narrowed to ``band_mm`` about ``surface``."""
        return DepthPrior(self.near_mm, self.far_mm, band_surface=surface, band_mm=band_mm)

    def ray_ranges(self, pose: Pose, rays_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """z-depth range (near (N,), far (N,), mm) of each ray ``rays_cam`` (N, 3) (camera frame, z = 1)
        of a frame at ``pose``; NaN where nothing more than the global range is known."""
        rays = np.asarray(rays_cam, float).reshape(-1, 3)
        if self.box_min_mm is not None:
            return _box_ray_ranges(self.box_min_mm, self.box_max_mm, pose, rays)
        if self.band_surface is not None:
            z = self.band_surface.ray_depths(pose, rays)
            d = rays @ pose.rotation
            # moving the surface by band along n changes the ray's z-depth by band / |d . n|
            dz = self.band_mm / np.maximum(np.abs(d @ self.band_surface.axes[2]), 1e-3)
            return z - dz, z + dz
        nan = np.full(len(rays), np.nan)
        return nan, nan.copy()


def _box_ray_ranges(lo: np.ndarray, hi: np.ndarray, pose: Pose, rays_cam: np.ndarray):
    """Slab test: the z-depths (N,) at which each ray enters and leaves the box (NaN if it misses)."""
    d = rays_cam @ pose.rotation  # world direction per unit z-depth
    c = pose.centre
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - c) / d
        t2 = (hi - c) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    miss = ~(t_far >= np.maximum(t_near, 0.0))
    t_near[miss] = np.nan
    t_far[miss] = np.nan
    return np.maximum(t_near, 1e-3), t_far


def predict_segments(
    camera: Camera, pose_i: Pose, pose_j: Pose, keypoints_i: np.ndarray, depth_prior: DepthPrior
) -> tuple[np.ndarray, np.ndarray]:
    """Where features of frame i may appear in frame j.

    keypoints_i : (N, 2) pixels in frame i. Returns the two ends of each feature's epipolar segment in
    frame j, ``near_px`` and ``far_px``, (N, 2) each: the projections of the feature's ray at z-depths
    ``depth_prior.near_mm`` and ``depth_prior.far_mm`` (camera i), or the per-ray range of :meth:`DepthPrior.ray_ranges`. Ends
    behind camera j are NaN. With
    ``near == far`` both ends are the plane-induced homography's prediction ``H = K (R - t n^T / d) K^-1``
    (distortion included).
    """
    return _project_ray_ranges(camera, pose_i, pose_j, *_ray_depth_ranges(camera, pose_i, keypoints_i, depth_prior))


def _ray_depth_ranges(camera: Camera, pose_i: Pose, keypoints_i: np.ndarray, depth_prior: DepthPrior):
    """Rays (N, 3) (camera i, z = 1) of the keypoints and their z-depth ranges near, far (N,) mm.
    Depends on frame i only, so it is computed once per frame, not once per pair."""
    kp = np.asarray(keypoints_i, dtype=float).reshape(-1, 2)
    rays = camera.unproject(kp, np.ones(len(kp)))
    near = np.full(len(kp), depth_prior.near_mm)
    far = np.full(len(kp), depth_prior.far_mm)
    if depth_prior.per_ray:
        lo, hi = depth_prior.ray_ranges(pose_i, rays)
        known = np.isfinite(lo) & np.isfinite(hi)
        near[known] = np.clip(lo[known], depth_prior.near_mm, depth_prior.far_mm)
        far[known] = np.clip(hi[known], depth_prior.near_mm, depth_prior.far_mm)
    return rays, near, far


def _project_ray_ranges(camera: Camera, pose_i: Pose, pose_j: Pose, rays, near, far):
    """Both ends of each ray's depth range (camera i) projected into frame j, (N, 2) each."""
    ends = []
    for z in (near, far):
        x_world = (rays * z[:, None] - pose_i.translation) @ pose_i.rotation
        ends.append(camera.project_world(pose_j, x_world))
    return ends[0], ends[1]


def pose_error_px(camera: Camera, tolerance: PoseTolerance, depth_prior: DepthPrior | None) -> float:
    """How far (px) a pose error within ``tolerance`` can move the image of a point at the nearest depth.

    A centre error ``dp`` (mm, the box's half-diagonal) shifts a point at the nearest depth by
    ``f dp / z_near``; an orientation error ``dw`` (rad) by about ``f dw`` (small angles, near the image
    centre). 0 for an exact pose or without a depth prior; inf for an unknown (infinite) tolerance.
    """
    if depth_prior is None or tolerance.is_exact:
        return 0.0
    f = max(camera.fx, camera.fy)
    dp, dw = np.linalg.norm(tolerance.position_mm), np.linalg.norm(tolerance.orientation_rad)
    return float(f * dp / depth_prior.near_mm + f * dw) if np.isfinite(dp + dw) else float("inf")


def window_radius_px(camera: Camera, tolerance_i: PoseTolerance, tolerance_j: PoseTolerance, depth_prior: DepthPrior,
                     base_radius_px: float) -> float:
    """Search-window radius (px) that contains the true match given both poses' tolerance boxes: the base
    radius plus what each pose's error can move the point (:func:`pose_error_px`; the distortion-free
    worst case grows towards the image edge, covered by ``base_radius_px``)."""
    return float(base_radius_px + pose_error_px(camera, tolerance_i, depth_prior)
                 + pose_error_px(camera, tolerance_j, depth_prior))
