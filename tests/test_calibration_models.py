"""calibrate with every camera model (issue 32): the real capsule boards against OpenCV on the same
corners, the covariance against OpenCV's, and `scope3d calibrate --model fisheye` end to end."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.errors import InputError
from scope3d.io.camera_json import read_camera_json
from scope3d.io.images import read_image, write_image
from scope3d.io.intrinsic_bounds import read_intrinsic_bounds
from scope3d.phantoms.boards import random_board_poses, render_board_views
from scope3d.sensor.calibration import (
    BoardDetection,
    BoardSpec,
    CalibrationOptions,
    DetectionOptions,
    calibrate,
    detect_board,
)
from scope3d.sensor.camera import Camera

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "endoslam_pillcam_cam1"
REAL_BOARD = BoardSpec(8, 6, 2.0)  # 2 mm assumed (SOURCE.txt): pixels do not depend on it
# OpenCV's stopping rule (relative change 1e-12, 200 iterations) leaves the RMS converged far below this
CONVERGED = 1e-6
FISHEYE = Camera.from_params(320, 240, "OPENCV_FISHEYE", [110.0, 110.0, 159.5, 119.5, 0.02, -0.01, 0.001, 0.0])


@pytest.fixture(scope="module")
def real():
    paths = sorted(p for p in REAL.glob("*") if p.suffix in (".bmp", ".png"))
    if not paths:
        pytest.fail(f"real data missing: {REAL} (see /work/shared/data/README.md)")
    images = [read_image(p, grey=True) for p in paths]
    # the capsule's tiny squares: the sector detector's own corners (--no-refine, docs/calibration.md)
    own = DetectionOptions(refine_corners=False)
    return paths, images, [detect_board(im, REAL_BOARD, name=p.name, options=own) for p, im in zip(paths, images)]


def test_real_corners_are_the_sector_detectors_own(real):
    """The detector is cv2.findChessboardCornersSB with its sub-pixel accuracy flags, its corners unchanged
    without cornerSubPix."""
    _, images, detections = real
    assert sum(d.found for d in detections) >= 6
    for image, det in zip(images, detections):
        ok, corners = cv2.findChessboardCornersSB(image, (8, 6), flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        assert ok == det.found
        if ok:
            np.testing.assert_array_equal(det.pixels, corners.reshape(-1, 2).astype(np.float64))


def _opencv_rms(detections, names, size, model):
    used = [d for d in detections if d.name in names]
    obj = [REAL_BOARD.object_points()[d.corner_ids] for d in used]
    img = [d.pixels for d in used]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    if model == "fisheye":
        return cv2.fisheye.calibrate([o.reshape(1, -1, 3) for o in obj], [i.reshape(1, -1, 2) for i in img], size,
                                     None, None, flags=cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW,
                                     criteria=criteria)[0]
    flags = {"radial": cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3, "opencv": cv2.CALIB_FIX_K3,
             "full-opencv": cv2.CALIB_RATIONAL_MODEL, "plain": 0}[model]
    return cv2.calibrateCamera([o.astype(np.float32) for o in obj], [i.astype(np.float32) for i in img], size,
                               None, None, flags=flags, criteria=criteria)[0]


def test_every_model_fits_the_real_capsule_boards_as_well_as_opencv(real):
    _, images, detections = real
    size = (images[0].shape[1], images[0].shape[0])
    rms = {}
    for model in ("radial", "opencv", "full-opencv", "fisheye"):
        cal = calibrate(detections, REAL_BOARD, size, options=CalibrationOptions(model=model))
        assert cal.camera().model == cal.model and len(cal.std) == len(cal.values)
        assert np.all(np.isfinite(cal.std)) and np.all(cal.std > 0)
        assert cal.rms_px <= _opencv_rms(detections, cal.views, size, model) * (1 + CONVERGED)
        rms[model] = cal.rms_px
    # nested models on the same corners: more parameters never fit worse
    assert rms["full-opencv"] <= rms["opencv"] * (1 + CONVERGED) <= rms["radial"] * (1 + CONVERGED) ** 2
    # a lens this wide: the fisheye and the rational model beat the radial one by far
    assert rms["fisheye"] < 0.6 * rms["radial"] and rms["full-opencv"] < 0.6 * rms["radial"]


@pytest.mark.parametrize("model, camera", [
    ("opencv", Camera.from_params(320, 240, "OPENCV", [228.5, 228.5, 159.5, 119.5, -0.25, 0.08, 0.002, -0.0015])),
    ("full-opencv", Camera.from_params(320, 240, "FULL_OPENCV", [228.5, 228.5, 159.5, 119.5, -0.2, 0.05, 0.001,
                                                                  -0.001, 0.01, 0.1, 0.02, 0.003])),
])
def test_covariance_from_scope3d_jacobians_matches_opencvs(model, camera):
    """Our Gauss-Newton covariance (analytic Jacobians of the model) against OpenCV's stdDeviationsIntrinsics,
    computed independently from its own Jacobians: the same quantity, so equal to rounding (1 %)."""
    board = BoardSpec(9, 6, 2.0)
    poses = random_board_poses(camera, board, 12, seed=7)
    rng = np.random.default_rng(0)
    dets = [BoardDetection(f"v{i}", camera.project(p.transform(board.object_points())) + 0.1 * rng.standard_normal(
        (board.num_corners, 2)), np.arange(board.num_corners)) for i, p in enumerate(poses)]
    cal = calibrate(dets, board, (camera.width, camera.height), options=CalibrationOptions(model=model))
    np.testing.assert_allclose(cal.std, cal.opencv_std, rtol=0.01)


def test_cli_calibrate_fisheye_writes_a_fisheye_camera_and_its_bounds(tmp_path):
    views = render_board_views(FISHEYE, BoardSpec(9, 6, 2.0), n_views=10, seed=21)
    paths = []
    for i, im in enumerate(views.images):
        paths.append(tmp_path / f"board{i}.png")
        write_image(paths[-1], im)
    out = tmp_path / "cal"
    assert main(["calibrate", *map(str, paths), "--board", "9x6", "--square", "2", "--out", str(out),
                 "--model", "fisheye"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["model"] == "OPENCV_FISHEYE"
    camera = read_camera_json(out / "camera.json")
    assert camera.model == "OPENCV_FISHEYE" and camera.fov_deg > 150
    bounds = json.loads((out / "intrinsic_bounds.json").read_text())
    assert bounds["model"] == "OPENCV_FISHEYE"
    std = np.array([report["intrinsics"][n]["std"] for n in camera.param_names])
    for name, s in zip(camera.param_names, std):
        assert bounds[name]["upper"] - bounds[name]["lower"] == pytest.approx(6 * s)
    # focal length and principal point recovered to a fraction of a pixel (sigma ~0.1 px, corner bias of
    # the detector on rendered boards ~0.1 px)
    np.testing.assert_allclose(camera.params[:4], FISHEYE.params[:4], atol=0.5)
    # a fisheye dataset's map reads the bounds of the parameters it refines (fx .. k2, the fisheye's own k1,
    # k2); a radial dataset's refuses them rather than read a fisheye's k1, k2 as radial ones
    lower, upper = read_intrinsic_bounds(out / "intrinsic_bounds.json", "OPENCV_FISHEYE")
    np.testing.assert_array_equal(lower, [bounds[n]["lower"] for n in ("fx", "fy", "cx", "cy", "k1", "k2")])
    np.testing.assert_array_equal(upper, [bounds[n]["upper"] for n in ("fx", "fy", "cx", "cy", "k1", "k2")])
    with pytest.raises(InputError, match="bounds of a 'OPENCV_FISHEYE' camera, for a pinhole_radial_k1k2 camera"):
        read_intrinsic_bounds(out / "intrinsic_bounds.json")


def test_fisheye_calibration_where_cv2_fisheye_fails_outright():
    """On these exact corners (+0.1 px noise) of a 165 deg lens cv2.fisheye.calibrate stops on an assertion
    in its per-view initialisation; scope3d starts from the radial fit and the poses from the rays."""
    board = BoardSpec(9, 6, 2.0)
    poses = random_board_poses(FISHEYE, board, 10, seed=512)
    rng = np.random.default_rng(12)
    dets = [BoardDetection(f"v{i}", FISHEYE.project(p.transform(board.object_points()))
                           + 0.1 * rng.standard_normal((board.num_corners, 2)), np.arange(board.num_corners))
            for i, p in enumerate(poses)]
    with pytest.raises(cv2.error, match="InitExtrinsics"):
        cv2.fisheye.calibrate([board.object_points().reshape(1, -1, 3)] * len(dets),
                              [d.pixels.reshape(1, -1, 2) for d in dets], (320, 240), None, None,
                              flags=cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW)
    cal = calibrate(dets, board, (320, 240), options=CalibrationOptions(model="fisheye"))
    assert len(cal.views) == 10
    # the corner noise sets the RMS: 0.1 px per coordinate is 0.14 px per corner
    assert cal.rms_px < 0.15
    # every parameter within 4 of its sigmas (a 1-in-16000 event per parameter for an honest sigma)
    assert np.all(np.abs(cal.values - FISHEYE.params) < 4 * cal.std), (cal.values - FISHEYE.params) / cal.std
