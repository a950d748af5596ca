"""Video files in and out: probe, stream frames one at a time, write an MP4.

Reading goes through OpenCV's FFmpeg back end (``cv2.VideoCapture``), so any container and codec the
opencv wheel's FFmpeg decodes works (MP4, AVI, MKV, MOV; MPEG-4, H.264, MJPEG...). Frames are decoded one
at a time and never held together, so a 20,000-frame scan (the reference's 15 mm bladder scan: 19,753
frames at 30 fps, sec. 2.3.2) streams in constant memory. Writing uses the MPEG-4 Part 2 codec (``mp4v``),
the one the opencv wheel can encode without extra libraries.

Times are the container's presentation times (``CAP_PROP_POS_MSEC``), in seconds from the first frame,
so a variable-rate video keeps its real timing.

Damaged frames. FFmpeg conceals a damaged frame (it fills the blocks it cannot decode from their
neighbours and the previous frame) and returns it as if whole; OpenCV exposes no flag for that. What
FFmpeg does say is a line on stderr at its error level ("[mpeg4 @ 0x...] ac-tex damaged at 17 13"). Frames
are therefore decoded on one thread (with decoder threads the line comes while a later frame is being
read, and can come outside the window in which stderr is captured), and the lines written during each
frame's decoding are that frame's :attr:`DamagedFrame.messages`. This finds damage the bitstream's syntax
reveals, not all of it: a flipped bit can leave a valid stream that decodes to wrong pixels without a
word (measured in ``benchmarks/bench_video_damage.py``), and frames predicted from a damaged one up to the
next key frame carry its concealment silently. A user's own ``OPENCV_FFMPEG_LOGLEVEL`` or
``OPENCV_FFMPEG_DEBUG`` sends FFmpeg's lines elsewhere (OpenCV prints them on stdout): no damage can be
seen then (:func:`damage_check_available`).
"""
from __future__ import annotations

import math
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from scope3d.errors import InputError
from scope3d.io.images import quiet_decoders
from scope3d.utils.atomic import atomic_path

MP4_FOURCC = "mp4v"  # MPEG-4 Part 2: encodable by the opencv wheel's FFmpeg (H.264 'avc1' is not)
# The codec :func:`write_video` uses for a file's suffix: MPEG-4 Part 2 in .mp4 (lossy: at OpenCV's default
# bitrate a 304 px phantom frame comes back ~5 grey levels RMS off), FFV1 in .mkv (lossless, ~7x larger), and
# Motion JPEG in .avi (each frame a JPEG, ~1 grey level off: a frame grabber's recording).
VIDEO_CODECS = {".mp4": (MP4_FOURCC, []), ".mkv": ("FFV1", []), ".avi": ("MJPG", [])}


@dataclass(frozen=True)
class VideoInfo:
    """What a video file's container says about it.

    width, height : int, pixels. fps : float, frames per second (nominal). n_frames : int, the frame
    count the container states (an estimate for some containers; the frames read are what counts).
    duration_s : float, ``n_frames / fps``.
    """

    path: Path
    width: int
    height: int
    fps: float
    n_frames: int

    @property
    def duration_s(self) -> float:
        return self.n_frames / self.fps


@dataclass(frozen=True)
class VideoFrame:
    """index : int, position in the video (0 = first frame). time_s : float, presentation time in seconds
    from the first frame. image : (H, W, 3) uint8 RGB."""

    index: int
    time_s: float
    image: np.ndarray


@dataclass(frozen=True)
class DamagedFrame:
    """A frame FFmpeg decoded with errors and concealed. index : int, position in the video (0 = first).
    time_s : float, its presentation time in seconds. messages : tuple of str, FFmpeg's lines about it.
    next_key_frame : int or None, the index of the next key (intra) frame after it, or None if the video
    ended first (or its container does not say which frames are key frames): frames ``index`` up to it
    (excluded) may carry the concealment, each predicted from the one before (with B frames, a frame
    just before ``index`` may too)."""

    index: int
    time_s: float
    messages: tuple[str, ...]
    next_key_frame: int | None = None

    def carries_damage(self, frame_index: int) -> bool:
        """Whether the frame at ``frame_index`` is this one or predicted from it (see the class docstring)."""
        return self.index <= frame_index and (self.next_key_frame is None or frame_index < self.next_key_frame)


@dataclass
class DecodeCheck:
    """What :func:`read_video` saw while decoding, filled in as it goes. damaged : list of
    :class:`DamagedFrame`, in order. frames_decoded : int, frames read so far, yielded or skipped (fewer
    than the container states: a truncated or damaged file, or a container's estimate)."""

    damaged: list[DamagedFrame] = field(default_factory=list)
    frames_decoded: int = 0


def damage_check_available() -> bool:
    """Whether FFmpeg's error lines reach stderr, where :func:`read_video` reads them: not when the user set
    ``OPENCV_FFMPEG_LOGLEVEL`` or ``OPENCV_FFMPEG_DEBUG`` (OpenCV then prints FFmpeg's log on stdout at the
    level given; without them it leaves FFmpeg's own printer on stderr at its error level)."""
    return "OPENCV_FFMPEG_LOGLEVEL" not in os.environ and "OPENCV_FFMPEG_DEBUG" not in os.environ


