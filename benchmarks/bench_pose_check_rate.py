"""Does the per-frame pose check (scope3d.sfm.pose_checks) hold its stated false-alarm rate? (issue 16 section 5)

For each case (survey, seed, glitch) the map's stages run up to the bounded adjustment, then the check
alone (cheaper than two whole maps, which benchmarks/bench_pose_outliers.py runs). Recorded per frame:
the statistic d2, its critical value, the p-value, and d2 against the *true* pose (what the test assumes is
about 6 F(6, nu)); per case: flagged frames, hits (glitched frames found), false alarms, the variance
factor, CPU time. A glitch moves frame n // 2's reported centre along x by G mm.

    PYTHONPATH=src python benchmarks/bench_pose_check_rate.py --cases dome12:21:0,dome12:21:3

Results: results/pose_check_rate.json (merged with the cases already there).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from scope3d import phantoms  # noqa: E402
from scope3d.feature.tracks import build_tracks  # noqa: E402
from scope3d.geometry.pose import Pose  # noqa: E402
from scope3d.geometry.rotation import matrix_to_rotvec  # noqa: E402
from scope3d.io.dataset import load_dataset  # noqa: E402
from scope3d.pipelines import surgical_map as sm  # noqa: E402
from scope3d.sensor.pose_tolerance import MeasuredPose  # noqa: E402
from scope3d.sfm.pose_checks import PoseCheckOptions, test_reported_poses  # noqa: E402
from scope3d.utils.jsonio import write_json  # noqa: E402

SURVEYS = {"dome12": ("grid5x6", 12), "dome56": ("grid7x8", 56)}


def one_case(survey: str, seed: int, shift_mm: float, tmp: Path) -> dict:
    trajectory, n = SURVEYS[survey]
    seq = phantoms.generate("dome", trajectory, size=(320, 240), seed=seed, n_frames=n, pose_noise_mm=0.5)
    dataset = load_dataset(phantoms.write(seq, tmp / f"{survey}_{seed}"))
    glitched = [n // 2] if shift_mm else []
    poses = list(dataset.poses)
    for k in glitched:
        m = poses[k]
        poses[k] = MeasuredPose(Pose.from_centre(m.pose.rotation, m.pose.centre + [shift_mm, 0.0, 0.0]), m.tolerance)
    dataset = replace(dataset, poses=poses)
    options = replace(sm.MapOptions(), figures=False, fluorescence=None, pose_check=PoseCheckOptions())
    frames = [dataset.frame(k) for k in range(len(dataset))]
    features = sm.detect_features(options, dataset, frames)
    matching = sm.match_frames(options, dataset, features)
    sparse = sm.reconstruct(options, dataset, features, matching)
    tracks = build_tracks(features, matching.matches, min_track_length=options.tracks.min_track_length)
    t0 = time.process_time()
    check = test_reported_poses(sparse.camera, dataset.poses, tracks, sparse.poses, options.tracks, options.pose_check)
    cpu = time.process_time() - t0
    truth = dataset.ground_truth.poses
    frames_out = []
    for t in check.tests:
        row = {"frame": t.frame, "status": t.status}
        if t.status == "ok":
            report = dataset.poses[t.frame].pose
            true_offset = np.r_[matrix_to_rotvec(truth[t.frame].rotation @ report.rotation.T),
                                truth[t.frame].centre - report.centre]
            e = t.offset - true_offset
            row.update(d2=round(t.statistic, 3), critical=round(t.critical_value, 2), p_value=t.p_value,
                       d2_vs_truth=round(float(e @ np.linalg.solve(t.covariance, e)), 3), flagged=t.flagged,
                       error_vs_truth_mm=round(float(np.linalg.norm(e[3:])), 3))
        frames_out.append(row)
    flagged = check.flagged
    return {"survey": survey, "seed": seed, "shift_mm": shift_mm, "glitched": glitched, "flagged": flagged,
            "hits": len(set(flagged) & set(glitched)), "false_alarms": sorted(set(flagged) - set(glitched)),
            "variance_factor": check.variance_factor, "frames_tested": sum(r["status"] == "ok" for r in frames_out),
            "check_cpu_s": round(cpu, 2), "load_average": list(os.getloadavg()), "frames": frames_out}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", required=True, help="comma-separated survey:seed:shift_mm")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "pose_check_rate.json"))
    args = ap.parse_args(argv)
    out = Path(args.out)
    runs = json.loads(out.read_text())["runs"] if out.is_file() else []
    tmp = Path(tempfile.mkdtemp(prefix="pose_check_rate_"))
    for case in args.cases.split(","):
        survey, seed, shift = case.split(":")
        row = one_case(survey, int(seed), float(shift), tmp)
        print(json.dumps({k: v for k, v in row.items() if k != "frames"}), flush=True)
        runs = [r for r in runs if (r["survey"], r["seed"], r["shift_mm"]) != (survey, int(seed), float(shift))] + [row]
        out.parent.mkdir(parents=True, exist_ok=True)
        write_json(out, {"runs": runs})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
