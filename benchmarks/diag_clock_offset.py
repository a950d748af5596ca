"""Can a camera/robot clock offset be read off a map? (issue 33: a 5 ms offset left uncorrected)

The phantom lab's raw recording (exact robot, docs/own_data.md's scan) with the frame times given ``--sync``
seconds off on the robot's clock is imported as the walkthrough does (true camera and hand-eye, 0.5 mm /
0.25 deg box) and mapped. A frame time off by ``dt`` puts each imported pose ``v dt`` along the scan's velocity
``v`` (50 mm/s: 0.25 mm at 5 ms); the raster's rows run in alternate directions, so the images see it as a
shift between rows, not as a gauge motion. The map's adjusted centres minus the imported ones, regressed on
the velocity, give ``dt = -sum v.(c_map - c_imported) / sum |v|^2`` (and the same with the true centres: the
offset the imported poses really carry, the interpolation's own share included). Not part of ``scope3d``: a
diagnostic of whether the data hold the offset. Writes benchmarks/results/clock_offset.json.

    python benchmarks/diag_clock_offset.py [--seeds 0 5] [--syncs 0 0.005]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_map_box_width import prepare  # the same recording and import (a script beside this one)

RESULTS = Path(__file__).resolve().parent / "results" / "clock_offset.json"


def case(root: Path, seed: int, sync_s: float) -> dict:
    from scope3d.io.dataset import load_dataset
    from scope3d.io.poses_csv import read_poses_csv
    from scope3d.phantoms.recording import RecordingOptions
    from scope3d.pipelines.surgical_map import MapOptions, run

    rec = root / "rec"
    ds = load_dataset(prepare(root, seed, 304, sync_s))
    result = run(replace(MapOptions(), figures=False, fluorescence=None), ds, root / "map")
    names, truth = read_poses_csv(rec / "truth" / "poses.csv")
    every = {n: p.pose.centre for n, p in zip(names, truth)}
    order = sorted(every)
    at = {n: k for k, n in enumerate(order)}
    # the true velocity at each mapped frame, central differences over the video's neighbouring frames
    velocity = []
    for n in ds.names:
        a, b = max(at[n] - 1, 0), min(at[n] + 1, len(order) - 1)
        velocity.append((every[order[b]] - every[order[a]]) * RecordingOptions().fps / (b - a))
    v = np.stack(velocity)
    imported = np.stack([m.pose.centre for m in ds.poses])
    mapped = np.stack([p.centre for p in result.poses])
    true = np.stack([every[n] for n in ds.names])

    def offset(centres):
        return float(-np.sum(v * (centres - imported)) / np.sum(v * v))

    reported = result.report.get("clock_offset") or {}
    return {"seed": seed, "sync_error_s": sync_s, "offset_from_map_s": offset(mapped), "offset_from_truth_s": offset(true),
            "map_reports": {k: reported.get(k) for k in ("s", "sigma_s", "significant")},
            "imported_vs_truth_mm": float(np.linalg.norm(imported - true, axis=1).mean()),
            "map_vs_truth_mm": float(np.linalg.norm(mapped - true, axis=1).mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 5])
    parser.add_argument("--syncs", type=float, nargs="+", default=[0.0, 0.005])
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    rows = []
    for sync in args.syncs:
        for seed in args.seeds:
            with tempfile.TemporaryDirectory(prefix="diag-clock-") as tmp:
                rows.append(case(Path(tmp), seed, sync))
            print(json.dumps(rows[-1]), flush=True)
    args.results.resolve().write_text(json.dumps({"machine": platform.platform(), "cpus": os.cpu_count(),
                                                  "load_average": os.getloadavg(), "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
