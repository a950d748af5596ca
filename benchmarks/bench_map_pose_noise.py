"""Surgical-field map against the pose noise level: bounded, free and fixed poses vs image-only COLMAP.

The issue's goal, on the dome, the flat sheet and the Middlebury temple ring, for pose errors up to
±5 mm and ±2.5° (uniform, and a common bias plus a drift along the trajectory): every frame in the
model; mean surface error after ICP below the image-only + similarity baseline at every level, ≤ 0.1 mm
up to ±1 mm and as close as the scale information in the poses allows beyond; camera error after BCBA
at most half the measured error; time within 2x of the exact-pose case. This benchmark measures each
clause at every noise level and writes a pass/fail per clause and run.

Scenes (one rendering per scene and seed; only ``poses.csv`` changes between levels):
  dome   -- phantom dome, grid5x6 (30 frames), 608 x 608 (``--size small``: 304 x 304);
  sheet  -- phantom flat sheet, grid5x6, same camera;
  temple -- Middlebury templeSparseRing (16 views 640 x 480, ``scope3d import middlebury``), preset
            ``photograph``. Its calibration is the truth; it has no true surface, so it reports camera
            error against the calibration, reprojection error and points. The temple is ~560 mm from
            the cameras where the phantoms' grid is 15 mm above the plate: its *position* noise (and
            tolerance) is the level times stand-off / 15 mm (±1 mm -> about ±37 mm), as in
            bench_map_middlebury.py; the *orientation* noise (an angle) is not scaled.

Noise models, level N mm (orientation a = 0.5°/mm x N, the phantom lab's ratio: ±5 mm <-> ±2.5°):
  uniform    -- every centre off by U(-N, N) per axis, orientation by U(-a, a) per axis, tolerance
                written ±N, ±a (exactly ``scope3d phantom --pose-noise N``: phantoms.measure_poses);
  bias_drift -- a common bias of 0.4 N per axis (signs drawn from the seed) plus a drift growing
                linearly along the trajectory to 0.4 N per axis at the last frame (pose.perturb_poses_drift)
                plus uniform jitter ±0.2 N; orientation: common bias 0.6 a plus jitter ±0.4 a (the
                library's drift model moves centres only). Tolerance ±N, ±a: the box holds the truth.
  Level 0 is the exact poses with the micro-stage tolerance (0.01 mm; the temple: scaled like its
  noise), run once per scene and shared by both models.

Per level (and seed), the same dataset is mapped by:
  scope3d bounded / free / fixed -- ``surgical_map.run`` with MAP_PRESETS (default; photograph for
      the temple), figures and fluorescence targets off;
  baseline -- image-only COLMAP through pycolmap: extract_features (with the endoscope's circular
      mask), match_exhaustive, incremental_mapping with the intrinsics given and fixed (largest model);
      then the 7-dof similarity (Umeyama) from its camera centres to the *reported* (noisy) centres; then
      its points seen in >= 3 images (COLMAP keeps ~0.5 % wrong matches millimetres off, which multiply
      its mean by 3-10 and are all two-view points; scope3d's own off-surface filter, tried instead,
      dropped 1-23 % of COLMAP's points from run to run, mostly good ones; the unfiltered errors are
      kept as surface_error_mm_unfiltered); then the same rigid ICP to the true surface as scope3d's
      evaluation (icp_from_initial_poses, same EvaluationOptions). The images are identical at every
      level, so COLMAP reconstructs once per scene and seed and only the similarity changes with the
      level; its time is that one reconstruction's;
  oracle -- the scale-information limit. With known intrinsics the images fix the shape and the
      poses only its similarity; after rigid ICP only the similarity's scale error is left. The oracle
      has the TRUE shape (true-surface samples seen unoccluded in >= 2 frames) and places it by the
      least-squares similarity from the true to the reported camera centres (what a least-squares
      gauge fit of the centres can reach), then the same ICP. Its camera error (true centres moved by
      that similarity) is the camera-error floor: a common bias is a translation no image can see.
      camera_error_box_gauge_mm: the true centres placed by the bounded map's own gauge rule instead
      (estimators.gauge.align_gauge, bounded): the camera error a bounded map with a perfect shape has.
      A scale error costs more after ICP on a wider point set, so each method's row also has
      floor_on_own_points_mm: the oracle on the true-surface points nearest to that method's points
      (after ICP). The tolerance boxes hold more than a least-squares fit uses: the oracle row also
      gives the interval of scales for which every true centre stays in its box (a linear programme,
      orientation boxes unused) and the error of the true shape scaled to its middle and its farther
      end. On the flat sheet every floor is 0 (a scaled plane is a plane).

Recorded per run: frames in the model (>= 30 observations of model points, read from the COLMAP text
model the map writes; COLMAP: registered), points, mean / median / p95 surface error after ICP (and
direct), camera position error after adjustment and as measured, and after the best similarity to the
truth (the trajectory's shape, gauge-free; on the temple the closest thing to a shape error),
reprojection error, the pipeline's time_s (outputs included, evaluation excluded), its core time
(load + features + matching + bundle) and the wall time. A failing mode (e.g. "cannot estimate a depth
prior") is a row with the error message. Goal clauses per scope3d run (None = not applicable):
every_frame_in_model; surface_below_baseline (mean after ICP; the baseline on its >= 3-view points; the
comparison with all its points is surface_below_unfiltered_baseline, outside the pass); surface_le_0.1mm
(levels <= 1 mm); surface_le_floor_plus_0.1mm (every level, own-points floor: this benchmark's reading of
"as close as the scale information allows"); camera_below_baseline; camera_le_half_measured (levels > 0);
time_le_2x_exact (time_s against level 0 of the same mode and seed). ``pass``: every applicable clause.

Writes benchmarks/results/map_pose_noise.json (command, machine, library versions, options, all rows,
and scale_limit: the oracle per scene, model and level) and map_pose_noise_<scene>_<model>.png (surface
error, camera error, camera shape error, points, time and reprojection error against the level; log y
for errors; red bands where a scope3d mode failed); prints tables. A full run (3 scenes x 15 pose sets x
4 methods, 608 px) should take 2-3 hours on 2 shared cores (an estimate: a 608 px dome map takes 20-75 s
per mode, COLMAP ~2 min per scene, the oracle and floor ICPs ~10 s per row). Run:
    .venv/bin/python benchmarks/bench_map_pose_noise.py
    .venv/bin/python benchmarks/bench_map_pose_noise.py --quick        # dome, 0/1/3 mm, 304 px: 4-7 min
    .venv/bin/python benchmarks/bench_map_pose_noise.py --scenes dome --models uniform --levels 0,1,3 --seeds 11,12
--quick writes map_pose_noise_quick*.{json,png}, never the full run's files.
"""
from __future__ import annotations

