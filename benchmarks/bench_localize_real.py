"""Localization on real photographs, side by side with COLMAP (pycolmap) in the same process (issue 34).

Each scene is split: the map from the even views with their calibrated poses, the odd views localized from
their images alone, every error against the odd view's calibrated pose.

* scope3d: ``scope3d map`` (preset ``photograph``) of the even views, then each odd view through the
  :class:`~scope3d.sfm.localization.Localizer` (no tracking: each view is a relocalization).
* COLMAP: SIFT on every view (``extract_features``), exhaustive matching, a known-pose reconstruction of the
  even views (``triangulate_points``), then each odd view's 2-D/3-D correspondences through its verified
  matches to the even views' triangulated keypoints (what COLMAP's mapper registers an image with), and
  ``estimate_and_refine_absolute_pose`` with its defaults.
* Crossed (``diagnosis``): scope3d's pose estimator on COLMAP's correspondences, COLMAP's on scope3d's, and
  scope3d's localizer on COLMAP's map (its points, one descriptor per point chosen as scope3d's maps
  choose it): which of map, matching and pose estimate loses the accuracy.

Scenes: the Middlebury templeSparseRing (16 views, 640 x 480) and the Strecha fountain-P11 and Herz-Jesu-P8
(3072 x 2048; ``SCALE`` sets a resolution factor, 1 = full).

A pose is *wrong* when its position error exceeds 10 x the median of COLMAP's on the same scene (issue 34).

Writes benchmarks/results/localize_real.json. Run (one at a time; ``SCENES=temple,fountain,herzjesu``):
    .venv/bin/python benchmarks/bench_localize_real.py
"""
from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from scope3d.cli.main import main as cli
from scope3d.estimators.absolute_pose import estimate_absolute_pose
from scope3d.geometry.pose import Pose
from scope3d.io.dataset import load_dataset, write_dataset
from scope3d.io.map_points import MapPoints, read_map_points
from scope3d.pipelines.surgical_map import MAP_PRESETS
from scope3d.pipelines.surgical_map import run as run_map
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.localization import Localizer, LocalizerOptions

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_map_middlebury import _known_pose_reconstruction  # noqa: E402  (the same known-pose COLMAP map)

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
DATA = ROOT.parent / "shared" / "data"
WRONG_FACTOR = 10.0  # issue 34: a pose > 10x the median error is wrong


# --- scenes ----------------------------------------------------------------------------------------


def temple(work: Path):
    path = work / "temple"
    if not path.exists():
        assert cli(["import", "middlebury", str(DATA / "middlebury_templeSparseRing" / "templeSR_par.txt"),
                    "--out", str(path), "--quiet"]) == 0
    return load_dataset(path)


def read_strecha_camera(path: Path) -> tuple[np.ndarray, Pose, int, int]:
    """A Strecha ``.camera`` file (SOURCE.txt): K, a distortion line, R = world-from-camera, C (m), w h.
    Returns K, ``cam_from_world`` in mm, width, height. R is printed to 6 digits: it is replaced by the
    nearest rotation (SVD), a change of ~1e-6 rad."""
    v = np.array(path.read_text().split(), float)
    k, rotation, centre_m, (w, h) = v[:9].reshape(3, 3), v[12:21].reshape(3, 3), v[21:24], v[24:26]
    u, _, vt = np.linalg.svd(rotation)
    rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return k, Pose.from_centre(rotation.T, 1000.0 * centre_m), int(w), int(h)


