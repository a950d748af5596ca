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

``RESECT=1``: the same video with tissue resected half-way (``scope3d phantom dome --video 30 --resect
5:3:1.5:9:5``: at 5 s a pit of 3 mm radius and 1.5 mm depth is cut into the wall under (9, 5) mm, in view as
the survey turns from its first row to its second, mapped by the first: the surgeon cuts what the scope
looks at). Measured against the
phantom's ground truth: the first frame whose true view holds the pit's deep part (the wall moved 1 mm or
more), and, as the live map changes, its points over that part, each judged by its observations: its track
triangulated with its keyframes' true poses, and called *old* when nearer the wall before the cut than after
it (the two are 1-1.5 mm apart there). The map is not aligned to the truth for this: an ICP onto the dome's
sphere slides about its centre and carried unmoved wall into the pit (all 28 "old" points of an earlier
judging lay off the pit when re-triangulated). The target (issue 36): the live map holds new points there and no old one within 2 s of the
first sight; the final map keeps no old point there. Writes benchmarks/results/live_resect.json.

``BLADDER=1``: the issue's second recording, the lab's bladder: ``scope3d plan-scan bladder --standoff 30`` (54
views, 70 deg field), its spiral rendered as a 30 fps video (``scope3d phantom bladder --plan ... --video 30``,
1.13 s from view to view), ``N_FRAMES`` of ``SIZE`` px with the same robot error, replayed through ``scope3d
live`` with each preset. No map on the same keyframes here (the bladder is a closed cavity, not the height
field `scope3d map` assumes). Writes benchmarks/results/live_bladder.json.
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
from scope3d.estimators.triangulation import triangulate_observations
from scope3d.mvs.surface_change import SurfaceChangeOptions
from scope3d.phantoms.resection import Resection, wall_moved_mm
from scope3d.pipelines.live import LiveOptions, frame_times, replay
from scope3d.pipelines.live import run as run_live
from scope3d.pipelines.surgical_map import MapOptions
from scope3d.pipelines.surgical_map import run as run_map
from scope3d.sfm.live_mapping import LIVE_PRESETS

RESULTS = Path(__file__).resolve().parent / "results"
N_FRAMES = int(os.environ.get("N_FRAMES", "300"))
SIZE = int(os.environ.get("SIZE", "320"))
ROBOT_MM = 3.0  # +-3 mm, and +-1.5 deg (the lab's 0.5 deg per mm)
RESECTION = Resection(5.0, radius_mm=3.0, depth_mm=1.5, centre_xy_mm=(9.0, 5.0))
DEEP_MM = 1.0  # the pit's part judged: the wall moved at least this much (old and new surfaces 1 mm apart or more)


def dome_video(root: Path, resection: Resection | None = None) -> Path:
    grid = build_trajectory("grid5x6")
    camera = phantoms.generate("dome", size=(SIZE, SIZE), n_frames=1).camera
    plan = PlanFile(list(grid.poses), np.zeros(len(grid.poses), int), camera.fov_deg, {})
    seq = phantoms.generate("dome", seed=0, pose_noise_mm=ROBOT_MM, size=(SIZE, SIZE), plan=plan, video_fps=30.0,
                            n_frames=N_FRAMES, resection=resection)
    return phantoms.write(seq, root / ("dome_resect" if resection else "dome_video"))


