"""The camera error a surgical-field map cannot go below: the gauge placed from noisy reported poses.

Images fix a map's cameras only up to a similarity (the gauge); the reported poses place it. A map whose
shape is perfect is still off by the placement its gauge rule picks from the reports. This benchmark
gives every rule the TRUE trajectory (a perfect shape) and the phantom lab's reported poses (uniform
errors, ``scope3d phantom --pose-noise N``: phantoms.measure_poses, ±N mm, ±0.5 N deg, tolerance the same)
and measures what each rule leaves, over many noise draws (no rendering: the poses alone decide it):

  bounded  -- estimators.gauge.align_gauge(bounded=True), the bounded map's rule (least squares among the
              placements that keep every pose in its box; before issue 33's box prior it was least squares
              among those well inside every box, and results/map_gauge_limit.json is of that rule);
  free     -- align_gauge(bounded=False), the free map's rule (least squares on centres and orientations);
  centres  -- the Umeyama similarity of the centres alone (bench_map_pose_noise.py's 'oracle' row).

Per rule, level and draw: mean and max camera-centre error (mm), mean orientation error (deg) and the
scale error |s - 1| (after rigid ICP only the scale is left of a gauge error; it sets the surface error
after ICP). A map's camera error near its rule's value here is the gauge's, not the shape's
(bench_map_pose_noise.py reports the map's camera_shape_error_mm, its error after a similarity to the truth).

Writes benchmarks/results/map_gauge_limit.json. Run (about a minute):
    PYTHONPATH=src .venv/bin/python benchmarks/bench_gauge_limit.py [--draws 100] [--levels 1,3,5]
"""
from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

from scope3d import phantoms
from scope3d.estimators.gauge import align_gauge
from scope3d.geometry.rotation import rotation_angle_between
from scope3d.geometry.similarity import fit_similarity
from scope3d.phantoms.trajectories import build_trajectory
from scope3d.utils.jsonio import write_json

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "map_gauge_limit.json"


def placement_errors(true_poses, placed_centres: np.ndarray, placed_rotations: np.ndarray | None) -> dict:
    true_c = np.stack([p.centre for p in true_poses])
    err = np.linalg.norm(placed_centres - true_c, axis=1)
    # the placement's scale: the true trajectory is moved rigidly plus a scale, so the spread ratio is it
    spread = np.linalg.norm(true_c - true_c.mean(axis=0))
    scale = float(np.linalg.norm(placed_centres - placed_centres.mean(axis=0)) / spread)
    out = {"camera_mean_mm": float(err.mean()), "camera_max_mm": float(err.max()), "scale_error": abs(scale - 1.0)}
    if placed_rotations is not None:
        out["orientation_mean_deg"] = float(np.degrees(np.mean(
            [rotation_angle_between(r, p.rotation) for r, p in zip(placed_rotations, true_poses)])))
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--draws", type=int, default=100, help="noise draws per level (seeds 0..draws-1; default 100)")
    p.add_argument("--levels", default="1,3,5", help="uniform noise levels, mm (default 1,3,5)")
    p.add_argument("--trajectory", default="grid5x6", help="phantom trajectory (default grid5x6, the dome's)")
    p.add_argument("--out", type=Path, default=OUT)
    a = p.parse_args(argv)
    levels = [float(v) for v in a.levels.split(",")]
    true_poses = build_trajectory(a.trajectory).poses
    t0 = time.perf_counter()
    rows = []
    for level in levels:
        for seed in range(a.draws):
            measured = phantoms.measure_poses(true_poses, level, seed=seed)
            for rule in ("bounded", "free"):
                placed = align_gauge(true_poses, measured, bounded=rule == "bounded")
                rows.append({"rule": rule, "level_mm": level, "seed": seed,
                             **placement_errors(true_poses, np.stack([q.centre for q in placed]),
                                                np.stack([q.rotation for q in placed]))})
            true_centres = np.stack([q.centre for q in true_poses])
            centres = fit_similarity(true_centres, np.stack([m.pose.centre for m in measured])).apply(true_centres)
            rows.append({"rule": "centres", "level_mm": level, "seed": seed,
                         **placement_errors(true_poses, centres, None)})
            rows.append({"rule": "reported", "level_mm": level, "seed": seed,
                         **placement_errors(true_poses, np.stack([m.pose.centre for m in measured]),
                                            np.stack([m.pose.rotation for m in measured]))})
    summary = []
    for level in levels:
        for rule in ("bounded", "free", "centres", "reported"):
            sel = [r for r in rows if r["rule"] == rule and r["level_mm"] == level]
            cam = np.array([r["camera_mean_mm"] for r in sel])
            sc = np.array([r["scale_error"] for r in sel])
            summary.append({"rule": rule, "level_mm": level, "draws": len(sel),
                            "camera_mean_mm": {"mean": float(cam.mean()), "p10": float(np.percentile(cam, 10)),
                                               "p90": float(np.percentile(cam, 90))},
                            "scale_error": {"mean": float(sc.mean()), "p90": float(np.percentile(sc, 90))}})
            print(f"{level:4g} mm {rule:9s} camera {cam.mean():.3f} mm (p10-p90 {np.percentile(cam, 10):.3f}-"
                  f"{np.percentile(cam, 90):.3f})  |scale-1| {sc.mean():.4f} (p90 {np.percentile(sc, 90):.4f})")
    write_json(a.out, {"benchmark": "camera error of a perfect shape placed by each gauge rule from reported poses",
                       "command": " ".join([Path(sys.executable).name, *sys.argv]),
                       "machine": {"python": platform.python_version(), "platform": platform.platform()},
                       "trajectory": a.trajectory, "frames": len(true_poses), "levels_mm": levels, "draws": a.draws,
                       "elapsed_s": round(time.perf_counter() - t0, 1), "summary": summary, "rows": rows})
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
