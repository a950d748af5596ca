"""Calibrated intrinsic bounds into BCBA (issue 14, reference sec. 6.3): the dome phantom surveyed with a
camera.json whose field of view is deliberately 3 deg off (56 instead of 53 deg).

1. The phantom's true endoscope camera (400x400, 53 deg, circular field) images a 9x6 board in 15 poses;
   `scope3d calibrate --mask-circle` gives camera.json and intrinsic_bounds.json (+-3 sigma).
2. The dome survey (grid5x6, exact stage poses) is mapped four ways, all in BCBA (bounded) mode:
   exact   : the true camera.json (the reference level),
   wrong   : the 56 deg camera.json, intrinsics held (what a wrong calibration does today),
   free    : the 56 deg camera.json, intrinsics refined without bounds,
   bounded : the 56 deg camera.json, intrinsics refined inside the calibrated bounds (`--intrinsic-bounds`).
   Reported: the adjusted FOV and the surface error against the true dome (direct, and after ICP).

Writes benchmarks/results/calibration_map.json and calibration_map.png. Run:
    PYTHONPATH=src .venv/bin/python benchmarks/bench_calibration_map.py
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path


from scope3d import phantoms
from scope3d.io.dataset import load_dataset
from scope3d.io.images import write_image
from scope3d.io.intrinsic_bounds import read_intrinsic_bounds
from scope3d.phantoms.boards import render_board_views
from scope3d.pipelines.calibrate import CalibrateOptions
from scope3d.pipelines.calibrate import run as run_calibrate
from scope3d.pipelines.surgical_map import MapOptions
from scope3d.pipelines.surgical_map import run as run_map
from scope3d.sensor.calibration import BoardSpec
from scope3d.sensor.camera import Camera
from scope3d.utils.figures import new_figure, save_figure

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
SIZE = (400, 400)
WRONG_FOV_DEG = 56.0


def main() -> int:
    OUT.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()
    c0, t0 = time.process_time(), time.perf_counter()
    seq = phantoms.generate("dome", "grid5x6", size=SIZE, seed=0)
    truth = seq.camera
    wrong = Camera.from_fov(truth.width, truth.height, WRONG_FOV_DEG, k1=truth.k1, k2=truth.k2,
                            mask_radius_px=truth.mask_radius_px)
    result: dict = {"true_fov_deg": truth.fov_deg, "wrong_fov_deg": wrong.fov_deg, "size": list(SIZE),
                    "scene": "dome", "trajectory": "grid5x6", "n_frames": len(seq)}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        board = BoardSpec(9, 6, 1.0)
        views = render_board_views(truth, board, n_views=15, seed=7)
        paths = []
        for i, image in enumerate(views.images):
            paths.append(tmp / f"board{i:02d}.png")
            write_image(paths[-1], image)
        cal = run_calibrate(CalibrateOptions(board, mask_circle=True), paths, tmp / "cal")
        lower, upper = read_intrinsic_bounds(tmp / "cal" / "intrinsic_bounds.json")
        result["calibration"] = {
            "rms_px": cal.calibration.rms_px, "n_views_used": len(cal.calibration.views),
            "fov_deg": cal.calibration.camera().fov_deg, "values": cal.calibration.values.tolist(),
            "std": cal.calibration.std.tolist(), "lower": lower.tolist(), "upper": upper.tolist(),
            "mask_radius_px": cal.calibration.mask_radius_px, "true_mask_radius_px": truth.mask_radius_px,
            "fov_deg_interval": [Camera.from_intrinsics(400, 400, upper).fov_deg,
                                 Camera.from_intrinsics(400, 400, lower).fov_deg],
        }
        phantoms.write(seq, tmp / "exact")
        phantoms.write(replace(seq, camera=wrong), tmp / "wrong")
        base = replace(MapOptions(), figures=False)
        runs = {
            "exact": (tmp / "exact", base),
            "wrong": (tmp / "wrong", base),
            "free": (tmp / "wrong", replace(base, bundle=replace(base.bundle, refine_intrinsics=True))),
            "bounded": (tmp / "wrong", replace(base, bundle=replace(
                base.bundle, refine_intrinsics=True, intrinsic_bounds=(tuple(lower), tuple(upper))))),
        }
        rows = {}
        for name, (folder, options) in runs.items():
            c1, t1 = time.process_time(), time.perf_counter()
            try:
                res = run_map(options, load_dataset(folder), tmp / f"map_{name}")
            except ValueError as exc:  # a wrong camera may leave too few consistent points
                rows[name] = {"failed": str(exc)}
                print(f"{name}: failed: {exc}", flush=True)
                continue
            r = res.report
            rows[name] = {
                "fov_deg": r["camera_adjusted"]["fov_deg"], "intrinsics": r["camera_adjusted"]["intrinsics"],
                "surface_error_mm": {k: {m: r["surface_error_mm"][k][m] for m in ("mean", "median", "rms")}
                                     for k in ("direct", "after_icp")},
                "n_points": r["n_points"], "mean_reprojection_error_px": r["mean_reprojection_error_px"],
                "cpu_s": time.process_time() - c1, "wall_s": time.perf_counter() - t1,
            }
            print(f"{name}: FOV {rows[name]['fov_deg']:.3f} deg, surface error direct mean "
                  f"{rows[name]['surface_error_mm']['direct']['mean']:.4f} mm, after ICP "
                  f"{rows[name]['surface_error_mm']['after_icp']['mean']:.4f} mm", flush=True)
        result["maps"] = rows
    result["machine"] = {"loadavg_at_start": load, "loadavg_at_end": os.getloadavg(),
                         "cpu_s": time.process_time() - c0, "wall_s": time.perf_counter() - t0}
    (OUT / "calibration_map.json").write_text(json.dumps(result, indent=2) + "\n")
    plot(result)
    return 0


def plot(result: dict) -> None:
    rows = {k: v for k, v in result["maps"].items() if "failed" not in v}
    fig = new_figure((9, 3.6), dpi=110)
    ax = fig.add_subplot(1, 2, 1)
    names = list(rows)
    ax.bar(names, [rows[n]["fov_deg"] for n in names], color="tab:blue")
    ax.axhline(result["true_fov_deg"], color="k", ls="--", lw=0.8, label="true FOV")
    lo, hi = result["calibration"]["fov_deg_interval"]
    ax.axhspan(lo, hi, color="tab:green", alpha=0.3, label="calibrated +-3 sigma")
    ax.set_ylim(result["true_fov_deg"] - 1.0, result["wrong_fov_deg"] + 1.0)
    ax.set_ylabel("FOV after bundle adjustment (deg)")
    ax.legend(fontsize=7)
    ax = fig.add_subplot(1, 2, 2)
    ax.bar(names, [rows[n]["surface_error_mm"]["direct"]["mean"] for n in names], color="tab:red")
    ax.set_ylabel("mean surface error, direct (mm)")
    fig.suptitle(f"dome, camera.json FOV {result['wrong_fov_deg']:.0f} deg (truth {result['true_fov_deg']:.0f})")
    fig.tight_layout()
    save_figure(fig, OUT / "calibration_map.png")


if __name__ == "__main__":
    sys.exit(main())