import argparse
import os
import platform
import shutil
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from scope3d import __version__ as scope3d_version
from scope3d import phantoms
from scope3d.estimators.gauge import align_gauge
from scope3d.geometry.pose import Pose
from scope3d.io.dataset import load_dataset, write_dataset
from scope3d.metrology.evaluation import EvaluationOptions, distance_summary, icp_from_initial_poses
from scope3d.pipelines.surgical_map import MAP_PRESETS, MapOptions, run
from scope3d.scene.mesh import SampledSurface
from scope3d.sensor.pose_tolerance import (
    MeasuredPose,
    PoseTolerance,
    perturb_poses_biased,
    perturb_poses_drift,
    perturb_poses_uniform,
)
from scope3d.utils.jsonio import write_json

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
TEMPLE_PAR = ROOT.parent / "shared" / "data" / "middlebury_templeSparseRing" / "templeSR_par.txt"

SCENES = ("dome", "sheet", "temple")
MODELS = ("uniform", "bias_drift")
MODES = ("bounded", "free", "fixed")
LEVELS_MM = (0.0, 0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 5.0)
QUICK = {"scenes": ("dome",), "models": ("uniform",), "levels": (0.0, 1.0, 3.0), "size": "small"}
SIZES = {"full": None, "small": (304, 304)}  # None: the scene's camera (608 x 608 endoscope)
DEFAULT_SEEDS = (11,)  # the unit tests do not use 11
ORIENTATION_DEG_PER_MM = phantoms.lab.ORIENTATION_NOISE_DEG_PER_MM  # 0.5°/mm: ±5 mm <-> ±2.5°
MICRO_STAGE_MM = 0.01  # level 0: exact poses with the micro-positioning stage's tolerance
REFERENCE_STANDOFF_MM = 15.0  # the phantoms' grid stand-off: the temple's noise is scaled by stand-off / this
BIAS, DRIFT, JITTER = 0.4, 0.4, 0.2  # bias_drift: fractions of the level, per axis (sum 1: truth in the box)
BIAS_ROT, JITTER_ROT = 0.6, 0.4  # and of the orientation level
MIN_BASELINE_TRACK = 3  # COLMAP points kept for the baseline's surface error: seen in >= 3 images
MIN_OBSERVATIONS = 30  # a frame is "in the model" with this many observations (COLMAP's abs_pose_min_num_inliers)
GOAL_MM = 0.1  # surface error goal up to ±1 mm (and the budget over the floor beyond)
GOAL_LEVEL_MM = 1.0


# --- scenes -----------------------------------------------------------------------------------


@dataclass
class Scene:
    """One rendered (or imported) scene: the exact-pose dataset and what is true about it.

    scale : position noise (mm) per level-mm (1 for the phantoms, stand-off / 15 mm for the temple).
    truth : the sampled true surface (None for the temple); footprint : (K, 3) true-surface samples seen
    in >= 2 frames (the oracle's shape).
    """

    name: str
    base: Path
    options: MapOptions
    true_poses: list[Pose]
    scale: float
    truth: SampledSurface | None
    footprint: np.ndarray | None
    info: dict
    sequence: object = None  # the PhantomSequence (phantoms only)

    def write(self, measured: list[MeasuredPose], out: Path, description: dict) -> Path:
        """The dataset with these reported poses (images and ground truth unchanged)."""
        if self.sequence is not None:
            seq = self.sequence
            seq.measured_poses = measured
            seq.scene_info = {**seq.scene_info, "pose_noise": description}
            return phantoms.write(seq, out)
        ds = load_dataset(self.base)
        meta = {"pose_noise": description}
        if ds.metadata.get("bounding_box_mm") is not None:  # the temple's box: the map's depth prior
            meta["bounding_box_mm"] = ds.metadata["bounding_box_mm"]
        return write_dataset(out, ds.camera, ds.frame_paths, measured, names=ds.names, true_poses=self.true_poses,
                             metadata=meta)


def make_scene(name: str, seed: int, size: tuple[int, int] | None, tmp: Path) -> Scene:
    options = replace(MAP_PRESETS["photograph" if name == "temple" else "default"], figures=False, fluorescence=None)
    if name == "temple":
        return _temple(options, tmp)
    t0 = time.perf_counter()
    seq = phantoms.generate(name, "grid5x6", seed=seed, size=size)
    render_s = time.perf_counter() - t0
    base = phantoms.write(seq, tmp / f"{name}_exact")
    ds = load_dataset(base)
    truth = SampledSurface(ds.ground_truth.surface(), options.evaluation.sample_step_mm)
    footprint = visible_surface(ds, truth)
    cam = ds.camera
    info = {"frames": len(ds), "size_px": [cam.width, cam.height], "trajectory": "grid5x6",
            "render_time_s": round(render_s, 2), "position_noise_mm_per_level_mm": 1.0,
            "footprint_points": int(len(footprint))}
    return Scene(name, base, options, list(seq.true_poses), 1.0, truth, footprint, info, seq)


