"""Throughput of `scope3d import video --keyframes` on a long synthetic scope video, and its key-frame rule.

Run:  PYTHONPATH=src .venv/bin/python benchmarks/bench_video_import.py [--frames 3000] [--size 608]
Writes benchmarks/results/video_import.json and video_import.png.

The video: a crop window of SIZE x SIZE (608, the scanning fibre endoscope's frame, sec. 3.1) moved over a
large tissue texture like the reference's scan (sec. 2.3.2, 30 fps, 1.13 s per planned view): at each
"view" the window dwells 14 frames, then moves half an image to the next view in 20 frames (views 50 %
apart, a lawn-mower path), while rolling slowly (10 degrees amplitude, 10 s period); the circular field
(radius 300/608 of the frame) is black outside, each frame has independent sensor noise (3 grey levels).
Written as MPEG-4 with cv2.VideoWriter, then timed in this process, one stage after another:

1. decode only (``read_video``), the floor any import pays;
2. decode + key-frame choice (``KeyframeSelector.offer`` on every frame);
3. the whole ``video_import.run`` with key frames (also PNG-encodes the key frames and writes the dataset);
4. ``scope3d import video --keyframes`` as a user runs it, in its own process (start-up included), whose
   peak memory is recorded: the import streams, so it should not grow with the video.

Frames per second are wall and CPU (process) time; the machine is shared by several jobs, so the 1-minute
load average is recorded around each stage and CPU time is the steadier figure. The 20,000-frame figure is
a linear extrapolation (the import streams: constant memory, constant work per frame; the key frames'
PNG writes grow with their number, which grows with the path length, also linearly).

Also: the key-frame count against ``min_shift_fraction`` (a sweep on the same video), the true overlap of
consecutive key frames (from the known window path), and the phase-correlation peak of one view against
itself moved, rolled, zoomed and against an unrelated view, on a dense and a pale texture, with and
without the circular field (the numbers behind ``KeyframeOptions.min_response``). And the lab's bladder:
the 30 mm spiral plan rendered as a 30 fps video (200 x 200, one view per second), written as MP4 and
imported with ``--keyframes`` and the plan: key frames against the true camera motion, and the planned
poses against the true ones.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from scope3d.feature.keyframes import KeyframeOptions, KeyframeSelector
from scope3d.io.video import probe_video, read_video, write_video
from scope3d.phantoms.textures import tissue_texture
from scope3d.pipelines import video_import
from scope3d.pipelines.video_import import VideoImportOptions
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import PoseTolerance
from scope3d.utils.figures import new_figure, save_figure

FPS = 30.0
DWELL_FRAMES, MOVE_FRAMES = 14, 20  # 34 frames = 1.13 s per view at 30 fps (sec. 2.3.2: 10 min, 529 views)
VIEW_STEP = 0.5  # of the image: views 50 % apart
ROLL_AMPLITUDE_DEG, ROLL_PERIOD_S = 10.0, 10.0
NOISE_GREY = 3.0
FIELD_RADIUS_FRACTION = 300.0 / 608.0
TEXTURE_MM, TEXTURE_MM_PER_TEXEL = 100.0, 0.04  # 2500 x 2500 texels


def window_path(n_frames: int, size: int, texture_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Window centres (n, 2) texture px and rolls (n,) degrees: dwell, move, dwell... along a lawn-mower
    path of views ``VIEW_STEP * size`` apart, back and forth."""
    margin = size * 0.75  # room for the rolled window's corners
    step = VIEW_STEP * size
    xs = np.arange(margin, texture_px - margin + 1e-9, step)
    ys = np.arange(margin, texture_px - margin + 1e-9, step)
    views = [np.array([x, y]) for r, y in enumerate(ys) for x in (xs if r % 2 == 0 else xs[::-1])]
    views = views + views[::-1][1:-1]  # back again
    centres = []
    k = 0
    while len(centres) < n_frames:
        a, b = views[k % len(views)], views[(k + 1) % len(views)]
        centres += [a] * DWELL_FRAMES
        centres += [a + (b - a) * (j + 1) / MOVE_FRAMES for j in range(MOVE_FRAMES)]
        k += 1
    centres = np.array(centres[:n_frames])
    rolls = ROLL_AMPLITUDE_DEG * np.sin(2 * np.pi * np.arange(n_frames) / (FPS * ROLL_PERIOD_S))
    return centres, rolls


