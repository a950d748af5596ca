"""A constant-velocity Kalman filter on a rigid pose, and the fusion of several pose sources through it.

The reference tracked the robot with two webcams and a Kalman filter (sec. 4.3.2, Table 4.1: 0.2 mm in x
and y, 0.5 mm in z), and proposed fusing the robot's reported pose, the tracker and vision into one
estimate (sec. 9.3.2). :class:`PoseKalmanFilter` is that filter:

* state: the pose (``w`` rad, the left rotation about world axes on the nominal orientation, and the
  centre ``C`` mm, the parametrisation of :class:`~scope3d.sensor.pose_tolerance.PoseTolerance`), and its
  rates (rad/s, mm/s); 12 scalars, an error state for the rotation (the nominal rotation absorbs ``w``
  after every step, so ``w`` stays small and the filter linear);
* motion: constant velocity, driven by white acceleration noise (the discrete Wiener process
  acceleration model, Bar-Shalom 2001, sec. 6.3.2);
* measurements: a full pose with its (6, 6) covariance — a tracker's fit, a localization's
  refinement, or a robot's report whose box of half-width ``a`` is a uniform error of sigma ``a/sqrt(3)``
  (:func:`tolerance_covariance`). Any number per step: sequential updates fuse them.

:func:`covariance_to_tolerance` turns the estimate back into the box bounded bundle adjustment needs.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import matrix_to_rotvec, rotvec_to_matrix
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance


@dataclass(frozen=True)
class KalmanOptions:
    """The motion model and the start.

    acceleration_sigma_mm_s2 : float, white acceleration noise on the centre (default 50 mm/s^2: a hand or
        a slow robot changes speed by a few mm/s within a tenth of a second).
    angular_acceleration_sigma_rad_s2 : float, on the orientation (default 0.5 rad/s^2, ~30 deg/s^2).
    initial_velocity_sigma_mm_s : float, initial_angular_velocity_sigma_rad_s : the start's rate
        uncertainty (defaults 20 mm/s, 0.3 rad/s); the start pose takes its first measurement's covariance.
    """

    acceleration_sigma_mm_s2: float = 50.0
    angular_acceleration_sigma_rad_s2: float = 0.5
    initial_velocity_sigma_mm_s: float = 20.0
    initial_angular_velocity_sigma_rad_s: float = 0.3

    def __post_init__(self) -> None:
        values = (self.acceleration_sigma_mm_s2, self.angular_acceleration_sigma_rad_s2,
                  self.initial_velocity_sigma_mm_s, self.initial_angular_velocity_sigma_rad_s)
        if not all(np.isfinite(v) and v > 0 for v in values):
            raise ValueError("Kalman noise levels must be positive and finite")


def tolerance_covariance(tolerance: PoseTolerance) -> np.ndarray:
    """(6, 6) diagonal covariance of ``(w, C)`` for a pose known within ``tolerance``'s box: a uniform error
    of half-width ``a`` has variance ``a^2 / 3``. Infinite half-widths give infinite variances."""
    half = np.concatenate([tolerance.orientation_rad, tolerance.position_mm])
    return np.diag(half**2 / 3.0)


def covariance_to_tolerance(covariance: np.ndarray, sigmas: float = 3.0) -> PoseTolerance:
    """The box of ``sigmas`` standard deviations per axis of a (6, 6) ``(w, C)`` covariance."""
    sd = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    return PoseTolerance(sigmas * sd[3:], sigmas * sd[:3])


class PoseKalmanFilter:
    """Constant-velocity filter on a pose (see the module docstring). Poses are ``cam_from_world`` (or any
    ``body_from_world``); the covariance is over ``(w rad, C mm, w' rad/s, C' mm/s)``."""

    def __init__(self, options: KalmanOptions = KalmanOptions()):
        self.options = options
        self._rotation: np.ndarray | None = None  # nominal cam_from_world rotation
        self.state = np.zeros(12)
        self.covariance = np.zeros((12, 12))

    @property
    def initialised(self) -> bool:
        return self._rotation is not None

    @property
    def pose(self) -> Pose:
        if self._rotation is None:
            raise ValueError("the filter has no estimate yet: update it with a measurement first")
        return Pose.from_centre(rotvec_to_matrix(self.state[:3]) @ self._rotation, self.state[3:6])

    @property
    def pose_covariance(self) -> np.ndarray:
        """(6, 6) covariance of ``(w, C)``."""
        return self.covariance[:6, :6].copy()

    def predict(self, dt_s: float) -> None:
        """Move the estimate ``dt_s`` seconds ahead at constant velocity; the covariance grows by the
        acceleration noise integrated over the interval."""
        if not self.initialised:
            return
        if not dt_s >= 0:
            raise ValueError(f"time step must be >= 0, got {dt_s}")
        f = np.eye(12)
        f[:6, 6:] = dt_s * np.eye(6)
        self.state = f @ self.state
        q_acc = np.r_[np.full(3, self.options.angular_acceleration_sigma_rad_s2 ** 2),
                      np.full(3, self.options.acceleration_sigma_mm_s2 ** 2)]
        q = np.zeros((12, 12))
        q[:6, :6] = np.diag(q_acc * dt_s**4 / 4.0)
        q[:6, 6:] = q[6:, :6] = np.diag(q_acc * dt_s**3 / 2.0)
        q[6:, 6:] = np.diag(q_acc * dt_s**2)
        self.covariance = f @ self.covariance @ f.T + q
        self._absorb_rotation()

    def update(self, pose: Pose, covariance: np.ndarray) -> None:
        """Fuse one measured pose with its (6, 6) ``(w, C)`` covariance (infinite variances: that scalar
        is not measured). The first measurement initialises the filter."""
        covariance = np.asarray(covariance, float)
        if covariance.shape != (6, 6):
            raise ValueError(f"measurement covariance must be (6, 6), got {covariance.shape}")
        measured = np.isfinite(np.diag(covariance))
        if not self.initialised:
            self._rotation = pose.rotation.copy()
            self.state = np.r_[np.zeros(3), pose.centre, np.zeros(6)]
            big = 1e12  # an unmeasured scalar starts unknown
            p0 = np.where(np.outer(measured, measured), np.nan_to_num(covariance, posinf=big), 0.0)
            p0[~measured, ~measured] = big
            self.covariance = np.zeros((12, 12))
            self.covariance[:6, :6] = p0
            self.covariance[6:, 6:] = np.diag(np.r_[np.full(3, self.options.initial_angular_velocity_sigma_rad_s ** 2),
                                                    np.full(3, self.options.initial_velocity_sigma_mm_s ** 2)])
            return
        if not np.any(measured):
            return
        idx = np.flatnonzero(measured)
        # innovation in the filter's parametrisation: the left rotation from the estimate to the measurement
        residual = np.r_[matrix_to_rotvec(pose.rotation @ self.pose.rotation.T), pose.centre - self.state[3:6]]
        h = np.zeros((len(idx), 12))
        h[np.arange(len(idx)), idx] = 1.0
        s = h @ self.covariance @ h.T + covariance[np.ix_(idx, idx)]
        gain = np.linalg.solve(s, h @ self.covariance).T
        self.state = self.state + gain @ residual[idx]
        joseph = np.eye(12) - gain @ h  # Joseph form: stays symmetric and positive
        self.covariance = joseph @ self.covariance @ joseph.T + gain @ covariance[np.ix_(idx, idx)] @ gain.T
        self._absorb_rotation()

    def change_world(self, new_from_old: Pose) -> None:
        """Express the estimate in another world frame (a live map whose adjustment moved it): the pose becomes
        ``pose @ new_from_old.inverse()``; the centre and its velocity turn and move with the frame, the
        rotation error and rate (on the camera's side of the nominal rotation) stay. Without this a moved
        map's first image pose would read as a jump, and the filter would take it for a velocity."""
        if not self.initialised:
            return
        rt = new_from_old.rotation
        self._rotation = self._rotation @ rt.T
        self.state[3:6] = rt @ self.state[3:6] + new_from_old.translation
        self.state[9:12] = rt @ self.state[9:12]
        j = np.eye(12)
        j[3:6, 3:6] = rt
        j[9:12, 9:12] = rt
        self.covariance = j @ self.covariance @ j.T

    def update_measured(self, measured: MeasuredPose) -> None:
        """Fuse a robot's report: its tolerance box as a uniform error (:func:`tolerance_covariance`)."""
        self.update(measured.pose, tolerance_covariance(measured.tolerance))

    def _absorb_rotation(self) -> None:
        """Move ``w`` into the nominal rotation (``w`` back to 0; to first order the covariance is unchanged)."""
        self._rotation = rotvec_to_matrix(self.state[:3]) @ self._rotation
        self.state[:3] = 0.0