def _temple(options: MapOptions, tmp: Path) -> Scene:
    from scope3d.cli.main import main as cli

    if not TEMPLE_PAR.exists():
        raise FileNotFoundError(f"{TEMPLE_PAR} not found (shared data)")
    if cli(["import", "middlebury", str(TEMPLE_PAR), "--out", str(tmp / "temple_import")]) != 0:
        raise RuntimeError("scope3d import middlebury failed")
    ds = load_dataset(tmp / "temple_import")
    true_poses = [m.pose for m in ds.poses]
    centres = np.stack([p.centre for p in true_poses])
    box = np.asarray(ds.metadata["bounding_box_mm"])
    standoff = float(np.median(np.linalg.norm(centres - box.mean(axis=0), axis=1)))
    scale = standoff / REFERENCE_STANDOFF_MM
    info = {"frames": len(ds), "size_px": [ds.camera.width, ds.camera.height], "standoff_mm": round(standoff, 1),
            "position_noise_mm_per_level_mm": round(scale, 3)}
    return Scene("temple", tmp / "temple_import", options, true_poses, scale, None, None, info)


def visible_surface(ds, truth: SampledSurface, max_points: int = 20000) -> np.ndarray:
    """True-surface samples (K, 3) that at least two frames see unoccluded (projected inside the image
    and its mask, in front, within 0.2 mm of the true depth map there): where a map can have points."""
    cam = ds.camera
    pts = truth.points
    views = np.zeros(len(pts), np.int32)
    for k, pose in enumerate(ds.ground_truth.poses):
        pc = pose.transform(pts)
        uv = cam.project(pc)
        ok = cam.in_image(uv) & (pc[:, 2] > 0)
        idx = np.flatnonzero(ok)
        depth = ds.ground_truth.depth(k)
        u = np.clip(np.rint(uv[idx, 0]).astype(int), 0, cam.width - 1)
        v = np.clip(np.rint(uv[idx, 1]).astype(int), 0, cam.height - 1)
        seen = np.abs(depth[v, u] - pc[idx, 2]) < 0.2  # NaN (no surface) compares False
        views[idx[seen]] += 1
    keep = pts[views >= 2]
    if len(keep) > max_points:
        keep = keep[np.random.default_rng(0).choice(len(keep), max_points, replace=False)]
    return keep


# --- noise models -----------------------------------------------------------------------------


def measured_poses(model: str, true_poses: list[Pose], level_mm: float, scale: float, seed: int):
    """Reported poses at ``level_mm`` (see the module docstring) and a JSON description of the model."""
    pos = level_mm * scale
    ang_deg = ORIENTATION_DEG_PER_MM * level_mm
    ang = np.deg2rad(ang_deg)
    if level_mm == 0:
        tol = PoseTolerance(MICRO_STAGE_MM * scale, 0.0)
        return [MeasuredPose(p, tol) for p in true_poses], {"model": "exact", "tolerance_mm": MICRO_STAGE_MM * scale}
    if model == "uniform":
        if scale == 1.0:  # the phantom lab's own model (scope3d phantom --pose-noise)
            measured = phantoms.measure_poses(true_poses, level_mm, seed=seed)
        else:
            measured = perturb_poses_uniform(true_poses, pos, ang, seed=seed + 7919)
        return measured, {"model": "uniform", "position_mm": pos, "orientation_deg": ang_deg, "tolerance_mm": pos}
    if model == "bias_drift":
        rng = np.random.default_rng([seed, 104729])
        sign_bias, sign_drift, sign_rot = (rng.choice([-1.0, 1.0], 3) for _ in range(3))
        n = len(true_poses)
        drift_total = DRIFT * pos * sign_drift
        drifted = perturb_poses_drift(true_poses, drift_total / max(n - 1, 1))
        tol = PoseTolerance(pos, ang)
        measured = perturb_poses_biased([m.pose for m in drifted], BIAS * pos * sign_bias, BIAS_ROT * ang * sign_rot,
                                        JITTER * pos, JITTER_ROT * ang, seed=seed + 7919, tolerance=tol)
        return measured, {"model": "bias_drift", "bias_mm": (BIAS * pos * sign_bias).tolist(),
                          "drift_mm_at_last_frame": drift_total.tolist(), "jitter_mm": JITTER * pos,
                          "bias_deg": (BIAS_ROT * ang_deg * sign_rot).tolist(), "jitter_deg": JITTER_ROT * ang_deg,
                          "tolerance_mm": pos, "tolerance_deg": ang_deg}
    raise ValueError(f"unknown noise model {model!r}")


# --- geometry helpers -------------------------------------------------------------------------


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (Umeyama) with dst ≈ s R src + t. src, dst : (N, 3). -> (s, R (3, 3), t (3,))."""
    ca, cb = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ca, dst - cb
    U, S, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / np.sum(a * a))
    return s, R, cb - s * R @ ca


def _apply(sim, x: np.ndarray) -> np.ndarray:
    s, R, t = sim
    return s * np.asarray(x, float) @ R.T + t


def _sim_summary(sim) -> dict:
    s, R, t = sim
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    return {"scale": s, "rotation_deg": angle, "translation_mm": float(np.linalg.norm(t))}


def surface_errors(points: np.ndarray, truth: SampledSurface, ev: EvaluationOptions) -> dict:
    """The pipeline's evaluation: distances direct and after ICP from eight starts (mm)."""
    best, _ = icp_from_initial_poses(points, truth, options=ev)
    return {"direct": _short(distance_summary(truth.distances(points))),
            "after_icp": _short(distance_summary(truth.distances(best.apply(points))))}


def _short(s: dict) -> dict:
    return {k: s[k] for k in ("n", "mean", "median", "p95", "within_1mm_fraction") if k in s}


# --- methods ----------------------------------------------------------------------------------


