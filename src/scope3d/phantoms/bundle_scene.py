"""Synthetic bundle adjustment scenes with known truth, BAL-like in structure: the phantom lab's scene for
bundle adjustment (tests, benchmarks and :func:`scope3d.estimators.bundle.warm_up`).

Cameras stand in a row along the world x axis (spacing ``baseline_mm``), looking along +z with a small
random tilt; each point is seen by ``observations_per_point`` consecutive cameras, like a vehicle's
image sequence in the BAL data. Units are mm and pixels.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scope3d.geometry.rotation import rotvec_to_matrix


@dataclass
class SyntheticScene:
    """Ground truth and observations.

    rotations : (m, 3, 3) cam_from_world. translations : (m, 3) mm. points : (n, 3) mm.
    intrinsics : (6,) shared ``(fx, fy, cx, cy, k1, k2)``.
    observations_px : (K, 2). camera_index, point_index : (K,).
    """

    rotations: np.ndarray
    translations: np.ndarray
    points: np.ndarray
    intrinsics: np.ndarray
    observations_px: np.ndarray
    camera_index: np.ndarray
    point_index: np.ndarray

    @property
    def centres(self) -> np.ndarray:
        """(m, 3) mm camera centres."""
        return -np.einsum("mji,mj->mi", self.rotations, self.translations)


def make_scene(
    num_cameras: int,
    num_points: int,
    *,
    observations_per_point: int = 4,
    pixel_noise_px: float = 0.0,
    baseline_mm: float = 1.0,
    depth_mm: tuple[float, float] = (8.0, 12.0),
    tilt_rad: float = 0.02,
    intrinsics: np.ndarray | None = None,
    seed: int = 0,
) -> SyntheticScene:
    """A row of cameras over a field of points, each point seen by consecutive cameras.

    With the default intrinsics (500 px focal length on a 640 x 480 image) every point projects inside
    every image that observes it.
    """
    rng = np.random.default_rng(seed)
    k = int(min(observations_per_point, num_cameras))
    if k < 2:
        raise ValueError("need at least two cameras and two observations per point")
    intr = np.array([500.0, 505.0, 320.0, 240.0, -0.05, 0.01]) if intrinsics is None else np.asarray(intrinsics, float)
    centres = np.column_stack([baseline_mm * np.arange(num_cameras), np.zeros(num_cameras), np.zeros(num_cameras)])
    rotations = rotvec_to_matrix(rng.uniform(-tilt_rad, tilt_rad, (num_cameras, 3)))
    translations = -np.einsum("mij,mj->mi", rotations, centres)
    first = rng.integers(0, num_cameras - k + 1, num_points)
    mid_x = baseline_mm * (first + (k - 1) / 2.0)
    depth = rng.uniform(*depth_mm, num_points)
    points = np.column_stack([
        mid_x + rng.uniform(-0.5, 0.5, num_points) * baseline_mm,
        rng.uniform(-0.2, 0.2, num_points) * depth,
        depth,
    ])
    camera_index = (first[:, None] + np.arange(k)[None, :]).ravel()
    point_index = np.repeat(np.arange(num_points), k)
    p_cam = np.einsum("kij,kj->ki", rotations[camera_index], points[point_index]) + translations[camera_index]
    xy = p_cam[:, :2] / p_cam[:, 2:3]
    r2 = np.sum(xy * xy, axis=1, keepdims=True)
    xy_d = xy * (1.0 + intr[4] * r2 + intr[5] * r2 * r2)
    obs = np.column_stack([intr[0] * xy_d[:, 0] + intr[2], intr[1] * xy_d[:, 1] + intr[3]])
    if pixel_noise_px:
        obs = obs + rng.normal(0.0, pixel_noise_px, obs.shape)
    return SyntheticScene(rotations, translations, points, intr, obs, camera_index, point_index)
