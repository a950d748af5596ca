"""Time the dome's survey video (issue 36): rendering it at 30 fps, with and without a resection, and the
change detection's sweep per reference frame.

Run:  .venv/bin/python benchmarks/bench_dome_video.py [--size 320x240] [--fps 30]
Writes benchmarks/results/dome_video.json: frames, wall and CPU (process) seconds per frame and the
1-minute load average around each case (the machine is shared: CPU time is the steadier figure); for
the detection, the scene of tests/test_surface_change.py at the same size (a map from three sweeps
before a 3 x 1.5 mm pit, six references after it).
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from scope3d.mvs.plane_sweep import sweep
from scope3d.mvs.surface_change import SurfaceChangeOptions, detect_surface_change
from scope3d.phantoms import build_scene, generate
from scope3d.phantoms.resection import Resection


def _timed(fn):
    load = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t0, time.process_time() - c0, [round(load, 2), round(os.getloadavg()[0], 2)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "dome_video.json"))
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    build_scene("dome")  # once per process, not timed
    rows = []
    for label, resection in (("survey video", None), ("survey video, pit cut at 7 s", Resection(7.0))):
        seq, wall, cpu, load = _timed(lambda: generate("dome", size=size, video_fps=args.fps, resection=resection))
        rows.append({"case": label, "frames": len(seq), "image": args.size, "fps": args.fps,
                     "video_s": float(seq.times_s[-1]), "render_s": round(wall, 2),
                     "seconds_per_frame": round(wall / len(seq), 4), "cpu_seconds_per_frame": round(cpu / len(seq), 4),
                     "load_1min": load})
        print(rows[-1])
    seq = generate("dome", size=size, video_fps=args.fps, n_frames=60,
                   resection=Resection(1.0, radius_mm=3.0, depth_mm=1.5, centre_xy_mm=(0.0, 9.0)))
    first, poses, options = seq.scene_info["resection"]["first_frame"], seq.true_poses, SurfaceChangeOptions()
    points, sigma = [], []
    for r in (4, 14, 24):
        m = sweep(seq.camera, seq.frames[r], poses[r], [seq.frames[r - 4], seq.frames[r + 4]],
                  [poses[r - 4], poses[r + 4]], (10.0, 35.0), options=options.sweep)
        points.append(poses[r].inverse().transform(m.points_cam))
        ij = m.pixels.astype(int)
        sigma.append(m.sigma_mm[ij[:, 1], ij[:, 0]])
    after = list(range(first, len(seq)))
    refs = list(range(0, len(after), 5))
    change, wall, cpu, load = _timed(lambda: detect_surface_change(
        seq.camera, np.concatenate(points), np.concatenate(sigma), [seq.frames[i] for i in after],
        [poses[i] for i in after], references=refs, options=options))
    detection = {"map_points": int(change.changed.size), "references": len(refs), "detect_s": round(wall, 2),
                 "seconds_per_reference": round(wall / len(refs), 3), "cpu_seconds_per_reference": round(cpu / len(refs), 3),
                 "load_1min": load, "summary": change.summary()}
    print(detection)
    out = {"benchmark": "dome_video", "note": __doc__.split("\n\n")[0], "render": rows, "surface_change": detection}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
