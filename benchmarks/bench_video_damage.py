"""How many damaged video frames `scope3d import video` names, and that it names no clean one.

Run:  PYTHONPATH=src .venv/bin/python benchmarks/bench_video_damage.py [--videos 6] [--frames 20]
Writes benchmarks/results/video_damage.json and video_damage.png.

FFmpeg conceals a damaged frame and OpenCV returns it as whole; ``scope3d.io.video.read_video`` names a
frame as damaged when FFmpeg printed an error line while decoding it (one decoder thread, the lines
captured per frame). This measures that check against the truth of where the bits were flipped:

* Damaged frames. Videos of a moving tissue-like texture with sensor noise (320 x 240, ``--frames`` at
  10 fps) are written with each codec the opencv wheel encodes (MPEG-4 Part 2 in MP4 and AVI, Motion JPEG,
  FFV1, VP8, HuffYUV); in each, three frames get F bits flipped at uniform positions of their own packet
  (the packets are found in the file from OpenCV's raw packets, ``CAP_PROP_FORMAT`` -1, so every
  container is covered the same way). Per codec and F: the fraction of damaged frames named (recall),
  the frames named that were not damaged (misnamed), the damaged frames left unnamed whose decoded pixels
  differ from the clean video's (silently wrong; with an inter-frame codec possibly through an earlier
  damaged frame), and the videos refused outright. And what a user sees: of the frames whose decoded
  pixels differ from the clean video's (wrong), how many the import flags as damaged or predicted from a
  damaged frame up to the next key frame (``DamagedFrame.carries_damage``), and how many it flags whose
  pixels are right.
* Headers zeroed: frames 5 and 6 with the first 64 bytes of their packets zeroed (a lost block): frames
  the container states, frames read (OpenCV stops at a frame it cannot decode in some codecs) and named.
* Clean videos: the same videos undamaged, and 60-frame ones: frames named (must be none), and the
  frames their containers state against those read (the import says when fewer are read).
* Cost: decoding a 608 x 608 MPEG-4 video on one decoder thread (what the check needs) against OpenCV's
  default (one per core), wall and CPU time, with the machine's load recorded.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from scope3d.errors import InputError
from scope3d.io.video import DamagedFrame, DecodeCheck, probe_video, read_video
from scope3d.utils.figures import new_figure, save_figure

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"
CODECS = [("mp4v", ".mp4"), ("XVID", ".avi"), ("MJPG", ".avi"), ("FFV1", ".mkv"), ("VP80", ".mkv"),
          ("HFYU", ".avi")]
FLIPS_PER_FRAME = (1, 4, 16)
DAMAGED_FRAMES = (3, 9, 14)  # of each video: one early, one mid, one late (within a 20-frame video)
WIDTH, HEIGHT, FPS = 320, 240, 10.0


def scope_frames(n: int, seed: int, size: tuple[int, int] = (WIDTH, HEIGHT)) -> list[np.ndarray]:
    """n BGR frames of a crop window moving 3 px a frame over a smooth random texture, with independent
    sensor noise (3 grey levels): compressible like a scope's video, never two identical frames."""
    rng = np.random.default_rng(seed)
    width, height = size
    texture = cv2.GaussianBlur(rng.random((height + 8, width + 3 * n, 3)).astype(np.float32), (0, 0), 4.0)
    texture = cv2.normalize(texture, None, 20, 235, cv2.NORM_MINMAX)
    frames = []
    for k in range(n):
        crop = texture[4:4 + height, 3 * k:3 * k + width] + rng.normal(0, 3.0, (height, width, 3))
        frames.append(np.clip(crop, 0, 255).astype(np.uint8))
    return frames


def write(path: Path, frames: list[np.ndarray], fourcc: str) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), FPS, frames[0].shape[1::-1])
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot write {fourcc}")
    for frame in frames:
        writer.write(frame)
    writer.release()


def packet_spans(path: Path) -> list[tuple[int, int]]:
    """(start, end) in the file of each frame's packet: OpenCV's raw packets found in the file's bytes."""
    data = path.read_bytes()
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG, [cv2.CAP_PROP_FORMAT, -1])
    spans, at = [], 0
    while capture.grab():
        ok, packet = capture.retrieve()
        raw = packet.tobytes()
        start = data.find(raw, at)
        if start < 0:
            raise RuntimeError(f"{path}: packet {len(spans)} not found in the file")
        spans.append((start, start + len(raw)))
        at = start + len(raw)
    capture.release()
    return spans


