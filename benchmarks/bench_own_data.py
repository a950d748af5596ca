"""docs/own_data.md's walkthrough measured against the phantom lab's truth, beside the true-pose twin.

For each robot error: render a raw recording, run the page's commands (calibrate, calibrate-hand-eye with
the robot log, import frames, check), then map the imported scan and its twin (the same frames with the
true camera poses and the same tolerance), both with the recording's truth attached. Writes
benchmarks/results/own_data.json.

The *robot twin* is the same log imported through the true hand-eye: the robot's own error without what
calibration, hand-eye and interpolation add. With an error-free robot it is the twin up to interpolation.

``--spread K`` also maps K copies of the twin whose true poses are each moved by a random rigid error of
``--spread-mm`` (and ``--spread-mm`` / 40 mm radians, the hand-eye's lever): how much the map's error moves
when its inputs move by far less than anything the import adds, i.e. the resolution at which a walkthrough
can be said to lose nothing against its twin.

    python benchmarks/bench_own_data.py [--robot-errors 0 0.2] [--seeds 0] [--size 304] [--spread K]
                                        [--spread-mm 0.01] [--results FILE]
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from scope3d.cli.main import main as scope3d
from scope3d.geometry.pose import Pose
from scope3d.io.camera_json import read_camera_json
from scope3d.io.dataset import load_dataset, write_dataset
from scope3d.io.hand_eye_json import read_hand_eye_json
from scope3d.io.ply import read_ply
from scope3d.io.poses_csv import read_poses_csv
from scope3d.phantoms.recording import RecordingOptions, write_recording
from scope3d.sensor.pose_tolerance import MeasuredPose

RESULTS = Path(__file__).resolve().parent / "results" / "own_data.json"


def _run(*args: str) -> None:
    words = [w for a in args for w in (sorted(glob.glob(a)) if "*" in a else [a])]
    if scope3d(words + ["--quiet"]) != 0:
        raise SystemExit(f"scope3d {' '.join(args)} failed")


def _with_truth(root: Path, dataset: Path, out: Path, *, true_poses_measured: bool,
                nudge: list[Pose] | None = None) -> Path:
    """``dataset`` with the recording's truth attached (or, for the twin, the true poses as measured, each
    first composed with its ``nudge``, a cam_from_cam error)."""
    ds = load_dataset(dataset)
    names, truth = read_poses_csv(root / "rec" / "truth" / "poses.csv")
    true = [dict(zip(names, truth))[n].pose for n in ds.names]
    measured = [MeasuredPose(p, m.tolerance) for p, m in zip(true, ds.poses)] if true_poses_measured else ds.poses
    if nudge is not None:
        measured = [MeasuredPose(e @ m.pose, m.tolerance) for e, m in zip(nudge, measured)]
    write_dataset(out, ds.camera, [dataset / "frames" / n for n in ds.names], measured, names=ds.names,
                  true_poses=true, true_surface=read_ply(root / "rec" / "truth" / "surface.ply"),
                  scene=json.loads((root / "rec" / "truth" / "scene.json").read_text()))
    return out


def _map(dataset: Path, out: Path) -> dict:
    _run("map", str(dataset), "--out", str(out))
    report = json.loads((out / "report.json").read_text())
    s, p = report["surface_error_mm"], report["pose_error"]
    return {"direct_mean_mm": s["direct"]["mean"], "after_icp_mean_mm": s["after_icp"]["mean"],
            "after_icp_median_mm": s["after_icp"]["median"], "poses_after_map_mm": p["position_mm_mean"],
            "time_s": report["time_s"]}


def _nudges(n: int, size_mm: float, rng: np.random.Generator) -> list[Pose]:
    """``n`` rigid errors, each a translation of ``size_mm`` and a rotation of ``size_mm / 40`` rad about
    uniformly random directions."""
    def directions() -> np.ndarray:
        d = rng.normal(size=(n, 3))
        return d / np.linalg.norm(d, axis=1, keepdims=True)
    return [Pose.from_rotvec(w, t) for w, t in zip(directions() * size_mm / 40.0, directions() * size_mm)]


def case(root: Path, robot_error_mm: float, seed: int, size: int, spread: int = 0, spread_mm: float = 0.01) -> dict:
    started = time.perf_counter()
    write_recording(RecordingOptions(size=(size, size), speed_mm_s=50.0, robot_error_mm=robot_error_mm, seed=seed),
                    root / "rec")
    os.chdir(root)
    _run("calibrate", "rec/calibration/*.png", "--board", "9x6", "--square", "2", "--mask-circle", "--out", "cal")
    _run("calibrate-hand-eye", "rec/hand_eye/*.png", "--camera", "cal/camera.json", "--board", "9x6", "--square", "2",
         "--robot-log", "rec/hand_eye/robot_log.csv", "--pose-format", "xyz-qxyzw", "--unit", "m",
         "--frame-times", "rec/hand_eye/frame_times.csv", "--out", "he")
    _run("import", "frames", "rec/scan/video.mkv", "--camera", "cal/camera.json", "--poses", "rec/scan/robot_log.csv",
         "--pose-format", "xyz-qxyzw", "--unit", "m", "--frame-times", "rec/scan/frame_times.csv",
         "--hand-eye", "he/hand_eye.json", "--tolerance", "0.5", "--tolerance-deg", "0.25", "--every", "3",
         "--out", "scan")
    _run("import", "frames", "rec/scan/video.mkv", "--camera", "cal/camera.json", "--poses", "rec/scan/robot_log.csv",
         "--pose-format", "xyz-qxyzw", "--unit", "m", "--frame-times", "rec/scan/frame_times.csv",
         "--hand-eye", "rec/truth/hand_eye.json", "--tolerance", "0.5", "--tolerance-deg", "0.25", "--every", "3",
         "--out", "robot_twin")
    ds = load_dataset(root / "scan", check_images=True)
    names, truth = read_poses_csv(root / "rec" / "truth" / "poses.csv")
    true = dict(zip(names, truth))
    errors = np.array([m.pose.distance_to(true[n].pose) for n, m in zip(ds.names, ds.poses)])
    got, he_truth = read_hand_eye_json(root / "he" / "hand_eye.json"), read_hand_eye_json(root / "rec" / "truth" / "hand_eye.json")
    return {
        "robot_error_mm": robot_error_mm, "seed": seed, "size_px": size, "frames": len(ds),
        "fx_px": read_camera_json(root / "cal" / "camera.json").fx,
        "fx_true_px": read_camera_json(root / "rec" / "truth" / "camera.json").fx,
        "hand_eye_error": {"mm": float(np.linalg.norm(got.translation - he_truth.translation)),
                           "deg": float(np.rad2deg(got.distance_to(he_truth)[1]))},
        "imported_pose_error": {"mean_mm": float(errors[:, 0].mean()), "max_mm": float(errors[:, 0].max()),
                                "max_deg": float(np.rad2deg(errors[:, 1].max()))},
        "walkthrough_map": _map(_with_truth(root, root / "scan", root / "scan_gt", true_poses_measured=False),
                                root / "map"),
        "twin_map": _map(_with_truth(root, root / "scan", root / "twin", true_poses_measured=True), root / "twin_map"),
        "robot_twin_map": _map(_with_truth(root, root / "robot_twin", root / "robot_twin_gt",
                                           true_poses_measured=False), root / "robot_twin_map"),
        "nudged_twin_maps": [
            _map(_with_truth(root, root / "scan", root / f"twin{k}", true_poses_measured=True,
                             nudge=_nudges(len(ds), spread_mm, np.random.default_rng([seed, 77, k]))),
                 root / f"twin{k}_map") for k in range(spread)],
        "spread_mm": spread_mm,
        "wall_s": round(time.perf_counter() - started, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot-errors", type=float, nargs="+", default=[0.0, 0.2])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--size", type=int, default=304)
    parser.add_argument("--spread", type=int, default=0, help="nudged twins per case (default 0)")
    parser.add_argument("--spread-mm", type=float, default=0.01, help="each nudged twin's pose error, mm")
    parser.add_argument("--results", type=Path, default=RESULTS, help=f"where the JSON goes (default {RESULTS.name})")
    args = parser.parse_args()
    args.results = args.results.resolve()  # each case works in its own folder
    rows = []
    for error in args.robot_errors:
        for seed in args.seeds:
            with tempfile.TemporaryDirectory(prefix="bench-own-data-") as tmp:
                rows.append(case(Path(tmp), error, seed, args.size, args.spread, args.spread_mm))
            print(json.dumps(rows[-1]))
    args.results.resolve().write_text(json.dumps({"machine": platform.platform(), "cpus": os.cpu_count(),
                                   "load_average": os.getloadavg(), "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
