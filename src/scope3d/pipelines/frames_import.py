"""A scope's frames (a folder of images or a video) and a robot's pose log as a scope3d dataset::

    log       <- read_pose_log          (robot_log: any column layout, unit and clock; bad rows refused or dropped)
    times     <- frame times            (a frame-time table, numbers in the file names, a constant rate, or the
                                         video's own clock; plus the camera-to-log clock offset)
    flange    <- Trajectory.at(times)   (linear + slerp between the log's rows; a frame interpolated across more
                                         than ``max_gap_s`` of log, or outside it, refused or skipped)
    camera    <- flange @ hand-eye      (``base_from_cam = base_from_flange @ flange_from_cam``; without a
                                         hand-eye the log is taken to hold the camera's own poses)
    dataset   <- write_dataset          (poses with the robot's tolerance; dataset.json records the provenance:
                                         the log's format, dropped rows, each frame's time and gap)

``run(options, source, log, camera, out_dir, *, frame_times=None, hand_eye=None)`` is what ``scope3d import
frames`` calls. The robot's base frame becomes the dataset's world frame.
"""
from __future__ import annotations

import math
import re
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.trajectory import Trajectory
from scope3d.io.dataset import write_dataset
from scope3d.io.robot_log import TIME_UNITS_TO_S, PoseLog, PoseLogFormat, read_pose_log
from scope3d.io.video import read_video
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.utils.progress import Progress, advance, stage
from scope3d.utils.threads import resolve_threads

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
#: Longest stretch of log a frame's pose may be interpolated across by default: at a 100-1000 Hz log the
#: normal interval is 1-10 ms, so 0.1 s means ten or more rows are missing; a scope moving 10 mm/s and
#: turning at 1 rad/s^2 strays up to a(gap/2)^2/2 ~ 1 mm / 0.07 deg from the line between the rows there.
DEFAULT_MAX_GAP_S = 0.1


