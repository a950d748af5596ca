"""Where the time of a whole ``scope3d panorama`` run goes (issue 11, "the whole 3D panorama of a spiral in
under 2 minutes"): :func:`scope3d.pipelines.panorama.run` as the command runs it (stars, textured wall,
files), with planned poses and images only, per stage in wall and CPU seconds (CPU: every thread of the
process, so CPU above wall means both cores worked), with the load average around each run and what the
map is worth against the truth (frames registered, wall error after similarity, the stars' scale error),
so that a faster run is seen to give the same map.

Cases: the sweep benchmark's datasets (``bench_panorama_3d_sweep.py``), rendered once into ``--cache`` by
the CLI: ``spiral15_unseen`` (the unseen cavity's 15 mm plan, 165 views of 608 px), ``dry_d1`` (the default
bladder spiral, 36 frames of 608 px, ``--pose-noise 1``), or any other case tag of the sweeps.

Usage: PYTHONPATH=src python benchmarks/bench_panorama_stages.py [--cases TAG ...] [--poses planned images]
    [--cache DIR]
merges its rows (one per case and poses; a row run again replaces the earlier one) into
benchmarks/results/panorama_3d_stages.json.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from bench_panorama_3d import load
from bench_panorama_3d_sweep import SWEEPS, dataset_for
from scope3d.io.dataset import load_dataset
from scope3d.pipelines.panorama import Panorama3dOptions, run
from scope3d.utils.atomic import atomic_file

RESULTS = Path(__file__).parent / "results"
CASES = {tag: (plan, args) for sweep in SWEEPS.values() for tag, _, plan, args in sweep}


def one_run(path: Path, use_planned: bool) -> dict:
    ds = load_dataset(path)
    before = load()
    c0, t0 = time.process_time(), time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        report = run(Panorama3dOptions(use_planned_poses=use_planned), ds, Path(tmp) / "out").report
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    timings = report["timings_s"]
    return {"poses": "planned" if use_planned else "images only", "n_frames": report["n_frames"],
            "image_px": [ds.camera.width, ds.camera.height],
            "n_registered": report["n_registered"], "n_points": report["n_points"],
            "n_pairs_tried": report["n_pairs_tried"], "n_pairs": report["n_pairs"],
            "surface_error_mean_mm": report.get("surface_error_mm", {}).get("after_similarity", {}).get("mean"),
            "scale_error_fraction": report.get("scale_error_fraction"),
            "texture_texel_mm": report.get("texture_texel_mm"), "texture_atlas_px": report.get("texture_atlas_px"),
            "wall_s": wall, "cpu_s": cpu,
            "stage_wall_s": {**timings, "rest_s": wall - sum(timings.values())},
            "stage_cpu_s": report["cpu_by_stage_s"],
            "load_before": before, "load_after": load()}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", nargs="*", default=["spiral15_unseen", "dry_d1"], choices=sorted(CASES))
    ap.add_argument("--poses", nargs="*", default=["planned", "images"], choices=["planned", "images"])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/scope3d_panorama_sweep"))
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    out = RESULTS / "panorama_3d_stages.json"
    for tag in args.cases:
        plan, phantom_args = CASES[tag]
        path, commands = dataset_for(args.cache, tag, plan, phantom_args)
        for poses in args.poses:
            row = {"case": tag, "commands": commands, **one_run(path, poses == "planned")}
            # read again just before writing: rows of other cases run meanwhile are kept
            result = json.loads(out.read_text()) if out.exists() else {"rows": []}
            result.update(cpu_count=os.cpu_count(),
                          note="wall and CPU seconds per stage of scope3d.pipelines.panorama.run (stars, "
                               "textured wall, files included); CPU counts every thread of the process")
            result["rows"] = [r for r in result["rows"] if (r["case"], r["poses"]) != (tag, row["poses"])] + [row]
            RESULTS.mkdir(exist_ok=True)
            with atomic_file(out) as f:
                f.write(json.dumps(result, indent=2, default=float))
            print(json.dumps(row, indent=1, default=float), flush=True)


if __name__ == "__main__":
    main()
