"""Dataset folders: round trip, validation errors (each naming file and row), atomic writes, CLI check."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at, rotation_angle_between
from scope3d.io.dataset import load_dataset, write_dataset
from scope3d.io.images import read_image
from scope3d.scene.mesh import Mesh
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance

REPO = Path(__file__).resolve().parents[1]
W, H = 32, 24


def _scene(n=3, seed=0):
    """n cameras on an arc 50 mm from the origin, looking at it; random small frames."""
    rng = np.random.default_rng(seed)
    camera = Camera(W, H, 30.0, 31.0, 15.5, 11.5, k1=-0.1, k2=0.01, mask_radius_px=12.0)
    poses = []
    for i in range(n):
        centre = np.array([50.0 * np.sin(0.3 * i), 5.0, -50.0 * np.cos(0.3 * i)])
        poses.append(Pose.from_centre(look_at(centre, np.zeros(3)), centre))
    tol = PoseTolerance.from_degrees([0.25, 0.25, 0.5], [0.1, 0.1, 0.2])
    measured = [MeasuredPose(p, tol) for p in poses]
    frames = [rng.integers(0, 255, (H, W, 3), dtype=np.uint8) for _ in range(n)]
    return camera, frames, measured, poses


@pytest.fixture
def good(tmp_path):
    camera, frames, measured, _ = _scene()
    return write_dataset(tmp_path / "ds", camera, frames, measured)


def _rewrite_poses(root: Path, edit) -> None:
    lines = (root / "poses.csv").read_text().splitlines()
    rows = [line.split(",") for line in lines]
    edit(rows)
    (root / "poses.csv").write_text("\n".join(",".join(r) for r in rows) + "\n")


def _col(name):
    from scope3d.io.poses_csv import POSE_COLUMNS

    return POSE_COLUMNS.index(name)


# --- round trip ---------------------------------------------------------------------------------


def test_write_then_load_round_trips_everything(tmp_path):
    camera, frames, measured, poses = _scene()
    fluo = [f[..., 1].copy() for f in frames]
    depths = [np.full((H, W), 50.0, np.float32) for _ in frames]
    surface = Mesh(np.eye(3), [[0, 1, 2]])
    root = write_dataset(tmp_path / "ds", camera, frames, measured, fluorescence=fluo, true_poses=poses,
                         true_surface=surface, true_depths=depths, scene={"name": "tube", "radius_mm": 5.0})
    ds = load_dataset(root, check_images=True)
    assert len(ds) == 3 and ds.names == ["0000.png", "0001.png", "0002.png"]
    assert ds.camera == camera
    for got, want in zip(ds.poses, measured):
        np.testing.assert_allclose(got.pose.rotation, want.pose.rotation, atol=1e-11)
        np.testing.assert_allclose(got.pose.translation, want.pose.translation, atol=1e-9)
        np.testing.assert_allclose(got.tolerance.position_mm, want.tolerance.position_mm)
        np.testing.assert_allclose(got.tolerance.orientation_rad, want.tolerance.orientation_rad, rtol=1e-8)
    np.testing.assert_array_equal(ds.frame(1), frames[1])  # PNG is lossless
    np.testing.assert_array_equal(ds.fluorescence_frame(2), fluo[2])
    np.testing.assert_array_equal(ds.ground_truth.depth(0), depths[0])
    np.testing.assert_array_equal(ds.ground_truth.surface().faces, [[0, 1, 2]])
    assert ds.ground_truth.scene["radius_mm"] == 5.0
    text = ds.summary()
    assert "3 images of 32x24 px" in text and "fluorescence  yes" in text and "surface mesh" in text
    assert "position +-0.25..0.5 mm" in text


def test_length_unit_is_converted_to_mm(good):
    meta = json.loads((good / "dataset.json").read_text())
    meta["length_unit"] = "cm"
    (good / "dataset.json").write_text(json.dumps(meta))
    in_mm = load_dataset(good)  # the same numbers, now read as cm
    meta["length_unit"] = "mm"
    (good / "dataset.json").write_text(json.dumps(meta))
    ref = load_dataset(good)
    np.testing.assert_allclose(in_mm.poses[1].pose.centre, 10.0 * ref.poses[1].pose.centre)
    np.testing.assert_allclose(in_mm.poses[1].tolerance.position_mm, 10.0 * ref.poses[1].tolerance.position_mm)


def test_unknown_tolerance_inf_is_accepted(good):
    _rewrite_poses(good, lambda rows: rows[2].__setitem__(_col("tol_x_mm"), "inf"))
    assert np.isinf(load_dataset(good).poses[1].tolerance.position_mm[0])


# --- each bad input: one InputError naming the file (and the row) -----------------------------------


def _expect(root, *fragments, check_images=False):
    with pytest.raises(InputError) as info:
        load_dataset(root, check_images=check_images)
    message = str(info.value)
    assert "\n" not in message
    for f in fragments:
        assert f in message, message
    return message


def test_missing_image(good):
    (good / "frames" / "0001.png").unlink()
    _expect(good, "poses.csv row 3", "frames/0001.png", "missing")


def test_corrupt_image_found_when_checking_images(good):
    data = (good / "frames" / "0002.png").read_bytes()
    (good / "frames" / "0002.png").write_bytes(data[: len(data) // 2])
    load_dataset(good)  # without decoding, a truncated file is not noticed
    _expect(good, "0002.png", "not a readable image", check_images=True)


def test_image_of_wrong_size(tmp_path):
    camera, frames, measured, _ = _scene()
    frames[1] = np.zeros((H + 2, W, 3), np.uint8)
    root = write_dataset(tmp_path / "ds", camera, frames, measured)
    _expect(root, "0001.png", "32x26", "camera.json says 32x24", check_images=True)


def test_missing_pose_row(good):
    _rewrite_poses(good, lambda rows: rows.pop(2))
    _expect(good, "poses.csv", "2 pose rows but 3 frames", "frames/0001.png")


def test_duplicate_image_name(good):
    _rewrite_poses(good, lambda rows: rows[3].__setitem__(0, "0000.png"))
    _expect(good, "poses.csv row 4", "listed twice", "row 2")


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_nan_and_infinite_pose_values(good, value):
    _rewrite_poses(good, lambda rows: rows[2].__setitem__(_col("y_mm"), value))
    _expect(good, "poses.csv row 3", "y_mm", "NaN or infinite")


def test_nan_tolerance(good):
    _rewrite_poses(good, lambda rows: rows[1].__setitem__(_col("tol_ry_deg"), "nan"))
    _expect(good, "poses.csv row 2", "tol_ry_deg")


def test_not_a_number(good):
    _rewrite_poses(good, lambda rows: rows[3].__setitem__(_col("qz"), "0.1o"))
    _expect(good, "poses.csv row 4", "qz", "not a number")


def test_negative_tolerance(good):
    _rewrite_poses(good, lambda rows: rows[2].__setitem__(_col("tol_z_mm"), "-0.5"))
    _expect(good, "poses.csv row 3", "tol_z_mm", "negative")


def test_non_unit_quaternion(good):
    _rewrite_poses(good, lambda rows: rows[1].__setitem__(_col("qw"), str(float(rows[1][_col("qw")]) + 0.1)))
    _expect(good, "poses.csv row 2", "quaternion", "not unit")


def test_zero_quaternion(good):
    _rewrite_poses(good, lambda rows: rows[2].__setitem__(slice(_col("qw"), _col("qz") + 1), ["0"] * 4))
    _expect(good, "poses.csv row 3", "quaternion", "not unit length (norm 0")


def test_quaternion_printed_with_4_digits_is_normalised(good):
    """A quaternion printed to 4 significant digits is q + e with |e| <= sqrt(4) 0.5e-4 = 1e-4: accepted,
    normalised, and its rotation within 2 asin(|e| / (1 - |e|)) of the exact one."""
    exact = load_dataset(good).poses

    def round_quaternions(rows):
        for row in rows[1:]:
            row[_col("qw"):_col("qz") + 1] = [f"{float(v):.4g}" for v in row[_col("qw"):_col("qz") + 1]]

    _rewrite_poses(good, round_quaternions)
    e = 1e-4
    for got, want in zip(load_dataset(good).poses, exact, strict=True):
        assert rotation_angle_between(got.pose.rotation, want.pose.rotation) <= 2 * np.arcsin(e / (1 - e))
        np.testing.assert_allclose(got.pose.centre, want.pose.centre, atol=1e-9)


def test_short_row(good):
    _rewrite_poses(good, lambda rows: rows[2].__delitem__(slice(5, None)))
    _expect(good, "poses.csv row 3", "expected 14 values, found 5")


def test_missing_column(good):
    _rewrite_poses(good, lambda rows: rows[0].__setitem__(_col("tol_rx_deg"), "tolerance"))
    _expect(good, "poses.csv row 1", "tol_rx_deg")


def test_unknown_length_unit(good):
    meta = json.loads((good / "dataset.json").read_text())
    meta["length_unit"] = "inch"
    (good / "dataset.json").write_text(json.dumps(meta))
    _expect(good, "dataset.json", "unknown length_unit 'inch'")


@pytest.mark.parametrize("key", ["fx", "height", "k2"])
def test_missing_camera_key(good, key):
    cam = json.loads((good / "camera.json").read_text())
    del cam[key]
    (good / "camera.json").write_text(json.dumps(cam))
    _expect(good, "camera.json", f"missing key(s) {key}")


def test_bad_camera_values(good):
    cam = json.loads((good / "camera.json").read_text())
    (good / "camera.json").write_text(json.dumps({**cam, "fx": "thirty"}))
    _expect(good, "camera.json", "fx", "not a number")
    (good / "camera.json").write_text(json.dumps({**cam, "fy": -3.0}))
    _expect(good, "camera.json", "focal lengths must be positive")
    (good / "camera.json").write_text(json.dumps({**cam, "width": 32.5}))
    _expect(good, "camera.json", "width", "whole number")
    (good / "camera.json").write_text("[1, 2]")
    _expect(good, "camera.json", "JSON object")
    (good / "camera.json").write_text("{\"fx\": 1,")
    _expect(good, "camera.json", "not valid JSON")


def test_missing_camera_file_and_folder(good, tmp_path):
    (good / "camera.json").unlink()
    _expect(good, "camera.json", "missing")
    _expect(tmp_path / "nowhere", "nowhere", "does not exist")


def test_missing_fluorescence_frame(tmp_path):
    camera, frames, measured, _ = _scene()
    root = write_dataset(tmp_path / "ds", camera, frames, measured, fluorescence=frames)
    (root / "fluorescence" / "0002.png").unlink()
    _expect(root, "fluorescence/0002.png", "missing")


def test_ground_truth_depth_of_wrong_shape(tmp_path):
    camera, frames, measured, poses = _scene()
    depths = [np.zeros((H, W)), np.zeros((H, W)), np.zeros((H, W + 1))]
    root = write_dataset(tmp_path / "ds", camera, frames, measured, true_depths=depths)
    load_dataset(root)
    _expect(root, "depth/0002.npy", "shape", check_images=True)


def test_read_image_errors(tmp_path):
    with pytest.raises(InputError, match="missing"):
        read_image(tmp_path / "no.png")
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(InputError, match="junk.png: not a readable image"):
        read_image(tmp_path / "junk.png")


# --- writing ---------------------------------------------------------------------------------------


def test_write_dataset_rejects_inconsistent_arguments(tmp_path):
    camera, frames, measured, _ = _scene()
    with pytest.raises(ValueError, match="3 frames but 2 poses"):
        write_dataset(tmp_path / "a", camera, frames, measured[:2])
    with pytest.raises(ValueError, match="unique"):
        write_dataset(tmp_path / "a", camera, frames, measured, names=["a.png", "b.png", "a.png"])
    with pytest.raises(ValueError, match="fluorescence"):
        write_dataset(tmp_path / "a", camera, frames, measured, fluorescence=frames[:1])
    assert not (tmp_path / "a").exists()


def test_write_failing_midway_leaves_nothing(tmp_path):
    camera, frames, measured, _ = _scene()
    frames[2] = np.zeros((H, W, 7), np.uint8)  # 7 channels: the third frame cannot be encoded
    with pytest.raises(Exception):
        write_dataset(tmp_path / "ds", camera, frames, measured)
    assert list(tmp_path.iterdir()) == []


def test_failed_rewrite_keeps_the_previous_dataset(good):
    before = (good / "poses.csv").read_text()
    camera, frames, measured, _ = _scene(seed=1)
    with pytest.raises(InputError):
        write_dataset(good, camera, [frames[0], good / "missing.png", frames[2]], measured)
    assert (good / "poses.csv").read_text() == before
    assert sorted(p.name for p in good.parent.iterdir()) == ["ds"]
    load_dataset(good, check_images=True)


def test_frames_given_as_paths_are_copied_byte_for_byte(good, tmp_path):
    ds = load_dataset(good)
    out = write_dataset(tmp_path / "copy", ds.camera, ds.frame_paths, ds.poses)
    assert (out / "frames" / "0001.png").read_bytes() == (good / "frames" / "0001.png").read_bytes()


# --- scope3d check ---------------------------------------------------------------------------------


def test_cli_check_good_dataset(good, capsys):
    assert main(["check", str(good)]) == 0
    out = capsys.readouterr().out
    assert "3 images of 32x24 px" in out and "ok" in out and "fluorescence  no" in out
    assert "circular mask radius 12" in out and "ground truth  none" in out


def test_cli_check_bad_dataset_is_one_line(good, capsys):
    _rewrite_poses(good, lambda rows: rows[2].__setitem__(_col("tol_x_mm"), "-1"))
    assert main(["check", str(good)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "poses.csv row 3" in err and "tol_x_mm" in err


def test_cli_check_corrupt_image_in_subprocess(good):
    (good / "frames" / "0000.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
    result = subprocess.run([sys.executable, "-m", "scope3d.cli.main", "check", str(good)],
                            capture_output=True, text=True, cwd=REPO, timeout=600)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr, result.stderr
    assert "0000.png: not a readable image" in result.stderr
    assert result.stdout == ""
