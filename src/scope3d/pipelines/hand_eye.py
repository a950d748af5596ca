"""Hand-eye calibration of a robot-held scope, as one job (reference sec. 8.1)::

    robot      <- poses.csv rows (the flange in the robot base: position mm, orientation quaternion), or
                  the robot's log interpolated to each image's time (robot_poses_from_log)
    corners    <- detect_board per image                (images without the board are listed and skipped)
    board      <- board_pose per view                   (solvePnP through the calibrated camera.json)
    hand-eye   <- calibrate_hand_eye                    (Park-Martin closed form, joint refinement)
    files      <- hand_eye.json (flange_from_cam, cam_from_flange, residuals, tolerance; report.json the same),
                  poses.csv (cam_from_base of every robot row with the tolerance: a dataset's poses)

``run(options, image_paths, robot, camera, out_dir, *, progress=None) -> HandEyeRunResult`` is what
``scope3d calibrate-hand-eye`` calls.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.trajectory import Trajectory
from scope3d.io.images import read_image
from scope3d.io.robot_log import PoseLogFormat, read_pose_log
from scope3d.io.poses_csv import format_poses_csv, read_poses_csv
from scope3d.sensor.calibration import BoardSpec, DetectionOptions, detect_board
from scope3d.sensor.camera import Camera
from scope3d.sensor.hand_eye import HandEyeOptions, HandEyeResult, board_pose, calibrate_hand_eye
from scope3d.sensor.pose_tolerance import MeasuredPose
from scope3d.utils.atomic import atomic_file
from scope3d.utils.jsonio import write_json
from scope3d.pipelines.frames_import import DEFAULT_MAX_GAP_S, unposed_reason
from scope3d.utils.progress import Progress, advance, stage


@dataclass(frozen=True)
class HandEyeRunOptions:
    board: BoardSpec
    detection: DetectionOptions = field(default_factory=DetectionOptions)
    hand_eye: HandEyeOptions = field(default_factory=HandEyeOptions)


@dataclass
class HandEyeRunResult:
    result: HandEyeResult
    views: list[str]
    skipped: dict[str, str]
    report: dict

    def summary(self) -> str:
        lines = [f"{len(self.views)} views; " + self.result.summary()]
        lines += [f"  skipped {k}: {v}" for k, v in self.skipped.items()]
        return "\n".join(lines)


def robot_flange_poses(path: str | Path) -> dict[str, Pose]:
    """poses.csv read as robot flange poses: each row is the flange's position (mm) and orientation in the
    robot base, i.e. ``base_from_flange``, keyed by the row's image name."""
    names, measured = read_poses_csv(path)
    return {n: m.pose.inverse() for n, m in zip(names, measured)}


def robot_poses_from_log(log: str | Path, log_format: PoseLogFormat, frame_times: dict[str, float], *,
                         max_gap_s: float = DEFAULT_MAX_GAP_S) -> dict[str, Pose]:
    """``base_from_flange`` at each image's time (``frame_times``: image name -> seconds on the log's
    clock), interpolated in the robot's log as ``scope3d import frames`` does. InputError naming the image
    for one outside the log or in a gap longer than ``max_gap_s``."""
    pose_log = read_pose_log(log, log_format)
    names = list(frame_times)
    times = np.array([frame_times[n] for n in names], dtype=float)
    rotations, positions, gaps = Trajectory(pose_log.times_s, pose_log.rotations, pose_log.positions_mm).at(times)
    bad = np.flatnonzero(~(gaps <= max_gap_s))
    if bad.size:
        k = bad[0]
        raise InputError(f"{log}: image {names[k]} {unposed_reason(times[k], gaps[k], pose_log, max_gap_s)}")
    return {n: Pose(r, p) for n, r, p in zip(names, rotations, positions)}


