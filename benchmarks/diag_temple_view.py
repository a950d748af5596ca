"""Why one temple view COLMAP localizes is refused by ours (issue 34), measured against its calibrated pose.

The split of ``bench_localize_real.py`` (map from the 8 even views of the Middlebury templeSparseRing, the odd
ones localized from their images alone). For the view ``VIEW`` (default templeSR0002.png) it reports, per
matching route of the :class:`~scope3d.sfm.localization.Localizer`: correspondences, how many are right
(the matched map point projects within 3 px of the keypoint through the *true* pose), the pose estimate's
status and inliers; what the map offers (map points the true pose sees, those with a SIFT keypoint of the
frame within 3 px); where the right map point ranks among the descriptor distances for those keypoints and
whether it passes the ratio test; and COLMAP's correspondences for the same view, right ones counted the
same way.

Writes benchmarks/results/diag_temple_view.json. Run:
    WORK=/tmp/n34work .venv/bin/python benchmarks/diag_temple_view.py
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from scope3d.estimators.absolute_pose import estimate_absolute_pose
from scope3d.pipelines.surgical_map import MAP_PRESETS
from scope3d.sfm.localization import Localizer, LocalizerOptions

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_localize_real import (colmap_correspondences, colmap_map, map_options, scope3d_map,  # noqa: E402
                                 temple)

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
RIGHT_PX = 3.0  # a keypoint's error (~0.3-1 px) plus the map point's and the calibration's (~1 px at 560 mm)


def _right(camera, truth, xyz: np.ndarray, px: np.ndarray) -> np.ndarray:
    proj = camera.project(truth.transform(xyz))
    return np.linalg.norm(proj - px, axis=1) <= RIGHT_PX


def _route(camera, truth, points, ids, kp, options) -> dict:
    xyz, px = points.xyz_mm[ids], kp
    right = _right(camera, truth, xyz, px)
    r = estimate_absolute_pose(camera, xyz, px, options=options.pose)
    out = {"correspondences": len(ids), "right": int(right.sum()), "status": r.status, "inliers": int(r.n_inliers)}
    if r.ok:
        d_mm, d_rad = r.pose.distance_to(truth)
        out.update(position_error_mm=d_mm, orientation_error_deg=float(np.rad2deg(d_rad)))
    if right.sum() >= 4:
        only = estimate_absolute_pose(camera, xyz[right], px[right], options=options.pose)
        out["pose_from_the_right_ones_only"] = {"status": only.status, "inliers": int(only.n_inliers)}
    return out


def main() -> None:
    view = os.environ.get("VIEW", "templeSR0002.png")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(os.environ.get("WORK", tmp))
        ds = temple(work)
        even = list(range(0, len(ds), 2))
        i = ds.names.index(view)
        truth, camera = ds.poses[i].pose, ds.camera
        points, _ = scope3d_map(ds, even, work / "temple_sparse_ring_map", map_options("temple"))
        options = LocalizerOptions(features=MAP_PRESETS["photograph"].features, tracking=False)
        loc = Localizer(points, camera, options)
        r = loc.localize(ds.frame(i))
        grey = cv2.cvtColor(ds.frame(i), cv2.COLOR_RGB2GRAY)
        kp, desc = loc._features(grey, loc._usable(None))
        out = {"view": view, "map_points": len(points), "keypoints": len(kp), "right_if_within_px": RIGHT_PX,
               "localizer": {"status": r.status, "mode": r.mode, "matches": r.n_matches, "inliers": r.n_inliers,
                             "min_inliers": options.pose.min_inliers}}
        ids, fidx = loc._match_global(desc)
        out["global_representative"] = _route(camera, truth, points, ids, kp[fidx], options)
        ids, fidx = loc._match_every_observation(desc)
        out["every_observation"] = _route(camera, truth, points, ids, kp[fidx], options)
        for radius in (4.0, 8.0):
            ids, fidx = loc._match_guided(truth, kp, desc, radius)
            out[f"guided_at_true_pose_{radius:g}px"] = _route(camera, truth, points, ids, kp[fidx], options)
        # what the map offers: visible points with a keypoint near their true projection
        vis, vis_px, _ = loc._visible(truth)
        d, j = cKDTree(kp).query(vis_px)
        near = d <= RIGHT_PX
        out["map_points_seen_by_true_pose"] = len(vis)
        out["with_a_keypoint_within_px"] = int(near.sum())
        # for those keypoint / point pairs: the point's rank among all map descriptors, and the ratio
        dd = np.sqrt(np.maximum(((desc[j[near], None, :] - points.descriptors[None, :, :]) ** 2).sum(-1), 0))
        own = dd[np.arange(near.sum()), vis[near]]
        rank = (dd < own[:, None]).sum(1)
        others = dd.copy()
        others[np.arange(near.sum()), vis[near]] = np.inf
        ratio = own / others.min(1)
        out["true_point_rank_among_map_descriptors"] = {
            "rank_0": int((rank == 0).sum()), "rank_1_4": int(((rank >= 1) & (rank <= 4)).sum()),
            "rank_5_plus": int((rank >= 5).sum()),
            "nearest_and_ratio_below_0.8": int(((rank == 0) & (ratio < 0.8)).sum()),
            "nearest_and_ratio_below_0.9": int(((rank == 0) & (ratio < 0.9)).sum()),
            "median_ratio_true_over_best_other": float(np.median(ratio))}
        rec, db_path, info = colmap_map(ds, even, work / "temple_colmap_diag")
        xyz, px = colmap_correspondences(rec, db_path, view)
        right = _right(camera, truth, xyz, px)
        out["colmap"] = {"map_points": info["n_points"], "correspondences": len(xyz), "right": int(right.sum())}
        # are COLMAP's right points in our map? nearest of our points to each (mm)
        if right.any():
            gap = cKDTree(points.xyz_mm).query(xyz[right])[0]
            out["colmap"]["its_right_points_within_2mm_of_ours"] = int((gap <= 2.0).sum())
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "diag_temple_view.json").write_text(json.dumps(out, indent=1, default=float))
    print(json.dumps(out, indent=1, default=float))


if __name__ == "__main__":
    main()
