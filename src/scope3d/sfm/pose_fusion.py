"""Fused pose bounds for the surgical map: robot, tracker and vision through one Kalman filter, into BCBA.

The reference proposed closing the loop between a Kalman filter and bundle adjustment (sec. 9.3.2): every
source of a frame's pose - the robot's report with its tolerance box, a marker tracker's fit, the frame
localized against an earlier map - is fused by :class:`~scope3d.estimators.kalman.PoseKalmanFilter`, and
the fused covariance becomes the box (:func:`~scope3d.estimators.kalman.covariance_to_tolerance`) that the
map's bounded bundle adjustment keeps each pose in. A tighter box pins the map's similarity gauge closer
to the truth than the robot's box does.

* :func:`vision_poses` — a dataset's frames localized against a map (:class:`~scope3d.sfm.localization.Localizer`),
  each as a :class:`PoseEstimate` whose covariance adds the map's own placement error to the frame's
  (the localization only knows the pose relative to the map).
* :func:`fuse_poses` — per frame, the robot's report and any number of other estimates fused; returns
  the :class:`~scope3d.sensor.pose_tolerance.MeasuredPose` list a :class:`~scope3d.io.dataset.Dataset`
  carries, ready for ``dataclasses.replace(dataset, poses=...)`` and :func:`scope3d.pipelines.surgical_map.run`.

Units: mm and radians; covariances over ``(w rad, C mm)`` (left rotation about the world axes, centre).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scope3d.estimators.kalman import KalmanOptions, PoseKalmanFilter, covariance_to_tolerance
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import matrix_to_rotvec, rotvec_to_matrix
from scope3d.io.dataset import Dataset
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.localization import Localizer


@dataclass(frozen=True)
class PoseEstimate:
    """One source's estimate of a frame's ``cam_from_world`` pose, with its (6, 6) ``(w, C)`` covariance."""

    pose: Pose
    covariance: np.ndarray


@dataclass(frozen=True)
class FusionOptions:
    """How pose sources are fused into bounds.

    kalman : the filter's motion model (:class:`~scope3d.estimators.kalman.KalmanOptions`).
    frame_interval_s : float or None, time between frames for the constant-velocity model; None (default)
        fuses every frame on its own (a survey that stops at every view, or frames without times: the
        motion model would only smear independent views).
    tolerance_sigmas : float, the fused box's half-width in standard deviations per scalar (default 3:
        99.7 % of a Gaussian error inside).
    within_reported_box : bool, cut the fused box down to its intersection with the robot's (default True:
        the robot's tolerance is a hard bound, and 3 sigma of a fused Gaussian can reach beyond it where
        another source is vaguer than the robot, e.g. a tracker's 0.5 deg against the robot's +-0.5 deg box;
        measured on the dome, the map's orientation got 2.5x worse without the cut).
    """

    kalman: KalmanOptions = field(default_factory=KalmanOptions)
    frame_interval_s: float | None = None
    tolerance_sigmas: float = 3.0
    within_reported_box: bool = True

    def __post_init__(self) -> None:
        if self.frame_interval_s is not None and not self.frame_interval_s > 0:
            raise ValueError(f"frame_interval_s must be positive or None, got {self.frame_interval_s}")
        if not self.tolerance_sigmas > 0:
            raise ValueError(f"tolerance_sigmas must be positive, got {self.tolerance_sigmas}")


def fuse_poses(reported: list[MeasuredPose], others: list[list[PoseEstimate | None]],
               *,
               options: FusionOptions = FusionOptions()) -> list[MeasuredPose]:
    """Per frame, the robot's ``reported`` pose (its box a uniform error) fused with every other source's
    estimate of that frame (``others[s][k]``; None where source ``s`` has none for frame ``k``).

    Returns one :class:`MeasuredPose` per frame: the fused pose and the box of ``options.tolerance_sigmas``
    standard deviations of its covariance (cut to the robot's box, :func:`intersect_boxes`, by default).
    """
    for s, source in enumerate(others):
        if len(source) != len(reported):
            raise ValueError(f"source {s} has {len(source)} estimates for {len(reported)} frames")
    fused = []
    kf = PoseKalmanFilter(options.kalman)
    for k, report in enumerate(reported):
        if options.frame_interval_s is None:
            kf = PoseKalmanFilter(options.kalman)  # every frame on its own
        elif k:
            kf.predict(options.frame_interval_s)
        kf.update_measured(report)
        for source in others:
            if source[k] is not None:
                kf.update(source[k].pose, source[k].covariance)
        box = MeasuredPose(kf.pose, covariance_to_tolerance(kf.pose_covariance, options.tolerance_sigmas))
        fused.append(intersect_boxes(box, report) if options.within_reported_box else box)
    return fused


def intersect_boxes(a: MeasuredPose, b: MeasuredPose) -> MeasuredPose:
    """The box of poses inside both ``a``'s and ``b``'s tolerance boxes, centred on its middle (in ``a``'s
    parametrisation: a left rotation about the world axes and the centre). Where the two do not overlap on a
    scalar (the sources disagree beyond both boxes), ``a``'s interval is kept: there is no pose to prefer."""
    half_a = np.r_[a.tolerance.orientation_rad, a.tolerance.position_mm]
    half_b = np.r_[b.tolerance.orientation_rad, b.tolerance.position_mm]
    offset = np.r_[matrix_to_rotvec(b.pose.rotation @ a.pose.rotation.T), b.pose.centre - a.pose.centre]
    lower, upper = np.maximum(-half_a, offset - half_b), np.minimum(half_a, offset + half_b)
    disjoint = lower > upper
    lower[disjoint], upper[disjoint] = -half_a[disjoint], half_a[disjoint]
    middle, half = (lower + upper) / 2, (upper - lower) / 2
    pose = Pose.from_centre(rotvec_to_matrix(middle[:3]) @ a.pose.rotation, a.pose.centre + middle[3:])
    return MeasuredPose(pose, PoseTolerance(half[3:], half[:3]))


def vision_poses(localizer: Localizer, dataset: Dataset, *, blocked: np.ndarray | None = None,
                 map_position_sigma_mm: float = 0.0, map_orientation_sigma_rad: float = 0.0
                 ) -> list[PoseEstimate | None]:
    """Every frame of ``dataset`` localized against ``localizer``'s map, from its image and reported pose.

    map_position_sigma_mm, map_orientation_sigma_rad : the map's own placement error (a map adjusted inside
        N independent boxes of sigma is placed to about sigma / sqrt(N); a micro-stage map to its stage's
        tolerance), added to every frame's covariance: the frames share it, and a filter told only the
        frame's own covariance would trust the map's error as if it were the truth.
    Returns a :class:`PoseEstimate` per frame, None where the frame could not be localized.
    """
    extra = np.diag(np.r_[np.full(3, map_orientation_sigma_rad**2), np.full(3, map_position_sigma_mm**2)])
    out: list[PoseEstimate | None] = []
    for k in range(len(dataset)):
        r = localizer.localize(dataset.frame(k), dataset.poses[k], blocked=blocked)
        out.append(PoseEstimate(r.pose, r.covariance + extra) if r.ok else None)
    return out
