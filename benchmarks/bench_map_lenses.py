"""`scope3d map` on the dome through each lens of the phantom lab (issue 32's target: every frame mapped, 8/8
targets, surface error after ICP and direct within 10 % of the pinhole render's).

Each lens renders the default demo (``scope3d phantom dome --seed 0 --pose-noise 0.25``: 608 x 608, the
5 x 6 grid, 30 frames; ``--size`` and ``--frames`` shrink it) through ``--lens pinhole|fisheye-140|
barrel-70``, and ``scope3d map`` runs on it with its defaults (the camera.json of the lens's model). Per lens:
frames used, targets found (of the scene's 8), the surface error against the true mesh (direct and after
ICP: mean, median), the mean reprojection error, the map's time; and the ratios to the pinhole's.

Run: ``.venv/bin/python benchmarks/bench_map_lenses.py`` (a few minutes on 2 cores);
writes benchmarks/results/map_lenses.json.
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lenses", nargs="+", default=list(LENS_NAMES), choices=LENS_NAMES)
    parser.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), help="default: the demo's 608 x 608")
    parser.add_argument("--frames", type=int, help="default: the grid's 30")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--pose-noise", type=float, default=0.25)
    parser.add_argument("--results", type=Path, default=RESULTS / "map_lenses.json")
    args = parser.parse_args()
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
              "machine": {"platform": platform.platform(), "cores": os.cpu_count(), "load_1min": os.getloadavg()[0]},
              "target": "every frame mapped, 8/8 targets, surface error (direct and after ICP) within 10 % of pinhole",
              "rows": rows}
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {args.results}")


if __name__ == "__main__":
    main()
