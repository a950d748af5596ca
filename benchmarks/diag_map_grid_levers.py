"""Which lever lifts the dome grids' point count to >= 1.3x COLMAP's, and what does it cost the default demo?

Issue 34: with the default preset the dome's 5x6 and 7x8 grids (30 and 56 frames, 608 x 608, exact poses,
bench_map_views.py) kept 0.83x and 0.72x COLMAP's points. Levers (docs/surgical_map.md, "More views"):
SIFT's contrast threshold (0.04: ~1,240 and ~820 keypoints per frame on the 30- and 56-frame grids), the partners per frame (10, one per
direction of motion, 20) and the splitting of match-graph components that hold one frame twice
(``TrackOptions.split_inconsistent``, on in ``map``; off = such components dropped whole).

Two parts, each variant of VARIANTS (or those named on the command line):
1. ``grids``: bench_map_views.py's grid rows (its scope3d_run: points, reprojection error, load + features +
   matching + bundle time, best of 2) and COLMAP once per grid (its colmap_run, known poses, the scope's
   mask), so the ratio is measured in the same run;
2. ``demo``: the default demo map (``make demo``: ``scope3d phantom dome --seed S --pose-noise 0.25`` then
   ``scope3d map``, i.e. ``run(MAP_PRESETS["default"])``) for seeds 0, 5 and 11: points, reprojection error,
   surface error against the CAD surface direct and after ICP, camera error, and the pipeline's time
   (the wall time of ``run``, best of 2; ``cpu_s``, the least CPU time of the 2, which the other jobs on a
   shared machine disturb less; the accuracy is the same in both runs; ``time_s_last`` and ``timings_s``:
   the pipeline's own times in the last run).

Writes benchmarks/results/map_grid_levers.json (or $MAP_GRID_LEVERS_OUT; rows appended as they finish) and prints them.
    PYTHONPATH=src .venv/bin/python benchmarks/diag_map_grid_levers.py [--part grids|demo] [--no-colmap] [VARIANT ...]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from bench_map_views import colmap_run, scope3d_run

from scope3d import phantoms
from scope3d.io.dataset import load_dataset
from scope3d.pipelines.surgical_map import MAP_PRESETS, MapOptions, run

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "map_grid_levers.json"
DEFAULT = MAP_PRESETS["default"]
DEMO_SEEDS = (0, 5, 11)
DEMO_POSE_NOISE_MM = 0.25  # make demo's
REPEATS = 2  # best of 2 for the times: the machine is shared


def variant(contrast: float = 0.04, partners: int = 10, per_direction: int = 0, split: bool = True) -> MapOptions:
    """The default preset with these four values (their defaults: the default preset's when this was written)."""
    return replace(DEFAULT, features=replace(DEFAULT.features, contrast_threshold=contrast),
                   pairs=replace(DEFAULT.pairs, max_pairs_per_frame=partners, max_pairs_per_direction=per_direction),
                   tracks=replace(DEFAULT.tracks, split_inconsistent=split))


VARIANTS = {
    "default": variant(),
    "split_off": variant(split=False),
    "per_direction_1": variant(per_direction=1),
    "partners_20": variant(partners=20),
    "contrast_0.035": variant(contrast=0.035),
    "contrast_0.03": variant(contrast=0.03),
    "contrast_0.03_per_direction_1": variant(contrast=0.03, per_direction=1),
    "contrast_0.025_per_direction_1": variant(contrast=0.025, per_direction=1),
    "contrast_0.02": variant(contrast=0.02),
    "contrast_0.02_split_off": variant(contrast=0.02, split=False),
    "contrast_0.02_per_direction_1": variant(contrast=0.02, per_direction=1),
    "contrast_0.02_partners_20": variant(contrast=0.02, partners=20),
    "contrast_0.01": variant(contrast=0.01),
}


def grid_rows(names: list[str], tmp: Path, *, colmap: bool = True) -> list[dict]:
    rows = []
    for trajectory in ("grid5x6", "grid7x8"):
        ds = load_dataset(phantoms.write(phantoms.generate("dome", trajectory, seed=0), tmp / trajectory))
        for name in names:
            m = scope3d_run(ds, replace(VARIANTS[name], figures=False, fluorescence=None), tmp / f"w_{trajectory}_{name}")
            rows.append(_emit({"part": "grids", "grid": trajectory, "n_views": len(ds), "variant": name, **m}))
        if colmap:
            rows.append(_emit({"part": "grids", "grid": trajectory, "n_views": len(ds), "variant": "colmap",
                               **colmap_run(ds, tmp / f"colmap_{trajectory}", 1)}))
    return rows


def demo_rows(names: list[str], tmp: Path) -> list[dict]:
    rows = []
    for seed in DEMO_SEEDS:
        ds = load_dataset(phantoms.write(phantoms.generate("dome", "grid5x6", seed=seed, pose_noise_mm=DEMO_POSE_NOISE_MM),
                                         tmp / f"demo{seed}"))
        report: dict[str, dict] = {}
        walls: dict[str, list[float]] = {name: [] for name in names}
        cpus: dict[str, list[float]] = {name: [] for name in names}
        for k in range(REPEATS):  # the variants interleaved, so that the load drifts over all of them alike
            for name in names:
                t0, cpu0 = time.perf_counter(), _cpu_s()
                report[name] = run(VARIANTS[name], ds, tmp / f"map_{seed}_{name}_{k}").report
                walls[name].append(time.perf_counter() - t0)
                cpus[name].append(_cpu_s() - cpu0)
        for name in names:
            r, wall, cpu = report[name], min(walls[name]), min(cpus[name])
            se = r["surface_error_mm"]
            rows.append(_emit({
                "part": "demo", "seed": seed, "variant": name, "n_points": r["n_points"], "n_features": r["n_features"],
                "n_pairs": r["n_pairs"], "mean_reprojection_error_px": round(r["mean_reprojection_error_px"], 4),
                "surface_direct_mean_mm": round(se["direct"]["mean"], 4), "surface_direct_p95_mm": round(se["direct"]["p95"], 4),
                "surface_after_icp_mean_mm": round(se["after_icp"]["mean"], 4),
                "surface_after_icp_p95_mm": round(se["after_icp"]["p95"], 4),
                "camera_position_mm_mean": round(r["pose_error"]["position_mm_mean"], 4),
                "camera_orientation_deg_mean": round(r["pose_error"]["orientation_deg_mean"], 4),
                "time_s_last": round(r["time_s"], 2), "wall_s": round(wall, 2), "cpu_s": round(cpu, 2),
                "timings_s": {k: round(v, 2) for k, v in r["timings_s"].items()}}))
    return rows


def _cpu_s() -> float:
    """CPU seconds of this process and its finished children (the figures' worker): less sensitive than
    the wall time to the other jobs on a shared machine."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _emit(row: dict) -> dict:
    print(json.dumps(row), flush=True)
    out = Path(os.environ.get("MAP_GRID_LEVERS_OUT", OUT))
    results = json.loads(out.read_text()) if out.exists() else {"rows": []}
    results["rows"].append({**row, "load_average": round(os.getloadavg()[0], 1),
                            "utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime())})
    out.write_text(json.dumps(results, indent=1) + "\n")
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--part", choices=("grids", "demo"), action="append")
    p.add_argument("--no-colmap", action="store_true", help="grids: scope3d only (COLMAP's rows of an earlier run apply)")
    p.add_argument("variants", nargs="*", metavar="VARIANT", help=f"any of {', '.join(VARIANTS)} (default: all)")
    args = p.parse_args()
    names = args.variants or list(VARIANTS)
    unknown = sorted(set(names) - set(VARIANTS))
    if unknown:
        p.error(f"unknown variant(s) {', '.join(unknown)}")
    with tempfile.TemporaryDirectory() as tmp_name:
        for part in args.part or ("grids", "demo"):
            if part == "grids":
                grid_rows(names, Path(tmp_name), colmap=not args.no_colmap)
            else:
                demo_rows(names, Path(tmp_name))


if __name__ == "__main__":
    main()
