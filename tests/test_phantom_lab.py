"""Phantom lab API and command line: pose reports, datasets on disk, errors."""
import json

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.errors import InputError
from scope3d.io.dataset import load_dataset
from scope3d.phantoms import generate
from scope3d.sensor.pose_tolerance import MICRO_STAGE


def test_pose_noise_stays_within_the_reported_tolerance():
    seq = generate("sheet", size=(48, 48), seed=2, pose_noise_mm=0.25)
    tol_deg = 0.25 * 0.5
    moved = []
    for true, meas in zip(seq.true_poses, seq.measured_poses):
        np.testing.assert_allclose(meas.tolerance.position_mm, 0.25)
        np.testing.assert_allclose(meas.tolerance.orientation_deg, tol_deg)
        assert meas.contains(true)
        moved.append(np.abs(true.centre - meas.pose.centre).max())
    # Uniform in ±0.25 mm per axis over 30 frames: the largest error is close to the bound.
    assert 0.15 < max(moved) <= 0.25


def test_zero_pose_noise_reports_true_poses_with_stage_tolerance():
    seq = generate("sheet", size=(32, 32), n_frames=3)
    for true, meas in zip(seq.true_poses, seq.measured_poses):
        # the true pose itself, to the bit (an angle computed between two equal matrices is 0 or a few eps,
        # depending on the rounding of R^T R in the machine's BLAS: comparing it with 0.0 tested that)
        np.testing.assert_array_equal(meas.pose.matrix, true.matrix)
        np.testing.assert_array_equal(meas.tolerance.position_mm, MICRO_STAGE.position_mm)


def test_trajectories_have_the_documented_shape():
    grid = generate("sheet", size=(32, 32)).true_poses
    assert len(grid) == 30
    centres = np.array([p.centre for p in grid])
    np.testing.assert_allclose(centres[:, 2], 15.0)
    assert np.allclose(np.sort(np.unique(np.round(centres[:, 0], 9))), [-10, -5, 0, 5, 10])
    axial = generate("thread", "axial", size=(32, 32), n_frames=4).true_poses
    np.testing.assert_allclose(np.diff([p.centre[2] for p in axial]), -0.25)
    seq = generate("thread", "quadrants", size=(40, 32), n_frames=24)
    quad = seq.true_poses
    assert len(quad) == 24
    off = np.hypot(*seq.scene_info["trajectory"]["axis_offset_mm"])
    np.testing.assert_allclose([np.hypot(*p.centre[:2]) for p in quad], off)
    # Quadrant 1 is quadrant 0 turned 30° about z: optical axes 30° apart in azimuth.
    a0, a1 = quad[0].optical_axis, quad[2].optical_axis
    assert np.degrees(np.arctan2(a1[1], a1[0]) - np.arctan2(a0[1], a0[0])) == pytest.approx(30.0)
    assert np.degrees(np.arccos(-a0[2])) == pytest.approx(45.0)


def test_cli_writes_a_dataset_that_loads(tmp_path, capsys):
    out = tmp_path / "dome"
    code = main(["phantom", "dome", "--out", str(out), "--size", "64x64", "--frames", "3", "--seed", "1",
                 "--pose-noise", "0.2", "--no-progress"])
    assert code == 0
    ds = load_dataset(out, check_images=True)
    assert len(ds) == 3 and ds.fluorescence_paths is not None
    assert (out / "contact_sheet.png").is_file() and (out / "poses.csv").is_file()
    gt = ds.ground_truth
    assert len(gt.poses) == 3 and gt.surface().faces.shape[1] == 3
    assert gt.depth(0).shape == (64, 64) and gt.depth(0).dtype == np.float32
    for meas, true in zip(ds.poses, gt.poses):
        np.testing.assert_allclose(meas.tolerance.position_mm, 0.2)
        assert meas.contains(true, slack=1e-6)
    scene = json.loads((out / "ground_truth" / "scene.json").read_text())
    assert len(scene["targets"]) == 8
    assert {"id", "shape", "size", "centroid_mm", "area_mm2", "outline_mm"} <= set(scene["targets"][0])


def test_cli_list(capsys):
    assert main(["phantom", "--list"]) == 0
    text = capsys.readouterr().out
    for word in ("dome", "sheet", "bladder", "thread", "grid5x6", "grid7x8", "axial", "quadrants", "spiral", "M6x1"):
        assert word in text


def test_cli_bad_thread_size_is_a_one_line_error(tmp_path, capsys):
    code = main(["phantom", "thread", "--out", str(tmp_path / "t"), "--thread", "M7x1"])
    err = capsys.readouterr().err
    assert code != 0
    assert err.count("\n") == 1 and "M7x1" in err and "Traceback" not in err
    assert not (tmp_path / "t").exists()


def test_bad_combinations_are_input_errors():
    with pytest.raises(InputError, match="does not fit"):
        generate("dome", "axial", size=(32, 32))
    with pytest.raises(InputError, match="unknown trajectory"):
        generate("dome", "zigzag")
    with pytest.raises(InputError, match="pose noise"):
        generate("sheet", size=(32, 32), n_frames=1, pose_noise_mm=-1.0)


def test_axial_axis_offset_and_tilt_are_applied_and_recorded(tmp_path):
    seq = generate("thread", "axial", n_frames=2, size=(48, 48), axis_offset_mm=0.3, axis_tilt_deg=2.0)
    centres = np.array([p.centre for p in seq.true_poses])
    np.testing.assert_allclose(centres[:, 0], 0.3)
    np.testing.assert_allclose(centres[1] - centres[0], [0.3 - 0.3, 0.0, -0.25], atol=1e-12)  # motion along -z
    for pose in seq.true_poses:
        angle = np.degrees(np.arccos(np.dot(pose.optical_axis, [0.0, 0.0, -1.0])))
        assert abs(angle - 2.0) < 1e-9
    assert seq.scene_info["trajectory"]["axis_offset_mm"] == 0.3
    assert seq.scene_info["trajectory"]["axis_tilt_deg"] == 2.0
    assert seq.scene_info["render"]["supersample"] == 2
    with pytest.raises(InputError, match="axial"):
        generate("dome", n_frames=1, size=(32, 32), axis_offset_mm=0.1)
    with pytest.raises(InputError, match="tilt"):
        generate("thread", "axial", n_frames=1, size=(32, 32), axis_tilt_deg=30.0)
    out = tmp_path / "mis"
    assert main(["phantom", "thread", "--out", str(out), "--frames", "2", "--size", "48x48", "--no-progress",
                 "--axis-offset", "0.1", "--axis-tilt", "1.5"]) == 0
    scene = json.loads((out / "ground_truth" / "scene.json").read_text())
    assert scene["trajectory"]["axis_offset_mm"] == 0.1 and scene["trajectory"]["axis_tilt_deg"] == 1.5