def oracle_floor(scene: Scene, measured: list[MeasuredPose]) -> dict:
    """The true shape placed by the similarity from the true to the reported centres, then ICP.

    Also the scale interval the tolerance boxes allow (:func:`feasible_scales`) and the error of the
    true shape scaled to its midpoint and to its farther end (after rigid ICP only the scale matters)."""
    true_c = np.stack([p.centre for p in scene.true_poses])
    sim = similarity(true_c, np.stack([m.pose.centre for m in measured]))
    row = {"method": "oracle", "status": "ok", "similarity": _sim_summary(sim),
           "camera_error_mm": float(np.mean(np.linalg.norm(_apply(sim, true_c) - true_c, axis=1)))}
    # the true shape placed by the map's own bounded gauge rule (the least-squares placement well inside
    # every box, estimators.gauge.align_gauge): what a bounded map with a perfect shape is left with
    boxed = np.stack([p.centre for p in align_gauge(scene.true_poses, measured, bounded=True)])
    row["camera_error_box_gauge_mm"] = float(np.mean(np.linalg.norm(boxed - true_c, axis=1)))
    row["camera_error_box_gauge_max_mm"] = float(np.max(np.linalg.norm(boxed - true_c, axis=1)))
    interval = feasible_scales(true_c - true_c.mean(axis=0), measured)
    if interval is not None:
        lo, hi = interval
        row["box_scale_interval"] = [lo, hi]
    if scene.truth is not None:
        ev = scene.options.evaluation
        row["surface_error_mm"] = surface_errors(_apply(sim, scene.footprint), scene.truth, ev)
        if interval is not None:
            c = scene.footprint.mean(axis=0)
            worst = max(lo, hi, key=lambda v: abs(v - 1.0))
            for name, s in (("box_mid_scale", 0.5 * (lo + hi)), ("box_worst_scale", worst)):
                scaled = c + s * (scene.footprint - c)
                row[name] = {"scale": s, "surface_error_mm": surface_errors(scaled, scene.truth, ev)}
    return row


def feasible_scales(true_centres: np.ndarray, measured: list[MeasuredPose]) -> tuple[float, float] | None:
    """[min, max] scale of the similarities that keep every true centre in its reported tolerance box:
    the scale information the poses hold under the box model (BCBA's). A linear programme in scale s,
    translation t and u = s w for a small rotation w (s R C ~ s C + u x C); orientation boxes unused.
    None when the boxes are unbounded or the programme fails."""
    from scipy.optimize import linprog

    tol = np.array([m.tolerance.position_mm for m in measured])
    if not np.all(np.isfinite(tol)):
        return None
    tol = np.maximum(tol, 1e-9)
    meas = np.stack([m.pose.centre for m in measured])
    rows, rhs = [], []
    for c, q, h in zip(true_centres, meas, tol):
        cross = -np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])  # u x c = -[c]x u
        for k in range(3):
            a = np.concatenate([[c[k]], cross[k], np.eye(3)[k]])  # variables: s, u (3), t (3)
            rows += [a, -a]
            rhs += [q[k] + h[k], -(q[k] - h[k])]
    A, b = np.array(rows), np.array(rhs)
    out = []
    for sign in (1.0, -1.0):
        res = linprog(np.concatenate([[sign], np.zeros(6)]), A_ub=A, b_ub=b, bounds=[(None, None)] * 7, method="highs")
        if res.status != 0:
            return None
        out.append(float(res.x[0]))
    return out[0], out[1]


def colmap_reconstruct(scene: Scene, work: Path, seed: int) -> dict:
    """Image-only incremental SfM (pycolmap), intrinsics given and fixed. -> dict with the largest model's
    camera centres by name, points (N, 3), times and counts (raises when nothing reconstructs)."""
    import cv2
    import pycolmap

    pycolmap.logging.minloglevel = 2  # errors only
    ds = load_dataset(scene.base)
    cam = ds.camera
    work.mkdir(parents=True, exist_ok=True)
    db = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "OPENCV"
    # COLMAP's pixel origin is the image corner: principal point + 0.5
    reader.camera_params = ",".join(str(v) for v in (cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5, cam.k1, cam.k2, 0, 0))
    if cam.mask_radius_px is not None:  # the endoscope's circular field, as scope3d masks it
        (work / "masks").mkdir(exist_ok=True)
        mask = cam.mask().astype(np.uint8) * 255
        for name in ds.names:
            cv2.imwrite(str(work / "masks" / f"{name}.png"), mask)
        reader.mask_path = str(work / "masks")
    opts = pycolmap.IncrementalPipelineOptions()
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.mapper.abs_pose_refine_focal_length = False
    opts.mapper.abs_pose_refine_extra_params = False
    opts.random_seed = seed
    t0 = time.perf_counter()
    pycolmap.extract_features(db, ds.root / "frames", image_names=ds.names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader)
    t1 = time.perf_counter()
    pycolmap.match_exhaustive(db)
    t2 = time.perf_counter()
    (work / "sparse").mkdir(exist_ok=True)
    models = pycolmap.incremental_mapping(db, ds.root / "frames", work / "sparse", options=opts)
    t3 = time.perf_counter()
    if not models:
        raise RuntimeError("COLMAP reconstructed no model")
    rec = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    centres = {im.name: np.asarray(im.projection_center()) for im in rec.images.values() if im.has_pose}
    points = np.array([p.xyz for p in rec.points3D.values()], float).reshape(-1, 3)
    track_lengths = np.array([p.track.length() for p in rec.points3D.values()], int)
    point_errors = np.array([p.error for p in rec.points3D.values()], float)
    return {"centres": centres, "points": points, "track_lengths": track_lengths, "point_errors_px": point_errors,
            "n_frames": len(ds), "n_models": len(models),
            "n_points": int(rec.num_points3D()),
            "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
            "time_s": round(t3 - t0, 3), "timings_s": {"extract": round(t1 - t0, 3), "match": round(t2 - t1, 3),
                                                        "mapping": round(t3 - t2, 3)}}