def strecha(work: Path, name: str, scale: float):
    """A Strecha scene as a dataset (calibrated poses, exact tolerance), resized by ``scale``."""
    path = work / f"{name}_x{scale:g}"
    if path.exists():
        return load_dataset(path)
    src = DATA / name
    frames, poses, names = [], [], []
    for cam_file in sorted((src / "gt_dense_cameras").glob("*.camera")):
        k, pose, w, h = read_strecha_camera(cam_file)
        image = cv2.cvtColor(cv2.imread(str(src / "images" / cam_file.stem)), cv2.COLOR_BGR2RGB)
        if scale != 1.0:
            image = cv2.resize(image, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
        frames.append(image)
        poses.append(MeasuredPose(pose, PoseTolerance.exact()))
        names.append(cam_file.stem.replace(".jpg", ".png"))
    h, w = frames[0].shape[:2]
    # K's pixel origin taken as the top-left pixel's centre (scope3d's); resizing maps u -> (u + 0.5) s - 0.5
    camera = Camera(w, h, k[0, 0] * scale, k[1, 1] * scale, (k[0, 2] + 0.5) * scale - 0.5, (k[1, 2] + 0.5) * scale - 0.5)
    return load_dataset(write_dataset(path, camera, frames, poses, names=names,
                                      metadata={"source": {"strecha": name, "scale": scale}}))


def subset(ds, keep: list[int]):
    return replace(ds, frame_paths=[ds.frame_paths[k] for k in keep], poses=[ds.poses[k] for k in keep],
                   ground_truth=None)


# --- scope3d -------------------------------------------------------------------------------------


def map_options(label: str):
    """``scope3d map``'s preset ``photograph``, with what each split needs (docs/localization.md, issue 34):
    the temple's even views are 45 deg apart, beyond the preset's 35 deg pair limit (set for the full ring:
    2 pairs would be left), so 60 deg; the Strecha scenes have no bounding box and the guided matcher's
    epipolar segments (depth prior 5-28 m, 3 m baselines) exceed its window limit everywhere, so the
    even views are matched exhaustively (the same pairs)."""
    base = replace(MAP_PRESETS["photograph"], figures=False)
    if label.startswith("temple"):
        return replace(base, pairs=replace(base.pairs, max_view_angle_deg=60.0))
    return replace(base, matcher="exhaustive")


def scope3d_map(ds, even: list[int], out: Path, options) -> tuple[MapPoints, float]:
    t0 = time.perf_counter()
    run_map(options, subset(ds, even), out)
    return read_map_points(out), time.perf_counter() - t0


def scope3d_localize(points: MapPoints, ds, odd: list[int], options: LocalizerOptions) -> list[dict]:
    rows = []
    with Localizer(points, ds.camera, options) as loc:
        for i in odd:
            image = ds.frame(i)
            loc.reset()
            t0 = time.perf_counter()
            r = loc.localize(image)
            rows.append(_row(ds.names[i], r.pose if r.ok else None, ds.poses[i].pose, time.perf_counter() - t0,
                             r.n_matches, r.n_inliers, r.status))
    return rows


def scope3d_correspondences(points: MapPoints, ds, i: int, options: LocalizerOptions):
    """View i's global matches against the map, as the localizer makes them: (N, 3) mm, (N, 2) px."""
    loc = Localizer(points, ds.camera, options)
    kp, desc = loc._features(cv2.cvtColor(ds.frame(i), cv2.COLOR_RGB2GRAY), loc._usable(None))
    ids, fidx = loc._match_global(desc)
    return points.xyz_mm[ids], kp[fidx]


# --- COLMAP --------------------------------------------------------------------------------------


def colmap_map(ds, even: list[int], work: Path):
    """COLMAP's known-pose map of the even views; features and matches of every view in its database."""
    import pycolmap

    shutil.rmtree(work, ignore_errors=True)  # extract_features skips images already in a database
    work.mkdir(parents=True)
    db_path = work / "database.db"
    cam = ds.camera
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "OPENCV"
    reader.camera_params = ",".join(str(v) for v in (cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5, cam.k1, cam.k2, 0, 0))
    t0 = time.perf_counter()
    pycolmap.extract_features(db_path, ds.root / "frames", image_names=ds.names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader)
    pycolmap.match_exhaustive(db_path)
    t1 = time.perf_counter()
    rec = _known_pose_reconstruction(pycolmap, db_path, {ds.names[k]: ds.poses[k].pose for k in even})
    (work / "sparse").mkdir(exist_ok=True)
    t2 = time.perf_counter()
    rec = pycolmap.triangulate_points(rec, db_path, ds.root / "frames", work / "sparse")
    return rec, db_path, {"extract_and_match_s": t1 - t0, "triangulate_s": time.perf_counter() - t2,
                          "n_points": rec.num_points3D()}


def colmap_correspondences(rec, db_path: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """The query's verified matches to map images' triangulated keypoints: (N, 3) mm, (N, 2) px in
    scope3d's pixel convention; one row per distinct (keypoint, 3-D point) pair, as COLMAP registers."""
    import pycolmap

    db = pycolmap.Database.open(db_path)
    query = db.read_image_with_name(name)
    kp = db.read_keypoints(query.image_id)[:, :2] - 0.5  # COLMAP's origin is the image corner
    pairs = set()
    for im in rec.images.values():
        if not db.exists_two_view_geometry(query.image_id, im.image_id):
            continue
        tvg = db.read_two_view_geometry(query.image_id, im.image_id)  # columns: query, map image
        m = np.asarray(tvg.inlier_matches)
        if len(m) == 0:
            continue
        for q, t in m:
            p2d = im.points2D[int(t)]
            if p2d.has_point3D():
                pairs.add((int(q), int(p2d.point3D_id)))
    db.close()
    pairs = sorted(pairs)
    xyz = np.array([rec.points3D[p].xyz for _, p in pairs]).reshape(-1, 3)
    return xyz, kp[[q for q, _ in pairs]].reshape(-1, 2)


def colmap_pose(camera: Camera, xyz: np.ndarray, px: np.ndarray) -> tuple[Pose | None, int]:
    """``estimate_and_refine_absolute_pose`` with COLMAP's defaults on scope3d-convention pixels."""
    import pycolmap

    cam = pycolmap.Camera(model="OPENCV", width=camera.width, height=camera.height,
                          params=[camera.fx, camera.fy, camera.cx + 0.5, camera.cy + 0.5, camera.k1, camera.k2, 0, 0])
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.random_seed = 0
    if len(xyz) < 4:
        return None, 0
    res = pycolmap.estimate_and_refine_absolute_pose(px + 0.5, xyz, cam, est)
    if res is None:
        return None, 0
    rig = res["cam_from_world"]
    return Pose(rig.rotation.matrix(), rig.translation), int(np.sum(res["inlier_mask"]))


def colmap_map_points(rec, db_path: Path) -> MapPoints:
    """COLMAP's map as a scope3d map: every point, the observation's descriptor nearest the track's mean."""
    import pycolmap

    db = pycolmap.Database.open(db_path)
    desc = {im.image_id: np.asarray(db.read_descriptors(im.image_id).data, np.float32) for im in rec.images.values()}
    db.close()
    ids = sorted(rec.points3D)
    xyz = np.array([rec.points3D[p].xyz for p in ids])
    out = np.zeros((len(ids), 128), np.float32)
    for n, p in enumerate(ids):
        obs = np.array([desc[e.image_id][e.point2D_idx] for e in rec.points3D[p].track.elements])
        mean = obs.mean(0)
        out[n] = obs[np.argmin(((obs - mean) ** 2).sum(1))]
    # COLMAP stores SIFT descriptors L1-root normalised as uint8 (x 512); scope3d's are OpenCV's (L2 ~512):
    # ratio tests need only a common scale, and OpenCV's L2 distances are computed on either alike
    n_obs = np.array([rec.points3D[p].track.length() for p in ids], np.int32)
    colors = np.array([rec.points3D[p].color for p in ids], np.uint8)
    return MapPoints(xyz, out, n_obs, colors)


# --- rows ------------------------------------------------------------------------------------------


def _row(name, pose, truth, seconds, n_matches, n_inliers, status="ok") -> dict:
    row = {"view": name, "status": status if pose is not None else (status if status != "ok" else "failed"),
           "time_s": seconds, "matches": int(n_matches), "inliers": int(n_inliers)}
    if pose is not None:
        d_mm, d_rad = pose.distance_to(truth)
        row.update(position_error_mm=d_mm, orientation_error_deg=float(np.rad2deg(d_rad)))
    return row


def summary(rows: list[dict], wrong_mm: float | None = None) -> dict:
    ok = [r for r in rows if "position_error_mm" in r]
    out = {"n_views": len(rows), "n_localized": len(ok)}
    if ok:
        out.update(median_position_error_mm=float(np.median([r["position_error_mm"] for r in ok])),
                   median_orientation_error_deg=float(np.median([r["orientation_error_deg"] for r in ok])),
                   max_position_error_mm=float(np.max([r["position_error_mm"] for r in ok])))
        if wrong_mm is not None:
            out["n_wrong"] = int(sum(r["position_error_mm"] > wrong_mm for r in ok))
        t = [r["time_s"] for r in rows]
        out["frames_per_s"] = len(t) / sum(t)
    return out


def scene_run(ds, work: Path, label: str, diagnose: bool) -> dict:
    even, odd = list(range(0, len(ds), 2)), list(range(1, len(ds), 2))
    load0 = os.getloadavg()[0]
    options = LocalizerOptions(features=MAP_PRESETS["photograph"].features, tracking=False)
    points, map_s = scope3d_map(ds, even, work / f"{label}_map", map_options(label))
    ours = scope3d_localize(points, ds, odd, options)
    rec, db_path, colmap_info = colmap_map(ds, even, work / f"{label}_colmap")
    theirs = []
    for i in odd:
        t0 = time.perf_counter()
        xyz, px = colmap_correspondences(rec, db_path, ds.names[i])
        pose, n_in = colmap_pose(ds.camera, xyz, px)
        theirs.append(_row(ds.names[i], pose, ds.poses[i].pose, time.perf_counter() - t0, len(xyz), n_in))
    # COLMAP's SIFT and matching ran on every view at once: its share per query view, to set beside ours
    # (whose frame time includes SIFT and matching)
    per_view_s = colmap_info["extract_and_match_s"] / len(ds)
    colmap_info["frames_per_s_with_features"] = len(theirs) / sum(r["time_s"] + per_view_s for r in theirs)
    colmap_summary = summary(theirs)
    wrong = WRONG_FACTOR * colmap_summary.get("median_position_error_mm", np.inf)
    out = {"scene": label, "camera": f"{ds.camera.width}x{ds.camera.height}", "map_views": [ds.names[k] for k in even],
           "query_views": [ds.names[k] for k in odd], "wrong_if_position_error_above_mm": wrong,
           "load_average_at_start": load0,
           "scope3d": {"map_points": len(points), "map_s": map_s, "summary": summary(ours, wrong), "views": ours},
           "colmap": {**colmap_info, "summary": summary(theirs, wrong), "views": theirs,
                      "note": "summary frames/s counts the correspondence look-up and the pose only (SIFT and "
                              "matching ran at extraction); frames_per_s_with_features adds their share per view"}}
    if diagnose:
        out["diagnosis"] = diagnosis(ds, odd, points, rec, db_path, options, wrong)
    out["load_average_at_end"] = os.getloadavg()[0]
    return out


def diagnosis(ds, odd, points, rec, db_path, options, wrong) -> dict:
    """Crossed runs: whose map, whose matches, whose pose estimator."""
    rows = {k: [] for k in ("scope3d_pose_on_colmap_matches", "colmap_pose_on_scope3d_matches")}
    for i in odd:
        truth = ds.poses[i].pose
        xyz, px = colmap_correspondences(rec, db_path, ds.names[i])
        r = estimate_absolute_pose(ds.camera, xyz, px, options=options.pose)
        rows["scope3d_pose_on_colmap_matches"].append(_row(ds.names[i], r.pose, truth, r.time_s, len(xyz), r.n_inliers,
                                                           r.status))
        xyz, px = scope3d_correspondences(points, ds, i, options)
        t0 = time.perf_counter()
        pose, n_in = colmap_pose(ds.camera, xyz, px)
        rows["colmap_pose_on_scope3d_matches"].append(_row(ds.names[i], pose, truth, time.perf_counter() - t0,
                                                           len(xyz), n_in))
    rows["scope3d_localizer_on_colmap_map"] = scope3d_localize(colmap_map_points(rec, db_path), ds, odd, options)
    return {k: {"summary": summary(v, wrong), "views": v} for k, v in rows.items()}


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    scenes = os.environ.get("SCENES", "temple").split(",")
    scale = float(os.environ.get("SCALE", "1"))
    diagnose = os.environ.get("DIAGNOSE", "1") == "1"
    result_path = OUT / "localize_real.json"
    result = json.loads(result_path.read_text()) if result_path.exists() else {}
    result["machine"] = {"cpus": os.cpu_count(), "note": "2 cores shared with other agents; see each scene's load"}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(os.environ.get("WORK", tmp))
        for scene in scenes:
            if scene == "temple":
                ds, label = temple(work), "temple_sparse_ring"
            else:
                name = {"fountain": "strecha_fountain_p11", "herzjesu": "strecha_herz_jesus_p8"}[scene]
                ds, label = strecha(work, name, scale), f"{name}_x{scale:g}"
            res = scene_run(ds, work, label, diagnose)
            result[label] = res
            print(json.dumps({label: {k: v["summary"] for k, v in res.items() if isinstance(v, dict) and "summary" in v}
                              | {f"diag_{k}": v["summary"] for k, v in res.get("diagnosis", {}).items()}},
                             indent=1, default=float), flush=True)
    result_path.write_text(json.dumps(result, indent=1, default=float))


if __name__ == "__main__":
    main()
