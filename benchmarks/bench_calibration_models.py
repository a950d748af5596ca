"""Calibration of every camera model (issue 32): real capsule boards against OpenCV, and sigma honesty on
rendered boards.

Real: the EndoSLAM PillCam capsule images (../shared/data/endoslam_pillcam_cam1/, 8x6 inner corners,
2 mm squares assumed: pixels do not depend on it). Corners from cv2.findChessboardCornersSB with
CALIB_CB_EXHAUSTIVE | CALIB_CB_ACCURACY ("sb", scope3d's default detector) and the same followed by
cornerSubPix ("sb_subpix", ``--refine``). For each model, scope3d's calibration (outlier views dropped)
beside OpenCV on the *same corners of the same views*: cv2.calibrateCamera with the model's flags (radial:
ZERO_TANGENT_DIST | FIX_K3; opencv: FIX_K3; full-opencv: RATIONAL_MODEL), plain cv2.calibrateCamera
(default flags: k1, k2, p1, p2, k3) and cv2.fisheye.calibrate; ratios are scope3d / OpenCV.

Rendered: boards drawn through a camera of each model (phantoms.boards renders through Camera.unproject),
10 views, 320x240, blur 0.6 px, noise 2 grey levels, SEEDS seeds; the fraction of the intrinsics' errors
within the reported 1 sigma (68.3 % for an honest sigma) pooled over the parameters, with scope3d's
default detector ("sb"), with cornerSubPix ("sb_subpix"), and with exact corners plus Gaussian noise of
0.1 px ("exact_plus_noise": the covariance's own assumption), to separate the covariance's honesty from
the detector's bias.

Writes benchmarks/results/calibration_models.json. Run (about 5 minutes on one core):
    PYTHONPATH=src .venv/bin/python benchmarks/bench_calibration_models.py
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np

from scope3d.errors import InputError
from scope3d.io.images import read_image
from scope3d.phantoms.boards import random_board_poses, render_board_views
from scope3d.sensor.calibration import (
    CAMERA_MODEL_OF,
    BoardDetection,
    BoardSpec,
    CalibrationOptions,
    DetectionOptions,
    calibrate,
    detect_board,
)
from scope3d.sensor.camera import Camera

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
REAL = ROOT.parent / "shared" / "data" / "endoslam_pillcam_cam1"
MODELS = ("radial", "opencv", "full-opencv", "fisheye")
OPENCV_FLAGS = {"radial": cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3, "opencv": cv2.CALIB_FIX_K3,
                "full-opencv": cv2.CALIB_RATIONAL_MODEL}
SEEDS = int(sys.argv[1]) if len(sys.argv) > 1 else 20
# Rendered lenses, 320x240: a 70 deg scope with barrel distortion (the reference's), the same with a
# decentred element (tangential terms), a rational lens, and a ~165 deg capsule-like fisheye.
TRUE_CAMERAS = {
    "radial": Camera.from_fov(320, 240, 70.0, k1=-0.25, k2=0.08),
    "opencv": Camera.from_params(320, 240, "OPENCV", [228.5, 228.5, 159.5, 119.5, -0.25, 0.08, 0.002, -0.0015]),
    "full-opencv": Camera.from_params(320, 240, "FULL_OPENCV", [228.5, 228.5, 159.5, 119.5, -0.2, 0.05, 0.001,
                                                                 -0.001, 0.01, 0.1, 0.02, 0.003]),
    "fisheye": Camera.from_params(320, 240, "OPENCV_FISHEYE", [110.0, 110.0, 159.5, 119.5, 0.02, -0.01, 0.001, 0.0]),
}


def opencv_rms(detections, names, board, size, kind: str) -> float:
    """OpenCV's own RMS on the same corners of the views ``names``: kind is a model of OPENCV_FLAGS,
    "plain" (calibrateCamera's default flags) or "fisheye"."""
    used = [d for d in detections if d.name in names]
    obj = [board.object_points()[d.corner_ids].astype(np.float64) for d in used]
    img = [d.pixels.astype(np.float64) for d in used]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    if kind == "fisheye":
        rms, *_ = cv2.fisheye.calibrate([o.reshape(1, -1, 3) for o in obj], [i.reshape(1, -1, 2) for i in img],
                                        size, None, None, flags=cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW,
                                        criteria=criteria)
    else:
        flags = 0 if kind == "plain" else OPENCV_FLAGS[kind]
        rms, *_ = cv2.calibrateCamera([o.astype(np.float32) for o in obj], [i.astype(np.float32) for i in img],
                                      size, None, None, flags=flags, criteria=criteria)
    return float(rms)


def real_boards() -> dict:
    paths = sorted(p for p in REAL.iterdir() if p.suffix in (".bmp", ".png"))
    board = BoardSpec(8, 6, 2.0)
    images = [read_image(p, grey=True) for p in paths]
    size = (images[0].shape[1], images[0].shape[0])
    out: dict = {"images": [p.name for p in paths], "board": "8x6"}
    for label, refine in (("sb", False), ("sb_subpix", True)):
        dets = [detect_board(im, board, name=p.name, options=DetectionOptions(refine_corners=refine))
                for p, im in zip(paths, images)]
        found = [d.name for d in dets if d.found]
        rows = {"found": found}
        for model in MODELS:
            cal = calibrate(dets, board, size, options=CalibrationOptions(model=model))
            row = {"camera_model": cal.model, "rms_px": cal.rms_px, "views_used": cal.views,
                   "rejected": cal.rejected, "values": dict(zip(cal.names, cal.values.tolist())),
                   "std": dict(zip(cal.names, cal.std.tolist()))}
            # OpenCV on the views scope3d kept, and on every view with a board
            for views_label, names in (("same_views", cal.views), ("all_found", found)):
                ref = {"model_flags": opencv_rms(dets, names, board, size, "fisheye" if model == "fisheye" else model),
                       "plain_calibrateCamera": opencv_rms(dets, names, board, size, "plain"),
                       "fisheye_calibrate": opencv_rms(dets, names, board, size, "fisheye")}
                row[f"opencv_{views_label}_rms_px"] = ref
                row[f"ratio_to_opencv_{views_label}"] = {k: cal.rms_px / v for k, v in ref.items()}
            rows[model] = row
            print(f"real {label} {model}: rms {cal.rms_px:.4f} px over {len(cal.views)} views; OpenCV same views "
                  f"{row['opencv_same_views_rms_px']}", flush=True)
        out[label] = rows
    return out


def honesty(model: str, seeds: int) -> dict:
    truth = TRUE_CAMERAS[model]
    board = BoardSpec(9, 6, 2.0)
    size = (truth.width, truth.height)
    options = CalibrationOptions(model=model)
    inside = {"sb": [], "sb_subpix": [], "exact_plus_noise": []}
    rms = {k: [] for k in inside}
    found = []
    for seed in range(seeds):
        views = render_board_views(truth, board, n_views=10, seed=500 + seed)
        rng = np.random.default_rng(seed)
        sets = {"exact_plus_noise": [BoardDetection(f"v{i}", px + 0.1 * rng.standard_normal(px.shape),
                                                    np.arange(len(px))) for i, px in enumerate(views.corners_px)]}
        for label, refine in (("sb", False), ("sb_subpix", True)):
            sets[label] = [detect_board(im, board, name=f"v{i}", options=DetectionOptions(refine_corners=refine))
                           for i, im in enumerate(views.images)]
        found.append(sum(d.found for d in sets["sb"]))
        for label, dets in sets.items():
            try:
                cal = calibrate(dets, board, size, options=options)
            except InputError as exc:  # too few views found in this seed's images
                print(f"  seed {seed} {label}: {exc}", flush=True)
                continue
            inside[label].append(np.abs(cal.values - truth.params) <= cal.std)
            rms[label].append(cal.rms_px)
    spread = float(np.sqrt(0.683 * 0.317 / seeds))
    out = {"camera_model": truth.model, "true_params": truth.params.tolist(), "seeds": seeds,
           "fov_deg": truth.fov_deg, "views_found_mean_of_10": float(np.mean(found)),
           "binomial_spread_per_param": spread}
    for label, rows in inside.items():
        rows = np.array(rows)
        out[label] = {"calibrations": len(rows), "rms_px_mean": float(np.mean(rms[label])),
                      "within_1_sigma": float(rows.mean()),
                      "within_1_sigma_per_param": dict(zip(truth.param_names, rows.mean(0).tolist()))}
    print(f"honesty {model}: " + ", ".join(f"{k} {out[k]['within_1_sigma']:.3f}" for k in inside)
          + f" (binomial spread {spread:.3f})", flush=True)
    return out


def main() -> None:
    result = {"real": real_boards(),
              "honesty": {m: honesty(m, SEEDS) for m in MODELS},
              "camera_model_of": CAMERA_MODEL_OF}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "calibration_models.json").write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {OUT / 'calibration_models.json'}")


if __name__ == "__main__":
    main()