def baseline_row(scene: Scene, recon: dict, measured: list[MeasuredPose], names: list[str]) -> dict:
    """Similarity from COLMAP's centres to the reported ones, then the evaluation."""
    index = {n: k for k, n in enumerate(names)}
    reg = [n for n in names if n in recon["centres"]]
    if len(reg) < 3:
        raise RuntimeError(f"COLMAP registered {len(reg)} frames: too few for a similarity")
    a = np.stack([recon["centres"][n] for n in reg])
    b = np.stack([measured[index[n]].pose.centre for n in reg])
    true_c = np.stack([scene.true_poses[index[n]].centre for n in reg])
    sim = similarity(a, b)
    row = {"method": "baseline", "status": "ok", "frames": recon["n_frames"], "frames_in_model": len(reg),
           "n_models": recon["n_models"], "n_points": recon["n_points"], "n_points_all": recon["n_points"],
           "mean_reprojection_error_px": recon["mean_reprojection_error_px"], "time_s": recon["time_s"],
           "timings_s": recon["timings_s"], "similarity": _sim_summary(sim),
           "camera_error_mm": float(np.mean(np.linalg.norm(_apply(sim, a) - true_c, axis=1))),
           "measured_camera_error_mm": float(np.mean(np.linalg.norm(b - true_c, axis=1))),
           "camera_shape_error_mm": shape_error(a, true_c)}
    if scene.truth is not None:
        # COLMAP's points seen in >= 3 images: its gross errors (wrong matches along an epipolar line,
        # millimetres off) are all two-view points, which nothing can check
        pts = _apply(sim, recon["points"])
        keep = recon["track_lengths"] >= MIN_BASELINE_TRACK
        row.update({"n_points": int(keep.sum()), "n_points_two_view_dropped": int((~keep).sum()),
                    "surface_error_mm": surface_errors(pts[keep], scene.truth, scene.options.evaluation),
                    "surface_error_mm_unfiltered": surface_errors(pts, scene.truth, scene.options.evaluation),
                    "floor_on_own_points_mm": own_floor(scene, measured, pts[keep])})
    return row


def scope3d_row(scene: Scene, mode: str, dataset_path: Path, out: Path) -> dict:
    ds = load_dataset(dataset_path)
    t0 = time.perf_counter()
    res = run(replace(scene.options, pose_mode=mode), ds, out)
    wall = time.perf_counter() - t0
    r = res.report
    t = r.get("timings_s", {})
    pe = r.get("pose_error", {})
    per_frame, centres, points = read_model(out, ds.names)
    row = {"method": mode, "status": "ok", "frames": r["n_frames"],
           "frames_in_model": int(np.sum(per_frame >= MIN_OBSERVATIONS)) if per_frame is not None else None,
           "min_observations_per_frame": int(per_frame.min()) if per_frame is not None else None,
           "n_points": r["n_points"], "n_observations": r.get("n_observations"),
           "mean_reprojection_error_px": r.get("mean_reprojection_error_px"),
           "time_s": r["time_s"],
           "core_time_s": round(sum(t.get(k, 0.0) for k in ("load", "features", "matching", "bundle")), 4),
           "wall_time_s": round(wall, 3), "timings_s": t,
           "camera_error_mm": pe.get("position_mm_mean"), "measured_camera_error_mm": pe.get("measured_position_mm_mean"),
           "camera_shape_error_mm": None if centres is None else
           shape_error(centres, np.stack([p.centre for p in scene.true_poses])),
           "pose_error": pe, "matching": r.get("matching"), "depth_prior_mm": r.get("depth_prior_mm")}
    if "surface_error_mm" in r:
        row["surface_error_mm"] = {k: _short(r["surface_error_mm"][k]) for k in ("direct", "after_icp")}
        row["floor_on_own_points_mm"] = own_floor(scene, ds.poses, points)
    return row


def read_model(out: Path, names: list[str]):
    """From the COLMAP text model the map writes: observations of model points per frame (n_frames,),
    the adjusted camera centres (n_frames, 3) in ``names`` order, and the points (N, 3) mm;
    (None, None, None) if unreadable."""
    from scope3d.io.colmap import read_colmap_text

    try:
        model = read_colmap_text(out / "sparse")
        index = {n: k for k, n in enumerate(model.image_names)}
        counts = np.array([len(model.keypoints[index[n]]) if n in index else 0 for n in names])
        centres = np.stack([model.poses[index[n]].centre if n in index else np.full(3, np.nan) for n in names])
        return counts, centres, model.points3d
    except Exception:  # noqa: BLE001 - an output the pipeline may stop writing: then unknown
        return None, None, None


def own_floor(scene: Scene, measured: list[MeasuredPose], points: np.ndarray | None) -> float | None:
    """The oracle on a method's own points: after ICP of its points to the truth, their nearest true-surface
    samples, placed by the least-squares similarity from the true to the reported centres, then ICP; the
    mean distance (mm). After rigid ICP a scale error costs more on a wider point set, so the floor
    depends on where a method has points: this is the one to hold that method's error against."""
    if scene.truth is None or points is None or len(points) < 10:
        return None
    ev = scene.options.evaluation
    best, _ = icp_from_initial_poses(points, scene.truth, options=ev)
    shadow = scene.truth.nearest(best.apply(points))[0]
    true_c = np.stack([p.centre for p in scene.true_poses])
    sim = similarity(true_c, np.stack([m.pose.centre for m in measured]))
    return surface_errors(_apply(sim, shadow), scene.truth, ev)["after_icp"].get("mean")


def shape_error(centres: np.ndarray, true_centres: np.ndarray) -> float | None:
    """Mean camera error (mm) after the best similarity to the truth: the trajectory's shape, gauge-free."""
    ok = np.all(np.isfinite(centres), axis=1)
    if ok.sum() < 3:
        return None
    sim = similarity(centres[ok], true_centres[ok])
    return float(np.mean(np.linalg.norm(_apply(sim, centres[ok]) - true_centres[ok], axis=1)))


def failure(method: str, exc: BaseException) -> dict:
    return {"method": method, "status": "failed", "error": f"{type(exc).__name__}: {exc}",
            "traceback": traceback.format_exc(limit=4)}


# --- the sweep --------------------------------------------------------------------------------