@dataclass(frozen=True)
class FrameTiming:
    """Where each frame's time comes from (the first that applies), on the camera's clock:

    ``table`` given to :func:`run` (frame_times): the table's time. ``name_time_unit``: the last number in
    the file name, in that unit (s, ms, us, ns). ``rate_hz``: frame ``i`` (in name order; a video's frame
    index) at ``first_frame_s + i / rate_hz``. Otherwise a video's own presentation times (a folder needs one
    of the above). ``clock_offset_s`` is added to every frame time to put it on the log's clock.
    """

    name_time_unit: str | None = None
    rate_hz: float | None = None
    first_frame_s: float = 0.0
    clock_offset_s: float = 0.0

    def __post_init__(self) -> None:
        if self.name_time_unit is not None and self.name_time_unit not in TIME_UNITS_TO_S:
            raise ValueError(f"unknown time unit {self.name_time_unit!r}; known: {', '.join(TIME_UNITS_TO_S)}")
        if self.rate_hz is not None and not (math.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ValueError(f"frame rate must be positive, got {self.rate_hz}")
        if not (math.isfinite(self.first_frame_s) and math.isfinite(self.clock_offset_s)):
            raise ValueError("the first frame's time and the clock offset must be finite")


@dataclass(frozen=True)
class FramesImportOptions:
    """log : how to read the robot log. timing : frame times. tolerance : the box around each camera pose
    (the robot's accuracy, plus the hand-eye's). tolerance_source : where it comes from, recorded.
    max_gap_s : longest log interval to interpolate across (:data:`DEFAULT_MAX_GAP_S`). skip_unposed_frames :
    leave out frames outside the log or across a longer gap (listed in the provenance) instead of refusing.
    every : keep video frames 0, every, 2 * every... (a folder keeps every image)."""

    log: PoseLogFormat = field(default_factory=PoseLogFormat)
    timing: FrameTiming = field(default_factory=FrameTiming)
    tolerance: PoseTolerance = field(default_factory=PoseTolerance.unknown)
    tolerance_source: str = "given"
    max_gap_s: float = DEFAULT_MAX_GAP_S
    skip_unposed_frames: bool = False
    every: int = 1

    def __post_init__(self) -> None:
        if not (self.max_gap_s > 0):
            raise ValueError(f"max_gap_s must be positive, got {self.max_gap_s}")
        if isinstance(self.every, bool) or not isinstance(self.every, int) or self.every < 1:
            raise ValueError(f"every must be a whole number >= 1, got {self.every!r}")


@dataclass(frozen=True)
class FramesImportResult:
    """out_dir : the dataset written. names : its frames. times_s : each frame's time on the log's clock.
    gap_s : the log interval each pose was interpolated across. skipped : frames left out, name -> why.
    log : the log as read (rows used, rows dropped)."""

    out_dir: Path
    names: list[str]
    times_s: np.ndarray
    gap_s: np.ndarray
    skipped: dict[str, str]
    log: PoseLog

    def summary(self) -> str:
        dropped = sum(self.log.dropped.values())
        lines = [f"{len(self.names)} frames with poses from {len(self.log)} log rows "
                 f"({np.median(np.diff(self.log.times_s)) * 1e3:.3g} ms apart)"
                 + (f", {dropped} rows dropped" if dropped else ""),
                 f"interpolation gap: median {np.median(self.gap_s) * 1e3:.3g} ms, max {self.gap_s.max() * 1e3:.3g} ms"]
        if self.skipped:
            lines.append(f"{len(self.skipped)} frame(s) skipped without a pose (dataset.json source lists them)")
        return "\n".join(lines)


def run(options: FramesImportOptions, source: str | Path, log: str | Path, camera: Camera, out_dir: str | Path, *,
        frame_times: dict[str, float] | None = None, hand_eye: Pose | None = None, progress: Progress | None = None,
        finish=None) -> FramesImportResult:
    """Write ``source``'s frames with the log's poses as a dataset (module docstring); atomic.

    source : a folder of images (every file with an image suffix, in natural name order) or a video file.
    log : the robot log (CSV, :mod:`scope3d.io.robot_log`). camera : the intrinsics (each frame's size must
    be its size). frame_times : image name (a video's frame: its index or ``NNNNNN.png``) -> seconds on the
    camera's clock. hand_eye : ``flange_from_cam``, or None when the log holds camera poses. finish : see
    :func:`scope3d.io.dataset.write_dataset`. InputError (one line naming the file, row or frame) for
    anything the data cannot support.
    """
    source, log = Path(source), Path(log)
    pose_log = read_pose_log(log, options.log)
    trajectory = Trajectory(pose_log.times_s, pose_log.rotations, pose_log.positions_mm)
    with tempfile.TemporaryDirectory(prefix="scope3d-frames-") as tmp:
        if source.is_dir():
            paths, names, times = _folder_frames(source, camera, options.timing, frame_times, progress)
            kind = "folder"
        elif source.is_file():
            paths, names, times = _video_frames(source, camera, options, frame_times, Path(tmp), progress)
            kind = "video"
        else:
            raise InputError(f"{source}: no such folder or video")
        times = times + options.timing.clock_offset_s
        rotations, positions, gaps = trajectory.at(times)
        bad = ~(gaps <= options.max_gap_s)
        skipped = {names[k]: unposed_reason(times[k], gaps[k], pose_log, options.max_gap_s) for k in np.flatnonzero(bad)}
        if skipped and not options.skip_unposed_frames:
            name, why = next(iter(skipped.items()))
            where = f"{source / name}: the frame" if kind == "folder" else f"{source}: frame {name}"
            raise InputError(f"{where} {why}"
                             f"{f' (and {len(skipped) - 1} more frames)' if len(skipped) > 1 else ''}; "
                             "fix the clocks, or skip such frames")
        keep = np.flatnonzero(~bad)
        if keep.size == 0:
            raise InputError(f"{source}: no frame falls inside the log {log} "
                             f"({pose_log.times_s[0]:.6g} to {pose_log.times_s[-1]:.6g} s)")
        cam_from_world = _camera_poses(rotations[keep], positions[keep], hand_eye)
        measured = [MeasuredPose(p, options.tolerance) for p in cam_from_world]
        kept_names = [names[k] for k in keep]
        provenance = _provenance(options, source, kind, log, pose_log, hand_eye, kept_names, times[keep], gaps[keep],
                                 skipped)
        stage(progress, "write dataset", None)
        write_dataset(out_dir, camera, [paths[k] for k in keep], measured, names=kept_names,
                      metadata={"source": provenance}, finish=finish, move_frames=kind == "video")
    return FramesImportResult(Path(out_dir), kept_names, times[keep], gaps[keep], skipped, pose_log)


def _folder_frames(folder: Path, camera: Camera, timing: FrameTiming, table: dict[str, float] | None,
                   progress: Progress | None) -> tuple[list[Path], list[str], np.ndarray]:
    paths = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                   key=lambda p: _natural_key(p.name))
    if not paths:
        raise InputError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
    stage(progress, "frames", len(paths))
    for path in paths:
        _check_size(path, camera)
        advance(progress)
    names = [p.name for p in paths]
    if table is not None:
        times = _times_from_table(table, names, [p.name for p in paths], folder)
    elif timing.name_time_unit is not None:
        times = np.array([_time_in_name(p, timing.name_time_unit) for p in paths])
    elif timing.rate_hz is not None:
        times = timing.first_frame_s + np.arange(len(paths)) / timing.rate_hz
    else:
        raise InputError(f"{folder}: the frames' times are unknown: give a frame-time table, a unit for the "
                         "numbers in the file names, or a frame rate")
    return paths, names, times


