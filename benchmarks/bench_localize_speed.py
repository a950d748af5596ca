"""Localization speed at ~1 Mpx on real photographs (issue 34: tracked frames >= 30 frames/s, a
relocalization <= 0.3 s at 1 Mpx), COLMAP's absolute pose on the same matches beside.

Scene: Strecha fountain-P11 (3072 x 2048, metric calibrated cameras) resized by ``SCALE`` (default 0.4:
1229 x 819, 1.0 Mpx) through ``bench_localize_real.strecha``; the map from the even views with their
calibrated poses (``scope3d map``, the same options as ``bench_localize_real``), the odd views localized.

* Relocalization: each odd view with no prior (``Localizer.reset()``: the global path), ``REPEATS`` times.
* Tracked frames: there is no real video of these scenes, so each odd view is turned into a short
  sequence of frames by rotating the camera about its own centre: a pure rotation ``R_d`` maps the image
  by the homography ``K R_d K^-1`` exactly (the scene's depth does not enter; the Strecha cameras have no
  distortion), so the warped frames are real photographs with a known true pose ``R_d cam_from_world``
  (only resampling and the black rim the warp leaves differ from a real camera turning). The optical axis
  circles slowly, its tilt growing by ``STEP_DEG / 2`` a frame (median turn 1.5 px a frame at 1 Mpx, at most
  3.2 px: a steady hand at 30 frames/s). The first frame relocalizes; the rest take the Localizer's
  tracking path (optical flow, a SIFT refresh every ``refresh_every`` frames), as ``scope3d localize`` runs them.
* COLMAP (pycolmap) beside: ``estimate_and_refine_absolute_pose`` on the very correspondences our pose
  estimator was given in each frame (recorded from the localizer), and COLMAP's SIFT on the same 1 Mpx
  frame (its relocalization needs at least SIFT + pose; its matching against a map is not counted).

``LocalizerOptions()`` (``scope3d localize``'s default, 2000 features), the ``photograph`` features (8000),
``sift_image_scale=0.5`` and the ``threaded`` preset are timed. Wall time and process CPU time (all threads) per frame, median and p95.

Writes benchmarks/results/localize_speed.json. Run:
    WORK=/tmp/n34work .venv/bin/python benchmarks/bench_localize_speed.py
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotation_angle_between, rotvec_to_matrix
from scope3d.pipelines.surgical_map import MAP_PRESETS
from scope3d.sfm.localization import LOCALIZER_PRESETS, Localizer, LocalizerOptions

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_localize_real import colmap_pose, map_options, scope3d_map, strecha  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"


def rotated_sequence(image: np.ndarray, k: np.ndarray, truth: Pose, n: int, step_deg: float):
    """``n`` frames of the camera turning about its centre from ``truth``: (frames, true poses)."""
    frames, poses = [], []
    h, w = image.shape[:2]
    for j in range(n):
        # a slow circle of the optical axis: yaw and pitch, amplitude growing by step_deg a frame
        a = np.deg2rad(step_deg) * j
        rot = rotvec_to_matrix(np.array([a * np.sin(0.2 * j), a * np.cos(0.2 * j) * 0.5, 0.0]) / 2.0)
        hom = k @ rot @ np.linalg.inv(k)
        frames.append(cv2.warpPerspective(image, hom, (w, h), flags=cv2.INTER_LINEAR))
        poses.append(Pose(rot @ truth.rotation, rot @ truth.translation))
    return frames, poses


def _stats(values: list[float]) -> dict:
    v = np.asarray(values, float)
    return {"n": len(v), "median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "max": float(v.max())}


class _Recorder:
    """Records the correspondences each frame's pose was estimated from (the localizer's ``_pose``)."""

    def __init__(self, loc: Localizer):
        self.calls: list[tuple[np.ndarray, np.ndarray]] = []
        self._inner = loc._pose
        loc._pose = self

    def __call__(self, ids, pixels, reported):
        out = self._inner(ids, pixels, reported)
        self.calls.append((out[1], out[2]))
        return out


def run_options(label: str, options: LocalizerOptions, points, ds, odd: list[int], k: np.ndarray,
                n_frames: int, step_deg: float, repeats: int) -> dict:
    import pycolmap

    sift = pycolmap.Sift()
    reloc, track, colmap_pose_s, colmap_sift_s = [], [], {"relocalization": [], "tracking": []}, []
    with Localizer(points, ds.camera, replace(options, tracking=False)) as loc:
        loc.localize(ds.frame(odd[0]))  # warm-up (first BFMatcher call, numba)
        rec = _Recorder(loc)
        for _ in range(repeats):
            for i in odd:
                image = ds.frame(i)
                loc.reset()
                rec.calls.clear()
                r = loc.localize(image)
                row = {"view": ds.names[i], "status": r.status, "mode": r.mode, "wall_s": r.time_s, "cpu_s": r.cpu_s,
                       "matches": r.n_matches, "inliers": r.n_inliers}
                if r.ok:
                    d_mm, d_rad = r.pose.distance_to(ds.poses[i].pose)
                    row.update(position_error_mm=d_mm, orientation_error_deg=float(np.rad2deg(d_rad)))
                xyz = points.xyz_mm[rec.calls[-1][0]]
                t0 = time.perf_counter()
                pose, n_in = colmap_pose(ds.camera, xyz, rec.calls[-1][1])
                row["colmap_pose_s"] = time.perf_counter() - t0
                row["colmap_pose_inliers"] = n_in
                grey = np.ascontiguousarray(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY))
                t0 = time.perf_counter()
                kp, _ = sift.extract(grey)
                row["colmap_sift_s"], row["colmap_sift_features"] = time.perf_counter() - t0, len(kp)
                reloc.append(row)
    with Localizer(points, ds.camera, options) as loc:
        rec = _Recorder(loc)
        for i in odd:
            frames, truths = rotated_sequence(ds.frame(i), k, ds.poses[i].pose, n_frames, step_deg)
            loc.reset()
            for j, (frame, truth) in enumerate(zip(frames, truths)):
                rec.calls.clear()
                r = loc.localize(frame)
                row = {"view": ds.names[i], "frame": j, "status": r.status, "mode": r.mode, "wall_s": r.time_s,
                       "cpu_s": r.cpu_s, "matches": r.n_matches, "inliers": r.n_inliers}
                if r.ok:
                    d_mm, d_rad = r.pose.distance_to(truth)
                    row.update(position_error_mm=d_mm, orientation_error_deg=float(np.rad2deg(d_rad)))
                if rec.calls:
                    t0 = time.perf_counter()
                    _, n_in = colmap_pose(ds.camera, points.xyz_mm[rec.calls[-1][0]], rec.calls[-1][1])
                    row["colmap_pose_s"] = time.perf_counter() - t0
                track.append(row)
    # the camera's turn between consecutive frames, in pixels at the focal length
    truths = rotated_sequence(ds.frame(odd[0]), k, ds.poses[odd[0]].pose, n_frames, step_deg)[1]
    turn_px = [ds.camera.fx * float(rotation_angle_between(a.rotation, b.rotation)) for a, b in zip(truths, truths[1:])]
    tracked = [r for r in track if r["mode"] == "tracking" and r["status"] == "ok"]
    sift_frames = [r for r in track if r["frame"] > 0 and r["mode"] != "tracking"]
    after_first = [r for r in track if r["frame"] > 0]
    ok_r = [r for r in reloc if "position_error_mm" in r]
    ok_t = [r for r in track if "position_error_mm" in r]
    summary = {
        "relocalization": {
            "localized": f"{len(ok_r)}/{len(reloc)}",
            "wall_s": _stats([r["wall_s"] for r in reloc]), "cpu_s": _stats([r["cpu_s"] for r in reloc]),
            "median_position_error_mm": float(np.median([r["position_error_mm"] for r in ok_r])) if ok_r else None,
            "colmap_pose_on_same_matches_s": _stats([r["colmap_pose_s"] for r in reloc]),
            "colmap_sift_s": _stats([r["colmap_sift_s"] for r in reloc]),
        },
        "sequence": {
            "frames": len(track), "localized": len(ok_t),
            "tracking_frames": len(tracked), "sift_frames_after_the_first": len(sift_frames),
            "tracked_frame_wall_s": _stats([r["wall_s"] for r in tracked]) if tracked else None,
            "tracked_frame_cpu_s": _stats([r["cpu_s"] for r in tracked]) if tracked else None,
            "every_frame_after_the_first_wall_s": _stats([r["wall_s"] for r in after_first]),
            "frames_per_s_after_the_first": len(after_first) / sum(r["wall_s"] for r in after_first),
            "frames_per_s_tracked_only": len(tracked) / sum(r["wall_s"] for r in tracked) if tracked else None,
            "median_position_error_mm": float(np.median([r["position_error_mm"] for r in ok_t])) if ok_t else None,
            "median_orientation_error_deg": float(np.median([r["orientation_error_deg"] for r in ok_t])) if ok_t else None,
            "median_turn_per_frame_px": float(np.median(turn_px)),
            "colmap_pose_on_same_tracked_matches_s": _stats([r["colmap_pose_s"] for r in tracked if "colmap_pose_s" in r])
            if tracked else None,
        },
    }
    return {"options": label, "summary": summary, "relocalization_rows": reloc, "sequence_rows": track}


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    scale = float(os.environ.get("SCALE", "0.4"))
    n_frames = int(os.environ.get("FRAMES", "40"))
    step_deg = float(os.environ.get("STEP_DEG", "0.05"))
    repeats = int(os.environ.get("REPEATS", "2"))
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(os.environ.get("WORK", tmp))
        name = "strecha_fountain_p11"
        ds = strecha(work, name, scale)
        cam = ds.camera
        k = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
        even, odd = list(range(0, len(ds), 2)), list(range(1, len(ds), 2))
        label = f"{name}_x{scale:g}"
        points, map_s = scope3d_map(ds, even, work / f"{label}_speed_map", map_options(label))
        runs = {
            "default": run_options("LocalizerOptions()", LocalizerOptions(), points, ds, odd, k, n_frames, step_deg,
                                   repeats),
            "photograph_features": run_options(
                "LocalizerOptions(features=FEATURE_PRESETS['photograph'])",
                LocalizerOptions(features=MAP_PRESETS["photograph"].features), points, ds, odd, k, n_frames,
                step_deg, repeats),
            # the SIFT refresh on a worker thread (every 5 frames, half size, merged 2 frames later): the
            # stream's thread then only tracks
            # SIFT on the half-size frame for the first frame, relocalizations and synchronous refreshes
            "sift_image_scale_0.5": run_options("LocalizerOptions(sift_image_scale=0.5)",
                                                LocalizerOptions(sift_image_scale=0.5), points, ds, odd, k, n_frames,
                                                step_deg, repeats),
            "threaded": run_options("LOCALIZER_PRESETS['threaded']", LOCALIZER_PRESETS["threaded"], points, ds, odd,
                                    k, n_frames, step_deg, repeats),
        }
    result = {"scene": label, "camera": f"{cam.width}x{cam.height}", "megapixels": cam.width * cam.height / 1e6,
              "map_points": len(points), "map_s": map_s, "frames_per_sequence": n_frames, "step_deg": step_deg,
              "machine": {"cpus": os.cpu_count(), "load_average_at_start": load0,
                          "load_average_at_end": os.getloadavg()[0],
                          "note": "2 cores shared with other agents: wall times are the loaded machine's; "
                                  "cpu_s counts every thread of the process"},
              "runs": runs}
    (OUT / "localize_speed.json").write_text(json.dumps(result, indent=1, default=float))
    print(json.dumps({k: v["summary"] for k, v in runs.items()}, indent=1, default=float))


if __name__ == "__main__":
    main()