def first_sight(dataset, truth: dict) -> int:
    """The first frame at or after the cut whose true view holds a point of the pit's deep part."""
    c, radius = np.asarray(truth["sphere_centre_mm"]), truth["sphere_radius_mm"]
    # the deep part's rim on the wall after the cut: (1 - (d/r)^2)^2 = DEEP/depth
    d = truth["radius_mm"] * np.sqrt(1.0 - np.sqrt(DEEP_MM / truth["depth_mm"]))
    centre = np.asarray(truth["centre_mm"])
    u = (centre - c) / np.linalg.norm(centre - c)
    a = np.cross(u, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(u, a)
    ring = [centre + d * (np.cos(t) * a + np.sin(t) * b) for t in np.linspace(0, 2 * np.pi, 16, endpoint=False)]
    samples = np.array([centre, *ring])
    samples = c + (radius + wall_moved_mm(samples, truth))[:, None] * (samples - c) / np.linalg.norm(
        samples - c, axis=1, keepdims=True)
    cam = dataset.camera
    for k in range(truth["first_frame"], len(dataset)):
        pose = dataset.ground_truth.poses[k]
        px = cam.project_world(pose, samples)
        if np.any((pose.transform(samples)[:, 2] > 0) & cam.in_image(px)):
            return k
    return -1


def old_and_new(tracks, keyframe_frames: np.ndarray, dataset, truth: dict) -> tuple[int, int]:
    """How many map points lie over the pit's deep part on the wall before the cut (old) and after it (new),
    judged by what their observations say: each point's track triangulated with its keyframes' true poses,
    called old when nearer the wall before the cut than after it. No alignment of the map to the truth: on
    the dome's sphere an ICP slides freely about the centre (13 deg on the live map) and moved points of
    unmoved wall into the pit; the keyframe poses' gauge (~1 mm) is as large as the pit's deep part."""
    if tracks is None or tracks.n_tracks == 0:
        return 0, 0
    poses = [dataset.ground_truth.poses[int(k)] for k in keyframe_frames]
    X = triangulate_observations(dataset.camera, poses, tracks.track, tracks.frame, tracks.pixels, tracks.n_tracks)
    X = X[np.all(np.isfinite(X), axis=1)]
    rho = np.linalg.norm(X - np.asarray(truth["sphere_centre_mm"]), axis=1)
    moved = wall_moved_mm(X, truth)
    deep = moved >= DEEP_MM
    old = deep & (rho < truth["sphere_radius_mm"] + moved / 2)
    return int(old.sum()), int((deep & ~old).sum())


def resect_main(work: Path) -> None:
    video = dome_video(work, RESECTION)
    dataset = load_dataset(video)
    truth = dataset.ground_truth.scene["resection"]
    seen = first_sight(dataset, truth)
    options = LiveOptions(LIVE_PRESETS["dim_endoscope"], wait=True, change=SurfaceChangeOptions())
    history, last = [], [None]

    def look(frame, mapper):  # kept as it changes, judged after the replay (not on the stream's time)
        m = mapper.current_map()
        if len(m.points) and m.points is not last[0]:
            last[0] = m.points
            history.append((frame.index, m))

    times = frame_times(options, dataset)
    frames, final, _, _ = replay(options, dataset, times, on_frame=look)
    history = [(k, *old_and_new(m.tracks, m.keyframe_frames, dataset, truth)) for k, m in history]
    remapped = next((k for k, old, new in history if k >= seen and old == 0 and new > 0), None)
    final_old, final_new = old_and_new(final.tracks, final.keyframe_frames, dataset, truth)
    latency = np.array([f.latency_ms for f in frames])
    result = {
        "setup": {"scene": "dome, 5 x 6 survey grid as a 30 fps video, a pit cut at 5 s", "frames": N_FRAMES,
                  "size_px": SIZE, "pit": truth, "judged": f"the pit's part where the wall moved >= {DEEP_MM} mm",
                  "machine": "2 cores shared with other jobs"},
        "first_frame_seeing_the_pit": seen,
        "local_map_history": [{"frame": k, "old_points": o, "new_points": n} for k, o, n in history],
        "remapped_at_frame": remapped,
        "remapped_after_s": None if remapped is None else (remapped - seen) / 30.0,
        "final_map": {"old_points": final_old, "new_points": final_new, "n_points": int(len(final.points))},
        "points_dropped_as_changed": {str(f.index): f.dropped_points for f in frames if f.dropped_points},
        "latency_ms": {"median": float(np.median(latency)), "p99": float(np.percentile(latency, 99)),
                       "frames_waiting_for_the_worker": int(sum(f.waited_ms > 0 for f in frames))},
        "statuses": {s: sum(f.status == s for f in frames) for s in ("tracked", "keyframe", "relocalized", "lost")},
    }
    result["setup"]["load_average_at_end"] = list(os.getloadavg())
    result["targets_met"] = {"remapped_within_2s": remapped is not None and (remapped - seen) <= 60,
                             "final_map_no_old_points": final_old == 0}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "live_resect.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    print(json.dumps(result, indent=1, default=float))


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
                  "load_average_at_start": load_at_start, "render_s": render_s},
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
    result["setup"]["load_average_at_end"] = list(os.getloadavg())  # the latency depends on the machine's load
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "live.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    shutil.copy(work / "live" / "live.png", RESULTS / "live.png")
    print(json.dumps(result, indent=1, default=float))


def bladder_main(work: Path) -> None:
    from scope3d.io.scan_plan import read_scan_plan
    from scope3d.pipelines import scan_plan
    from scope3d.sfm.scan_planning import ScanPlanOptions

    load_at_start = list(os.getloadavg())
    scan_plan.run(ScanPlanOptions(standoff_mm=30.0, overlap=0.5, fov_deg=70.0), "bladder", work / "plan")
    plan = read_scan_plan(work / "plan" / "plan.json")
    seq = phantoms.generate("bladder", seed=0, pose_noise_mm=ROBOT_MM, size=(SIZE, SIZE), plan=plan, video_fps=30.0,
                            n_frames=N_FRAMES)
    dataset = load_dataset(phantoms.write(seq, work / "bladder_video"))
    truth = dataset.ground_truth.poses
    steps = [truth[k].distance_to(truth[k + 1]) for k in range(len(truth) - 1)]
    result = {"setup": {"scene": "bladder, the 30 mm / 70 deg spiral plan as a 30 fps video", "frames": N_FRAMES,
                        "size_px": SIZE, "robot_error": "+-3 mm, +-1.5 deg uniform per frame",
                        "true_motion_per_frame": {"mm_median": float(np.median([d for d, _ in steps])),
                                                  "deg_median": float(np.degrees(np.median([a for _, a in steps]))),
                                                  "deg_max": float(np.degrees(max(a for _, a in steps)))},
                        "machine": "2 cores shared with other jobs", "load_average_at_start": load_at_start}}
    for preset in ("default", "dim_endoscope"):
        r = run_live(LiveOptions(LIVE_PRESETS[preset], wait=True), dataset, work / f"live_{preset}").report
        err = r.get("tracking_error", {})
        result[preset] = {k: r.get(k) for k in ("n_keyframes", "n_points", "statuses", "latency_ms", "pose_error",
                                                "surface_error_mm")}
        result[preset]["tracking_error"] = err
        result[preset]["targets_met"] = {
            "latency_median_le_33ms": r["latency_ms"]["median"] <= 33.0,
            "latency_p99_le_100ms": r["latency_ms"]["p99"] <= 100.0,
            "fused_le_half_robot_every_frame_after_1s": err.get("fused_at_most_half_robot_fraction") == 1.0}
    result["setup"]["load_average_at_end"] = list(os.getloadavg())
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "live_bladder.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    print(json.dumps(result, indent=1, default=float))


if __name__ == "__main__":
    work_dir = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="bench_live_"))
    mode = "resect" if os.environ.get("RESECT") == "1" else "bladder" if os.environ.get("BLADDER") == "1" else "dome"
    {"resect": resect_main, "bladder": bladder_main, "dome": main}[mode](work_dir)