def decoded(path: Path) -> tuple[list[np.ndarray], list[DamagedFrame]]:
    check = DecodeCheck()
    frames = [f.image for f in read_video(path, check=check)]
    assert check.frames_decoded == len(frames)
    return frames, check.damaged


def damage_trials(work: Path, n_videos: int, n_frames: int) -> dict:
    results = {}
    for fourcc, ext in CODECS:
        for flips in FLIPS_PER_FRAME:
            counts = {"damaged_frames": 0, "named": 0, "misnamed": 0, "silently_wrong": 0, "unchanged": 0,
                      "videos": 0, "videos_refused": 0, "wrong_frames": 0, "wrong_frames_flagged": 0,
                      "right_frames_flagged": 0}
            for v in range(n_videos):
                clean = work / f"clean_{fourcc}_{v}{ext}"
                if not clean.exists():
                    write(clean, scope_frames(n_frames, seed=v), fourcc)
                clean_frames, clean_named = decoded(clean)
                assert not clean_named, f"clean {fourcc} video {v} flagged: {clean_named}"
                data = bytearray(clean.read_bytes())
                spans = packet_spans(clean)
                rng = random.Random(1000 * v + flips)
                truth = [k for k in DAMAGED_FRAMES if k < len(spans)]
                for k in truth:
                    start, end = spans[k]
                    for _ in range(flips):
                        data[rng.randrange(start, end)] ^= 1 << rng.randrange(8)
                damaged_path = work / f"damaged{ext}"
                damaged_path.write_bytes(bytes(data))
                counts["videos"] += 1
                try:
                    frames, named = decoded(damaged_path)
                except InputError:
                    counts["videos_refused"] += 1
                    continue
                named_set = {d.index for d in named}
                counts["damaged_frames"] += len(truth)
                counts["named"] += len(named_set & set(truth))
                counts["misnamed"] += len(named_set - set(truth))
                for k in set(truth) - named_set:
                    same = k < len(frames) and np.array_equal(frames[k], clean_frames[k])
                    counts["unchanged" if same else "silently_wrong"] += 1
                for k, (frame, clean_frame) in enumerate(zip(frames, clean_frames)):
                    wrong = not np.array_equal(frame, clean_frame)
                    flagged = any(d.carries_damage(k) for d in named)
                    counts["wrong_frames"] += wrong
                    counts["wrong_frames_flagged"] += wrong and flagged
                    counts["right_frames_flagged"] += flagged and not wrong
            counts["recall"] = round(counts["named"] / max(counts["damaged_frames"], 1), 3)
            counts["wrong_flagged_fraction"] = round(counts["wrong_frames_flagged"] / max(counts["wrong_frames"], 1), 3)
            results[f"{fourcc} {flips}"] = {"codec": fourcc, "container": ext, "flips_per_frame": flips, **counts}
            print(fourcc, flips, counts, flush=True)
    return results


def header_trials(work: Path, n_frames: int) -> dict:
    """Frames 5 and 6 of each codec's video with the first 64 bytes of their packets zeroed (a lost or
    overwritten block of the file): frames the container states, frames read, frames named."""
    out = {}
    for fourcc, ext in CODECS:
        path = work / f"header_{fourcc}{ext}"
        write(path, scope_frames(n_frames, seed=50), fourcc)
        spans = packet_spans(path)
        data = bytearray(path.read_bytes())
        for k in (5, 6):
            start, end = spans[k]
            data[start:min(start + 64, end)] = bytes(min(64, end - start))
        path.write_bytes(bytes(data))
        try:
            check = DecodeCheck()
            frames = sum(1 for _ in read_video(path, check=check))
            out[fourcc] = {"frames_in_container": probe_video(path).n_frames, "frames_read": frames,
                           "frames_named": [d.index for d in check.damaged]}
        except InputError as exc:
            out[fourcc] = {"refused": str(exc)}
        print("headers zeroed", fourcc, out[fourcc], flush=True)
    return out


