"""`scope3d map` through a fisheye lens against ground truth (issue 32): the phantom lab's fisheye-140 dome,
its OPENCV_FISHEYE camera.json taken as it is (no resampling), mapped to the two-view precision of that
lens."""
from __future__ import annotations

import json

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.io.camera_json import read_camera_json

SIZE = "400x400"
SIFT_SIGMA_PX = 0.5  # as tests/test_map.py


@pytest.fixture(scope="module")
def fisheye_map(tmp_path_factory):
    root = tmp_path_factory.mktemp("fisheye")
    assert main(["phantom", "dome", "--lens", "fisheye-140", "--size", SIZE, "--frames", "12",
                 "--out", str(root / "data"), "--no-progress"]) == 0
    assert main(["map", str(root / "data"), "--out", str(root / "map"), "--no-progress"]) == 0
    return read_camera_json(root / "data" / "camera.json"), json.loads((root / "map" / "report.json").read_text())


def test_the_map_keeps_the_lens_model(fisheye_map):
    camera, report = fisheye_map
    assert camera.model == "OPENCV_FISHEYE"
    assert list(report["camera_adjusted"]["intrinsics"]) == list(camera.param_names)
    # the observations fit the fisheye's projection (a pinhole's reading of them would miss by pixels)
    assert report["median_reprojection_error_px"] < 2 * SIFT_SIGMA_PX


def test_fisheye_dome_surface_error_follows_two_view_precision(fisheye_map):
    camera, report = fisheye_map
    # depth error of two views 5 mm apart at the farthest 25 mm, with the lens's focal length (its angular
    # resolution near the axis, where the dome is seen: d theta_d / d theta = 1 + 3 k1 theta^2 + ... >= 1)
    sigma_z = 25.0**2 * SIFT_SIGMA_PX / (camera.fx * 5.0)
    direct = report["surface_error_mm"]["direct"]
    assert direct["median"] < sigma_z and direct["mean"] < sigma_z
    assert direct["within_1mm_fraction"] > 0.99
    after = report["surface_error_mm"]["after_icp"]
    assert abs(after["mean"] - direct["mean"]) < 0.05  # exact poses: ICP has nothing to correct
    assert np.isfinite(after["mean"])
