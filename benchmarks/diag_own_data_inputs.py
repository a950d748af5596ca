"""Which of the walkthrough's inputs costs its map: the calibrated camera, the calibrated hand-eye, or both?

docs/own_data.md's recording of one seed, imported four ways (calibrated or true camera.json, to solve the
hand-eye with and to map through; calibrated or true hand_eye.json) and as the twin (true poses), each with
the same 0.5 mm / 0.25 deg box, mapped against the truth. Writes benchmarks/results/own_data_inputs.json.

    python benchmarks/diag_own_data_inputs.py [--seed 5] [--robot-error 0]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from pathlib import Path

import numpy as np
from bench_own_data import _map, _run, _with_truth  # the benchmark beside this one

from scope3d.io.dataset import load_dataset
from scope3d.io.hand_eye_json import read_hand_eye_json
from scope3d.io.poses_csv import read_poses_csv
from scope3d.phantoms.recording import RecordingOptions, write_recording

RESULTS = Path(__file__).resolve().parent / "results" / "own_data_inputs.json"
LOG = ["--pose-format", "xyz-qxyzw", "--unit", "m"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--robot-error", type=float, default=0.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="diag-own-data-") as tmp:
        root = Path(tmp)
        write_recording(RecordingOptions(size=(304, 304), speed_mm_s=50.0, robot_error_mm=args.robot_error,
                                         seed=args.seed), root / "rec")
        os.chdir(root)
        _run("calibrate", "rec/calibration/*.png", "--board", "9x6", "--square", "2", "--mask-circle", "--out", "cal")
        he_truth = read_hand_eye_json(root / "rec" / "truth" / "hand_eye.json")
        names, truth = read_poses_csv(root / "rec" / "truth" / "poses.csv")
        true = dict(zip(names, truth))
        rows = {}
        for name, camera, hand_eye in [("calibrated camera, calibrated hand-eye", "cal", "he_cal"),
                                       ("calibrated camera, true hand-eye", "cal", None),
                                       ("true camera, hand-eye calibrated through it", "rec/truth", "he_true_cam"),
                                       ("true camera, true hand-eye", "rec/truth", None)]:
            if hand_eye is not None and not Path(hand_eye).exists():
                _run("calibrate-hand-eye", "rec/hand_eye/*.png", "--camera", f"{camera}/camera.json", "--board", "9x6",
                     "--square", "2", "--robot-log", "rec/hand_eye/robot_log.csv", *LOG,
                     "--frame-times", "rec/hand_eye/frame_times.csv", "--out", hand_eye)
            he_file = f"{hand_eye}/hand_eye.json" if hand_eye else "rec/truth/hand_eye.json"
            scan = f"scan{len(rows)}"
            _run("import", "frames", "rec/scan/video.mkv", "--camera", f"{camera}/camera.json", "--poses",
                 "rec/scan/robot_log.csv", *LOG, "--frame-times", "rec/scan/frame_times.csv", "--hand-eye", he_file,
                 "--tolerance", "0.5", "--tolerance-deg", "0.25", "--every", "3", "--out", scan)
            ds = load_dataset(root / scan)
            errors = np.array([m.pose.distance_to(true[n].pose)[0] for n, m in zip(ds.names, ds.poses)])
            he = read_hand_eye_json(root / he_file)
            rows[name] = {"hand_eye_error_mm": float(np.linalg.norm(he.translation - he_truth.translation)),
                          "hand_eye_error_along_axis_mm": float((he_truth.rotation.T @ (he.translation - he_truth.translation))[2]),
                          "imported_pose_error_mm": {"mean": float(errors.mean()), "max": float(errors.max())},
                          "map": _map(_with_truth(root, root / scan, root / f"{scan}_gt", true_poses_measured=False),
                                      root / f"{scan}_map")}
            if name.endswith("true hand-eye") and name.startswith("true camera"):
                rows["twin: true camera, true poses"] = {"map": _map(_with_truth(
                    root, root / scan, root / "twin_gt", true_poses_measured=True), root / "twin_map")}
            print(name, json.dumps(rows[name]), flush=True)
    RESULTS.write_text(json.dumps({"machine": platform.platform(), "cpus": os.cpu_count(),
                                   "load_average": os.getloadavg(), "seed": args.seed,
                                   "robot_error_mm": args.robot_error, "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
