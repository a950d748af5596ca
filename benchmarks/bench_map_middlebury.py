"""Surgical-field map pipeline vs COLMAP on real photographs: Middlebury templeSparseRing (16 views, calibrated).

1. ``scope3d import middlebury`` turns the calibrated ring into a dataset (mm). scope3d maps it with the
   given poses (preset ``photograph``); COLMAP, through pycolmap in the same process, extracts SIFT,
   matches exhaustively and triangulates with the same known poses (``triangulate_points``). Compared:
   time, points, mean reprojection error. Targets: >= 2x faster than COLMAP, >= 1.3x its points, a
   reprojection error no worse.
2. The poses are then perturbed (uniform, +-0.25 mm at the reference's 15 mm stand-off scaled to the
   temple's ~560 mm: +-9.3 mm per axis, plus +-0.25 deg) and mapped with poses fixed, free and bounded:
   how far the poses end from the calibration, and the reprojection error.

Writes benchmarks/results/map_middlebury.json and map_middlebury_matches.png; prints tables. Run:
    .venv/bin/python benchmarks/bench_map_middlebury.py
"""
from __future__ import annotations

import json
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from scope3d.cli.main import main as cli
from scope3d.geometry.rotation import matrix_to_quaternion
from scope3d.io.dataset import load_dataset, write_dataset
from scope3d.pipelines.surgical_map import MAP_PRESETS, run
from scope3d.sensor.pose_tolerance import perturb_poses_uniform

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
PAR = ROOT.parent / "shared" / "data" / "middlebury_templeSparseRing" / "templeSR_par.txt"
REPEATS = 3  # best of 3: the machine is shared
REFERENCE_STANDOFF_MM = 15.0
REFERENCE_NOISE_MM = 0.25


def scope3d_run(ds, out: Path, options=None) -> dict:
    best = None
    for _ in range(REPEATS):
        res = run(options or MAP_PRESETS["photograph"], ds, out)
        t = res.report["timings_s"]
        core = t["load"] + t["features"] + t["matching"] + t["bundle"]
        if best is None or core < best[0]:
            best = (core, res)
    core, res = best
    r = res.report
    return {"time_s": round(core, 3), "time_with_outputs_s": r["time_s"], "timings_s": r["timings_s"],
            "n_points": r["n_points"], "n_observations": r["n_observations"],
            "mean_reprojection_error_px": r["mean_reprojection_error_px"], "n_pairs": r["n_pairs"],
            "n_matches": r["n_matches"], "figure_pair": r.get("figure_pair"), "_out": res.out_dir}


def colmap_run(ds, work: Path) -> dict:
    import pycolmap

    best = None
    for k in range(REPEATS):
        rec, _, (t0, t1, t2, t3) = colmap_known_pose_map(pycolmap, ds, work / f"colmap{k}")
        row = {"time_s": round(t3 - t0, 3), "extract_s": round(t1 - t0, 3), "match_s": round(t2 - t1, 3),
               "triangulate_s": round(t3 - t2, 3), "n_points": rec.num_points3D(),
               "n_observations": int(sum(p.track.length() for p in rec.points3D.values())),
               "mean_reprojection_error_px": rec.compute_mean_reprojection_error()}
        if best is None or row["time_s"] < best["time_s"]:
            best = row
    return best


def colmap_known_pose_map(pycolmap, ds, run_dir: Path):
    """COLMAP's SIFT extraction, exhaustive matching and ``triangulate_points`` on ``ds``'s poses, in
    ``run_dir``. Returns the reconstruction, the database path and the times before and after each step."""
    run_dir.mkdir(parents=True, exist_ok=True)
    db_path = run_dir / "database.db"
    db_path.unlink(missing_ok=True)  # COLMAP would skip the images an old database holds
    cam = ds.camera
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "OPENCV"
    # COLMAP's pixel origin is the image corner: principal point + 0.5
    reader.camera_params = ",".join(str(v) for v in (cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5, 0, 0, 0, 0))
    t0 = time.perf_counter()
    pycolmap.extract_features(db_path, ds.root / "frames", image_names=ds.names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader)
    t1 = time.perf_counter()
    pycolmap.match_exhaustive(db_path)
    t2 = time.perf_counter()
    rec = _known_pose_reconstruction(pycolmap, db_path, {n: m.pose for n, m in zip(ds.names, ds.poses)})
    (run_dir / "sparse").mkdir(exist_ok=True)
    rec = pycolmap.triangulate_points(rec, db_path, ds.root / "frames", run_dir / "sparse")
    return rec, db_path, (t0, t1, t2, time.perf_counter())


def _known_pose_reconstruction(pycolmap, db_path: Path, pose_of: dict):
    """A pycolmap Reconstruction holding the database's cameras, rigs, frames and images, posed with
    the calibration (images are matched by name: COLMAP numbers them in its own order); images whose name
    ``pose_of`` lacks are left out (bench_localize_real.py maps a subset of the views)."""
    db = pycolmap.Database.open(db_path)
    rec = pycolmap.Reconstruction()
    for c in db.read_all_cameras():
        rec.add_camera(c)
    for r in db.read_all_rigs():
        rec.add_rig(r)
    images = [im for im in db.read_all_images() if im.name in pose_of]
    image_of_frame = {im.frame_id: im for im in images}
    for f in db.read_all_frames():
        if f.frame_id not in image_of_frame:
            continue
        p = pose_of[image_of_frame[f.frame_id].name]
        f.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(matrix_to_quaternion(p.rotation)), p.translation)
        rec.add_frame(f)
    for im in images:
        rec.add_image(im)
    db.close()
    return rec


