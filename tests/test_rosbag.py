"""ROS bags in: bags written here with rosbags' own writers (ROS 1 and ROS 2) from a rendered phantom,
imported, and compared with the phantom's frames and poses."""
from __future__ import annotations

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from scope3d import phantoms
from scope3d.cli.main import main
from scope3d.errors import InputError
from scope3d.io.dataset import load_dataset
from scope3d.io.images import read_image
from scope3d.io.rosbag import RosbagOptions, import_rosbag, pair_by_time, tolerance_from_covariance

FRAME_PERIOD_NS = 100_000_000  # a 10 Hz camera
POSE_PERIOD_NS = 10_000_000  # a 100 Hz robot
CAMERA_LAG_NS = 3_000_000  # the image stamp trails the nearest pose sample by 3 ms


@pytest.fixture(scope="module")
def sequence():
    return phantoms.generate("dome", "grid5x6", size=(160, 120), seed=0, n_frames=4)


def _stamp(types, ns: int):
    return types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _header(types, ns: int, frame: str, ros1: bool):
    extra = {"seq": 0} if ros1 else {}
    return types["std_msgs/msg/Header"](stamp=_stamp(types, ns), frame_id=frame, **extra)


def _ros_pose(types, pose):
    """scope3d cam_from_world (mm) -> geometry_msgs Pose of the camera in the world (m)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(pose.rotation.T).as_quat()
    c = pose.centre / 1000.0
    return types["geometry_msgs/msg/Pose"](position=types["geometry_msgs/msg/Point"](x=c[0], y=c[1], z=c[2]),
                                           orientation=types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))


def _write_bag(path, seq, *, ros1: bool, compressed: bool, pose_kind: str = "PoseStamped",
               pose_offset_ns: int = 0, sigma_m: float = 0.0):
    """A bag: frames at 10 Hz, camera info, and a 100 Hz pose stream whose sample at each frame's time
    (minus the camera lag) is the frame's measured pose; the samples between are the neighbours'
    interpolation (a robot moving between stops)."""
    import cv2

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types = store.types
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import Writer

        writer = Writer(path, version=8)
    cam = seq.camera
    image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    pose_type = {"PoseStamped": "geometry_msgs/msg/PoseStamped", "tf": "tf2_msgs/msg/TFMessage",
                 "covariance": "geometry_msgs/msg/PoseWithCovarianceStamped"}[pose_kind]
    with writer:
        c_img = writer.add_connection("/scope/image", image_type, typestore=store)
        c_info = writer.add_connection("/scope/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store)
        c_pose = writer.add_connection("/tf" if pose_kind == "tf" else "/robot/pose", pose_type, typestore=store)
        t0 = 1_700_000_000 * 1_000_000_000
        poses = [m.pose for m in seq.measured_poses]
        n_steps = (len(poses) - 1) * FRAME_PERIOD_NS // POSE_PERIOD_NS + 1
        for step in range(n_steps):
            ns = step * POSE_PERIOD_NS
            k, frac = divmod(ns, FRAME_PERIOD_NS)
            pose = poses[k] if frac == 0 else poses[k].interpolate(poses[k + 1], frac / FRAME_PERIOD_NS)
            stamp = t0 + ns + pose_offset_ns
            header = _header(types, stamp, "world", ros1)
            if pose_kind == "PoseStamped":
                msg = types[pose_type](header=header, pose=_ros_pose(types, pose))
            elif pose_kind == "covariance":
                cov = np.diag([sigma_m**2] * 3 + [1e-6] * 3).ravel()
                msg = types[pose_type](header=header, pose=types["geometry_msgs/msg/PoseWithCovariance"](
                    pose=_ros_pose(types, pose), covariance=cov))
            else:
                def transform(child, p):
                    ros = _ros_pose(types, p)
                    return types["geometry_msgs/msg/TransformStamped"](
                        header=header, child_frame_id=child, transform=types["geometry_msgs/msg/Transform"](
                            translation=types["geometry_msgs/msg/Vector3"](x=ros.position.x, y=ros.position.y,
                                                                            z=ros.position.z),
                            rotation=ros.orientation))
                # another frame first on the same topic: the import must pick the camera's
                msg = types[pose_type](transforms=[transform("base_link", poses[0]), transform("scope_optical", pose)])
            writer.write(c_pose, stamp, serialize(msg, pose_type))
        for i, frame in enumerate(seq.frames):
            stamp = t0 + i * FRAME_PERIOD_NS + CAMERA_LAG_NS
            header = _header(types, stamp, "scope_optical", ros1)
            if compressed:
                ok, png = cv2.imencode(".png", frame[..., ::-1])
                msg = types[image_type](header=header, format="png", data=png.ravel())
            else:
                msg = types[image_type](header=header, height=cam.height, width=cam.width, encoding="bgr8",
                                        is_bigendian=0, step=cam.width * 3, data=frame[..., ::-1].ravel().copy())
            writer.write(c_img, stamp, serialize(msg, image_type))
            k = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]], float).ravel()
            fields = {"D" if ros1 else "d": np.zeros(5), "K" if ros1 else "k": k,
                      "R" if ros1 else "r": np.eye(3).ravel(), "P" if ros1 else "p": np.zeros(12)}
            info = types["sensor_msgs/msg/CameraInfo"](
                header=header, height=cam.height, width=cam.width, distortion_model="plumb_bob",
                binning_x=0, binning_y=0, roi=types["sensor_msgs/msg/RegionOfInterest"](
                    x_offset=0, y_offset=0, height=0, width=0, do_rectify=False), **fields)
            writer.write(c_info, stamp, serialize(info, "sensor_msgs/msg/CameraInfo"))
    return path


def _options(**kw) -> RosbagOptions:
    base = dict(image_topic="/scope/image", pose_topic="/robot/pose", camera_info_topic="/scope/camera_info",
                slop_s=0.005)
    base.update(kw)
    return RosbagOptions(**base)


def _assert_same_as_phantom(out, seq):
    ds = load_dataset(out)
    assert len(ds) == len(seq.frames)
    for i, (measured, truth) in enumerate(zip(ds.poses, seq.measured_poses)):
        # float64 through metres and quaternions: far below a micrometre
        assert np.linalg.norm(measured.pose.centre - truth.pose.centre) < 1e-9
        assert np.abs(measured.pose.rotation - truth.pose.rotation).max() < 1e-12
        np.testing.assert_array_equal(read_image(ds.frame_paths[i]), seq.frames[i])
    assert (ds.camera.fx, ds.camera.cy) == (seq.camera.fx, seq.camera.cy)
    return ds


@pytest.mark.parametrize("ros1, compressed", [(False, False), (True, True)])
def test_images_and_poses_round_trip(sequence, tmp_path, ros1, compressed):
    bag = _write_bag(tmp_path / ("scope.bag" if ros1 else "scope_bag"), sequence, ros1=ros1, compressed=compressed)
    ds = _assert_same_as_phantom(import_rosbag(bag, tmp_path / "ds", options=_options()), sequence)
    # the nearest 100 Hz sample is 3 ms before each frame; no covariance, no --tolerance: exact poses
    np.testing.assert_allclose(ds.metadata["source"]["pose_gaps_s"], 0.003, atol=1e-9)
    assert all(m.tolerance.is_exact for m in ds.poses)


def test_tf_stream_picks_the_camera_frame(sequence, tmp_path):
    bag = _write_bag(tmp_path / "tf_bag", sequence, ros1=False, compressed=False, pose_kind="tf")
    _assert_same_as_phantom(import_rosbag(bag, tmp_path / "ds", options=_options(pose_topic="/tf",
                                                                         camera_frame="scope_optical")), sequence)
    with pytest.raises(InputError, match="--camera-frame"):
        import_rosbag(bag, tmp_path / "ds2", options=_options(pose_topic="/tf"))


def test_a_flange_stream_through_the_hand_eye_gives_the_camera_poses(sequence, tmp_path):
    """A robot's tf publishes its flange, not the camera: --hand-eye turns each into the camera's pose."""
    import dataclasses

    from scope3d.geometry.pose import Pose
    from scope3d.sensor.pose_tolerance import MeasuredPose

    flange_from_cam = Pose.from_rotvec([0.05, -0.1, 1.2], [3.0, -2.0, 40.0])
    flange = [MeasuredPose(flange_from_cam @ m.pose, m.tolerance) for m in sequence.measured_poses]
    bag = _write_bag(tmp_path / "flange_bag", dataclasses.replace(sequence, measured_poses=flange), ros1=False,
                     compressed=False, pose_kind="tf")
    options = _options(pose_topic="/tf", camera_frame="scope_optical", flange_from_cam=flange_from_cam)
    _assert_same_as_phantom(import_rosbag(bag, tmp_path / "ds", options=options), sequence)
    # and without it the flange's poses, 40 mm behind the camera, are taken for the camera's
    ds = load_dataset(import_rosbag(bag, tmp_path / "raw", options=_options(pose_topic="/tf", camera_frame="scope_optical")))
    assert np.linalg.norm(ds.poses[0].pose.centre - sequence.measured_poses[0].pose.centre) > 39.0


def test_tolerance_from_covariance_or_from_the_parameter(sequence, tmp_path):
    bag = _write_bag(tmp_path / "cov_bag", sequence, ros1=False, compressed=False, pose_kind="covariance",
                     sigma_m=0.0005)
    ds = load_dataset(import_rosbag(bag, tmp_path / "ds", options=_options()))
    for m in ds.poses:
        # 3 sigma of 0.5 mm per axis; 3 sigma of 1 mrad (variance 1e-6 rad²) = 0.172 deg
        np.testing.assert_allclose(m.tolerance.position_mm, 1.5, rtol=1e-6)
        np.testing.assert_allclose(m.tolerance.orientation_deg, np.rad2deg(0.003), rtol=1e-3)
    # the CLI: --tolerance wins over the covariance
    assert main(["import", "rosbag", str(bag), "--image-topic", "/scope/image", "--pose-topic", "/robot/pose",
                 "--camera-info-topic", "/scope/camera_info", "--slop-ms", "5", "--tolerance", "0.2",
                 "--out", str(tmp_path / "cli")]) == 0
    assert all(np.allclose(m.tolerance.position_mm, 0.2) for m in load_dataset(tmp_path / "cli").poses)


def test_missing_topic_and_unsynchronisable_streams_are_one_line_errors(sequence, tmp_path, capsys):
    bag = _write_bag(tmp_path / "bag", sequence, ros1=False, compressed=False)
    args = ["import", "rosbag", str(bag), "--image-topic", "/scope/image", "--camera-info-topic",
            "/scope/camera_info", "--out", str(tmp_path / "o")]
    assert main(args + ["--pose-topic", "/nope"]) == 2
    err = capsys.readouterr().err
    assert "no topic '/nope'" in err and "/robot/pose" in err and err.count("\n") == 1
    # a pose clock 1 s late: no image within a 20 ms slop of any pose
    late = _write_bag(tmp_path / "late", sequence, ros1=False, compressed=False, pose_offset_ns=1_000_000_000)
    assert main(["import", "rosbag", str(late), *args[3:], "--pose-topic", "/robot/pose"]) == 2
    err = capsys.readouterr().err
    assert "never come within the slop" in err and err.count("\n") == 1
    assert not (tmp_path / "o").exists()
    # a slop below the 3 ms camera lag pairs nothing either
    with pytest.raises(InputError, match="closest 0.003 s"):
        import_rosbag(bag, tmp_path / "o", options=_options(slop_s=0.002))


def test_pairing_is_one_to_one_smallest_gap_first():
    images = np.array([0, 100, 200, 300])
    poses = np.array([95, 105, 290, 1000])
    # image 100 takes pose 95 or 105 (both 5 away: the first in order); image 0 has nothing within 10;
    # 95 and 105 are both in reach of image 100 only; 290 goes to image 300
    assert pair_by_time(images, poses, 10) == [(1, 0), (3, 2)]
    assert pair_by_time(images, poses, 1) == []


def test_covariance_box_takes_the_largest_rotation_sigma():
    tol = tolerance_from_covariance(np.diag([1e-6, 4e-6, 9e-6, 1e-4, 4e-4, 1e-6]), 3.0)
    np.testing.assert_allclose(tol.position_mm, [3.0, 6.0, 9.0])
    np.testing.assert_allclose(tol.orientation_rad, 0.06)
    with pytest.raises(InputError):
        tolerance_from_covariance(np.diag([-1.0, 1, 1, 1, 1, 1]), 3.0)


def test_raw_image_encodings_decode_to_the_same_pixels():
    from types import SimpleNamespace

    from scope3d.io.rosbag import decode_image

    rgb = np.random.default_rng(0).integers(0, 256, (5, 7, 3), dtype=np.uint8)

    def msg(encoding, data, step, bigendian=0):
        return SimpleNamespace(encoding=encoding, height=5, width=7, step=step, is_bigendian=bigendian,
                               data=np.frombuffer(data, np.uint8))

    padded = np.zeros((5, 7 * 3 + 3), np.uint8)  # rows padded past width * channels: step > row
    padded[:, :21] = rgb[..., ::-1].reshape(5, 21)
    np.testing.assert_array_equal(decode_image(msg("bgr8", padded.tobytes(), 24), "sensor_msgs/msg/Image", "t"), rgb)
    rgba = np.concatenate([rgb, np.full((5, 7, 1), 255, np.uint8)], axis=2)
    np.testing.assert_array_equal(decode_image(msg("rgba8", rgba.tobytes(), 28), "sensor_msgs/msg/Image", "t"), rgb)
    depth = np.arange(35, dtype=np.uint16).reshape(5, 7) * 1000
    for order, big in ((">u2", 1), ("<u2", 0)):
        got = decode_image(msg("mono16", depth.astype(order).tobytes(), 14, big), "sensor_msgs/msg/Image", "t")
        np.testing.assert_array_equal(got, depth)
    with pytest.raises(InputError, match="'32FC1' not supported"):
        decode_image(msg("32FC1", bytes(140), 28), "sensor_msgs/msg/Image", "t")
    with pytest.raises(InputError, match="shorter"):
        decode_image(msg("rgb8", bytes(50), 21), "sensor_msgs/msg/Image", "t")


@pytest.mark.parametrize("skew, refused", [(60.0 * 8e-8, False), (0.5, True)])
def test_camera_info_skew_is_zero_within_rounding_and_refused_beyond(skew, refused):
    """A camera holds no skew: 8e-8 fx (a decomposed projection matrix's rounding) moves no pixel of the
    64 x 48 image by more than skew * 24 / 60 = 2e-6 px and is dropped; 0.5 px moves the corners by
    0.5 * 24 / 60 = 0.2 px, more than SAME_CALIBRATION_PX: refused in one line (issue 34; it was dropped)."""
    from types import SimpleNamespace

    from scope3d.io.rosbag import camera_from_info
    from scope3d.sensor.camera import Camera

    message = SimpleNamespace(width=64, height=48, k=[60.0, skew, 31.5, 0, 60.0, 23.5, 0, 0, 1],
                              distortion_model="plumb_bob", d=[0.1, 0.02, 0.0, 0.0, 0.0])
    if not refused:
        assert camera_from_info(message, "b") == Camera(64, 48, 60.0, 60.0, 31.5, 23.5, 0.1, 0.02)
        return
    with pytest.raises(InputError) as info:
        camera_from_info(message, "scope.bag: /info")
    text = str(info.value)
    assert text.startswith("scope.bag: /info: ") and "no skew" in text and "0.2 px" in text and "\n" not in text