def run(options: HandEyeRunOptions, image_paths: list[str | Path], robot: str | Path | dict[str, Pose],
        camera: Camera, out_dir: str | Path, *, progress: Progress | None = None,
        intrinsic_sigmas: np.ndarray | None = None, intrinsic_sigmas_source: str | None = None) -> HandEyeRunResult:
    """Hand-eye calibration from board images taken at the robot's poses, through the calibrated
    ``camera``; writes ``hand_eye.json``, ``poses.csv`` and ``report.json`` into ``out_dir``.

    robot : a poses.csv of flange poses (:func:`robot_flange_poses`), or image name -> ``base_from_flange``
    (e.g. :func:`robot_poses_from_log`). progress : counts the images searched for the board.
    intrinsic_sigmas : (P,) the calibration's sigma of each of ``camera.params`` (e.g.
    :func:`scope3d.io.intrinsic_bounds.read_intrinsic_sigmas`), for the intrinsics' share of the tolerance;
    intrinsic_sigmas_source : where they came from, for the report."""
    where = "the robot poses" if isinstance(robot, dict) else robot
    robot = dict(robot) if isinstance(robot, dict) else robot_flange_poses(robot)
    image_paths = [Path(p) for p in image_paths]
    missing = [p.name for p in image_paths if p.name not in robot]
    if missing:
        raise InputError(f"{where}: no robot pose for image(s) {', '.join(missing)}")
    obj_all = options.board.object_points()
    views, flange, boards, objs, pixels, skipped = [], [], [], [], [], {}
    stage(progress, "detect", len(image_paths))
    for path in image_paths:
        advance(progress)
        det = detect_board(read_image(path, grey=True), options.board, name=path.name, options=options.detection)
        if not det.found:
            skipped[path.name] = det.reason
            continue
        views.append(path.name)
        flange.append(robot[path.name])
        objs.append(obj_all[det.corner_ids])
        pixels.append(det.pixels)
        boards.append(board_pose(camera, objs[-1], det.pixels))
    if len(views) < 3:
        raise InputError(f"only {len(views)} image(s) show the board, need 3; not found in: "
                         f"{', '.join(skipped) or 'none'}")
    result = calibrate_hand_eye(flange, boards, camera=camera, object_points=objs, pixels=pixels,
                                options=options.hand_eye, intrinsic_sigmas=intrinsic_sigmas)
    report = {
        "flange_from_cam": _pose_dict(result.flange_from_cam),
        "cam_from_flange": _pose_dict(result.cam_from_flange),
        "closed_form_flange_from_cam": _pose_dict(result.closed_form),
        "base_from_board": _pose_dict(result.base_from_board),
        "rms_px": result.rms_px,
        "n_views_used": len(views),
        "skipped": skipped,
        "residual_rms_mm": np.sqrt(np.mean(result.position_residual_mm ** 2, axis=0)).tolist(),
        "residual_rms_deg": float(np.rad2deg(np.sqrt(np.mean(result.orientation_residual_rad ** 2)))),
        "per_view": {v: {"position_mm": p.tolist(), "orientation_deg": float(np.rad2deg(a))}
                     for v, p, a in zip(views, result.position_residual_mm, result.orientation_residual_rad)},
        "tolerance": {"position_mm": result.tolerance.position_mm.tolist(),
                      "orientation_deg": np.rad2deg(result.tolerance.orientation_rad).tolist(),
                      "sigmas": options.hand_eye.tolerance_sigmas,
                      "intrinsics_share_mm": result.intrinsics_share_mm.tolist(),
                      "intrinsics_share_deg": np.rad2deg(result.intrinsics_share_rad).tolist(),
                      "intrinsics_sigmas_from": intrinsic_sigmas_source},
    }
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = list(robot)
    cameras = result.camera_poses([robot[n] for n in names])
    with atomic_file(out / "poses.csv") as fh:
        fh.write(format_poses_csv(names, [MeasuredPose(c, result.tolerance) for c in cameras]))
    write_json(out / "hand_eye.json", report)  # the calibration product other tools read
    write_json(out / "report.json", report)  # the run's report, as every job writes one (report.html)
    return HandEyeRunResult(result, views, skipped, report)


def _pose_dict(pose: Pose) -> dict:
    return {"rotation": pose.rotation.tolist(), "translation_mm": pose.translation.tolist(),
            "quaternion_xyzw": pose.quaternion.tolist(), "rotvec_deg": np.rad2deg(pose.rotvec).tolist()}