def perturbed(ds, tmp: Path) -> dict:
    centres = np.stack([m.pose.centre for m in ds.poses])
    box = np.asarray(ds.metadata["bounding_box_mm"])
    standoff = float(np.median(np.linalg.norm(centres - box.mean(axis=0), axis=1)))
    noise_mm = REFERENCE_NOISE_MM * standoff / REFERENCE_STANDOFF_MM
    noise_rad = np.deg2rad(0.25)
    measured = perturb_poses_uniform([m.pose for m in ds.poses], noise_mm, noise_rad, seed=3)
    frames = [ds.frame(k) for k in range(len(ds))]
    path = write_dataset(tmp / "temple_noisy", ds.camera, frames, measured, names=ds.names,
                         true_poses=[m.pose for m in ds.poses], metadata={"bounding_box_mm": ds.metadata["bounding_box_mm"]})
    noisy = load_dataset(path)
    rows = {"standoff_mm": round(standoff, 1), "position_noise_mm": round(noise_mm, 3), "orientation_noise_deg": 0.25}
    for mode in ("fixed", "free", "bounded"):
        res = run(replace(MAP_PRESETS["photograph"], pose_mode=mode, figures=False), noisy, tmp / f"out_{mode}")
        r = res.report
        rows[mode] = {"pose_error": r["pose_error"], "n_points": r["n_points"],
                      "mean_reprojection_error_px": r["mean_reprojection_error_px"], "time_s": r["time_s"],
                      "bundle_rms_px": [[round(b["rms_initial_px"], 3), round(b["rms_final_px"], 3)] for b in r["bundle"]]}
    return rows


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        assert cli(["import", "middlebury", str(PAR), "--out", str(tmp / "temple")]) == 0
        ds = load_dataset(tmp / "temple")
        s3 = scope3d_run(ds, tmp / "scope3d")
        shutil.copy(s3.pop("_out") / "matches_with_without_prediction.png", OUT / "map_middlebury_matches.png")
        # the same with the endoscope's 2 px reprojection gate instead of the preset's 1 px, for transparency
        gate2 = scope3d_run(ds, tmp / "scope3d_2px", replace(MAP_PRESETS["photograph"],
                            tracks=replace(MAP_PRESETS["photograph"].tracks, max_reprojection_error_px=2.0)))
        gate2.pop("_out")
        cm = colmap_run(ds, tmp)
        noisy = perturbed(ds, tmp)
    results = {
        "benchmark": "Middlebury templeSparseRing, 16 views 640x480, known poses",
        "scope3d": s3, "scope3d_2px_gate": gate2, "colmap": cm,
        "speedup": round(cm["time_s"] / s3["time_s"], 2),
        "points_ratio": round(s3["n_points"] / max(cm["n_points"], 1), 2),
        "reprojection_error_ratio": round(s3["mean_reprojection_error_px"] / cm["mean_reprojection_error_px"], 3),
        "targets": {"speedup": ">= 2", "points_ratio": ">= 1.3", "reprojection_error_ratio": "<= 1"},
        "note": "scope3d time = load + features + matching + triangulation/BA (outputs excluded; COLMAP's "
                "time = extract_features + match_exhaustive + triangulate_points)",
        "perturbed_poses": noisy,
    }
    (OUT / "map_middlebury.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    print(f"{'':12s} {'time s':>7s} {'points':>7s} {'obs':>7s} {'reproj px':>9s}")
    for name, r in (("scope3d", s3), ("scope3d 2px", gate2), ("COLMAP", cm)):
        print(f"{name:12s} {r['time_s']:7.3f} {r['n_points']:7d} {r['n_observations']:7d} {r['mean_reprojection_error_px']:9.3f}")
    print(f"ratios: speed-up {results['speedup']}x, points {results['points_ratio']}x, "
          f"reprojection error {results['reprojection_error_ratio']}x")
    print(f"\nperturbed poses: +-{noisy['position_noise_mm']} mm, +-0.25 deg (stand-off {noisy['standoff_mm']} mm)")
    print(f"{'mode':8s} {'pos err mean mm':>15s} {'max':>7s} {'rot err deg':>11s} {'points':>7s} {'reproj px':>9s}")
    for mode in ("fixed", "free", "bounded"):
        r = noisy[mode]
        pe = r["pose_error"]
        print(f"{mode:8s} {pe['position_mm_mean']:15.3f} {pe['position_mm_max']:7.3f} {pe['orientation_deg_mean']:11.3f} "
              f"{r['n_points']:7d} {r['mean_reprojection_error_px']:9.3f}")
    print(f"(measured poses: {noisy['fixed']['pose_error']['measured_position_mm_mean']:.3f} mm mean from the calibration)")


if __name__ == "__main__":
    main()