def sweep(args, results: dict, save) -> None:
    rows = results["rows"]
    for scene_name in args.scenes:
        for seed in args.seeds:
            with tempfile.TemporaryDirectory(prefix="scope3d_pose_noise_") as tmp_name:
                tmp = Path(tmp_name)
                key = {"scene": scene_name, "seed": seed}
                try:
                    scene = make_scene(scene_name, seed, SIZES[args.size], tmp)
                except Exception as exc:  # noqa: BLE001 - the benchmark goes on with the other scenes
                    rows.append({**key, "noise_model": None, "level_mm": None, **failure("scene", exc)})
                    print(f"{scene_name} seed {seed}: scene failed: {rows[-1]['error']}", flush=True)
                    save()
                    continue
                results["scenes"][scene_name] = scene.info
                recon = None
                if not args.no_baseline:
                    try:
                        recon = colmap_reconstruct(scene, tmp / "colmap", seed)
                    except Exception as exc:  # noqa: BLE001
                        recon = failure("baseline", exc)
                    print(f"{scene_name} seed {seed}: COLMAP "
                          + (f"{len(recon['centres'])}/{recon['n_frames']} frames, {recon['n_points']} points, "
                             f"{recon['time_s']:.1f} s" if "centres" in recon else recon["error"]), flush=True)
                names = load_dataset(scene.base).names
                runs = [("exact", 0.0)] if 0.0 in args.levels else []
                runs += [(m, lv) for m in args.models for lv in args.levels if lv > 0]
                for model, level in runs:
                    here = {**key, "noise_model": model, "level_mm": level}
                    try:
                        measured, description = measured_poses(model, scene.true_poses, level, scene.scale, seed)
                        here["noise"] = description
                        path = scene.write(measured, tmp / "dataset", description)
                    except Exception as exc:  # noqa: BLE001
                        rows.append({**here, **failure("dataset", exc)})
                        print(_progress_line(rows[-1]), flush=True)
                        save()
                        continue
                    todo = [("oracle", lambda: oracle_floor(scene, measured))]
                    if recon is not None:
                        todo.append(("baseline", lambda: baseline_row(scene, recon, measured, names) if "centres" in recon
                                     else dict(recon)))
                    todo += [(mode, lambda mode=mode: scope3d_row(scene, mode, path, tmp / "out")) for mode in args.modes]
                    for method, fn in todo:
                        try:
                            row = fn()
                        except Exception as exc:  # noqa: BLE001 - a failing mode is a result, not a crash
                            row = failure(method, exc)
                        rows.append({**here, **row})
                        shutil.rmtree(tmp / "out", ignore_errors=True)
                        print(_progress_line(rows[-1]), flush=True)
                        save()
                    shutil.rmtree(path, ignore_errors=True)


def _progress_line(r: dict) -> str:
    level = "-" if r["level_mm"] is None else f"{r['level_mm']:g}"
    head = f"{r['scene']:6s} {r['noise_model'] or '-':10s} {level:>5s} {r['method']:8s}"
    if r["status"] != "ok":
        return f"{head} FAILED {r['error']}"
    s = (r.get("surface_error_mm") or {}).get("after_icp", {})
    parts = [f"ICP mean {s['mean']:.4f} median {s['median']:.4f} mm" if s else "",
             f"cam {r['camera_error_mm']:.3f} mm" if r.get("camera_error_mm") is not None else "",
             f"frames {r['frames_in_model']}/{r['frames']}" if "frames" in r else "",
             f"points {r['n_points']}" if "n_points" in r else "",
             f"time {r['time_s']:.1f} s" if "time_s" in r else ""]
    return f"{head} " + ", ".join(p for p in parts if p)


# --- goals ------------------------------------------------------------------------------------


def _icp_mean(row: dict | None):
    if row is None or row.get("status") != "ok":
        return None
    return ((row.get("surface_error_mm") or {}).get("after_icp") or {}).get("mean")


def _sub_mean(row: dict, key: str):
    """The oracle's mean after ICP at a box scale (``box_mid_scale`` / ``box_worst_scale``), or None."""
    return (((row.get(key) or {}).get("surface_error_mm") or {}).get("after_icp") or {}).get("mean")


def evaluate_goals(rows: list[dict]) -> None:
    """Adds ``goals`` (clause -> True/False/None) and ``pass`` to every scope3d row."""
    def find(r, method, model=None, level=None):
        want = (r["scene"], r["seed"], method, model or r["noise_model"], r["level_mm"] if level is None else level)
        return next((x for x in rows if (x["scene"], x["seed"], x["method"], x["noise_model"], x["level_mm"]) == want),
                    None)

    for r in rows:
        if r["method"] not in MODES:
            continue
        if r["status"] != "ok":
            r["goals"] = {"runs": False}
            r["pass"] = False
            continue
        level = r["level_mm"]
        mean = _icp_mean(r)
        base, oracle, exact = find(r, "baseline"), find(r, "oracle"), find(r, r["method"], "exact", 0.0)
        base_mean = _icp_mean(base)
        floor = r.get("floor_on_own_points_mm")
        if floor is None:
            floor = _icp_mean(oracle)
        g = {"every_frame_in_model": None if r["frames_in_model"] is None else r["frames_in_model"] == r["frames"]}
        if mean is not None:
            g["surface_below_baseline"] = None if base is None else (base_mean is None or mean < base_mean)
            unfiltered = ((base or {}).get("surface_error_mm_unfiltered") or {}).get("after_icp", {}).get("mean")
            r["surface_below_unfiltered_baseline"] = None if unfiltered is None else mean < unfiltered
            g["surface_le_0.1mm"] = mean <= GOAL_MM if level <= GOAL_LEVEL_MM else None
            g["surface_le_floor_plus_0.1mm"] = None if floor is None else mean <= floor + GOAL_MM
            r["surface_gap_to_floor_mm"] = None if floor is None else mean - floor
        cam, meas = r.get("camera_error_mm"), r.get("measured_camera_error_mm")
        if base is not None and base.get("status") == "ok" and cam is not None:
            g["camera_below_baseline"] = cam < base["camera_error_mm"]
        g["camera_le_half_measured"] = (cam <= 0.5 * meas) if (level > 0 and cam is not None and meas) else None
        if level > 0:
            g["time_le_2x_exact"] = (r["time_s"] <= 2.0 * exact["time_s"]) if exact and exact["status"] == "ok" else None
            r["time_ratio_to_exact"] = r["time_s"] / exact["time_s"] if exact and exact["status"] == "ok" else None
        r["goals"] = g
        r["pass"] = all(v for v in g.values() if v is not None)


