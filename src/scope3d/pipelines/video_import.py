"""A scope's video as a scope3d dataset: every Nth frame or the key frames, poses unknown or planned.

The reference recorded its bladder scans as 30 fps video (19,753 frames for 10 minutes, sec. 2.3.2) and
mapped from the frames. :func:`run` streams a video file once (:mod:`scope3d.io.video`), keeps
every Nth frame or the key frames (:mod:`scope3d.feature.keyframes`), and writes the kept frames as a
dataset (:func:`scope3d.io.dataset.write_dataset`, atomic: the folder appears complete or not at all).

Poses. Without a plan every pose is unknown (identity with tolerance ``inf``: mapping from images alone).
With a scan plan (``plan.json``, ``scope3d plan-scan``) the robot is taken to follow it in time: the scan
starts at view 0 at ``plan_start_s`` into the video and moves from one view to the next in
``seconds_per_view`` seconds, centres linearly and orientations by slerp, as the phantom lab's video path
does. A frame at time ``t`` gets the planned pose at view position ``(t - plan_start_s) /
seconds_per_view`` with the given (loose) tolerance; frames before the first view or after the last are
unknown (insertion, retraction).
"""
from __future__ import annotations

import math
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2

from scope3d.errors import InputError
from scope3d.feature.keyframes import KeyframeOptions, KeyframeSelector
from scope3d.geometry.pose import Pose
from scope3d.io.dataset import write_dataset
from scope3d.io.scan_plan import PlanFile
from scope3d.io.video import DecodeCheck, damage_check_available, probe_video, read_video
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.utils.progress import Progress, advance, stage

SECONDS_PER_PLANNED_VIEW = 600.0 / 529.0  # the reference's 15 mm scan: about 10 min for 529 views (sec. 2.3.2)


@dataclass(frozen=True)
class VideoImportOptions:
    """Which frames to keep and how to time a plan.

    every : int >= 1, keep frames 0, every, 2 * every... (ignored when ``keyframes`` is given).
    keyframes : KeyframeOptions or None, keep the key frames instead (every frame is looked at).
    plan_tolerance : PoseTolerance, the box around a planned pose (used only with a plan; a robot that
        follows a plan only roughly needs a loose one, e.g. 5 mm and 10 degrees).
    seconds_per_view : float > 0, time from one planned view to the next (default: the reference's 10 min
        for 529 views). plan_start_s : float, time into the video at which the scan is at view 0.
    """

    every: int = 1
    keyframes: KeyframeOptions | None = None
    plan_tolerance: PoseTolerance = field(default_factory=PoseTolerance.unknown)
    seconds_per_view: float = SECONDS_PER_PLANNED_VIEW
    plan_start_s: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.every, bool) or not isinstance(self.every, int) or self.every < 1:
            raise ValueError(f"every must be a whole number >= 1, got {self.every!r}")
        if not (math.isfinite(self.seconds_per_view) and self.seconds_per_view > 0):
            raise ValueError(f"seconds_per_view must be positive, got {self.seconds_per_view}")
        if not math.isfinite(self.plan_start_s):
            raise ValueError(f"plan_start_s must be finite, got {self.plan_start_s}")


def planned_pose(plan: PlanFile, time_s: float, options: VideoImportOptions) -> Pose | None:
    """The plan's pose at ``time_s`` seconds into the video, or None outside the planned scan."""
    position = (time_s - options.plan_start_s) / options.seconds_per_view
    last = len(plan.poses) - 1
    # a frame time is rounded to the microsecond by containers: allow that much past either end
    slack = 1e-6 / options.seconds_per_view
    if not -slack <= position <= last + slack:
        return None
    position = min(max(position, 0.0), float(last))
    view = min(int(math.floor(position)), max(last - 1, 0))
    if last == 0:
        return plan.poses[0]
    return plan.poses[view].interpolate(plan.poses[view + 1], position - view)


@dataclass
class VideoImportResult:
    """dataset_dir : the dataset folder written; source : what its ``dataset.json`` records under ``source``
    (the video, the selection rule, each kept frame's index and time, the decode damage, the plan)."""

    dataset_dir: Path
    source: dict

    def summary(self) -> str:
        s = self.source
        rule = s["selection"]["rule"] + (f" {s['selection']['every']}" if s["selection"]["rule"] == "every" else "")
        line = f"{s['frames_kept']} of {s['frames_in_container']} frames kept ({rule})"
        if "plan" in s:
            line += f", {s['plan']['frames_with_planned_pose']} with a planned pose"
        return "\n".join([line, *decode_damage_summary(s["decode_damage"])])


