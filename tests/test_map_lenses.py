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
    return (read_camera_json(root / "data" / "camera.json"), json.loads((root / "map" / "report.json").read_text()),
            root / "data")


def test_the_map_keeps_the_lens_model(fisheye_map):
    camera, report, _ = fisheye_map
    assert camera.model == "OPENCV_FISHEYE"
    assert list(report["camera_adjusted"]["intrinsics"]) == list(camera.param_names)
    # the observations fit the fisheye's projection (a pinhole's reading of them would miss by pixels)
    assert report["median_reprojection_error_px"] < 2 * SIFT_SIGMA_PX


def test_fisheye_dome_surface_error_follows_two_view_precision(fisheye_map):
    camera, report, _ = fisheye_map
    # depth error of two views 5 mm apart at the farthest 25 mm, with the lens's focal length (its angular
    # resolution near the axis, where the dome is seen: d theta_d / d theta = 1 + 3 k1 theta^2 + ... >= 1)
    sigma_z = 25.0**2 * SIFT_SIGMA_PX / (camera.fx * 5.0)
    direct = report["surface_error_mm"]["direct"]
    assert direct["median"] < sigma_z and direct["mean"] < sigma_z
    assert direct["within_1mm_fraction"] > 0.99
    after = report["surface_error_mm"]["after_icp"]
    assert abs(after["mean"] - direct["mean"]) < 0.05  # exact poses: ICP has nothing to correct
    assert np.isfinite(after["mean"])


def test_pose_refinement_through_any_model_sums_as_the_radial_kernel():
    """The NumPy path of the pose refinement (any lens) and the compiled radial loop agree on the radial lens
    read as OPENCV with p1 = p2 = 0: cost, Gauss-Newton matrix, gradient and residuals to rounding."""
    from scope3d.estimators import absolute_pose
    from scope3d.geometry.rotation import SMALL_ANGLE_RAD, rotvec_to_matrix
    from scope3d.sensor.camera import Camera

    rng = np.random.default_rng(0)
    radial = Camera(320, 240, 300.0, 302.0, 160.0, 120.0, -0.2, 0.05)
    opencv = Camera.from_params(320, 240, "OPENCV", [300.0, 302.0, 160.0, 120.0, -0.2, 0.05, 0.0, 0.0])
    points = np.c_[rng.uniform(-3, 3, (50, 2)), rng.uniform(8, 12, 50)]
    pixels = radial.project(points) + rng.normal(0, 1.0, (50, 2))  # some beyond the Huber scale
    x = np.array([0.01, -0.02, 0.03, 0.1, -0.1, 0.2])
    ref = rotvec_to_matrix(np.array([0.1, 0.2, -0.1]))
    kernel = absolute_pose._kernels.huber_normal_equations(points, pixels, x, ref, radial.intrinsics, 1.5,
                                                           SMALL_ANGLE_RAD)
    numpy = absolute_pose._lens_normal_equations(opencv, points, pixels, x, ref, 1.5)
    for a, b in zip(kernel, numpy):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * np.max(np.abs(a)))


def test_localization_through_the_fisheye_against_the_truth(tmp_path):
    """A survey map and an approach (poses 2 mm off), both through fisheye-140: the frames are localized
    against the map to the precision tests/test_localization.py asks of the pinhole at this size, scaled by
    the focal lengths (a pixel's angle is 1 / f)."""
    from scope3d import phantoms
    from scope3d.io.dataset import load_dataset
    from scope3d.pipelines.surgical_map import MapOptions
    from scope3d.pipelines.surgical_map import run as run_map

    size = (240, 240)
    survey = phantoms.write(phantoms.generate("dome", "grid5x6", size=size, seed=0, lens="fisheye-140"),
                            tmp_path / "survey")
    run_map(MapOptions(pose_mode="fixed", surface=None, fluorescence=None, figures=False), load_dataset(survey),
            tmp_path / "map")
    approach = phantoms.write(phantoms.generate("dome", "approach", target=4, size=size, seed=1, n_frames=8,
                                                pose_noise_mm=2.0, lens="fisheye-140"), tmp_path / "approach")
    assert main(["localize", str(tmp_path / "map"), str(approach), "--out", str(tmp_path / "loc"),
                 "--no-progress"]) == 0
    report = json.loads((tmp_path / "loc" / "report.json").read_text())
    fisheye = read_camera_json(approach / "camera.json")
    pinhole = phantoms.default_camera(phantoms.build_scene("dome"), "approach", size=size)
    scale = pinhole.fx / fisheye.fx
    assert report["n_localized"] >= 5
    assert report["median_position_error_mm"] < 0.3 * scale and report["median_orientation_error_deg"] < 1.0 * scale
    done = [f for f in report["frames"] if f["status"] == "ok"]
    assert max(f["position_error_mm"] for f in done) < 1.0 * scale


def test_map_refuses_bounds_of_another_model_in_one_line(fisheye_map, tmp_path, capsys):
    from scope3d.io.intrinsic_bounds import write_intrinsic_bounds

    data = fisheye_map[2]
    write_intrinsic_bounds(tmp_path / "radial.json", np.array([115.0, 115.0, 199.5, 199.5, 0.0, 0.0]),
                           np.full(6, 0.1), 3.0)
    assert main(["map", str(data), "--out", str(tmp_path / "m"), "--intrinsic-bounds", str(tmp_path / "radial.json"),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bounds of a 'pinhole_radial_k1k2' camera, for a OPENCV_FISHEYE camera" in err[0]
    assert not (tmp_path / "m").exists()


def test_map_refines_the_fisheyes_later_parameters_inside_their_bounds(fisheye_map, tmp_path):
    """`--intrinsic-bounds` with `--refine-later-intrinsics`: k3, k4 refined too, and every parameter of the
    model ends inside its box (a calibration's +-3 sigma of the sizes the lab's boards give); without the flag
    k3, k4 stay at camera.json's values. The flag alone is refused in one line."""
    from scope3d.io.intrinsic_bounds import write_intrinsic_bounds

    camera, _, data = fisheye_map
    std = np.array([0.15, 0.15, 0.1, 0.1, 1e-3, 2e-3, 2e-3, 8e-4])
    write_intrinsic_bounds(tmp_path / "b.json", camera.params, std, 3.0, model=camera.model,
                           names=camera.param_names)
    box = json.loads((tmp_path / "b.json").read_text())
    adjusted = {}
    for label, flag in (("held", []), ("freed", ["--refine-later-intrinsics"])):
        assert main(["map", str(data), "--out", str(tmp_path / label), "--intrinsic-bounds", str(tmp_path / "b.json"),
                     "--no-figures", "--no-progress", *flag]) == 0
        adjusted[label] = json.loads((tmp_path / label / "report.json").read_text())["camera_adjusted"]["intrinsics"]
        for name, value in adjusted[label].items():
            assert box[name]["lower"] <= value <= box[name]["upper"], (label, name)
    assert [adjusted["held"][n] for n in ("k3", "k4")] == list(camera.params[6:])
    assert [adjusted["freed"][n] for n in ("k3", "k4")] != list(camera.params[6:])
    assert main(["map", str(data), "--out", str(tmp_path / "x"), "--refine-later-intrinsics", "--no-progress"]) == 2
