"""Fused pose bounds into BCBA (issue 12 sec. 4, reference sec. 9.3.2): is the map more accurate?

The dome, 608 x 608. An earlier map of the field exists (the 5 x 6 survey with micro-stage poses, the
map ``bench_localize.py`` localizes against). The robot surveys the field again (the same raster, its
own sensor noise) reporting poses +-1 mm, +-0.5 deg (uniform). Per frame three sources:

* robot: the report and its box;
* tracker: an optical tracker's pose, Gaussian 0.2 / 0.2 / 0.5 mm and 0.5 deg (the reference's Table 4.1,
  ``OPTICAL_TRACKER``), simulated from the truth with a seed;
* vision: the frame localized against the earlier map (``sfm.localization``, no tracking between the
  raster's jumps), its covariance plus the map's placement (the micro-stage's tolerance).

Maps of the second survey (``pipelines.surgical_map``, BCBA) with the robot's boxes, and with the 3-sigma
boxes of robot + tracker, and of robot + tracker + vision (``sfm.pose_fusion``). Errors against the truth:
cameras (mean centre and angle) and points (distance to the true surface, direct: no ICP, so the map's
placement counts).

Writes benchmarks/results/fused_map.json. Run (one benchmark at a time; data cached in WORK, shared with
bench_localize.py):
    .venv/bin/python benchmarks/bench_fused_map.py [WORK]
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_localize import prepare  # noqa: E402  (the same earlier map and cache)

from scope3d import phantoms  # noqa: E402
from scope3d.geometry.pose import Pose  # noqa: E402
from scope3d.geometry.rotation import rotvec_to_matrix  # noqa: E402
from scope3d.io.dataset import load_dataset  # noqa: E402
from scope3d.io.map_points import read_map_points  # noqa: E402
from scope3d.pipelines.surgical_map import MapOptions  # noqa: E402
from scope3d.pipelines.surgical_map import run as run_map  # noqa: E402
from scope3d.sensor.pose_tolerance import MICRO_STAGE, OPTICAL_TRACKER  # noqa: E402
from scope3d.sfm.localization import Localizer, LocalizerOptions  # noqa: E402
from scope3d.sfm.pose_fusion import PoseEstimate, fuse_poses, vision_poses  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "benchmarks" / "results"
POSE_NOISE_MM = 1.0
SURVEY_SEED = 11  # the second survey's sensor and pose noise (the first map's survey is seed 0)
TRACKER_SEED = 3


def simulated_tracker(truth: list[Pose], seed: int) -> list[PoseEstimate]:
    sd = np.r_[OPTICAL_TRACKER.orientation_rad, OPTICAL_TRACKER.position_mm]
    rng = np.random.default_rng(seed)
    return [PoseEstimate(Pose.from_centre(rotvec_to_matrix(rng.normal(0, sd[:3])) @ p.rotation,
                                          p.centre + rng.normal(0, sd[3:])), np.diag(sd**2)) for p in truth]


def source_errors(poses: list[Pose], truth: list[Pose]) -> dict:
    d = np.array([p.distance_to(t) for p, t in zip(poses, truth)])
    return {"position_mm_mean": float(d[:, 0].mean()), "orientation_deg_mean": float(np.rad2deg(d[:, 1]).mean())}


def main() -> None:
    work = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.gettempdir()) / "scope3d_bench_localize"
    result = {"machine": {"cpus": os.cpu_count(), "load_average_at_start": os.getloadavg()},
              "pose_noise_mm": POSE_NOISE_MM, "tracker_sigma": {"position_mm": OPTICAL_TRACKER.position_mm.tolist(),
                                                                "orientation_deg": np.rad2deg(OPTICAL_TRACKER.orientation_rad).tolist()}}
    map_dir, _ = prepare(work)
    survey = work / f"survey_robot{SURVEY_SEED}"
    if not survey.exists():
        phantoms.write(phantoms.generate("dome", "grid5x6", seed=SURVEY_SEED, pose_noise_mm=POSE_NOISE_MM), survey)
    ds = load_dataset(survey)
    truth = ds.ground_truth.poses
    tracker = simulated_tracker(truth, TRACKER_SEED)
    t0 = time.perf_counter()
    with Localizer(read_map_points(map_dir), ds.camera, LocalizerOptions(tracking=False)) as loc:
        vision = vision_poses(loc, ds, map_position_sigma_mm=float(MICRO_STAGE.position_mm.max()))
    result["vision_time_s"] = time.perf_counter() - t0
    result["vision_localized"] = sum(v is not None for v in vision)
    boxes = {"robot": ds.poses, "robot+tracker": fuse_poses(ds.poses, [tracker]),
             "robot+tracker+vision": fuse_poses(ds.poses, [tracker, vision])}
    result["sources"] = {"robot": source_errors([m.pose for m in ds.poses], truth),
                         "tracker": source_errors([e.pose for e in tracker], truth),
                         "vision": source_errors([v.pose for v in vision if v is not None],
                                                 [t for v, t in zip(vision, truth) if v is not None])}
    result["rows"] = {}
    for name, poses in boxes.items():
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            report = run_map(replace(MapOptions(), figures=False, fluorescence=None), replace(ds, poses=poses),
                             Path(tmp) / "map").report
        half = np.array([m.tolerance.position_mm for m in poses])
        row = {"bounds": source_errors([m.pose for m in poses], truth),
               "box_half_width_mm_mean": half.mean(axis=0).tolist(),
               "map_cameras": report["pose_error"],
               "map_points_to_true_surface_mm": {"direct_mean": report["surface_error_mm"]["direct"]["mean"],
                                                 "after_icp_mean": report["surface_error_mm"]["after_icp"]["mean"]},
               "n_points": report["n_points"], "time_s": time.perf_counter() - t0}
        result["rows"][name] = row
        print(name, json.dumps(row), flush=True)
    result["machine"]["load_average_at_end"] = os.getloadavg()
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "fused_map.json").write_text(json.dumps(result, indent=1, default=float))


if __name__ == "__main__":
    main()