def run(options: VideoImportOptions, video: str | Path, camera: Camera, out_dir: str | Path, *,
        plan: PlanFile | None = None, intrinsics: str = "given", progress: Progress | None = None,
        finish=None) -> VideoImportResult:
    """Write the kept frames of ``video`` as a dataset folder ``out_dir``.

    camera : the intrinsics (its size must be the video's). plan : planned poses by time (see the module
    docstring), or None for unknown poses. intrinsics : where the camera came from, recorded in
    ``dataset.json`` (e.g. "nominal, not calibrated"). progress : counts frames read (see
    :mod:`scope3d.utils.progress`). ``dataset.json``'s ``source`` records the video, the selection rule,
    each kept frame's index and time, and the frames FFmpeg decoded with errors (``decode_damage``, see
    :func:`decode_damage_record`). finish : see :func:`scope3d.io.dataset.write_dataset`. Raises
    InputError naming the file for a missing, unreadable or empty video, or a camera of another size.
    """
    video = Path(video)
    info = probe_video(video)
    if (camera.width, camera.height) != (info.width, info.height):
        raise InputError(f"{video}: frames are {info.width}x{info.height} px, the camera {camera.width}x{camera.height}")
    selector = None
    if options.keyframes is not None:
        selector = KeyframeSelector(options.keyframes, field_radius_px=camera.mask_radius_px)
    stage(progress, "import video", info.n_frames)
    with tempfile.TemporaryDirectory(prefix="scope3d-video-") as tmp:
        paths, names, indices, times, measured = [], [], [], [], []
        n_planned = 0
        unknown = MeasuredPose(Pose.identity(), PoseTolerance.unknown())
        check = DecodeCheck()
        for frame in read_video(video, every=1 if selector else options.every, check=check):
            advance(progress, 1 if selector else min(options.every, max(info.n_frames - frame.index, 1)))
            if selector is not None and not selector.offer(frame.image).keep:
                continue
            name = f"{frame.index:06d}.png"
            path = Path(tmp) / name
            if not cv2.imwrite(str(path), cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR)):
                raise InputError(f"{path}: could not write a frame")
            pose = planned_pose(plan, frame.time_s, options) if plan is not None else None
            measured.append(MeasuredPose(pose, options.plan_tolerance) if pose is not None else unknown)
            n_planned += pose is not None
            paths.append(path)
            names.append(name)
            indices.append(frame.index)
            times.append(round(frame.time_s, 6))
        selection = ({"rule": "key frames", **asdict(options.keyframes)} if selector is not None
                     else {"rule": "every", "every": options.every})
        source = {"video": str(video), "fps": info.fps, "frames_in_container": info.n_frames, "frames_kept": len(paths),
                  "intrinsics": intrinsics,
                  "selection": selection, "frame_indices": indices, "frame_times_s": times,
                  "decode_damage": decode_damage_record(check, indices, info.n_frames)}
        if plan is not None:
            source["plan"] = {"views": len(plan.poses), "seconds_per_view": options.seconds_per_view,
                              "start_s": options.plan_start_s,
                              "frames_with_planned_pose": n_planned}
        written = write_dataset(out_dir, camera, paths, measured, names=names, metadata={"source": source},
                                finish=finish)
    return VideoImportResult(Path(written), source)



MESSAGES_KEPT = 20  # FFmpeg's lines are recorded for this many damaged frames (a wrecked video has thousands)


def decode_damage_record(check: DecodeCheck, kept_indices: list[int], frames_in_container: int) -> dict:
    """What ``dataset.json`` says about a damaged video: ``frames_in_container`` and ``frames_decoded``
    (fewer decoded than stated: a truncated or damaged file, or a container's estimate), and the frames
    FFmpeg decoded with errors and concealed (imported as if whole, since that is what OpenCV returns):
    ``checked`` (False when the user's OpenCV FFmpeg log setting hides FFmpeg's lines), ``frames`` (their
    indices in the video), ``frames_kept`` (those among
    the dataset's frames), ``kept_frames_carrying_damage`` (the dataset's frames that are damaged or
    predicted from a damaged one, up to the next key frame), ``messages`` (FFmpeg's lines for the first
    few, by frame index) and what the check cannot see."""
    kept = set(kept_indices)
    damaged = check.damaged
    return {
        "frames_in_container": frames_in_container,
        "frames_decoded": check.frames_decoded,
        "checked": damage_check_available(),
        "frames": [d.index for d in damaged],
        "frames_kept": [d.index for d in damaged if d.index in kept],
        # a concealed block is copied into every frame predicted from it, up to the next key frame
        "kept_frames_carrying_damage": [i for i in kept_indices if any(d.carries_damage(i) for d in damaged)],
        "messages": {str(d.index): list(d.messages) for d in damaged[:MESSAGES_KEPT]},
        "not_seen": "damage that leaves a valid stream (a flipped bit decoding to wrong pixels without an "
                    "error) and the frames predicted from such a frame",
    }


def decode_damage_summary(record: dict) -> list[str]:
    """Lines for the import's output about a damaged video (none for a clean one)."""
    lines = []
    stated, decoded = record.get("frames_in_container", 0), record.get("frames_decoded", 0)
    if decoded < stated:
        lines.append(f"damage        the container states {stated} frames, {decoded} could be read: the file is "
                     f"truncated or damaged (or its frame count an estimate)")
    if not record.get("checked", False):
        lines.append("damage        frames not checked: OPENCV_FFMPEG_LOGLEVEL or OPENCV_FFMPEG_DEBUG sends "
                     "FFmpeg's error lines away from scope3d")
        return lines
    frames = record.get("frames", [])
    if frames:
        shown = ", ".join(str(i) for i in frames[:20]) + (", ..." if len(frames) > 20 else "")
        carrying = len(record.get("kept_frames_carrying_damage", []))
        lines.append(f"damage        {len(frames)} frame{'s' if len(frames) != 1 else ''} could not be decoded "
                     f"cleanly (frames {shown}; {len(record.get('frames_kept', []))} of them in the dataset, and "
                     f"{carrying} of the dataset's frames are them or predicted from them): FFmpeg concealed the "
                     f"damage; dataset.json source.decode_damage lists them")
    return lines
