"""Organ panorama benchmark (issue 11): scan-plan counts for the bladder, and the 2-D mosaic beside OpenCV's
Stitcher (SCANS mode) on the same frames.

1. Plans of the bladder phantom at 15 and 30 mm stand-off, 50 % overlap, FOV 50° and 70°, with and without
   the reference's ~125° bending limit: number of views and coverage (ray casting), beside the reference's
   529 and 199 imaging points and ~60 % coverage (sec. 2.3.2, 2.4.2).
2. Mosaic of the flat sheet phantom (grid 5 x 6, 30 frames of 304 x 304, planar truth): ours and
   cv2.Stitcher SCANS: success, frames used, time, alignment error against the true frame -> mosaic
   mapping. The Stitcher returns only a composed image, so its per-frame mapping is measured by
   registering every input frame onto its panorama (SIFT + RANSAC homography) and fitting one homography
   from the panorama to the first frame's pixels over all frames (its gauge); ours gets the same fit.

Writes benchmarks/results/panorama.json, panorama_plan_{15,30}.png, panorama_mosaic_sheet.png and
panorama_mosaic_bladder.png. Run:  .venv/bin/python benchmarks/bench_panorama.py
"""
from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from scope3d import phantoms
from scope3d.io.dataset import load_dataset
from scope3d.pipelines import mosaic as mosaic_job
from scope3d.pipelines import scan_plan as scan_plan_job
from scope3d.registration import mosaic as mos
from scope3d.sfm.scan_planning import ScanPlanOptions

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
REFERENCE = {"views_15mm": 529, "views_30mm": 199, "coverage": 0.60}


def plans(tmp: Path) -> list[dict]:
    """One plan per stand-off and FOV with the 125° limit; the plan also reports every planned view's
    coverage without the limit, so both rows come from one run."""
    rows = []
    for standoff in (15.0, 30.0):
        for fov in (50.0, 70.0):
            c0 = time.process_time()
            folder = tmp / f"plan_{standoff:g}_{fov:g}"
            plan = scan_plan_job.run(ScanPlanOptions(standoff_mm=standoff, overlap=0.5, fov_deg=fov,
                                                     bend_limit_deg=125.0), "bladder", folder).plan
            rows.append({"standoff_mm": standoff, "fov_deg": fov, "n_views_no_limit": plan.n_planned,
                         "coverage_no_limit": plan.coverage_unlimited.fraction, "bend_limit_deg": 125.0,
                         "n_views_bend_limit": plan.n_views, "coverage_bend_limit": plan.coverage.fraction,
                         "cpu_s": time.process_time() - c0})
            print(f"plan {standoff:g} mm, FOV {fov:g}: {plan.n_planned} views (coverage "
                  f"{plan.coverage_unlimited.fraction:.1%}); {plan.summary()}", flush=True)
            if fov == 70.0:
                shutil.copy(folder / "plan.png", OUT / f"panorama_plan_{int(standoff)}.png")
    return rows


def _register_to(panorama: np.ndarray, frame: np.ndarray, camera) -> np.ndarray | None:
    """Homography frame -> panorama from SIFT + RANSAC, or None."""
    sift = cv2.SIFT_create(4000)
    ka, da = sift.detectAndCompute(cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY), camera.mask().astype(np.uint8))
    kb, db = sift.detectAndCompute(cv2.cvtColor(panorama, cv2.COLOR_RGB2GRAY), None)
    if da is None or db is None:
        return None
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
    if len(good) < 15:
        return None
    a = np.float32([ka[m.queryIdx].pt for m in good])
    b = np.float32([kb[m.trainIdx].pt for m in good])
    h, mask = cv2.findHomography(a, b, cv2.RANSAC, 3.0, confidence=0.99)
    return h if h is not None and mask.sum() >= 15 else None


def _gauge_fitted_errors(maps: dict[int, np.ndarray], truth: np.ndarray, camera) -> np.ndarray:
    """Fit one homography G (panorama -> first frame's pixels) over all frames, then the per-point errors."""
    u, v = np.meshgrid(np.linspace(0, camera.width - 1, 12), np.linspace(0, camera.height - 1, 12))
    pts = np.stack([u.ravel(), v.ravel()], 1)
    pts = pts[camera.in_image(pts)]
    src = np.concatenate([mos._apply(h, pts) for h in maps.values()])
    dst = np.concatenate([mos._apply(truth[i], pts) for i in maps])
    g, _ = cv2.findHomography(src, dst, 0)
    return np.linalg.norm(mos._apply(g, src) - dst, axis=1)


