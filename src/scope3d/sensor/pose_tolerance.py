"""Poses as a robot reports them: a measurement with a tolerance, and models of its error.

A :class:`PoseTolerance` bounds how far the true pose (:class:`scope3d.geometry.pose.Pose`) may lie
from the measured one: per world axis on the camera centre (mm), and per axis on a small rotation ``w``
(rad) applied on the left of the measured orientation, ``R_true = exp([w]x) @ R_measured``. Both are
boxes, which is what bound-constrained bundle adjustment (reference eq. 6.2) needs. The ``perturb_*``
functions draw measured poses from true ones under a noise model (uniform, bias, drift) with a seed.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import (
    matrix_to_rotvec,
    rotvec_to_matrix,
)


@dataclass(frozen=True)
class PoseTolerance:
    """Half-widths of the box in which the true pose lies around a measured one.

    position_mm : (3,) float, per world axis, on the camera centre. 0 = exact, inf = unknown.
    orientation_rad : (3,) float, per axis of the left rotation ``w`` with
        ``R_true = exp([w]x) @ R_measured``. 0 = exact, inf = unknown.
    """

    position_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    orientation_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        p = np.broadcast_to(np.asarray(self.position_mm, dtype=float), (3,)).copy()
        o = np.broadcast_to(np.asarray(self.orientation_rad, dtype=float), (3,)).copy()
        if np.any(np.isnan(p)) or np.any(np.isnan(o)):
            raise ValueError("pose tolerance has NaN values")
        if np.any(p < 0) or np.any(o < 0):
            raise ValueError("pose tolerance must be non-negative (it is a half-width)")
        object.__setattr__(self, "position_mm", p)
        object.__setattr__(self, "orientation_rad", o)

    @classmethod
    def exact(cls) -> "PoseTolerance":
        return cls()

    @classmethod
    def unknown(cls) -> "PoseTolerance":
        return cls(np.full(3, np.inf), np.full(3, np.inf))

    @classmethod
    def from_degrees(cls, position_mm, orientation_deg) -> "PoseTolerance":
        return cls(position_mm, np.deg2rad(np.asarray(orientation_deg, dtype=float)))

    @property
    def orientation_deg(self) -> np.ndarray:
        return np.rad2deg(self.orientation_rad)

    @property
    def is_exact(self) -> bool:
        return bool(np.all(self.position_mm == 0) and np.all(self.orientation_rad == 0))


# Tolerances of the positioning devices named in the reference (chapters 4 and 6).
MICRO_STAGE = PoseTolerance.from_degrees(0.01, 0.0)


OPTICAL_TRACKER = PoseTolerance.from_degrees([0.2, 0.2, 0.5], 0.5)


CABLE_DRIVEN_ARM = PoseTolerance.from_degrees(3.0, 3.0)

# An uncalibrated six-axis industrial arm: absolute pose accuracy (ISO 9283) of about 0.5-1 mm at the flange
# over its working volume, about ten times its repeatability; the orientation to a few tenths of a degree.
INDUSTRIAL_ARM = PoseTolerance.from_degrees(1.0, 0.25)


@dataclass(frozen=True)
class RobotClass:
    """A named kind of positioning device and the tolerance it reports poses to, with where that comes from.
    A data sheet's figure for the user's own device is always better: give it as numbers instead."""

    name: str
    tolerance: "PoseTolerance"
    source: str


ROBOT_CLASSES = {
    c.name: c
    for c in (
        RobotClass("micro-stage", MICRO_STAGE, "micro-positioning stage, 0.01 mm (reference sec. 7.3, 8.3)"),
        RobotClass("optical-tracker", OPTICAL_TRACKER,
                   "optical tracker, 0.2, 0.2, 0.5 mm along world x, y, z, 0.5 deg (reference ch. 4, 6)"),
        RobotClass("industrial-arm", INDUSTRIAL_ARM,
                   "uncalibrated six-axis industrial arm, 1 mm, 0.25 deg: typical ISO 9283 absolute pose accuracy "
                   "(about ten times the repeatability a data sheet states)"),
        RobotClass("cable-driven-arm", CABLE_DRIVEN_ARM,
                   "cable-driven surgical arm without joint encoders (RAVEN II), 3 mm, 3 deg (reference ch. 3-4)"),
    )
}


@dataclass(frozen=True)
class MeasuredPose:
    """A pose as the robot or tracker reported it, with the tolerance of that report."""

    pose: Pose
    tolerance: PoseTolerance = field(default_factory=PoseTolerance.exact)

    def contains(self, true_pose: Pose, slack: float = 1e-9) -> bool:
        """Whether ``true_pose`` lies inside this measurement's tolerance box."""
        dc = np.abs(true_pose.centre - self.pose.centre)
        w = matrix_to_rotvec(true_pose.rotation @ self.pose.rotation.T)
        return bool(
            np.all(dc <= self.tolerance.position_mm + slack)
            and np.all(np.abs(w) <= self.tolerance.orientation_rad + slack)
        )


