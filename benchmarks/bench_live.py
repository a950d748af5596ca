"""The live map (issue 36): latency, camera error and the final map on the dome survey rendered as video.

The dome phantom's 5 x 6 survey grid (5 mm apart, 15 mm above the wall) as a 30 fps video (the plan's
continuous path, ``SECONDS_PER_PLANNED_VIEW`` from view to view, poses interpolated), ``N_FRAMES`` frames
(default 300) of ``SIZE`` px (default 320: the dome's SIFT needs more than 300 px, 200 px gives ~20
features), the robot reporting every frame within +-3 mm / +-1.5 deg (uniform, independent per frame).
Both the live mapper and the map use the ``dim_endoscope`` preset (CLAHE, lower SIFT threshold: ~1,100
features per 320 px frame instead of ~200).

1. ``scope3d live`` on it at the recording's rate (the stream waits for each frame's time): latency median
   and p99, frames over the 33 ms frame interval, statuses; the camera error per frame after the first
   second of the fused pose, the robot's report and the image's own pose (the tracking's PnP, bounded by the
   robot's box, before fusion).
2. ``scope3d map`` on the same keyframes (their frames and the robot's reports, nothing else): its surface
   error (direct and after ICP) against the live map's after the global BCBA.

Targets (issue 36): latency <= 33 ms median, <= 100 ms p99; live camera error <= half the robot's at every
frame after the first second, fused below both the robot's and the image-only estimate; the final map's
surface error within 10 % of ``scope3d map`` on the same keyframes. The JSON says which were met.

Writes benchmarks/results/live.json and live.png (error along the trajectory, latency histogram).
Run (one benchmark at a time): .venv/bin/python benchmarks/bench_live.py [WORK]
"""
from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from scope3d import phantoms
from scope3d.io.dataset import load_dataset, write_dataset
from scope3d.io.scan_plan import PlanFile
from scope3d.phantoms.trajectories import build_trajectory
from scope3d.feature.detection import FEATURE_PRESETS
from scope3d.pipelines.live import LiveOptions
from scope3d.pipelines.live import run as run_live
from scope3d.pipelines.surgical_map import MapOptions
from scope3d.pipelines.surgical_map import run as run_map
from scope3d.sfm.live_mapping import LIVE_PRESETS

RESULTS = Path(__file__).resolve().parent / "results"
N_FRAMES = int(os.environ.get("N_FRAMES", "300"))
SIZE = int(os.environ.get("SIZE", "320"))
ROBOT_MM = 3.0  # +-3 mm, and +-1.5 deg (the lab's 0.5 deg per mm)


def dome_video(root: Path) -> Path:
    grid = build_trajectory("grid5x6")
    camera = phantoms.generate("dome", size=(SIZE, SIZE), n_frames=1).camera
    plan = PlanFile(list(grid.poses), np.zeros(len(grid.poses), int), camera.fov_deg, {})
    seq = phantoms.generate("dome", seed=0, pose_noise_mm=ROBOT_MM, size=(SIZE, SIZE), plan=plan, video_fps=30.0,
                            n_frames=N_FRAMES)
    return phantoms.write(seq, root / "dome_video")


def keyframe_dataset(src: Path, frames: list[int], dest: Path) -> Path:
    """The keyframes as a dataset of their own: frames, the robot's reports, the ground truth."""
    ds = load_dataset(src)
    gt = ds.ground_truth
    return write_dataset(dest, ds.camera, [ds.frame_paths[k] for k in frames], [ds.poses[k] for k in frames],
                         names=[ds.names[k] for k in frames], true_poses=[gt.poses[k] for k in frames],
                         true_surface=gt.surface(), true_depths=[gt.depth(k) for k in frames], scene=gt.scene)


def main(work: Path) -> None:
    work.mkdir(parents=True, exist_ok=True)
    load_at_start = os.getloadavg()  # latency is the machine's as much as the code's: say how busy it was
    t0 = time.perf_counter()
    video = dome_video(work)
    render_s = time.perf_counter() - t0
    dataset = load_dataset(video)
    live = run_live(LiveOptions(LIVE_PRESETS["dim_endoscope"], wait=True), dataset, work / "live")
    r = live.report
    kf = r["keyframe_frames"]
    map_out = run_map(MapOptions(features=FEATURE_PRESETS["dim_endoscope"], figures=False, fluorescence=None),
                      load_dataset(keyframe_dataset(video, kf, work / "keyframes")), work / "map")
    m = map_out.report
    live_surf, map_surf = r.get("surface_error_mm"), m.get("surface_error_mm")
    err = r.get("tracking_error", {})
    result = {
        "setup": {"scene": "dome, 5 x 6 survey grid as a 30 fps video", "frames": N_FRAMES, "size_px": SIZE,
                  "robot_error": "+-3 mm, +-1.5 deg uniform per frame", "machine": "2 cores shared with other jobs",
                  "load_average_at_start": load_at_start, "load_average_at_end": os.getloadavg(),
                  "render_s": render_s},
        "live": {k: r[k] for k in ("n_frames", "n_keyframes", "n_points", "statuses", "latency_ms", "global_bcba_s",
                                   "replayed_at_rate")},
        "tracking_error": err,
        "live_pose_error": r.get("pose_error"),
        "live_surface_error_mm": live_surf,
        "map_same_keyframes": {"surface_error_mm": map_surf, "pose_error": m.get("pose_error")},
    }
    lat = r["latency_ms"]
    targets = {"latency_median_le_33ms": lat["median"] <= 33.0, "latency_p99_le_100ms": lat["p99"] <= 100.0}
    if err:
        targets["fused_le_half_robot_every_frame_after_1s"] = err["fused_at_most_half_robot_fraction"] == 1.0
        # like for like: on the frames the image posed (a lost frame has the robot's pose only)
        same = err["on_imaged_frames"]
        targets["fused_median_below_robot_and_image"] = (
            same["fused"]["position_mm_median"] < same["robot"]["position_mm_median"]
            and same["fused"]["position_mm_median"] < same["image"].get("position_mm_median", np.inf))
    if live_surf and map_surf:
        for key in ("direct", "after_icp"):
            ratio = live_surf[key]["mean"] / map_surf[key]["mean"]
            result[f"surface_error_ratio_live_to_map_{key}"] = ratio
            targets[f"surface_{key}_within_10pct_of_map"] = ratio <= 1.10
    result["targets_met"] = targets
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "live.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    shutil.copy(work / "live" / "live.png", RESULTS / "live.png")
    print(json.dumps(result, indent=1, default=float))


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="bench_live_")))