def floor_table(rows: list[dict]) -> list[dict]:
    """The scale-information limit per scene, model and level: the oracle's errors, mean over seeds."""
    out = {}
    for r in rows:
        if r["method"] == "oracle" and r["status"] == "ok":
            k = (r["scene"], r["noise_model"], r["level_mm"])
            out.setdefault(k, []).append(r)
    table = []
    for (scene, model, level), rs in sorted(out.items(), key=lambda kv: (kv[0][0], kv[0][1], kv[0][2])):
        def mean_of(get):
            v = [get(r) for r in rs if get(r) is not None]
            return float(np.mean(v)) if v else None

        table.append({"scene": scene, "noise_model": model, "level_mm": level,
                      "surface_error_after_icp_mean_mm": mean_of(_icp_mean),
                      "camera_error_mm": mean_of(lambda r: r["camera_error_mm"]),
                      "scale_error": mean_of(lambda r: abs(r["similarity"]["scale"] - 1.0)),
                      "box_scale_half_width": mean_of(lambda r: 0.5 * np.ptp(r["box_scale_interval"])
                                                      if "box_scale_interval" in r else None),
                      "box_mid_scale_after_icp_mean_mm": mean_of(lambda r: _sub_mean(r, "box_mid_scale")),
                      "box_worst_scale_after_icp_mean_mm": mean_of(lambda r: _sub_mean(r, "box_worst_scale"))})
    return table


# --- output -----------------------------------------------------------------------------------


def machine() -> dict:
    cpu = None
    try:
        cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                    if line.startswith("model name")), None)
    except OSError:
        pass
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    return {"nproc": os.cpu_count(), "cpu_model": cpu, "platform": platform.platform(),
            "load_average_at_start": [round(v, 2) for v in load] if load else None}


def versions() -> dict:
    import cv2
    import scipy

    out = {"python": platform.python_version(), "scope3d": scope3d_version, "numpy": np.__version__,
           "scipy": scipy.__version__, "opencv": cv2.__version__}
    try:
        import pycolmap

        out["pycolmap"] = pycolmap.__version__
    except ImportError:
        out["pycolmap"] = None
    return out


def plot(rows: list[dict], scene: str, model: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sel = [r for r in rows if r["scene"] == scene and r["noise_model"] in ("exact", model) and r["status"] == "ok"]
    if not sel:
        return
    # series: (method of the rows, label, colour, marker, line style, which panels' value to take)
    series = [(m, f"scope3d {m}", c, mk, "-", None) for m, c, mk in (("bounded", "C0", "o"), ("free", "C1", "s"),
                                                                      ("fixed", "C2", "^"))]
    series += [("baseline", "COLMAP image-only + similarity", "C3", "D", "--", None),
               ("oracle", "floor: true shape placed by the centres (least squares)", "k", ".", ":", None),
               ("oracle", "true shape at the mid-scale the tolerance boxes allow", "grey", ".", ":", "box_mid_scale"),
               ("bounded", "floor on scope3d bounded's points", "C0", ".", ":", "floor_on_own_points_mm")]
    panels = [("surface error after ICP, mean (mm)", "surface", True),
              ("camera position error (mm)", "camera", True),
              ("camera error after a similarity to the truth (mm)", "shape", True),
              ("points", "points", False),
              ("time (s; COLMAP: once per scene)", "time", False),
              ("mean reprojection error (px)", "reprojection", False)]

    def value(r, what, sub):
        if sub:
            if what != "surface":
                return None
            return r.get(sub) if sub == "floor_on_own_points_mm" else _sub_mean(r, sub)
        return {"surface": _icp_mean(r), "camera": r.get("camera_error_mm"), "points": r.get("n_points"),
                "shape": r.get("camera_shape_error_mm"),
                "time": r.get("time_s"), "reprojection": r.get("mean_reprojection_error_px")}[what]

    fig, axes = plt.subplots(2, 3, figsize=(16, 8.5), dpi=100)
    failed = sorted({r["level_mm"] for r in rows if r["scene"] == scene and r["noise_model"] in ("exact", model)
                     and r["status"] != "ok" and r["method"] in MODES})
    for ax, (title, what, logy) in zip(axes.ravel(), panels):
        for method, label, c, mk, ls, sub in series:
            pts = {}
            for r in sel:
                v = value(r, what, sub) if r["method"] == method else None
                if v is not None and (v > 1e-4 or not logy):  # the floor at level 0 is (numerically) 0: no log
                    pts.setdefault(r["level_mm"], []).append(float(v))
            if pts:
                x = sorted(pts)
                ax.plot(x, [np.mean(pts[v]) for v in x], color=c, marker=mk, ls=ls, label=label)
        for v in failed:
            ax.axvline(v, color="r", alpha=0.15, lw=6)
        if what == "surface" and scene == "temple":
            ax.text(0.5, 0.5, "no true surface", transform=ax.transAxes, ha="center")
        elif logy:
            ax.set_yscale("log")
        if what == "surface" and scene != "temple":
            ax.axhline(GOAL_MM, color="grey", lw=0.8, ls="-.", label="goal 0.1 mm (up to ±1 mm)")
        ax.set_xlabel("pose noise level (mm" + (", x stand-off / 15 mm for positions)" if scene == "temple" else ")"))
        ax.set_title(title)
        ax.grid(alpha=0.3, which="both")
    handles = {}
    for ax in axes.ravel():
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=4, fontsize=8, frameon=False)
    seeds = sorted({r["seed"] for r in sel})
    fig.suptitle(f"{scene}, {model} pose noise (seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}"
                 f"{', mean over seeds' if len(seeds) > 1 else ''}; red bands: a scope3d mode failed)")
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(path)
    plt.close(fig)