def mosaic_vs_stitcher(tmp: Path) -> dict:
    seq = phantoms.generate("sheet", "grid5x6", size=(304, 304))
    phantoms.write(seq, tmp / "sheet")
    ds = load_dataset(tmp / "sheet")
    cams = [ds.camera] * len(ds)
    truth = mos.true_plane_homographies(cams, list(ds.ground_truth.poses), np.zeros(3), [0.0, 0.0, 1.0])
    c0, t0 = time.process_time(), time.perf_counter()
    job = mosaic_job.run(mos.MosaicOptions(), [ds], tmp / "sheet_mosaic")
    ours, res = job.report, job.mosaic
    ours_cpu, ours_wall = time.process_time() - c0, time.perf_counter() - t0
    shutil.copy(tmp / "sheet_mosaic" / "mosaic_path.png", OUT / "panorama_mosaic_sheet.png")

    frames = [ds.frame(i) for i in range(len(ds))]
    stitcher = cv2.Stitcher_create(cv2.Stitcher_SCANS)
    c0, t0 = time.process_time(), time.perf_counter()
    status, pano = stitcher.stitch([cv2.cvtColor(f, cv2.COLOR_RGB2BGR) for f in frames])
    st_cpu, st_wall = time.process_time() - c0, time.perf_counter() - t0
    peer = {"status": int(status), "success": status == cv2.Stitcher_OK, "time_s": st_wall, "cpu_s": st_cpu}
    if status == cv2.Stitcher_OK:
        pano = cv2.cvtColor(pano, cv2.COLOR_BGR2RGB)
        maps = {i: h for i, f in enumerate(frames) if (h := _register_to(pano, f, ds.camera)) is not None}
        peer["frames_found_in_panorama"] = len(maps)
        if len(maps) >= 2:
            err = _gauge_fitted_errors(maps, truth, ds.camera)
            peer["alignment_error_px"] = {"mean": float(err.mean()), "p95": float(np.percentile(err, 95))}
    # Ours through the same gauge fit (our mosaic is already in the first frame's pixels; the fit can only help).
    err = _gauge_fitted_errors({i: res.homographies[i] for i in np.flatnonzero(res.registered)}, truth, ds.camera)
    return {"frames": len(ds), "size_px": [ds.camera.width, ds.camera.height],
            "ours": {**{k: ours[k] for k in ("n_registered", "coverage_fraction", "alignment_error_px", "residual_px")},
                     "alignment_error_px_same_gauge_fit": {"mean": float(err.mean()), "p95": float(np.percentile(err, 95))},
                     "time_s": ours_wall, "cpu_s": ours_cpu},
            "opencv_stitcher_scans": peer,
            "cpu_ratio_stitcher_over_ours": st_cpu / ours_cpu}


def bladder_mosaic(tmp: Path) -> dict:
    from scope3d.io.scan_plan import read_scan_plan

    scan_plan_job.run(ScanPlanOptions(standoff_mm=30.0, overlap=0.5, fov_deg=70.0), "bladder", tmp / "plan_30_free")
    seq = phantoms.generate("bladder", plan=read_scan_plan(tmp / "plan_30_free" / "plan.json"), size=(304, 304))
    phantoms.write(seq, tmp / "bladder30")
    ds = load_dataset(tmp / "bladder30")
    c0 = time.process_time()
    report = mosaic_job.run(mos.MosaicOptions(), [ds], tmp / "bladder_mosaic").report
    shutil.copy(tmp / "bladder_mosaic" / "mosaic_path.png", OUT / "panorama_mosaic_bladder.png")
    return {"plan": "bladder, 30 mm stand-off, FOV 70°, 50 % overlap", **{k: report[k] for k in (
        "n_frames", "n_registered", "n_linked_pairs", "coverage_fraction", "residual_px", "time_s")},
        "cpu_s": time.process_time() - c0}


def main() -> int:
    OUT.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        result = {"machine": {"cores": os.cpu_count(), "load_avg_1_5_15": load}, "reference": REFERENCE,
                  "plans": plans(tmp)}
        (OUT / "panorama.json").write_text(json.dumps(result, indent=2) + "\n")  # each part saved as it ends
        result["mosaic_sheet"] = mosaic_vs_stitcher(tmp)
        print(json.dumps(result["mosaic_sheet"], indent=1))
        (OUT / "panorama.json").write_text(json.dumps(result, indent=2) + "\n")
        result["mosaic_bladder"] = bladder_mosaic(tmp)
        print(json.dumps(result["mosaic_bladder"], indent=1))
    result["machine"]["load_avg_after"] = os.getloadavg()
    (OUT / "panorama.json").write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
