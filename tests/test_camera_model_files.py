"""Camera models in files (issue 32): camera.json <-> COLMAP cameras.txt <-> ROS camera_info round trips,
old camera.json files, and bad input refused in one line naming the file."""
import json
from types import SimpleNamespace

import numpy as np
import pytest

from scope3d.errors import InputError
from scope3d.io.camera_json import camera_to_dict, read_camera_json
from scope3d.io.colmap import camera_line, read_colmap_cameras
from scope3d.io.rosbag import camera_from_info, camera_info_fields
from scope3d.sensor.camera import Camera

CAMERAS = [
    Camera(640, 480, 300.0, 310.0, 320.2, 239.7, -0.25, 0.06),
    Camera(640, 480, 300.0, 300.0, 320.2, 239.7, -0.25, 0.06),
    Camera.from_params(640, 480, "OPENCV", [300.0, 310.0, 320.2, 239.7, -0.25, 0.06, 0.0012, -0.0021]),
    Camera.from_params(640, 480, "FULL_OPENCV",
                       [300.0, 310.0, 320.2, 239.7, -0.2, 0.05, 0.001, -0.002, 0.01, 0.1, 0.02, 0.003]),
    Camera.from_params(256, 256, "OPENCV_FISHEYE", [120.5, 121.0, 127.6, 128.1, 0.05, -0.01, 0.002, -0.0003]),
]


def _json_round_trip(camera, tmp_path):
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(camera_to_dict(camera)))
    return read_camera_json(path)


def _colmap_round_trip(camera, tmp_path):
    path = tmp_path / "cameras.txt"
    path.write_text("# a comment\n" + camera_line(1, camera) + "\n")
    (back,) = read_colmap_cameras(path)
    return back


def _ros_round_trip(camera):
    return camera_from_info(SimpleNamespace(**camera_info_fields(camera)), "test.bag: /info")


@pytest.mark.parametrize("camera", CAMERAS, ids=lambda c: c.model)
def test_camera_json_colmap_and_camera_info_round_trips_keep_model_and_parameters(camera, tmp_path):
    via_json = _json_round_trip(camera, tmp_path)
    assert via_json == camera
    via_colmap = _colmap_round_trip(via_json, tmp_path)
    # COLMAP's principal point is shifted by 0.5 px and back: exact in binary for these values
    assert via_colmap.model == camera.model
    np.testing.assert_allclose(via_colmap.params, camera.params, rtol=0, atol=1e-12)
    via_ros = _ros_round_trip(via_colmap)
    assert via_ros.model == camera.model
    np.testing.assert_array_equal(via_ros.params, via_colmap.params)
    assert _json_round_trip(via_ros, tmp_path).model == camera.model


def test_pinhole_round_trips_to_the_same_projection(tmp_path):
    camera = Camera.from_params(640, 480, "PINHOLE", [300.0, 310.0, 320.2, 239.7])
    assert _json_round_trip(camera, tmp_path) == camera
    pts = np.array([[0.1, -0.2, 1.0], [0.5, 0.3, 2.0]])
    # COLMAP's and ROS's pinhole is read as the default model with k1 = k2 = 0, as it always was
    for back in (_colmap_round_trip(camera, tmp_path), _ros_round_trip(camera)):
        np.testing.assert_allclose(back.project(pts), camera.project(pts), rtol=0, atol=1e-12)


def test_old_camera_json_without_a_model_key_is_the_radial_model(tmp_path):
    path = tmp_path / "camera.json"
    path.write_text(json.dumps({"width": 64, "height": 48, "fx": 60, "fy": 61, "cx": 31.5, "cy": 23.5,
                                "k1": -0.1, "k2": 0.01, "mask_radius_px": None}))
    assert read_camera_json(path) == Camera(64, 48, 60.0, 61.0, 31.5, 23.5, -0.1, 0.01)
    data = json.loads(path.read_text())
    data["model"] = "pinhole_radial_k1k2"
    path.write_text(json.dumps(data))
    assert read_camera_json(path) == Camera(64, 48, 60.0, 61.0, 31.5, 23.5, -0.1, 0.01)
    # and the default model is written as it always was
    assert camera_to_dict(Camera(64, 48, 60, 61, 31.5, 23.5, -0.1, 0.01)) == {
        "model": "pinhole_radial_k1k2", "width": 64, "height": 48, "fx": 60, "fy": 61, "cx": 31.5, "cy": 23.5,
        "k1": -0.1, "k2": 0.01, "mask_radius_px": None, "fov_deg": Camera(64, 48, 60, 61, 31.5, 23.5).fov_deg}


