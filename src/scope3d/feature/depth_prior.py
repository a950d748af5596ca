"""Where the scene may lie along each ray, and where a feature may appear in another frame."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import PoseTolerance


@dataclass(frozen=True)
class DepthPrior:
    """Range of z-depths (mm, camera frame, along the optical axis) at which the scene may lie.

    near_mm, far_mm : float, 0 < near <= far. The overlap and the matcher's prediction use the
    geometric mean as the "expected" depth (the depth of the plane in the homography case).
    per_ray : optional callable ``per_ray(pose, rays_cam) -> (near (N,), far (N,))`` giving a tighter
        z-depth range (mm) for each ray ``rays_cam`` (N, 3) (camera frame, z = 1) of a frame at
        ``pose`` — e.g. the band around a coarse surface already reconstructed; NaN where it knows
        nothing (the global range is used there). Ranges are clipped to [near_mm, far_mm].
    """

    near_mm: float
    far_mm: float
    per_ray: object = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.near_mm) and np.isfinite(self.far_mm)) or not 0 < self.near_mm <= self.far_mm:
            raise ValueError(f"depth prior must satisfy 0 < near <= far, got [{self.near_mm}, {self.far_mm}] mm")

    @property
    def mid_mm(self) -> float:
        return float(np.sqrt(self.near_mm * self.far_mm))


def predict_segments(
    camera: Camera, pose_i: Pose, pose_j: Pose, keypoints_i: np.ndarray, depth: DepthPrior
) -> tuple[np.ndarray, np.ndarray]:
    """Where features of frame i may appear in frame j.

    keypoints_i : (N, 2) pixels in frame i. Returns the two ends of each feature's epipolar segment in
    frame j, ``near_px`` and ``far_px``, (N, 2) each: the projections of the feature's ray at z-depths
    ``depth.near_mm`` and ``depth.far_mm`` (camera i), or the per-ray range of ``depth.per_ray``. Ends
    behind camera j are NaN. With
    ``near == far`` both ends are the plane-induced homography's prediction ``H = K (R - t n^T / d) K^-1``
    (distortion included).
    """
    return _project_ray_ranges(camera, pose_i, pose_j, *_ray_depth_ranges(camera, pose_i, keypoints_i, depth))


def _ray_depth_ranges(camera: Camera, pose_i: Pose, keypoints_i: np.ndarray, depth: DepthPrior):
    """Rays (N, 3) (camera i, z = 1) of the keypoints and their z-depth ranges near, far (N,) mm.
    Depends on frame i only, so it is computed once per frame, not once per pair."""
    kp = np.asarray(keypoints_i, dtype=float).reshape(-1, 2)
    rays = camera.unproject(kp, np.ones(len(kp)))
    near = np.full(len(kp), depth.near_mm)
    far = np.full(len(kp), depth.far_mm)
    if depth.per_ray is not None:
        lo, hi = depth.per_ray(pose_i, rays)
        known = np.isfinite(lo) & np.isfinite(hi)
        near[known] = np.clip(lo[known], depth.near_mm, depth.far_mm)
        far[known] = np.clip(hi[known], depth.near_mm, depth.far_mm)
    return rays, near, far


def _project_ray_ranges(camera: Camera, pose_i: Pose, pose_j: Pose, rays, near, far):
    """Both ends of each ray's depth range (camera i) projected into frame j, (N, 2) each."""
    ends = []
    for z in (near, far):
        x_world = (rays * z[:, None] - pose_i.translation) @ pose_i.rotation
        ends.append(camera.project_world(pose_j, x_world))
    return ends[0], ends[1]


def window_radius_px(
    camera: Camera, tolerance_i: PoseTolerance, tolerance_j: PoseTolerance, depth: DepthPrior, base_radius_px: float
) -> float:
    """Search-window radius (px) that contains the true match given both poses' tolerance boxes.

    A centre error ``dp`` (mm, the box's half-diagonal, both frames) shifts a point at the nearest depth
    by ``f dp / z_near``; an orientation error ``dw`` (rad) by about ``f dw`` (small angles, near the
    image centre; the distortion-free worst case grows towards the edge, covered by ``base_radius_px``).
    """
    f = max(camera.fx, camera.fy)
    dp = np.linalg.norm(tolerance_i.position_mm) + np.linalg.norm(tolerance_j.position_mm)
    dw = np.linalg.norm(tolerance_i.orientation_rad) + np.linalg.norm(tolerance_j.orientation_rad)
    if not np.isfinite(dp + dw):
        return float("inf")
    return float(base_radius_px + f * dp / depth.near_mm + f * dw)
