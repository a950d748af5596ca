"""Rigid camera poses.

A :class:`Pose` is the transform ``cam_from_world``: a point ``x_world`` (mm) is seen by the camera at
``x_cam = R @ x_world + t``. The camera centre in the world is ``C = -R.T @ t``. The camera looks
along its +z axis, x to the right of the image and y down (OpenCV / COLMAP convention).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scope3d.geometry.rotation import (
    matrix_to_quaternion,
    matrix_to_rotvec,
    quaternion_to_matrix,
    rotation_angle_between,
    rotvec_to_matrix,
    slerp_rotations,
)


@dataclass(frozen=True)
class Pose:
    """Rigid transform ``cam_from_world``.

    rotation : (3, 3) float, orthonormal, det +1.
    translation : (3,) float, mm.
    """

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, dtype=float).reshape(3, 3)
        t = np.asarray(self.translation, dtype=float).reshape(3)
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(t))):
            raise ValueError("pose has NaN or infinite values")
        if np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0:
            raise ValueError("pose rotation is not a proper rotation matrix")
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation", t)

    # --- constructors -------------------------------------------------------------------------
    @classmethod
    def identity(cls) -> "Pose":
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_rotvec(cls, rotvec: np.ndarray, translation: np.ndarray) -> "Pose":
        """rotvec : (3,) rad; translation : (3,) mm."""
        return cls(rotvec_to_matrix(rotvec), translation)

    @classmethod
    def from_quaternion(cls, quat_xyzw: np.ndarray, translation: np.ndarray) -> "Pose":
        return cls(quaternion_to_matrix(quat_xyzw), translation)

    @classmethod
    def from_centre(cls, rotation: np.ndarray, centre_mm: np.ndarray) -> "Pose":
        """Pose of a camera with orientation ``rotation`` (cam_from_world) whose centre is ``centre_mm``."""
        rotation = np.asarray(rotation, dtype=float)
        return cls(rotation, -rotation @ np.asarray(centre_mm, dtype=float))

    # --- views ----------------------------------------------------------------------------------
    @property
    def rotvec(self) -> np.ndarray:
        return matrix_to_rotvec(self.rotation)

    @property
    def quaternion(self) -> np.ndarray:
        """(4,) scalar-last (x, y, z, w)."""
        return matrix_to_quaternion(self.rotation)

    @property
    def centre(self) -> np.ndarray:
        """Camera centre in the world, (3,) mm."""
        return -self.rotation.T @ self.translation

    @property
    def optical_axis(self) -> np.ndarray:
        """Viewing direction (+z of the camera) in world coordinates, unit (3,)."""
        return self.rotation[2].copy()

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.translation
        return m

    # --- algebra ------------------------------------------------------------------------------
    def transform(self, points_world: np.ndarray) -> np.ndarray:
        """points_world : (N, 3) mm -> points in camera frame (N, 3) mm."""
        return np.asarray(points_world, dtype=float) @ self.rotation.T + self.translation

    def inverse(self) -> "Pose":
        return Pose(self.rotation.T, -self.rotation.T @ self.translation)

    def compose(self, other: "Pose") -> "Pose":
        """``self ∘ other``: apply ``other`` first. If other is b_from_a and self is c_from_b, gives c_from_a."""
        return Pose(self.rotation @ other.rotation, self.rotation @ other.translation + self.translation)

    def __matmul__(self, other: "Pose") -> "Pose":
        return self.compose(other)

    def interpolate(self, other: "Pose", fraction: float) -> "Pose":
        """Pose part-way to ``other``: slerp on orientation, linear on the camera centre."""
        rotation = slerp_rotations(self.rotation, other.rotation, fraction)
        centre = (1.0 - fraction) * self.centre + fraction * other.centre
        return Pose.from_centre(rotation, centre)

    def distance_to(self, other: "Pose") -> tuple[float, float]:
        """(centre distance in mm, orientation difference in rad)."""
        return (
            float(np.linalg.norm(self.centre - other.centre)),
            float(rotation_angle_between(self.rotation, other.rotation)),
        )