def print_tables(results: dict) -> None:
    rows = results["rows"]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for model in results["options"]["models"]:
            sel = [r for r in rows if r["scene"] == scene and r["noise_model"] in ("exact", model)]
            if not sel:
                continue
            print(f"\n{scene}, {model} (level mm; surface error after ICP, mm; camera error after adjustment / as "
                  "measured / after a similarity to the truth, mm)")
            print(f"{'level':>5s} {'seed':>4s} {'method':8s} {'frames':>7s} {'points':>6s} {'ICP mean':>8s} {'median':>7s} {'floor':>6s} "
                  f"{'cam mm':>7s} {'meas mm':>7s} {'shape':>6s} {'time s':>7s}  goals")
            for r in sorted(sel, key=lambda r: (r["level_mm"], r["seed"], (*MODES, "baseline", "oracle").index(r["method"]))):
                if r["status"] != "ok":
                    print(f"{r['level_mm']:5.2f} {r['seed']:4d} {r['method']:8s} FAILED: {r['error'][:90]}")
                    continue
                s = (r.get("surface_error_mm") or {}).get("after_icp") or {}
                f = lambda v, w, p: f"{v:{w}.{p}f}" if isinstance(v, (int, float)) else f"{'-':>{w}s}"  # noqa: E731
                frames = f"{r['frames_in_model']}/{r['frames']}" if r.get("frames_in_model") is not None else "-"
                goals = " ".join(f"{k}={'ok' if v else 'NO'}" for k, v in (r.get("goals") or {}).items() if v is not None)
                print(f"{r['level_mm']:5.2f} {r['seed']:4d} {r['method']:8s} {frames:>7s} {f(r.get('n_points'), 6, 0)} "
                      f"{f(s.get('mean'), 8, 4)} {f(s.get('median'), 7, 4)} {f(r.get('floor_on_own_points_mm'), 6, 4)} "
                      f"{f(r.get('camera_error_mm'), 7, 3)} "
                      f"{f(r.get('measured_camera_error_mm'), 7, 3)} {f(r.get('camera_shape_error_mm'), 6, 3)} "
                      f"{f(r.get('time_s'), 7, 1)}  {goals}")
    print("\nscale-information limit. LS: the true shape placed by the least-squares similarity to the reported "
          "centres;\nbox: the scale interval the tolerance boxes allow (half-width), the true shape at its middle / "
          "its farther end")
    print(f"{'scene':6s} {'model':10s} {'level':>5s} {'LS ICP mm':>9s} {'LS cam mm':>9s} {'LS |s-1|':>8s} "
          f"{'box +-s':>8s} {'mid mm':>7s} {'worst mm':>8s}")

    def f(v, w, p):
        return f"{v:{w}.{p}f}" if v is not None else f"{'-':>{w}s}"

    for t in results["scale_limit"]:
        print(f"{t['scene']:6s} {t['noise_model']:10s} {t['level_mm']:5.2f} {f(t['surface_error_after_icp_mean_mm'], 9, 4)} "
              f"{f(t['camera_error_mm'], 9, 3)} {f(t['scale_error'], 8, 5)} {f(t['box_scale_half_width'], 8, 5)} "
              f"{f(t['box_mid_scale_after_icp_mean_mm'], 7, 4)} {f(t['box_worst_scale_after_icp_mean_mm'], 8, 4)}")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", help=f"comma-separated, from {','.join(SCENES)} (default all)")
    p.add_argument("--models", help=f"comma-separated, from {','.join(MODELS)} (default all)")
    p.add_argument("--modes", help=f"comma-separated scope3d pose modes (default {','.join(MODES)})")
    p.add_argument("--levels", help=f"comma-separated noise levels, mm (default {','.join(f'{v:g}' for v in LEVELS_MM)})")
    p.add_argument("--seeds", help=f"comma-separated seeds (default {','.join(map(str, DEFAULT_SEEDS))})")
    p.add_argument("--size", choices=list(SIZES), help="phantom image size: full 608 x 608, small 304 x 304 (default full)")
    p.add_argument("--quick", action="store_true",
                   help="smoke run: dome, uniform, levels 0,1,3, small images (options given explicitly win)")
    p.add_argument("--no-baseline", action="store_true", help="skip COLMAP (the oracle floor is still computed)")
    p.add_argument("--out", type=Path, default=OUT, help=f"results folder (default {OUT})")
    a = p.parse_args(argv)
    q = QUICK if a.quick else {}
    a.scenes = _list(a.scenes, str) or q.get("scenes") or SCENES
    a.models = _list(a.models, str) or q.get("models") or MODELS
    a.modes = _list(a.modes, str) or MODES
    a.levels = sorted(set(_list(a.levels, float) or q.get("levels") or LEVELS_MM))
    a.seeds = _list(a.seeds, int) or DEFAULT_SEEDS
    a.size = a.size or q.get("size") or "full"
    for name, got, allowed in (("scene", a.scenes, SCENES), ("model", a.models, MODELS), ("mode", a.modes, MODES)):
        bad = [v for v in got if v not in allowed]
        if bad:
            p.error(f"unknown {name} {bad[0]!r} (use {', '.join(allowed)})")
    if any(v < 0 for v in a.levels):
        p.error("noise levels must be >= 0 mm")
    return a


def _list(text, kind):
    return tuple(kind(v) for v in text.split(",") if v.strip()) if text else None


def main(argv=None) -> None:
    args = parse_args(argv)
    prefix = "map_pose_noise_quick" if args.quick else "map_pose_noise"
    args.out.mkdir(parents=True, exist_ok=True)
    results = {
        "benchmark": "surgical-field map vs pose noise level: scope3d bounded/free/fixed, COLMAP image-only + "
                     "similarity, and the scale-information floor",
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "machine": machine(), "versions": versions(),
        "options": {"scenes": list(args.scenes), "models": list(args.models), "modes": list(args.modes),
                    "levels_mm": list(args.levels), "seeds": list(args.seeds), "size": args.size,
                    "orientation_deg_per_mm": ORIENTATION_DEG_PER_MM, "min_observations_per_frame": MIN_OBSERVATIONS,
                    "bias_drift_fractions": {"bias": BIAS, "drift": DRIFT, "jitter": JITTER, "bias_rot": BIAS_ROT,
                                             "jitter_rot": JITTER_ROT}},
        "scenes": {}, "rows": [],
    }
    json_path = args.out / f"{prefix}.json"
    t_start = time.perf_counter()

    def save():
        results["elapsed_s"] = round(time.perf_counter() - t_start, 1)
        evaluate_goals(results["rows"])
        results["scale_limit"] = floor_table(results["rows"])
        write_json(json_path, results)

    sweep(args, results, save)
    save()
    for scene in args.scenes:
        for model in args.models:
            plot(results["rows"], scene, model, args.out / f"{prefix}_{scene}_{model}.png")
    print_tables(results)
    print(f"\nwrote {json_path} and {prefix}_<scene>_<model>.png ({results['elapsed_s']:.0f} s)")


if __name__ == "__main__":
    main()
