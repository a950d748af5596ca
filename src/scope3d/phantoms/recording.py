"""A raw recording, the way a lab would have it after a session with a robot-held scope: what a user
brings to scope3d before any of its own files exist (the walkthrough of ``docs/own_data.md``).

::

    RECORDING/
      README.txt                 what each file is, in the lab's words
      calibration/board_NN.png   checkerboard views for the intrinsics (9 x 6 inner corners, 2 mm squares)
      hand_eye/board_NN.png      checkerboard stills, the robot dwelling at each view
      hand_eye/robot_log.csv     the flange pose during that session (same layout as the scan's log)
      hand_eye/frame_times.csv   image,t: when each still was taken, on the robot's clock
      scan/video.mkv             the scan: 30 fps along a raster over the dome phantom (lossless FFV1)
      scan/robot_log.csv         the flange pose at 250 Hz: t (s, the robot's clock), x, y, z (metres),
                                 qx, qy, qz, qw (base_from_flange)
      scan/frame_times.csv       image,t: each video frame (by index) on the robot's clock
      truth/                     what the lab does not know, for checking only: camera.json, hand_eye.json
                                 (flange_from_cam), poses.csv (every video frame's true cam_from_world, named
                                 NNNNNN.png as `scope3d import frames` names them), surface.ply, scene.json

The robot's base frame is the phantom's world frame. The controller's log carries a smooth pose error (a
sum of slow sinusoids per axis, ``robot_error_mm`` at most, and ``robot_error_mm * 0.5`` degrees at most,
like an uncalibrated arm's kinematic error along a path), printed with the digits a controller prints
(micrometres, 1e-9 on quaternions). The robot's clock reads ``clock_offset_s`` more than the camera's;
``frame_times.csv`` gives the frames on the robot's clock, as a lab's trigger or sync would, off by
``sync_error_s`` (0 by default) to test what an uncorrected clock error does.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from scope3d.geometry.pose import Pose
from scope3d.io.camera_json import camera_to_dict
from scope3d.io.images import write_image
from scope3d.io.ply import write_ply
from scope3d.io.poses_csv import format_poses_csv
from scope3d.io.video import write_video
from scope3d.phantoms.boards import (LAB_BOARD, LAB_BOARD_OPTIONS, random_board_poses, render_board_view,
                                     render_board_views)
from scope3d.phantoms.lab import ORIENTATION_NOISE_DEG_PER_MM, default_camera
from scope3d.phantoms.render import RenderOptions, render_frame, sequence_exposure
from scope3d.phantoms.scenes import build_scene
from scope3d.phantoms.trajectories import SurveyMotion, grid_trajectory, poses_at
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.utils.atomic import atomic_directory
from scope3d.utils.jsonio import write_json
from scope3d.utils.progress import Progress, advance, stage

FLANGE_FROM_CAM = Pose.from_rotvec([0.05, -0.1, 1.2], [3.0, -2.0, 40.0])  # a scope 40 mm beyond the flange
BASE_FROM_BOARD = Pose(Rotation.from_rotvec([np.pi, 0.0, 0.0]).as_matrix() @ Rotation.from_rotvec([0, 0, 0.3]).as_matrix(),
                       np.array([60.0, -40.0, 0.0]))  # face up beside the phantom


@dataclass(frozen=True)
class RecordingOptions:
    """size : (width, height) of the scope's frames (None: the dome's 608 x 608). calibration_views,
    hand_eye_views : board images of each session. grid : (rows, cols) of the scan's raster over the dome
    (5 mm apart, 15 mm above it, as ``grid5x6``). speed_mm_s : the scan's speed between raster points
    (the frames in between are rendered too). accel_mm_s2 : the robot's acceleration: it starts and stops
    at rest at each turn of the raster (default 1200 mm/s^2, Universal Robots' default tool acceleration for
    a linear move, ``movel``'s ``a=1.2`` m/s^2; None: constant speed with instant turns, a velocity no
    controller logs). fps, log_hz : the camera's and the log's rates.
    video_name : the scan's file, its codec by its suffix (:func:`scope3d.io.video.write_video`: .mkv
    lossless, .avi Motion JPEG, .mp4 MPEG-4). clock_offset_s : the robot's clock minus the camera's. sync_error_s : error of the frame times given
    on the robot's clock. robot_error_mm : the controller's pose error (module docstring). seed : every
    random choice (board poses, the robot's error, image noise)."""

    size: tuple[int, int] | None = None
    calibration_views: int = 15
    hand_eye_views: int = 12
    grid: tuple[int, int] = (5, 6)
    speed_mm_s: float = 25.0
    accel_mm_s2: float | None = 1200.0
    fps: float = 30.0
    log_hz: float = 250.0
    clock_offset_s: float = 1000.137
    sync_error_s: float = 0.0
    robot_error_mm: float = 0.2
    video_name: str = "video.mkv"
    seed: int = 0
    render: RenderOptions = field(default_factory=RenderOptions)


def write_recording(options: RecordingOptions, out_dir: str | Path, *, progress: Progress | None = None) -> Path:
    """Render and write a raw recording (module docstring); atomic. Returns ``out_dir``."""
    scene = build_scene("dome")
    camera = default_camera(scene, "grid5x6", size=options.size)
    rng = np.random.default_rng([options.seed, 40])
    error = _RobotError(options.robot_error_mm, rng)
    motion = SurveyMotion(grid_trajectory(*options.grid), speed_mm_s=options.speed_mm_s,
                          accel_mm_s2=options.accel_mm_s2)
    scan_times = np.arange(0.0, motion.duration_s + 1e-9, 1.0 / options.fps)  # the video's frames
    scan_poses = motion.poses_at(scan_times)
    with atomic_directory(Path(out_dir)) as tmp:
        for sub in ("calibration", "hand_eye", "scan", "truth"):
            (tmp / sub).mkdir()
        board_options = LAB_BOARD_OPTIONS
        stage(progress, "recording: boards", options.calibration_views + options.hand_eye_views)
        views = render_board_views(camera, LAB_BOARD, n_views=options.calibration_views, seed=options.seed + 1,
                                   options=board_options)
        for i, image in enumerate(views.images):
            write_image(tmp / "calibration" / f"board_{i:02d}.png", image)
            advance(progress)
        board_rng = np.random.default_rng([options.seed, 41])
        cam_from_board = random_board_poses(camera, LAB_BOARD, options.hand_eye_views, seed=options.seed + 2,
                                            options=board_options)
        still_times = []
        for i, pose in enumerate(cam_from_board):
            write_image(tmp / "hand_eye" / f"board_{i:02d}.png",
                        render_board_view(camera, LAB_BOARD, pose, rng=board_rng, options=board_options))
            still_times.append(1.0 + 2.0 * i + 0.5)  # dwell 1 s at each view, 1 s to the next
            advance(progress)
        key_times, key_poses = _dwell_path([c @ BASE_FROM_BOARD.inverse() for c in cam_from_board])
        log_times = np.arange(key_times[0] - 0.5, key_times[-1] + 0.5, 1.0 / options.log_hz)
        _write_log(tmp / "hand_eye" / "robot_log.csv", log_times, poses_at(key_times, key_poses, log_times), error,
                   options)
        _write_frame_times(tmp / "hand_eye" / "frame_times.csv",
                           [f"board_{i:02d}.png" for i in range(len(cam_from_board))], still_times, options)

        exposure = sequence_exposure(scene, camera, scan_poses, options=options.render)
        stage(progress, "recording: scan video", len(scan_poses))
        frames = []
        for i, pose in enumerate(scan_poses):
            frames.append(render_frame(scene, camera, pose, seed=options.seed, frame_index=i, exposure=exposure,
                                       options=options.render).image)
            advance(progress)
        write_video(tmp / "scan" / options.video_name, frames, options.fps)
        # the controller's ticks fall anywhere between the camera's
        phase = np.random.default_rng([options.seed, 42]).uniform(0.0, 1.0 / options.log_hz)
        log_times = np.arange(scan_times[0] - 0.5 + phase, scan_times[-1] + 0.5, 1.0 / options.log_hz)
        _write_log(tmp / "scan" / "robot_log.csv", log_times, motion.poses_at(log_times), error, options)
        _write_frame_times(tmp / "scan" / "frame_times.csv", [str(i) for i in range(len(frames))], scan_times,
                           options)

        names = [f"{i:06d}.png" for i in range(len(frames))]
        write_json(tmp / "truth" / "camera.json", camera_to_dict(camera))
        write_json(tmp / "truth" / "hand_eye.json", {"flange_from_cam": {
            "rotation": FLANGE_FROM_CAM.rotation.tolist(), "translation_mm": FLANGE_FROM_CAM.translation.tolist()}})
        (tmp / "truth" / "poses.csv").write_text(
            format_poses_csv(names, [MeasuredPose(p, PoseTolerance.exact()) for p in scan_poses]))
        write_ply(tmp / "truth" / "surface.ply", scene.mesh)
        write_json(tmp / "truth" / "scene.json", {**scene.info, "recording": _describe(options)})
        (tmp / "README.txt").write_text(_README.format(**_describe(options)))
    return Path(out_dir)


def _dwell_path(cam_from_world: list[Pose]) -> tuple[np.ndarray, list[Pose]]:
    """Key times and poses of a robot that dwells 1 s at each view and takes 1 s to the next."""
    key_times, key_poses = [], []
    for i, pose in enumerate(cam_from_world):
        key_times += [1.0 + 2.0 * i, 2.0 + 2.0 * i]
        key_poses += [pose, pose]
    return np.array(key_times), key_poses


class _RobotError:
    """A controller's smooth pose error: per axis a sum of two sinusoids with periods of 2-9 s (position,
    mm; orientation, rad, about base axes), at most ``position_mm`` and ``position_mm * 0.5`` deg."""

    def __init__(self, position_mm: float, rng: np.random.Generator) -> None:
        self.amplitude = np.array([position_mm] * 3 + [np.deg2rad(position_mm * ORIENTATION_NOISE_DEG_PER_MM)] * 3)
        self.periods = rng.uniform(2.0, 9.0, (2, 6))
        self.phases = rng.uniform(0, 2 * np.pi, (2, 6))

    def __call__(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(times, dtype=float)[:, None, None]
        wave = np.sin(2 * np.pi * t / self.periods + self.phases).sum(axis=1) / 2.0  # (N, 6), within +-1
        return wave[:, :3] * self.amplitude[:3], wave[:, 3:] * self.amplitude[3:]


def _write_log(path: Path, camera_times: np.ndarray, cam_from_world: list[Pose], error: _RobotError,
               options: RecordingOptions) -> None:
    """The flange's reported pose at each time, as the controller prints it (module docstring)."""
    base_from_flange = [c.inverse() @ FLANGE_FROM_CAM.inverse() for c in cam_from_world]
    dp, dw = error(camera_times)
    rotations = Rotation.from_rotvec(dw) * Rotation.from_matrix([b.rotation for b in base_from_flange])
    positions = np.array([b.translation for b in base_from_flange]) + dp
    quats = rotations.as_quat()
    lines = ["t,x,y,z,qx,qy,qz,qw"]
    for t, p, q in zip(camera_times + options.clock_offset_s, positions / 1000.0, quats):
        lines.append(f"{t:.4f},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f},{q[0]:.9f},{q[1]:.9f},{q[2]:.9f},{q[3]:.9f}")
    path.write_text("\n".join(lines) + "\n")


def _write_frame_times(path: Path, names: list[str], camera_times, options: RecordingOptions) -> None:
    lines = ["image,t"] + [f"{n},{t + options.clock_offset_s + options.sync_error_s:.6f}"
                           for n, t in zip(names, camera_times)]
    path.write_text("\n".join(lines) + "\n")


def _describe(options: RecordingOptions) -> dict:
    return {"board": "9x6 inner corners, 2 mm squares", "grid": "x".join(map(str, options.grid)),
            "video_name": options.video_name,
            "speed_mm_s": options.speed_mm_s, "accel_mm_s2": options.accel_mm_s2, "fps": options.fps, "log_hz": options.log_hz,
            "clock_offset_s": options.clock_offset_s, "sync_error_s": options.sync_error_s,
            "robot_error_mm": options.robot_error_mm, "seed": options.seed}


_README = """A session with a robot-held endoscope over a dome phantom (rendered by scope3d's phantom lab).

calibration/       {board} checkerboard views for the camera's intrinsics
hand_eye/          checkerboard stills with the robot dwelling at each view; robot_log.csv is the robot's flange
                   pose log of that session, frame_times.csv when each still was taken (robot clock)
scan/{video_name}     the scan, {fps:g} fps: a {grid} raster at {speed_mm_s:g} mm/s, 15 mm over the phantom,
                   from rest to rest along each straight run at {accel_mm_s2} mm/s^2
scan/robot_log.csv the flange pose at {log_hz:g} Hz: t in seconds on the robot's clock, x, y, z in metres,
                   qx, qy, qz, qw (base_from_flange)
scan/frame_times.csv image,t: each video frame (its index) on the robot's clock
truth/             not known in a real lab: the true camera, hand-eye, camera poses and surface, to check
                   a map against (see docs/own_data.md)

The robot's data sheet says its pose error along a path stays within {robot_error_mm:g} mm.
"""
