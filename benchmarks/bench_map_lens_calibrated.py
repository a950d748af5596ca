"""`scope3d map` through a lens with a camera.json from `scope3d calibrate` and its intrinsic_bounds.json (issue
32's target: "BCBA ends with intrinsics inside the bounds and the same accuracy"), the model's later parameters
(OPENCV's p1, p2; the fisheye's k3, k4) held against refined inside their bounds.

Per lens and seed, as a user would run it:

1. ``scope3d phantom dome --lens LENS --boards 15 --seed S --pose-noise 0.25`` (the default demo: 608 x 608,
   the 5 x 6 grid, 30 frames; plus 15 board views, 9x6 inner corners of 2 mm, through the same lens);
2. ``scope3d calibrate DIR/boards/*.png --board 9x6 --square 2 --model MODEL`` (barrel-70: opencv,
   fisheye-140: fisheye), whose camera.json replaces the dataset's (the lens's true one);
3. ``scope3d map`` three ways, everything else at its defaults:

   * ``fixed``: the calibrated camera held (no bounds file);
   * ``held``: ``--intrinsic-bounds FILE`` (the default): fx, fy, cx, cy, k1, k2 refined inside their bounds,
     the later parameters held at their calibrated values;
   * ``freed``: ``--intrinsic-bounds FILE --refine-later-intrinsics``: every parameter of the model refined
     inside its bounds.

Reported per map: the surface error against the true dome (direct and after ICP; mean, median), the camera
errors against the true poses (mean centre distance, mean rotation), every adjusted intrinsic with its bounds,
whether it ends inside them, and its error against the lens's true value in the calibration's sigmas.

Run (about 25 minutes on 2 cores; ``--work DIR`` keeps the rendered datasets and calibrations for a re-run):
    PYTHONPATH=src .venv/bin/python benchmarks/bench_map_lens_calibrated.py --seeds 0 5 19
Writes benchmarks/results/map_lens_calibrated.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "src"))

LENS_MODELS = {"barrel-70": "opencv", "fisheye-140": "fisheye"}
VARIANTS = ("fixed", "held", "freed")


def stage(lens: str, seed: int, work: Path) -> tuple[Path, Path]:
    """The dataset (its camera.json the calibrated one; the true one kept as camera_true.json) and the
    calibration folder of ``lens`` at ``seed``, rendered and calibrated through the CLI unless already there."""
    from scope3d.cli.main import main as cli

    data = work / f"{lens}_s{seed}"
    cal = work / f"{lens}_s{seed}_cal"
    if not (data / "camera_true.json").is_file():  # camera.json is still the lens's true one
        if not (data / "camera.json").is_file():
            assert cli(["phantom", "dome", "--lens", lens, "--boards", "15", "--seed", str(seed), "--pose-noise",
                        "0.25", "--out", str(data), "--quiet"]) == 0
        shutil.copy(data / "camera.json", data / "camera_true.json")
    if not (cal / "camera.json").is_file():
        boards = sorted(str(p) for p in (data / "boards").glob("*.png"))
        assert cli(["calibrate", *boards, "--board", "9x6", "--square", "2", "--model", LENS_MODELS[lens],
                    "--out", str(cal), "--quiet"]) == 0
    shutil.copy(cal / "camera.json", data / "camera.json")
    return data, cal


def map_variant(variant: str, data: Path, cal: Path, out: Path) -> dict:
    """One `scope3d map` of ``data`` in ``variant`` (see the module docstring); its report's figures."""
    from scope3d.cli.main import main as cli

    args = ["map", str(data), "--out", str(out), "--no-figures", "--quiet"]
    if variant != "fixed":
        args += ["--intrinsic-bounds", str(cal / "intrinsic_bounds.json")]
    if variant == "freed":
        args += ["--refine-later-intrinsics"]
    start = time.perf_counter()
    assert cli(args) == 0, args
    elapsed = time.perf_counter() - start
    return json.loads((out / "report.json").read_text()) | {"_map_time_s": elapsed}


