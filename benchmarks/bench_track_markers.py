"""Marker tracking with and without the Kalman filter, on a simulated plate with tracker-like noise.

A four-marker plate (50 x 40 x 10 mm) moves on a smooth curve (40 mm sway, 30 mm/s drift, slow turns) for
20 s at 60 Hz; markers get Gaussian noise of 0.12, 0.25 and 0.5 mm per axis (NDI Polaris Vega's and
Spectra's stated RMS, and twice that), 5 % of rows lose two markers (predicted, not fitted) and 2 % the
whole tool ("Missing", garbage pose). The export is written as NDI Track CSV with the true plate pose as
the tool's own pose, so `scope3d track-markers`'s agreement with it is the error.

Writes benchmarks/results/track_markers.json and track_markers.png. Run:
    .venv/bin/python benchmarks/bench_track_markers.py
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np

from scope3d.cli.main import main as cli
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import matrix_to_quaternion, rotvec_to_matrix
from scope3d.utils.figures import new_figure, save_figure

OUT = Path(__file__).resolve().parents[1] / "benchmarks" / "results"
PLATE_MM = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, 40.0, 0.0], [30.0, 30.0, 10.0]])
RATE_HZ, SECONDS = 60.0, 20.0
SIGMAS_MM = (0.12, 0.25, 0.5)


def write_export(path: Path, sigma: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    t = np.arange(int(RATE_HZ * SECONDS)) / RATE_HZ
    lines = []
    for k, s in enumerate(t):
        plate_from_tracker = Pose.from_centre(rotvec_to_matrix(np.array([0.2 * np.sin(0.3 * s), 0.1 * s, 0.05])),
                                              [300 + 40 * np.sin(0.5 * s), -20 + 30 * s, -1500 + 5 * np.cos(s)])
        tracker_from_plate = plate_from_tracker.inverse()
        markers = tracker_from_plate.transform(PLATE_MM) + rng.normal(0, sigma, (4, 3))
        q = matrix_to_quaternion(tracker_from_plate.rotation)
        missing, drop = rng.random() < 0.02, rng.random() < 0.05
        pose = [1e28, -3e27, 0, 0, 9e9, 0, 0] if missing else [q[3], q[0], q[1], q[2], *tracker_from_plate.translation]
        cells = ["1", "plate", str(k), "1", "Missing" if missing else "OK", *(f"{v:.6f}" for v in pose), "0.1", "4"]
        for m in range(4):
            cells += ["Missing", "nan", "nan", "nan"] if drop and m < 2 else ["OK", *(f"{v:.4f}" for v in markers[m])]
        lines.append(",".join(cells))
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    result = {"machine": {"load_average": os.getloadavg()}, "rate_hz": RATE_HZ, "seconds": SECONDS, "cases": {}}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for sigma in SIGMAS_MM:
            export = tmp / f"ndi_{sigma}.csv"
            write_export(export, sigma, seed=int(sigma * 1000))
            case = {}
            for name, extra in (("raw_fit", ["--no-filter"]), ("kalman", [])):
                out = tmp / f"{name}_{sigma}"
                assert cli(["track-markers", str(export), "--out", str(out), "--marker-sigma", str(sigma), *extra]) == 0
                r = json.loads((out / "report.json").read_text())
                case[name] = {k: r.get(k) for k in ("n_frames", "n_fitted", "n_predicted", "n_without_pose",
                                                    "median_position_diff_mm", "median_orientation_diff_deg",
                                                    "max_position_diff_mm", "max_orientation_diff_deg")}
            result["cases"][str(sigma)] = case
            print(sigma, case, flush=True)
    (OUT / "track_markers.json").write_text(json.dumps(result, indent=1))
    fig = new_figure((6, 4), dpi=100)
    ax = fig.add_subplot()
    for name, marker in (("raw_fit", "o-"), ("kalman", "s-")):
        ax.plot(SIGMAS_MM, [result["cases"][str(s)][name]["median_position_diff_mm"] for s in SIGMAS_MM], marker,
                label=name.replace("_", " "))
    ax.set_xlabel("marker noise per axis (mm)")
    ax.set_ylabel("median plate position error (mm)")
    ax.set_title("marker tracking, 4-marker plate, 60 Hz: with and without the filter", fontsize=9)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, OUT / "track_markers.png")


if __name__ == "__main__":
    main()