def render_views(texture: np.ndarray, centres, rolls, size: int, seed: int, *, field: bool = True):
    """The window's frames, (size, size, 3) uint8 RGB, one at a time."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size]
    outside = np.hypot(xx - (size - 1) / 2, yy - (size - 1) / 2) > FIELD_RADIUS_FRACTION * size
    # a bank of noise frames used in turn (drawing 1.1 M normal numbers per frame would make writing the
    # video the slowest part of the benchmark); consecutive frames still never share their noise
    bank = [np.round(rng.normal(0, NOISE_GREY, (size, size, 3))).astype(np.int16) for _ in range(7)]
    for k, ((cx, cy), roll) in enumerate(zip(centres, rolls)):
        m = cv2.getRotationMatrix2D((float(cx), float(cy)), float(roll), 1.0)
        m[:, 2] += [(size - 1) / 2 - cx, (size - 1) / 2 - cy]
        view = cv2.warpAffine(texture, m, (size, size), flags=cv2.INTER_LINEAR)
        view = np.clip(view + bank[k % len(bank)], 0, 255).astype(np.uint8)
        if field:
            view[outside] = 0
        yield view


def timed(label: str, n_frames: int, run) -> dict:
    load0 = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    extra = run() or {}
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    cpu = extra.get("child_cpu_s", cpu)  # a stage run in its own process counts that process's CPU
    row = {"stage": label, "frames": n_frames, "wall_s": round(wall, 3), "cpu_s": round(cpu, 3),
           "frames_per_s_wall": round(n_frames / wall, 1), "frames_per_s_cpu": round(n_frames / cpu, 1),
           "extrapolated_20000_frames_wall_s": round(20000 * wall / n_frames, 1),
           "extrapolated_20000_frames_cpu_s": round(20000 * cpu / n_frames, 1),
           "load_1min": [round(load0, 2), round(os.getloadavg()[0], 2)], **extra}
    print(f"{label:34s} {row['frames_per_s_wall']:7.1f} frames/s wall, {row['frames_per_s_cpu']:7.1f} CPU "
          f"(20,000 frames: {row['extrapolated_20000_frames_wall_s']:.0f} s wall; load {row['load_1min']})")
    return row


def cli_import(video: Path, camera: Camera, out: Path) -> dict:
    """The command a user runs, in its own process: its wall time is in the stage, its peak memory here."""
    import subprocess
    import sys

    from scope3d.io.camera_json import camera_to_dict
    from scope3d.utils.jsonio import write_json

    write_json(out.parent / "camera.json", camera_to_dict(camera))
    # the child reports its own VmHWM: getrusage's ru_maxrss would carry this process's size through the
    # fork (Linux keeps the pre-exec high-water mark)
    code = ("import sys; from scope3d.cli.main import main; rc = main(sys.argv[1:]); "
            "sys.stderr.write([l for l in open('/proc/self/status') if l.startswith('VmHWM')][0]); sys.exit(rc)")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run([sys.executable, "-c", code, "import", "video", str(video), "--camera",
                           str(out.parent / "camera.json"), "--keyframes", "--no-progress", "--out", str(out)],
                          check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    hwm_kb = int(done.stderr.strip().splitlines()[-1].split()[1])
    return {"child_cpu_s": round(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, 3),
            "child_peak_rss_mb": round(hwm_kb / 1024, 1)}


def bladder_video(n_frames: int) -> dict:
    """The lab's bladder, the 30 mm / 70 deg spiral plan rendered as a 30 fps video (one view per second),
    written as MP4 and imported with --keyframes and the plan: key frames against the true motion."""
    from scope3d.io.scan_plan import read_scan_plan
    from scope3d.phantoms import generate
    from scope3d.pipelines import scan_plan
    from scope3d.sfm.scan_planning import ScanPlanOptions

    with tempfile.TemporaryDirectory(prefix="bench-bladder-") as tmp:
        tmp = Path(tmp)
        scan_plan.run(ScanPlanOptions(standoff_mm=30.0, overlap=0.5, fov_deg=70.0), "bladder", tmp / "plan")
        plan = read_scan_plan(tmp / "plan" / "plan.json")
        t0 = time.perf_counter()
        seq = generate("bladder", plan=plan, video_fps=FPS, seconds_per_view=1.0, size=(200, 200), n_frames=n_frames)
        render_s = time.perf_counter() - t0
        write_video(tmp / "video.mp4", seq.frames, FPS)
        options = VideoImportOptions(keyframes=KeyframeOptions(), seconds_per_view=1.0,
                                     plan_tolerance=PoseTolerance.from_degrees(5.0, 10.0))
        out = video_import.run(options, tmp / "video.mp4", seq.camera, tmp / "dataset", plan=plan).dataset_dir
        source = json.loads((out / "dataset.json").read_text())["source"]
        from scope3d.io.dataset import load_dataset

        imported = load_dataset(out)
    kept = source["frame_indices"]
    truth = seq.true_poses
    steps = [truth[a].distance_to(truth[b]) for a, b in zip(kept[:-1], kept[1:])]
    per_frame = [truth[i].distance_to(truth[i + 1]) for i in range(len(truth) - 1)]
    planned_error = [m.pose.distance_to(truth[i]) for m, i in zip(imported.poses, kept)]
    row = {
        "frames": len(seq), "size_px": [200, 200], "fps": FPS, "seconds_per_view": 1.0,
        "views_covered": round(len(seq) / FPS, 1), "render_s": round(render_s, 1),
        "key_frames": len(kept), "key_frame_indices": kept,
        "true_motion_per_frame": {"centre_mm_median": round(float(np.median([d[0] for d in per_frame])), 3),
                                  "rotation_deg_median": round(float(np.degrees(np.median([d[1] for d in per_frame]))), 2)},
        "true_motion_between_key_frames": {
            "centre_mm_median": round(float(np.median([d[0] for d in steps])), 3),
            "rotation_deg_median": round(float(np.degrees(np.median([d[1] for d in steps]))), 2),
            "rotation_deg_max": round(float(np.degrees(np.max([d[1] for d in steps]))), 2)},
        "planned_pose_error": {"centre_mm_max": float(max(e[0] for e in planned_error)),
                               "rotation_deg_max": float(np.degrees(max(e[1] for e in planned_error)))},
    }
    print(f"bladder video: {len(seq)} frames, {len(kept)} key frames; true rotation between key frames "
          f"{row['true_motion_between_key_frames']['rotation_deg_median']} deg median "
          f"(per frame {row['true_motion_per_frame']['rotation_deg_median']})")
    return row


def response_table(size: int = 304) -> list[dict]:
    """Phase-correlation peak of a view against itself moved, rolled, zoomed, and against another view."""
    rows = []
    rng = np.random.default_rng(5)
    cases = [("same view", 0, 0, 0, 1), ("shift 0.1", 0.1, 0, 0, 1), ("shift 0.2", 0.2, 0, 0, 1),
             ("shift 0.3", 0.3, 0, 0, 1), ("shift 0.45", 0.45, 0, 0, 1), ("roll 5 deg", 0, 0, 5, 1),
             ("roll 10 deg", 0, 0, 10, 1), ("roll 20 deg", 0, 0, 20, 1), ("zoom 1.1", 0, 0, 0, 1.1),
             ("zoom 1.25", 0, 0, 0, 1.25), ("unrelated view", 0, 0.8, 0, 1)]
    for density_label, density in (("dense vessels", 0.7), ("pale (0.25 x vessels)", 0.175)):
        texture = tissue_texture((60.0, 60.0), 0.04, seed=11, vessel_density_per_cm2=density)
        c = np.array([750.0, 750.0])
        for field in (False, True):
            for label, sx, sy, roll, zoom in cases:
                views = []
                for centre, angle, scale in ((c, 0.0, 1.0), (c + np.array([sx, sy]) * size, roll, zoom)):
                    m = cv2.getRotationMatrix2D(tuple(float(v) for v in centre), angle, scale)
                    m[:, 2] += [(size - 1) / 2 - centre[0], (size - 1) / 2 - centre[1]]
                    view = cv2.warpAffine(texture, m, (size, size)).astype(np.float32)
                    view = np.clip(view + rng.normal(0, NOISE_GREY, view.shape), 0, 255).astype(np.uint8)
                    if field:
                        yy, xx = np.mgrid[0:size, 0:size]
                        view[np.hypot(xx - (size - 1) / 2, yy - (size - 1) / 2) > FIELD_RADIUS_FRACTION * size] = 0
                    views.append(view)
                sel = KeyframeSelector(field_radius_px=FIELD_RADIUS_FRACTION * size if field else None)
                sel.offer(views[0])
                d = sel.offer(views[1])
                rows.append({"texture": density_label, "circular_field": field, "case": label,
                             "shift_fraction": round(d.shift_fraction, 3), "response": round(d.response, 3),
                             "kept": d.keep})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3000)
    parser.add_argument("--size", type=int, default=608)
    parser.add_argument("--bladder-frames", type=int, default=240,
                        help="frames of the rendered bladder video (30 fps, one planned view per second)")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "video_import.json"))
    parser.add_argument("--throughput-only", action="store_true",
                        help="time only decoding and decode + key frames (e.g. on a real 20,000-frame video, not "
                             "extrapolated): no dataset import, sweep, bladder video or figure")
    args = parser.parse_args()
    size, n = args.size, args.frames

    texture = tissue_texture((TEXTURE_MM, TEXTURE_MM), TEXTURE_MM_PER_TEXEL, seed=7)
    centres, rolls = window_path(n, size, texture.shape[0])
    camera = Camera.from_fov(size, size, 70.0, mask_radius_px=FIELD_RADIUS_FRACTION * size)
    with tempfile.TemporaryDirectory(prefix="bench-video-") as tmp:
        video = Path(tmp) / "scan.mp4"
        t0 = time.perf_counter()
        write_video(video, render_views(texture, centres, rolls, size, seed=1), FPS)
        print(f"wrote {n} frames of {size}x{size} in {time.perf_counter() - t0:.0f} s "
              f"({video.stat().st_size / 1e6:.0f} MB)")
        info = probe_video(video)

        # warm OpenCV's FFT and FFmpeg's decoder before timing
        warm = KeyframeSelector(field_radius_px=camera.mask_radius_px)
        for frame, _ in zip(read_video(video), range(30)):
            warm.offer(frame.image)

        stages = []
        stages.append(timed("decode only", n, lambda: {"frames_read": sum(1 for _ in read_video(video))}))
        decisions = []

        def choose():
            selector = KeyframeSelector(field_radius_px=camera.mask_radius_px)
            decisions.extend(selector.offer(f.image) for f in read_video(video))
            return {"key_frames": selector.n_kept}

        stages.append(timed("decode + key frames", n, choose))
        if args.throughput_only:
            result = {"benchmark": "video_import (throughput only)",
                      "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
                      "video": {"frames": n, "size_px": [size, size], "fps": FPS, "codec": "mp4v (MPEG-4 Part 2)",
                                "duration_s": round(n / FPS, 1), "container_frames": info.n_frames,
                                "file_mb": round(video.stat().st_size / 1e6, 1)},
                      "goal_frames_per_s": 30.0, "stages": stages,
                      "key_frames": sum(1 for d in decisions if d.keep)}
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
            print(f"wrote {args.out}")
            return
        out_dir = Path(tmp) / "dataset"

        def whole():
            video_import.run(VideoImportOptions(keyframes=KeyframeOptions()), video, camera, out_dir)
            return {"key_frames": len(list((out_dir / "frames").iterdir()))}

        stages.append(timed("import_video --keyframes (dataset)", n, whole))
        stages.append(timed("scope3d import video --keyframes (CLI process)", n,
                            lambda: cli_import(video, camera, Path(tmp) / "cli")))

        kept = [i for i, d in enumerate(decisions) if d.keep]
        # true motion between consecutive key frames: translation as a fraction of the image, and roll
        true_shift = [float(np.hypot(*(centres[b] - centres[a])) / size) for a, b in zip(kept[:-1], kept[1:])]
        true_roll = [float(abs(rolls[b] - rolls[a])) for a, b in zip(kept[:-1], kept[1:])]
        static = [i for i in range(1, n) if np.all(centres[i] == centres[i - 1]) and abs(rolls[i] - rolls[i - 1]) < 0.05]
        static_kept = sorted(set(static) & set(kept))
        moving_frames = n - len(static)
        measured_error = []
        last = 0
        for i, d in enumerate(decisions[1:], start=1):
            # where the last key frame's centre appears in frame i, relative to frame i's centre: the
            # texture offset turned by frame i's roll (cv2.getRotationMatrix2D's rotation part)
            a, b = math.cos(math.radians(rolls[i])), math.sin(math.radians(rolls[i]))
            true = np.array([[a, b], [-b, a]]) @ (centres[last] - centres[i])
            measured_error.append(float(np.hypot(*(np.array(d.shift_px) - true))))
            if d.keep:
                last = i

        sweep = []
        for fraction in (0.1, 0.15, 0.2, 0.25, 0.3, 0.4):
            selector = KeyframeSelector(KeyframeOptions(min_shift_fraction=fraction),
                                        field_radius_px=camera.mask_radius_px)
            for frame in read_video(video):
                selector.offer(frame.image)
            sweep.append({"min_shift_fraction": fraction, "key_frames": selector.n_kept})
            print(f"min_shift_fraction {fraction:.2f}: {selector.n_kept} key frames")

    responses = response_table()
    bladder = bladder_video(args.bladder_frames)
    result = {
        "benchmark": "video_import",
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "video": {"frames": n, "size_px": [size, size], "fps": FPS, "codec": "mp4v (MPEG-4 Part 2)",
                  "duration_s": round(n / FPS, 1), "container_frames": info.n_frames,
                  "path": f"lawn-mower over a tissue texture, views {VIEW_STEP} image apart, dwell {DWELL_FRAMES} "
                          f"frames + move {MOVE_FRAMES} frames per view, roll {ROLL_AMPLITUDE_DEG} deg amplitude "
                          f"{ROLL_PERIOD_S} s period, circular field r = {FIELD_RADIUS_FRACTION:.3f} x size, "
                          f"noise sigma {NOISE_GREY} grey levels"},
        "goal_frames_per_s": 30.0,
        "stages": stages,
        "bladder_phantom_video": bladder,
        "key_frames": {
            "options": KeyframeOptions().__dict__, "count": len(kept), "frames": n,
            "frames_static": len(static), "static_frames_kept": len(static_kept),
            "frames_moving": moving_frames,
            "true_shift_between_key_frames": {"median": round(float(np.median(true_shift)), 3),
                                              "p5": round(float(np.percentile(true_shift, 5)), 3),
                                              "p95": round(float(np.percentile(true_shift, 95)), 3),
                                              "max": round(float(np.max(true_shift)), 3)},
            "true_roll_between_key_frames_deg": {"median": round(float(np.median(true_roll)), 2),
                                                 "max": round(float(np.max(true_roll)), 2)},
            "shift_estimate_error_px": {"median": round(float(np.median(measured_error)), 2),
                                        "p95": round(float(np.percentile(measured_error, 95)), 2),
                                        "note": "against the true image shift of the last key frame's centre"},
        },
        "sweep_min_shift_fraction": sweep,
        "phase_correlation_response": responses,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    figure(result, decisions, centres, size, Path(args.out).with_suffix(".png"))
    print(f"wrote {args.out}")


def figure(result: dict, decisions, centres, size: int, path: Path) -> None:
    fig = new_figure((11, 4), dpi=110)
    ax = fig.add_subplot(1, 2, 1)
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(centres, axis=0).T))]) / size
    frames = np.arange(len(centres))
    show = frames < min(len(frames), 600)
    ax.plot(frames[show], travelled[show], color="0.3", lw=1, label="window path travelled (images)")
    kept = [i for i, d in enumerate(decisions) if d.keep and show[i]]
    ax.plot(kept, travelled[kept], "o", ms=4, color="tab:red", label="key frames")
    ax.set_xlabel("frame (30 fps)")
    ax.set_ylabel("distance travelled / image size")
    ax.set_title("key frames on the first 20 s: none while dwelling")
    ax.legend(loc="upper left", fontsize=8)
    ax = fig.add_subplot(1, 2, 2)
    sweep = result["sweep_min_shift_fraction"]
    ax.plot([s["min_shift_fraction"] for s in sweep], [s["key_frames"] for s in sweep], "o-")
    ax.axvline(KeyframeOptions().min_shift_fraction, color="0.6", ls="--", lw=1, label="default")
    ax.set_xlabel("min_shift_fraction")
    ax.set_ylabel(f"key frames of {result['video']['frames']}")
    ax.set_title("key frames against the shift threshold")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


if __name__ == "__main__":
    main()