def _open(path: Path) -> cv2.VideoCapture:
    if not path.exists():
        raise InputError(f"{path}: no such video file")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a video file")
    # FFmpeg also opens still images as one-frame "videos"; a photo given as a video is a mistake
    if cv2.haveImageReader(str(path)):
        raise InputError(f"{path}: is a still image, not a video")
    # one decoder thread: FFmpeg's decoder threads reported a damaged stream ("[mpeg4 @ ...] ac-tex damaged")
    # on stderr whenever they reached it, outside quiet_decoders' window around each call (the import
    # printed lines beside its own), and a line could not be told to belong to one frame
    with quiet_decoders():
        capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG, [cv2.CAP_PROP_N_THREADS, 1])
    if not capture.isOpened():
        _quietly(capture.release)
        raise InputError(f"{path}: not a video file OpenCV's FFmpeg can decode (empty, truncated or another format)")
    return capture


def _quietly(step):
    """One demux or decode step with the decoders' own complaints about a damaged stream discarded."""
    with quiet_decoders():
        return step()


def probe_video(path: str | Path) -> VideoInfo:
    """Size, frame rate and frame count of a video file, and a check that its first frame decodes.

    Raises InputError naming the file when it is missing, not a video, or has no decodable frame.
    """
    path = Path(path)
    capture = _open(path)
    try:
        width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(capture.get(cv2.CAP_PROP_FPS))
        count = capture.get(cv2.CAP_PROP_FRAME_COUNT)
        with quiet_decoders():
            ok, _ = capture.read()
    finally:
        _quietly(capture.release)
    if not ok or width <= 0 or height <= 0:
        raise InputError(f"{path}: the video has no frames")
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(f"{path}: the video states no frame rate ({fps})")
    n_frames = int(count) if math.isfinite(count) and 0 < count < 2**53 else 1
    return VideoInfo(path, width, height, fps, max(n_frames, 1))


def read_video(path: str | Path, *, every: int = 1, check: DecodeCheck | None = None) -> Iterator[VideoFrame]:
    """The frames of a video, decoded one at a time, in order.

    every : int >= 1, yield frames 0, every, 2 * every... The others are only demuxed and decoded
    (``grab``), not converted to RGB: an inter-frame codec must decode every frame anyway, so this is
    all a skip can save. check : if given, a :class:`DamagedFrame` is appended to ``check.damaged`` for
    every frame, yielded or skipped, that FFmpeg said it decoded with errors (see the module docstring for
    what this misses), before that frame is yielded (its ``next_key_frame`` is filled in when that frame
    is reached), and ``check.frames_decoded`` counts the frames read. Yields :class:`VideoFrame`; raises
    InputError naming the file if it cannot be opened or holds no frame at all.
    """
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ValueError(f"every must be a whole number >= 1, got {every!r}")
    path = Path(path)
    capture = _open(path)
    try:
        index = 0
        open_damage: list[int] = []  # positions in ``check.damaged`` whose next key frame is not reached yet
        while True:
            messages: list[str] = []
            with quiet_decoders(messages):
                if not capture.grab():
                    break
                # the frame is decoded by grab; retrieve only converts it (to BGR), which is also where an
                # undecodable one shows
                wanted = index % every == 0
                ok, bgr = capture.retrieve() if wanted else (True, None)
            time_s = capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
            if check is not None:
                check.frames_decoded = index + 1
                damaged = check.damaged
                if open_damage and capture.get(cv2.CAP_PROP_FRAME_TYPE) == ord("I"):  # predicted from nothing
                    for position in open_damage:
                        damaged[position] = replace(damaged[position], next_key_frame=index)
                    open_damage.clear()
                if messages:
                    open_damage.append(len(damaged))
                    damaged.append(DamagedFrame(index, time_s, tuple(messages)))
            if wanted:
                if not ok:
                    raise InputError(f"{path}: frame {index} does not decode")
                yield VideoFrame(index, time_s, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
            index += 1
        if index == 0:
            raise InputError(f"{path}: the video has no frames")
    finally:
        _quietly(capture.release)


def write_video(path: str | Path, frames: Iterable[np.ndarray], fps: float) -> Path:
    """Write frames ((H, W, 3) uint8 RGB or (H, W) uint8 grey, all one size) as a video at ``fps`` frames
    per second, in the codec :data:`VIDEO_CODECS` gives ``path``'s suffix (.mp4, .mkv, .avi), atomically (a
    temporary beside ``path``, renamed at the end). Returns ``path``."""
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")
    path = Path(path)
    if path.suffix.lower() not in VIDEO_CODECS:
        raise ValueError(f"{path}: a video file's name ends in {', '.join(VIDEO_CODECS)}")
    fourcc, params = VIDEO_CODECS[path.suffix.lower()]
    with atomic_path(path) as tmp:
        writer = None
        try:
            size = None
            for k, frame in enumerate(frames):
                frame = np.asarray(frame)
                if frame.dtype != np.uint8 or not (frame.ndim == 2 or (frame.ndim == 3 and frame.shape[2] == 3)):
                    raise ValueError(f"frame {k}: expected (H, W[, 3]) uint8, got {frame.shape} {frame.dtype}")
                if writer is None:
                    size = (frame.shape[1], frame.shape[0])
                    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*fourcc), float(fps), size, params)
                    if not writer.isOpened():
                        raise OSError(f"{path}: OpenCV cannot open an {fourcc} video writer")
                if (frame.shape[1], frame.shape[0]) != size:
                    raise ValueError(f"frame {k} is {frame.shape[1]}x{frame.shape[0]}, the first {size[0]}x{size[1]}")
                writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR) if frame.ndim == 2 else frame[..., ::-1].copy())
            if writer is None:
                raise ValueError("a video needs at least one frame")
        finally:
            if writer is not None:
                writer.release()
    return path
