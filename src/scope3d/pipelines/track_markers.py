"""Marker tracking, as ``scope3d track-markers`` runs it (reference sec. 4.3.2: a marker plate on the robot,
tracked optically, de-noised by a Kalman filter).

Method, run top to bottom by :func:`run`:

1. :func:`scope3d.io.tracker.read_tracker` — the export, rows that are not OK kept out of every fit.
2. :func:`scope3d.estimators.marker_plate.plate_geometry` — the plate's markers in its own frame.
3. :func:`track` — per frame, the plate's rigid pose from its visible markers (three or more), fused by a
   constant-velocity :class:`~scope3d.estimators.kalman.PoseKalmanFilter`; a frame with too few markers is
   predicted, not fitted, and flagged. A plate-to-camera (hand-eye) transform turns each pose into the
   camera's.
4. :func:`write_outputs` — ``poses.csv`` (one row per frame of the export, in order; tolerance
   ``tolerance_sigmas`` standard deviations of the filter's covariance), ``report.json``: ``n_frames``,
   ``n_fitted``, ``n_predicted``, and where the tracker reported its own tool pose, the agreement with it
   after the one constant transform between the two tool definitions.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.estimators.kalman import KalmanOptions, PoseKalmanFilter, covariance_to_tolerance
from scope3d.estimators.marker_plate import fit_plate_pose, plate_geometry
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import quaternion_to_matrix, rotation_angle_between
from scope3d.io.poses_csv import format_poses_csv
from scope3d.io.tracker import TrackerRecording, read_tracker
from scope3d.sensor.pose_tolerance import MeasuredPose
from scope3d.utils.atomic import atomic_directory
from scope3d.utils.jsonio import write_json
from scope3d.utils.progress import Progress, advance, stage


@dataclass(frozen=True)
class TrackMarkersOptions:
    """rate_hz : the tracker's frame rate (default 60 Hz, NDI Polaris); the time step is the frame-number
        difference over it. marker_sigma_mm : a marker position's noise per axis (default 0.25 mm, the
        RMS volumetric accuracy NDI states for Polaris Spectra). kalman : the motion model.
    cam_from_plate : the hand-eye transform, or None (the plate's own pose is written).
    tolerance_sigmas : standard deviations in the written tolerance (default 3).
    filter : bool, smooth through the Kalman filter (default True; False writes the raw fits, and frames
        without a fit are then left without a pose).
    """

    rate_hz: float = 60.0
    marker_sigma_mm: float = 0.25
    kalman: KalmanOptions = field(default_factory=KalmanOptions)
    cam_from_plate: Pose | None = None
    tolerance_sigmas: float = 3.0
    filter: bool = True

    def __post_init__(self) -> None:
        if not (self.rate_hz > 0 and self.marker_sigma_mm > 0 and self.tolerance_sigmas > 0):
            raise ValueError("rate_hz, marker_sigma_mm and tolerance_sigmas must be positive")


@dataclass
class TrackMarkersResult:
    """poses : per frame, the filtered (or raw) pose with its tolerance, None where none exists.
    fitted : (F,) bool, the frame's markers gave a fit. report : as written."""

    poses: list[MeasuredPose | None]
    fitted: np.ndarray
    raw: list[Pose | None]
    report: dict = field(default_factory=dict)

    def summary(self) -> str:
        r = self.report
        line = f"{r['n_frames']} frames: {r['n_fitted']} fitted, {r['n_predicted']} predicted"
        if r.get("median_position_diff_mm") is not None:
            line += (f"; against the tracker's tool pose: median {r['median_position_diff_mm']:.3f} mm, "
                     f"{r['median_orientation_diff_deg']:.3f} deg")
        return line


def track(recording: TrackerRecording, options: TrackMarkersOptions, *,
          progress: Progress | None = None) -> TrackMarkersResult:
    """Fit, filter and predict every frame (see the module docstring); progress counts frames."""
    try:
        geometry = plate_geometry(recording.markers_mm)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    kf = PoseKalmanFilter(options.kalman)
    poses: list[MeasuredPose | None] = []
    raw: list[Pose | None] = []
    fitted = np.zeros(len(recording), bool)
    previous = None
    stage(progress, "tracking markers", len(recording))
    for k in range(len(recording)):
        advance(progress)
        if previous is not None:
            dt = (recording.frame[k] - previous) / options.rate_hz
            if dt < 0:
                raise InputError(f"row {recording.rows[k]}: frame {recording.frame[k]} comes before frame {previous}")
            kf.predict(dt)
        previous = recording.frame[k]
        fit = fit_plate_pose(geometry, recording.markers_mm[k], options.marker_sigma_mm)
        raw.append(None if fit is None else fit[0])
        if fit is not None:
            fitted[k] = True
            kf.update(*fit)
        if options.filter and kf.initialised:
            pose, cov = kf.pose, kf.pose_covariance
        elif fit is not None:
            pose, cov = fit
        else:
            poses.append(None)
            continue
        if options.cam_from_plate is not None:
            pose = options.cam_from_plate @ pose
        poses.append(MeasuredPose(pose, covariance_to_tolerance(cov, options.tolerance_sigmas)))
    return TrackMarkersResult(poses, fitted, raw)


def agreement_with_tool(recording: TrackerRecording, poses: list[Pose | None]) -> dict:
    """Median position and orientation difference between our ``plate_from_tracker`` poses and the
    tracker's own ``tracker_from_tool``, after the one constant ``plate_from_tool`` transform (the average
    of its per-frame values: rotations by the chordal mean, positions by the mean)."""
    both = [k for k in range(len(recording)) if recording.tool_ok[k] and poses[k] is not None]
    if not both:
        return {}
    tool = {}  # tool_from_tracker per frame, from the tracker's tracker_from_tool (quaternion scalar first)
    for k in both:
        q = recording.tool_quaternion_wxyz[k]
        tracker_from_tool = Pose(quaternion_to_matrix(q[[1, 2, 3, 0]] / np.linalg.norm(q)),
                                 recording.tool_translation_mm[k])
        tool[k] = tracker_from_tool.inverse()
    # plate_from_tool = plate_from_tracker @ tracker_from_tool, constant if both track the same body
    constant = [poses[k] @ tool[k].inverse() for k in both]
    u, _, vt = np.linalg.svd(np.sum([c.rotation for c in constant], axis=0))
    rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    plate_from_tool = Pose(rotation, np.mean([c.translation for c in constant], axis=0))
    d_mm, d_deg = [], []
    for k in both:
        predicted = plate_from_tool @ tool[k]  # plate_from_tracker from the tracker's own tool pose
        d_mm.append(float(np.linalg.norm(predicted.centre - poses[k].centre)))
        d_deg.append(float(np.rad2deg(rotation_angle_between(predicted.rotation, poses[k].rotation))))
    return {"n_compared": len(both), "median_position_diff_mm": float(np.median(d_mm)),
            "median_orientation_diff_deg": float(np.median(d_deg)),
            "max_position_diff_mm": float(np.max(d_mm)), "max_orientation_diff_deg": float(np.max(d_deg))}


def write_outputs(recording: TrackerRecording, result: TrackMarkersResult, options: TrackMarkersOptions, source: Path,
                  out_dir: Path) -> dict:
    """poses.csv (frames with a pose, in order) and report.json into ``out_dir`` (a temporary folder)."""
    names = [f"{f:06d}" for f in recording.frame]
    have = [k for k, p in enumerate(result.poses) if p is not None]
    (out_dir / "poses.csv").write_text(format_poses_csv([names[k] for k in have], [result.poses[k] for k in have]))
    plate = [p.pose if p is not None else None for p in result.poses]
    if options.cam_from_plate is not None:
        plate = [None if p is None else options.cam_from_plate.inverse() @ p for p in plate]
    report = {
        "tracker_file": str(source), "n_frames": len(recording), "n_fitted": int(result.fitted.sum()),
        "n_predicted": int(sum(1 for k in range(len(recording)) if not result.fitted[k] and result.poses[k] is not None)),
        "n_without_pose": int(sum(p is None for p in result.poses)),
        "n_tool_ok": int(recording.tool_ok.sum()), "n_markers": recording.n_markers, "filtered": options.filter,
        "rate_hz": options.rate_hz, "marker_sigma_mm": options.marker_sigma_mm,
        "frames": [{"frame": int(recording.frame[k]), "fitted": bool(result.fitted[k]),
                    "predicted": bool(not result.fitted[k] and result.poses[k] is not None)} for k in range(len(recording))],
    }
    report.update(agreement_with_tool(recording, plate))
    write_json(out_dir / "report.json", report)
    return report


def run(options: TrackMarkersOptions, tracker_file: str | Path, out_dir: str | Path, *,
        progress: Progress | None = None) -> TrackMarkersResult:
    """Track the plate through ``tracker_file`` and write ``poses.csv`` and ``report.json`` into ``out_dir``
    (atomically)."""
    recording = read_tracker(tracker_file)
    result = track(recording, options, progress=progress)
    with atomic_directory(Path(out_dir)) as tmp:
        result.report = write_outputs(recording, result, options, Path(tracker_file), tmp)
    return result