@pytest.mark.parametrize("edit, fragment", [
    ({"model": "KANNALA_BRANDT"}, "unknown camera model 'KANNALA_BRANDT'"),
    ({"model": "OPENCV_FISHEYE"}, "missing key(s) k3, k4 of the OPENCV_FISHEYE model"),
    ({"model": "OPENCV", "p1": 0.0, "p2": 0.0, "k3": 0.1}, "k3 is not a parameter of the OPENCV model"),
    ({"k1": float("nan")}, "k1 is NaN or infinite"),
])
def test_bad_camera_json_is_one_line_naming_the_file(edit, fragment, tmp_path):
    path = tmp_path / "camera.json"
    data = camera_to_dict(CAMERAS[0])
    data.update(edit)
    path.write_text(json.dumps(data).replace("NaN", "NaN"))
    with pytest.raises(InputError) as info:
        read_camera_json(path)
    message = str(info.value)
    assert message.startswith(str(path)) and fragment in message and "\n" not in message, message


@pytest.mark.parametrize("line, fragment", [
    ("1 KANNALA 64 48 60 60 32 24", "camera model KANNALA is not supported"),
    ("1 OPENCV_FISHEYE 64 48 60 60 32 24 0.1 0.01 0", "OPENCV_FISHEYE has 8 parameters, found 7"),
    ("1 OPENCV_FISHEYE 64 48 60 60 32 24 0.1 nan 0 0", "NaN or infinite"),
])
def test_bad_cameras_txt_is_one_line_naming_the_file(line, fragment, tmp_path):
    path = tmp_path / "cameras.txt"
    path.write_text(line + "\n")
    with pytest.raises(InputError) as info:
        read_colmap_cameras(path)
    message = str(info.value)
    assert message.startswith(f"{path} line 1") and fragment in message and "\n" not in message, message


@pytest.mark.parametrize("fields, fragment", [
    ({"distortion_model": "equidistant", "d": [0.1, float("nan"), 0.0, 0.0]}, "NaN or infinite"),
    ({"distortion_model": "kannala", "d": [0.1, 0.0, 0.0, 0.0]}, "distortion model 'kannala' is not supported"),
    ({"distortion_model": "equidistant", "d": [0.1, 0.0, 0.0, 0.0, 0.0]}, "equidistant has 4 distortion "
                                                                          "coefficients, D has 5"),
])
def test_bad_camera_info_is_one_line_naming_the_topic(fields, fragment):
    message = SimpleNamespace(width=64, height=48, k=[60.0, 0, 31.5, 0, 60.0, 23.5, 0, 0, 1], **fields)
    with pytest.raises(InputError) as info:
        camera_from_info(message, "scope.bag: /info")
    text = str(info.value)
    assert text.startswith("scope.bag: /info: ") and fragment in text and "\n" not in text, text


def test_camera_info_models_are_read_by_name():
    k = [60.0, 0, 31.5, 0, 61.0, 23.5, 0, 0, 1]
    fisheye = camera_from_info(SimpleNamespace(width=64, height=48, k=k, distortion_model="equidistant",
                                               d=[0.1, 0.02, 0.0, 0.0]), "b")
    # an equidistant camera's first two coefficients are the fisheye's, not radial k1, k2
    assert fisheye.model == "OPENCV_FISHEYE" and fisheye.params.tolist() == [60, 61, 31.5, 23.5, 0.1, 0.02, 0, 0]
    plumb = camera_from_info(SimpleNamespace(width=64, height=48, k=k, distortion_model="plumb_bob",
                                             d=[0.1, 0.02, 0.001, 0.0, 0.003]), "b")
    assert plumb.model == "FULL_OPENCV" and plumb.params[4:].tolist() == [0.1, 0.02, 0.001, 0.0, 0.003, 0, 0, 0]
    tangential = camera_from_info(SimpleNamespace(width=64, height=48, k=k, distortion_model="plumb_bob",
                                                  d=[0.1, 0.02, 0.001, 0.0, 0.0]), "b")
    assert tangential.model == "OPENCV"
    radial = camera_from_info(SimpleNamespace(width=64, height=48, k=k, distortion_model="plumb_bob",
                                              d=[0.1, 0.02, 0.0, 0.0, 0.0]), "b")
    assert radial == Camera(64, 48, 60.0, 61.0, 31.5, 23.5, 0.1, 0.02)


def test_datasets_take_the_radial_model_only_until_the_jobs_take_every_model(tmp_path):
    from scope3d.io.dataset import write_dataset

    with pytest.raises(InputError, match="OPENCV_FISHEYE camera; scope3d's jobs take pinhole_radial_k1k2"):
        write_dataset(tmp_path / "ds", CAMERAS[-1], [np.zeros((256, 256), np.uint8)], [None])
    assert not (tmp_path / "ds").exists()