def clean_trials(work: Path, n_videos: int) -> dict:
    """Longer clean videos of every codec: frames named (must be none)."""
    out = {}
    for fourcc, ext in CODECS:
        named = frames = stated = 0
        for v in range(n_videos):
            path = work / f"long_{fourcc}_{v}{ext}"
            write(path, scope_frames(60, seed=100 + v), fourcc)
            images, damaged = decoded(path)
            frames += len(images)
            named += len(damaged)
            stated += probe_video(path).n_frames
        # the container's count against the frames read: the import says when fewer are read
        out[fourcc] = {"videos": n_videos, "frames": frames, "frames_named": named, "frames_in_container": stated}
        print("clean", fourcc, out[fourcc], flush=True)
    return out


def decode_cost(work: Path, n_frames: int = 120) -> dict:
    """Decoding a 608 x 608 MPEG-4 video: one decoder thread against OpenCV's default."""
    path = work / "cost.mp4"
    write(path, scope_frames(n_frames, seed=7, size=(608, 608)), "mp4v")
    out = {"frames": n_frames, "size_px": [608, 608], "cpus": os.cpu_count()}
    for label, params in (("one_thread", [cv2.CAP_PROP_N_THREADS, 1]), ("opencv_default", [])):
        best = None
        for _ in range(3):
            load = os.getloadavg()[0]
            wall, cpu = time.perf_counter(), time.process_time()
            capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG, params)
            n = 0
            while capture.grab():
                capture.retrieve()
                n += 1
            capture.release()
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            if best is None or cpu < best["cpu_s"]:
                best = {"wall_s": round(wall, 3), "cpu_s": round(cpu, 3), "frames_per_s_wall": round(n / wall, 1),
                        "frames_per_cpu_s": round(n / cpu, 1), "load_average": round(load, 2)}
        out[label] = best
    print("cost", out, flush=True)
    return out


def plot(results: dict, path: Path) -> None:
    fig = new_figure(figsize=(11, 4.2))
    for column, (key, label) in enumerate((("recall", "damaged frames named"),
                                           ("wrong_flagged_fraction", "wrong frames flagged (named or predicted)"))):
        ax = fig.add_subplot(1, 2, column + 1)
        for fourcc, _ in CODECS:
            rows = [results[f"{fourcc} {f}"] for f in FLIPS_PER_FRAME]
            ax.plot(FLIPS_PER_FRAME, [r[key] for r in rows], marker="o", label=fourcc)
        ax.set_xscale("log")
        ax.set_xticks(FLIPS_PER_FRAME, [str(f) for f in FLIPS_PER_FRAME])
        ax.set_ylim(-0.03, 1.03)
        ax.set_xlabel("bits flipped in each damaged frame's packet")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("FFmpeg's error lines as a damage check (no frame of a clean video named)")
    save_figure(fig, path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--videos", type=int, default=6, help="videos per codec and flip count")
    parser.add_argument("--frames", type=int, default=20, help="frames per damaged video")
    parser.add_argument("--results", type=Path, default=RESULTS / "video_damage.json")
    args = parser.parse_args()
    start_load = os.getloadavg()
    with tempfile.TemporaryDirectory(dir="/dev/shm" if Path("/dev/shm").is_dir() else None) as tmp:
        work = Path(tmp)
        cpu = time.process_time()
        damage = damage_trials(work, args.videos, args.frames)
        headers = header_trials(work, args.frames)
        clean = clean_trials(work, 3)
        cost = decode_cost(work)
        cpu = time.process_time() - cpu
    report = {"what": __doc__.split("\n\n")[0], "damaged_frames_per_video": list(DAMAGED_FRAMES),
              "size_px": [WIDTH, HEIGHT], "frames_per_video": args.frames, "videos": args.videos,
              "damage": damage, "headers_zeroed": headers, "clean": clean, "decode_cost": cost, "cpu_s": round(cpu, 1),
              "load_average_at_start": start_load, "load_average_at_end": os.getloadavg()}
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(report, indent=2) + "\n")
    plot(damage, args.results.with_suffix(".png"))
    print("wrote", args.results)


if __name__ == "__main__":
    main()
