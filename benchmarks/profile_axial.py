"""Where one axial-stereo pair's time goes (issue 17): CPU and wall per sub-stage of ``reconstruct_pair``.

Renders the 4-frame M8 thread phantom at 608 x 608 (or reads DATASET), reconstructs frames 1-2 with the
pipeline's two-view options once to warm up (imports, numba's cache, OpenCV's first calls), then REPEATS
times with timers wrapped around the stage functions and OpenCV calls, and prints per-pair means with the
machine's load; merges them into benchmarks/results/profile_axial.json under LABEL. Run:
    PYTHONPATH=src .venv/bin/python benchmarks/profile_axial.py [DATASET] [--repeats 7] [--label LABEL]

Timers are inclusive and nested (the refinement includes its box filters). CPU is ``time.process_time``,
every thread of the process during the call: a stage that runs on both cores shows more CPU than wall on
a quiet machine. For a "before" table, run this file with another checkout's src on PYTHONPATH (stages a
version lacks are simply absent).
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import tempfile
import time
from pathlib import Path

import cv2

from scope3d import phantoms
from scope3d.io.dataset import load_dataset
from scope3d.mvs import axial, confidence, dense_matching, two_view
from scope3d.pipelines.axial import AxialOptions

OUT = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


def _timers(totals: dict):
    def timed(label, fn):
        def call(*args, **kwargs):
            cpu, wall = time.process_time(), time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                row = totals[label]
                row[0] += time.process_time() - cpu
                row[1] += time.perf_counter() - wall
                row[2] += 1
        return call
    return timed


def instrument(totals: dict) -> None:
    """Wrap the stage functions (module attributes the pair looks up at call time) and OpenCV's calls."""
    timed = _timers(totals)
    for name in ("remap", "boxFilter", "Sobel", "merge", "split", "erode"):
        if hasattr(cv2, name):
            setattr(cv2, name, timed("cv2." + name, getattr(cv2, name)))
    create = cv2.StereoSGBM_create

    class TimedMatcher:
        def __init__(self, matcher):
            self.matcher = matcher

        def compute(self, *args):
            return timed("cv2 StereoSGBM.compute", self.matcher.compute)(*args)

    cv2.StereoSGBM_create = lambda *a, **k: TimedMatcher(create(*a, **k))
    for module, name in ((two_view, "sgm_disparity"), (dense_matching, "refine_subpixel"), (two_view, "reliability"),
                         (two_view, "make_axial_pair")):
        setattr(module, name, timed(name, getattr(module, name)))
    for name in ("to_polar", "_compute_polar_maps", "range_sigma", "range_from_disparity"):
        setattr(axial.AxialPair, name, timed("AxialPair." + name, getattr(axial.AxialPair, name)))
    if hasattr(confidence, "window_statistics"):
        confidence.window_statistics = timed("window_statistics", confidence.window_statistics)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", nargs="?", help="an axial dataset (default: render the 4-frame thread phantom)")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--label", default="current", help="key of this run in the JSON (e.g. before-COMMIT)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(args.dataset) if args.dataset else phantoms.write(
            phantoms.generate("thread", "axial", seed=0, n_frames=4), Path(tmp) / "thread")
        ds = load_dataset(path)
        options = AxialOptions(method="sgm", frames=(1, 2)).two_view
        images = [ds.frame(k, grey=True) for k in (1, 2)]
        poses = [m.pose for m in ds.poses]

        def pair():
            return two_view.reconstruct_pair(ds.camera, images[0], images[1], poses[1], poses[2], options=options)

        pair()  # warm
        totals = collections.defaultdict(lambda: [0.0, 0.0, 0])
        instrument(totals)
        load_before = os.getloadavg()
        best = None
        for _ in range(args.repeats):
            cpu, wall = time.process_time(), time.perf_counter()
            result = pair()
            row = (time.process_time() - cpu, time.perf_counter() - wall)
            best = row if best is None or row[1] < best[1] else best
            totals["reconstruct_pair"][0] += row[0]
            totals["reconstruct_pair"][1] += row[1]
            totals["reconstruct_pair"][2] += 1
        load_after = os.getloadavg()
    n = args.repeats
    stages = {label: {"cpu_ms": 1e3 * c / n, "wall_ms": 1e3 * w / n, "calls_per_pair": k / n}
              for label, (c, w, k) in sorted(totals.items(), key=lambda kv: -kv[1][0])}
    out = {"grid": list(result.pair.grid.shape), "repeats": n, "best_pair_cpu_ms": 1e3 * best[0],
           "best_pair_wall_ms": 1e3 * best[1], "load_1min_before_after": [load_before[0], load_after[0]],
           "cpu_count": os.cpu_count(), "stages_mean_per_pair": stages}
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "profile_axial.json"
    table = json.loads(path.read_text()) if path.exists() else {}
    table[args.label] = out
    path.write_text(json.dumps(table, indent=2) + "\n")
    print(f"grid {result.pair.grid.shape}, load {load_before[0]:.1f} -> {load_after[0]:.1f}; best pair "
          f"{out['best_pair_wall_ms']:.0f} ms wall, {out['best_pair_cpu_ms']:.0f} ms CPU")
    print(f"{'stage (mean per pair, inclusive)':40s} {'calls':>6s} {'CPU ms':>8s} {'wall ms':>8s}")
    for label, row in stages.items():
        print(f"{label:40s} {row['calls_per_pair']:6.1f} {row['cpu_ms']:8.1f} {row['wall_ms']:8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
