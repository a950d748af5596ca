"""Image-only 3-D bladder panorama (issue 11 §4): ``scope3d panorama`` beside pycolmap's incremental and global
mappers on the same frames, the same intrinsics and the same metric.

The metric (all three): distance of every reconstructed point to the true wall after a 7-DoF similarity
fitted to the points' true positions (each track's keypoints looked up in the true depth maps with the true
poses: :func:`scope3d.metrology.evaluation.true_track_points`), and frames registered. pycolmap's keypoints
are converted from COLMAP's pixel convention (origin at the top-left pixel's corner) to scope3d's (centre).
Time: wall and CPU, features and matching included for everyone.

Usage: PYTHONPATH=src python benchmarks/bench_panorama_3d.py DATASET [--tag NAME] [--no-colmap]
writes benchmarks/results/panorama_3d[_TAG].json and .png.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.io.dataset import load_dataset
from scope3d.metrology.evaluation import errors_after_similarity, true_track_points
from scope3d.pipelines.panorama import Panorama3dOptions, run
from scope3d.scene.mesh import SampledSurface
from scope3d.sfm.cavity_map_choice import cameras_off_centre
from scope3d.utils.figures import new_figure, save_figure

RESULTS = Path(__file__).parent / "results"


def load() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def ours(ds, work: Path, use_planned: bool, stars: bool = False) -> dict:
    """Our map; with ``stars`` its scale from the star targets (``scale_error_fraction`` against the truth),
    or, when no star is seen whole, the unscaled map and the reason (``stars_error``)."""
    c0, t0 = time.process_time(), time.perf_counter()
    options = Panorama3dOptions(use_planned_poses=use_planned, figures=False)
    stars_error = None
    try:
        report = run(options if stars else replace(options, stars=None), ds, work / "ours").report
    except InputError as exc:  # no star seen whole: the map without a scale, and why
        if not stars:
            raise
        stars_error = str(exc)
        report = run(replace(options, stars=None), ds, work / "ours").report
    return {"method": "scope3d panorama" + (" (planned poses)" if use_planned else " (images only)"),
            "n_registered": report["n_registered"], "n_points": report["n_points"],
            "surface_error_mm": report.get("surface_error_mm", {}).get("after_similarity"),
            "scale_source": report["scale_source"], "scale_error_fraction": report.get("scale_error_fraction"),
            "n_star_views": (report["stars"] or {}).get("n_views", 0), "stars_error": stars_error,
            "self_check": report.get("self_check"),
            "scale_uncertainty_fraction": report.get("scale_uncertainty_fraction"),
            "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0, "timings_s": report["timings_s"]}


def colmap(ds, work: Path, mapper: str, truth: SampledSurface, sequential_overlap: int = 0) -> dict:
    """pycolmap's mapper on the dataset's frames; every pair matched (exhaustive), or with
    ``sequential_overlap`` > 0 each frame with that many successors (for plans of hundreds of views)."""
    import pycolmap

    cam = ds.camera
    db = work / f"{mapper}.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = f"{cam.fx},{cam.fy},{cam.cx + 0.5},{cam.cy + 0.5}"
    (work / "masks").mkdir(exist_ok=True)
    mask = cam.mask().astype(np.uint8) * 255
    for name in ds.names:
        cv2.imwrite(str(work / "masks" / f"{name}.png"), mask)
    reader.mask_path = str(work / "masks")
    c0, t0 = time.process_time(), time.perf_counter()
    pycolmap.extract_features(db, ds.root / "frames", image_names=ds.names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader)
    if sequential_overlap > 0:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = sequential_overlap
        pycolmap.match_sequential(db, pairing_options=pairing)
    else:
        pycolmap.match_exhaustive(db)
    t_match = time.perf_counter() - t0
    out = work / f"sparse_{mapper}"
    out.mkdir(exist_ok=True)
    if mapper == "incremental":
        opts = pycolmap.IncrementalPipelineOptions()
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        models = pycolmap.incremental_mapping(db, ds.root / "frames", out, options=opts)
    else:
        models = pycolmap.global_mapping(db, ds.root / "frames", out)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    row = {"method": f"pycolmap.{mapper}_mapping", "matching": f"sequential {sequential_overlap}" if sequential_overlap
           else "exhaustive", "wall_s": wall, "cpu_s": cpu, "features_and_matching_s": t_match,
           "n_models": len(models)}
    if not models:
        return {**row, "n_registered": 0, "surface_error_mm": None}
    rec = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    index = {n: k for k, n in enumerate(ds.names)}
    frame, track, pixels, points = [], [], [], []
    for pid, (_, p) in enumerate(rec.points3D.items()):
        points.append(p.xyz)
        for el in p.track.elements:
            im = rec.images[el.image_id]
            frame.append(index[im.name])
            track.append(pid)
            pixels.append(np.asarray(im.points2D[el.point2D_idx].xy) - 0.5)
    frame, track, pixels = np.array(frame), np.array(track), np.array(pixels)
    gt = ds.ground_truth
    true_points = true_track_points(cam, gt.poses, gt.depth, frame, track, pixels, len(points))
    summary, _, _ = errors_after_similarity(np.array(points), true_points, truth)
    # our self-check's measure on the peer's model (no truth): a broken model is a cavity seen from inside?
    centres = [Pose.from_centre(np.eye(3), np.asarray(rec.images[k].projection_center())) for k in rec.reg_image_ids()]
    return {**row, "n_registered": int(rec.num_reg_images()), "n_points": len(points), "surface_error_mm": summary,
            "cameras_off_centre": cameras_off_centre(np.array(points), centres)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--tag", default="")
    ap.add_argument("--no-colmap", action="store_true")
    args = ap.parse_args()
    ds = load_dataset(args.dataset)
    truth = SampledSurface(ds.ground_truth.surface(), 0.25)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        planned = bool(np.all([np.isfinite(m.tolerance.position_mm).all() for m in ds.poses]))
        rows.append(ours(ds, work, False))
        if planned:
            rows.append(ours(ds, work, True))
        if not args.no_colmap:
            for mapper in ("global", "incremental"):
                try:
                    rows.append(colmap(ds, work, mapper, truth))
                except Exception as exc:  # a peer's failure is a result, not a crash of the benchmark
                    rows.append({"method": f"pycolmap.{mapper}_mapping", "error": repr(exc)})
    result = {"dataset": str(args.dataset), "n_frames": len(ds), "image_size": [ds.camera.width, ds.camera.height],
              "load": load(), "cpu_count": os.cpu_count(), "rows": rows,
              "metric": "distance of each point to the true wall after a 7-DoF similarity fitted to the points' "
                        "true positions (true depth maps + true poses); same for every method"}
    name = "panorama_3d" + (f"_{args.tag}" if args.tag else "")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(result, indent=2, default=float))
    fig = new_figure(figsize=(8, 4))
    ax = fig.add_subplot(1, 1, 1)
    names = [r["method"] for r in rows]
    means = [(r.get("surface_error_mm") or {}).get("mean", np.nan) for r in rows]
    ax.barh(names, means)
    for k, r in enumerate(rows):
        ax.text(0, k, f" {r.get('n_registered', 0)}/{len(ds)} frames, {r.get('wall_s', 0):.0f} s", va="center")
    ax.set_xlabel("mean wall error after similarity, mm")
    ax.set_title(f"{args.dataset.name}: {len(ds)} frames {ds.camera.width}x{ds.camera.height}")
    fig.subplots_adjust(left=0.38)
    save_figure(fig, RESULTS / f"{name}.png")
    print(json.dumps(result, indent=1, default=float))


if __name__ == "__main__":
    main()