def _video_frames(video: Path, camera: Camera, options: FramesImportOptions, table: dict[str, float] | None,
                  tmp: Path, progress: Progress | None) -> tuple[list[Path], list[str], np.ndarray]:
    stage(progress, "decode video", None)
    paths, names, keys, times, pending = [], [], [], [], []

    def write(path: Path, rgb: np.ndarray) -> None:
        if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise InputError(f"{path}: could not write a frame")

    # the PNG encoding (OpenCV releases the GIL) runs beside the decoding; a bounded backlog keeps memory flat
    with ThreadPoolExecutor(max_workers=resolve_threads(0)) as pool:
        for frame in read_video(video, every=options.every):
            if frame.image.shape[:2] != (camera.height, camera.width):
                raise InputError(f"{video}: frames are {frame.image.shape[1]}x{frame.image.shape[0]} px, the camera "
                                 f"{camera.width}x{camera.height}")
            name = f"{frame.index:06d}.png"
            pending.append(pool.submit(write, tmp / name, frame.image))
            if len(pending) > 32:
                pending.pop(0).result()
            paths.append(tmp / name)
            names.append(name)
            keys.append(str(frame.index))
            timing = options.timing
            times.append(timing.first_frame_s + frame.index / timing.rate_hz if timing.rate_hz else frame.time_s)
            advance(progress)
        for job in pending:
            job.result()
    if table is not None:
        aliases = {**{k: n for k, n in zip(keys, names)}, **{n: n for n in names}}
        # rows of the frames --every passes over name frames of the video too: not a mistake
        passed_over = re.compile(r"\d+(\.png)?$")
        table = {aliases.get(k, k): t for k, t in table.items() if k in aliases or not passed_over.match(k)}
        times = _times_from_table(table, names, names, video)
    return paths, names, np.asarray(times, dtype=float)


def _times_from_table(table: dict[str, float], names: list[str], shown: list[str], where: Path) -> np.ndarray:
    missing = [s for n, s in zip(names, shown) if n not in table]
    if missing:
        raise InputError(f"{where}: frame {missing[0]} has no time in the frame-time table"
                         + (f" ({len(missing) - 1} more)" if len(missing) > 1 else ""))
    extra = sorted(set(table) - set(names))
    if extra:
        raise InputError(f"the frame-time table lists {extra[0]}, which is not a frame of {where}")
    return np.array([table[n] for n in names], dtype=float)