def perturb_poses_uniform(
    poses: list[Pose],
    position_mm: float | np.ndarray,
    orientation_rad: float | np.ndarray = 0.0,
    *,
    seed: int,
) -> list[MeasuredPose]:
    """Report each pose with independent uniform errors inside ±tolerance, and that tolerance.

    This is the reference's noise model (section 6.3: uniform on [-0.25, 0.25] mm per axis).
    """
    rng = np.random.default_rng(seed)
    tol = PoseTolerance(position_mm, orientation_rad)
    out = []
    for pose in poses:
        dc = rng.uniform(-1.0, 1.0, 3) * tol.position_mm
        w = rng.uniform(-1.0, 1.0, 3) * tol.orientation_rad
        rotation = rotvec_to_matrix(w) @ pose.rotation
        out.append(MeasuredPose(Pose.from_centre(rotation, pose.centre + dc), tol))
    return out


def perturb_poses_biased(
    poses: list[Pose],
    bias_mm: np.ndarray,
    bias_rad: np.ndarray,
    jitter_mm: float,
    jitter_rad: float,
    *,
    seed: int,
    tolerance: PoseTolerance | None = None,
) -> list[MeasuredPose]:
    """A fixed per-axis bias plus uniform jitter, like an uncalibrated cable-driven arm.

    The reported tolerance defaults to |bias| + jitter so that the truth stays inside the box.
    """
    rng = np.random.default_rng(seed)
    bias_mm = np.broadcast_to(np.asarray(bias_mm, float), (3,))
    bias_rad = np.broadcast_to(np.asarray(bias_rad, float), (3,))
    if tolerance is None:
        tolerance = PoseTolerance(np.abs(bias_mm) + jitter_mm, np.abs(bias_rad) + jitter_rad)
    out = []
    for pose in poses:
        dc = bias_mm + rng.uniform(-jitter_mm, jitter_mm, 3)
        w = bias_rad + rng.uniform(-jitter_rad, jitter_rad, 3)
        out.append(MeasuredPose(Pose.from_centre(rotvec_to_matrix(w) @ pose.rotation, pose.centre + dc), tolerance))
    return out


def perturb_poses_drift(
    poses: list[Pose],
    drift_mm_per_frame: np.ndarray,
    *,
    tolerance: PoseTolerance | None = None,
) -> list[MeasuredPose]:
    """Slow drift along a trajectory: frame i is off by ``i * drift`` (a stretching cable, say)."""
    drift = np.broadcast_to(np.asarray(drift_mm_per_frame, float), (3,))
    n = len(poses)
    if tolerance is None:
        tolerance = PoseTolerance(np.abs(drift) * max(n - 1, 0), 0.0)
    return [
        MeasuredPose(Pose.from_centre(p.rotation, p.centre + i * drift), tolerance) for i, p in enumerate(poses)
    ]
