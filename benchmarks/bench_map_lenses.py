"""`scope3d map` and `scope3d localize` on the dome through each lens of the phantom lab (issue 32's targets:
every frame mapped, 8/8 targets, surface error after ICP and direct within 10 % of the pinhole render's;
localization within 20 % of the pinhole's).

Each lens renders the default demo (``scope3d phantom dome --seed 0 --pose-noise 0.25``: 608 x 608, the
5 x 6 grid, 30 frames; ``--size`` and ``--frames`` shrink it) through ``--lens pinhole|fisheye-140|
barrel-70``, and ``scope3d map`` runs on it with its defaults (the camera.json of the lens's model). Per lens:
frames used, targets found (of the scene's 8), the surface error against the true mesh (direct and after
ICP: mean, median), the mean reprojection error, the map's time; and the ratios to the pinhole's.

``--job localize``: per lens, a map of the 5 x 6 survey with its exact poses (``pose_mode="fixed"``, no
surface), then ``scope3d localize`` of the approach to target 4 (8 frames, reported poses 2 mm off, a tool
hiding part of the view; the set-up of tests/test_localization.py) through the same lens: frames localized,
median position and orientation errors against the truth.

Run: ``.venv/bin/python benchmarks/bench_map_lenses.py [--job localize]`` (a few minutes on 2 cores);
writes benchmarks/results/map_lenses.json (localize_lenses.json).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "src"))

LENS_NAMES = ("pinhole", "fisheye-140", "barrel-70")


def run_lens(lens: str, size: tuple[int, int] | None, frames: int | None, seed: int, noise: float, work: Path) -> dict:
    from scope3d.io.dataset import load_dataset
    from scope3d.phantoms import generate, write
    from scope3d.pipelines.surgical_map import MapOptions, run

    seq = generate("dome", seed=seed, pose_noise_mm=noise, size=size, n_frames=frames, lens=lens)
    write(seq, work / lens)
    dataset = load_dataset(work / lens)
    start = time.perf_counter()
    run(MapOptions(), dataset, work / f"{lens}_map")
    elapsed = time.perf_counter() - start
    report = json.loads((work / f"{lens}_map" / "report.json").read_text())
    surface = report["surface_error_mm"]
    found = sum(t.get("found_label") is not None for t in report["targets_vs_truth"])
    checks = report["model_checks"]
    return {"lens": lens, "model": seq.camera.model, "params": seq.camera.params.tolist(),
            "frames": len(seq), "frames_used": int(checks["frames_used"]),
            "targets_found": found, "targets": len(report["targets_vs_truth"]),
            "n_features": report["n_features"], "n_points": report["n_points"],
            "mean_reprojection_error_px": report["mean_reprojection_error_px"],
            "surface_direct_mean_mm": surface["direct"]["mean"], "surface_direct_median_mm": surface["direct"]["median"],
            "surface_icp_mean_mm": surface["after_icp"]["mean"], "surface_icp_median_mm": surface["after_icp"]["median"],
            "map_time_s": elapsed}


def localize_lens(lens: str, size: tuple[int, int] | None, seed: int, work: Path) -> dict:
    from scope3d.cli.main import main as cli
    from scope3d.io.dataset import load_dataset
    from scope3d.phantoms import generate, write
    from scope3d.pipelines.surgical_map import MapOptions
    from scope3d.pipelines.surgical_map import run as run_map

    survey = write(generate("dome", "grid5x6", size=size, seed=seed, lens=lens), work / f"survey_{lens}")
    run_map(MapOptions(pose_mode="fixed", surface=None, fluorescence=None, figures=False), load_dataset(survey),
            work / f"map_{lens}")
    approach = write(generate("dome", "approach", target=4, size=size, seed=seed + 1, n_frames=8,
                              pose_noise_mm=2.0, lens=lens), work / f"approach_{lens}")
    assert cli(["localize", str(work / f"map_{lens}"), str(approach), "--out", str(work / f"loc_{lens}"),
                "--quiet"]) == 0
    report = json.loads((work / f"loc_{lens}" / "report.json").read_text())
    return {"lens": lens, "localized": report["n_localized"], "frames": report["n_frames"],
            "median_position_error_mm": report["median_position_error_mm"],
            "median_orientation_error_deg": report["median_orientation_error_deg"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lenses", nargs="+", default=list(LENS_NAMES), choices=LENS_NAMES)
    parser.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), help="default: the demo's 608 x 608")
    parser.add_argument("--frames", type=int, help="default: the grid's 30")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--pose-noise", type=float, default=0.25)
    parser.add_argument("--job", choices=("map", "localize"), default="map")
    parser.add_argument("--results", type=Path, help="default: results/map_lenses.json (localize_lenses.json)")
    args = parser.parse_args()
    machine = {"platform": platform.platform(), "cores": os.cpu_count(), "load_1min": os.getloadavg()[0]}
    if args.job == "localize":
        rows = []
        with tempfile.TemporaryDirectory() as tmp:
            for lens in args.lenses:
                rows.append(localize_lens(lens, tuple(args.size) if args.size else None, args.seed, Path(tmp)))
                print(rows[-1], flush=True)
        base = next((r for r in rows if r["lens"] == "pinhole"), None)
        for r in rows if base else []:
            r["position_ratio_to_pinhole"] = r["median_position_error_mm"] / base["median_position_error_mm"]
            r["meets_target"] = r["localized"] == r["frames"] and r["position_ratio_to_pinhole"] <= 1.2
        path = args.results or RESULTS / "localize_lenses.json"
        path.write_text(json.dumps({"command": "python benchmarks/bench_map_lenses.py " + " ".join(sys.argv[1:]),
                                    "machine": machine, "target": "localization within 20 % of the pinhole's",
                                    "rows": rows}, indent=1) + "\n")
        print(f"wrote {path}")
        return
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for lens in args.lenses:
            row = run_lens(lens, tuple(args.size) if args.size else None, args.frames, args.seed, args.pose_noise,
                           Path(tmp))
            rows.append(row)
            print(f"{lens:12s} frames {row['frames_used']}/{row['frames']}  targets {row['targets_found']}/"
                  f"{row['targets']}  surface direct {row['surface_direct_mean_mm']:.3f} mm, after ICP "
                  f"{row['surface_icp_mean_mm']:.3f} mm  points {row['n_points']}  {row['map_time_s']:.1f} s",
                  flush=True)
    base = next((r for r in rows if r["lens"] == "pinhole"), None)
    if base is not None:
        for r in rows:
            r["direct_ratio_to_pinhole"] = r["surface_direct_mean_mm"] / base["surface_direct_mean_mm"]
            r["icp_ratio_to_pinhole"] = r["surface_icp_mean_mm"] / base["surface_icp_mean_mm"]
            r["meets_target"] = (r["frames_used"] == r["frames"] and r["targets_found"] == r["targets"]
                                 and r["direct_ratio_to_pinhole"] <= 1.1 and r["icp_ratio_to_pinhole"] <= 1.1)
    report = {"command": "python benchmarks/bench_map_lenses.py " + " ".join(sys.argv[1:]),
              "machine": machine,
              "target": "every frame mapped, 8/8 targets, surface error (direct and after ICP) within 10 % of pinhole",
              "rows": rows}
    path = args.results or RESULTS / "map_lenses.json"
    path.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