_NUMBER = re.compile(r"\d+(?:\.\d+)?")


def _time_in_name(path: Path, unit: str) -> float:
    numbers = _NUMBER.findall(path.stem)
    if not numbers:
        raise InputError(f"{path}: no number in the file name to take its time from")
    return float(numbers[-1]) * TIME_UNITS_TO_S[unit]


def _natural_key(name: str) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def _check_size(path: Path, camera: Camera) -> None:
    try:
        with Image.open(path) as image:
            size = image.size
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise InputError(f"{path}: not a readable image ({exc})") from None
    if size != (camera.width, camera.height):
        raise InputError(f"{path}: {size[0]}x{size[1]} px, the camera is {camera.width}x{camera.height}")


def unposed_reason(time_s: float, gap_s: float, log: PoseLog, max_gap_s: float) -> str:
    """Why a frame at ``time_s`` gets no pose from ``log`` (outside it, or in a gap longer than allowed)."""
    if math.isinf(gap_s):
        return (f"at {time_s:.6g} s lies outside the log's {log.times_s[0]:.6g} to {log.times_s[-1]:.6g} s")
    return f"at {time_s:.6g} s falls in a {gap_s * 1e3:.4g} ms gap of the log (longest allowed {max_gap_s * 1e3:.4g} ms)"


def _camera_poses(base_from_flange_r: np.ndarray, flange_in_base_mm: np.ndarray, hand_eye: Pose | None) -> list[Pose]:
    """``cam_from_world`` (world = the robot's base) of each flange pose through ``flange_from_cam``."""
    if hand_eye is None:
        rotation, centre = base_from_flange_r, flange_in_base_mm
    else:
        rotation = base_from_flange_r @ hand_eye.rotation  # base_from_cam
        centre = base_from_flange_r @ hand_eye.translation + flange_in_base_mm
    return [Pose.from_centre(r.T, c) for r, c in zip(rotation, centre)]


def _provenance(options: FramesImportOptions, source: Path, kind: str, log_path: Path, log: PoseLog,
                hand_eye: Pose | None, names: list[str], times: np.ndarray, gaps: np.ndarray,
                skipped: dict[str, str]) -> dict:
    f = options.log
    timing = options.timing
    return {
        "frames": str(source), "kind": kind,
        "log": {"path": str(log_path), "pose_format": f.pose_format, "columns": dict(f.columns),
                "length_unit": f.length_unit, "time_unit": f.time_unit, "angle_unit": f.angle_unit,
                "rows_used": len(log), "rows_dropped": log.dropped, "first_dropped_row": log.first_dropped_row,
                "median_interval_s": float(np.median(np.diff(log.times_s)))},
        "frame_times": {"name_time_unit": timing.name_time_unit, "rate_hz": timing.rate_hz,
                        "first_frame_s": timing.first_frame_s, "clock_offset_s": timing.clock_offset_s},
        "hand_eye_flange_from_cam": None if hand_eye is None else
        {"rotation": hand_eye.rotation.tolist(), "translation_mm": hand_eye.translation.tolist()},
        "tolerance": {"position_mm": options.tolerance.position_mm.tolist(),
                      "orientation_deg": options.tolerance.orientation_deg.tolist(),
                      "source": options.tolerance_source},
        "interpolation": {"method": "linear position, slerp orientation", "max_gap_s": options.max_gap_s,
                          "gap_s_median": float(np.median(gaps)), "gap_s_max": float(gaps.max())},
        "frame_times_s": {n: round(float(t), 9) for n, t in zip(names, times)},
        "frame_gap_s": {n: round(float(g), 9) for n, g in zip(names, gaps)},
        "frames_without_pose": skipped,
    }