def summarise(variant: str, report: dict, truth: dict, cal_bounds: dict) -> dict:
    surface = report["surface_error_mm"]
    pose = report["pose_error"]
    adjusted = report["camera_adjusted"]["intrinsics"]
    intrinsics = {}
    for name, value in adjusted.items():
        entry = cal_bounds[name]
        intrinsics[name] = {
            "adjusted": value, "calibrated": entry["value"], "true": truth[name], "lower": entry["lower"],
            "upper": entry["upper"], "inside": bool(entry["lower"] <= value <= entry["upper"]),
            "error_sigma": (value - truth[name]) / entry["std"] if entry["std"] > 0 else None,
            "calibrated_error_sigma": (entry["value"] - truth[name]) / entry["std"] if entry["std"] > 0 else None,
        }
    return {"variant": variant,
            "surface_direct_mean_mm": surface["direct"]["mean"], "surface_direct_median_mm": surface["direct"]["median"],
            "surface_icp_mean_mm": surface["after_icp"]["mean"], "surface_icp_median_mm": surface["after_icp"]["median"],
            "pose_position_mm_mean": pose["position_mm_mean"], "pose_orientation_deg_mean": pose["orientation_deg_mean"],
            "measured_position_mm_mean": pose["measured_position_mm_mean"],
            "frames_used": int(report["model_checks"]["frames_used"]),
            "targets_found": sum(t.get("found_label") is not None for t in report["targets_vs_truth"]),
            "n_points": report["n_points"], "mean_reprojection_error_px": report["mean_reprojection_error_px"],
            "every_intrinsic_inside_bounds": all(v["inside"] for v in intrinsics.values()),
            "intrinsics": intrinsics, "map_time_s": report["_map_time_s"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lenses", nargs="+", default=list(LENS_MODELS), choices=list(LENS_MODELS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 5, 19])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--work", type=Path, help="keep rendered datasets and calibrations here (default: a temp dir)")
    parser.add_argument("--results", type=Path, default=RESULTS / "map_lens_calibrated.json")
    args = parser.parse_args()
    machine = {"platform": platform.platform(), "cores": os.cpu_count(), "load_1min_start": os.getloadavg()[0]}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for seed in args.seeds:
            for lens in args.lenses:
                data, cal = stage(lens, seed, work)
                true_cam = json.loads((data / "camera_true.json").read_text())
                cal_report = json.loads((cal / "report.json").read_text())
                cal_bounds = json.loads((cal / "intrinsic_bounds.json").read_text())
                names = [k for k, v in cal_bounds.items() if isinstance(v, dict)]
                truth = {n: true_cam[n] for n in names}
                for variant in args.variants:
                    report = map_variant(variant, data, cal, work / f"{lens}_s{seed}_{variant}")
                    row = {"lens": lens, "model": true_cam.get("model"), "seed": seed,
                           "calibration_rms_px": cal_report.get("rms_px")} | summarise(variant, report, truth, cal_bounds)
                    rows.append(row)
                    print(f"seed {seed:2d} {lens:12s} {variant:6s} surface direct {row['surface_direct_mean_mm']:.4f} "
                          f"after ICP {row['surface_icp_mean_mm']:.4f} mm  pose {row['pose_position_mm_mean']:.4f} mm "
                          f"{row['pose_orientation_deg_mean']:.4f} deg  inside bounds "
                          f"{row['every_intrinsic_inside_bounds']}  {row['map_time_s']:.0f} s", flush=True)
                    for name, v in row["intrinsics"].items():
                        print(f"      {name:3s} {v['adjusted']:12.6g} [{v['lower']:.6g}, {v['upper']:.6g}] true "
                              f"{v['true']:.6g}  err {v['error_sigma']:+.2f} sigma (calibrated "
                              f"{v['calibrated_error_sigma']:+.2f})", flush=True)
    machine["load_1min_end"] = os.getloadavg()[0]
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps({
        "command": "PYTHONPATH=src python benchmarks/bench_map_lens_calibrated.py " + " ".join(sys.argv[1:]),
        "machine": machine,
        "target": "BCBA ends with every intrinsic inside its bounds and the same accuracy (issue 32)",
        "rows": rows}, indent=1) + "\n")
    print(f"wrote {args.results}")


if __name__ == "__main__":
    main()
