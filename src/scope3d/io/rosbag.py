"""Robot logs in: a ROS 1 or ROS 2 bag's camera images and camera poses as a scope3d dataset.

Read with the ``rosbags`` library (pure Python, no ROS install). Images: ``sensor_msgs/Image`` (rgb8, bgr8,
rgba8, bgra8, mono8, mono16) or ``sensor_msgs/CompressedImage`` (any format OpenCV decodes). Poses of the
camera's optical frame (z forward, x right, y down: scope3d's camera frame, REP 103's ``_optical``
frame) in the world: ``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped``, ``TransformStamped``,
``nav_msgs/Odometry`` or ``tf2_msgs/TFMessage`` (``/tf``, the transform whose child frame is the
camera's). ROS lengths are metres (REP 103): converted to mm.

Each image is paired with the pose stamped nearest to it, within a slop, each pose used once (the
approximate-time pairing the reference used for its webcams): the pair with the smallest time gap first.
Images without a pose within the slop are left out; no pair at all is an InputError.
"""
from __future__ import annotations

import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import quaternion_to_matrix
from scope3d.io.images import decode_image_data
from scope3d.sensor.camera import SAME_CALIBRATION_PX, Camera, calibration_shift_px, without_skew
from scope3d.sensor.camera_models import DEFAULT_MODEL, lens_model
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
              "geometry_msgs/msg/TransformStamped", "nav_msgs/msg/Odometry", "tf2_msgs/msg/TFMessage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
M_TO_MM = 1000.0


@dataclass(frozen=True)
class RosbagOptions:
    """What to read and how to pair it.

    image_topic, pose_topic : str, topic names. camera_frame : str or None, the child frame id of the
        camera's pose in a tf or TransformStamped / Odometry stream (required for /tf, where many frames
        share the topic). camera_info_topic : str or None, where the intrinsics are (else give a Camera
        to :func:`import_rosbag`).
    slop_s : float, seconds, largest gap between an image's stamp and its pose's (ROS's approximate-time
        slop). tolerance : PoseTolerance or None, the poses' box; None = from the pose covariance when the
        messages carry one (``covariance_sigmas`` standard deviations), else exact.
    flange_from_cam : Pose or None, the hand-eye transform (``scope3d calibrate-hand-eye``'s hand_eye.json):
        the pose stream (or the tf frame ``camera_frame``) is then the robot's flange, and each camera pose
        is ``base_from_flange @ flange_from_cam``.
    """

    image_topic: str
    pose_topic: str
    camera_frame: str | None = None
    camera_info_topic: str | None = None
    slop_s: float = 0.02
    tolerance: PoseTolerance | None = None
    covariance_sigmas: float = 3.0  # a 3-sigma box holds 99.7 % of a Gaussian's mass per axis
    flange_from_cam: Pose | None = None

    def __post_init__(self) -> None:
        if not self.image_topic or not self.pose_topic:
            raise ValueError("image_topic and pose_topic are required")
        if not self.slop_s > 0:
            raise ValueError(f"slop_s must be positive, got {self.slop_s}")
        if not self.covariance_sigmas > 0:
            raise ValueError("covariance_sigmas must be positive")


@dataclass(frozen=True)
class StampedPose:
    """stamp_ns : int, header time; pose : cam_from_world (mm); covariance : (6, 6) in m² and rad²
    (x, y, z, rotation about x, y, z of the parent frame) or None."""

    stamp_ns: int
    pose: Pose
    covariance: np.ndarray | None = None


def _stamp_ns(header, fallback_ns: int) -> int:
    stamp = header.stamp
    ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return ns if ns > 0 else fallback_ns


# A ROS quaternion is written as doubles from a unit one: far from norm 1 it is no rotation (zeros are
# common from a driver that has no fix yet); 1e-3 is loose for any real writer's rounding.
_UNIT_QUATERNION_SLACK = 1e-3


def _pose_from(position, orientation, where: str) -> Pose:
    """ROS pose of the camera in the world (world_from_cam, metres) -> scope3d cam_from_world (mm)."""
    quat = np.array([orientation.x, orientation.y, orientation.z, orientation.w], float)
    centre = np.array([position.x, position.y, position.z], float) * M_TO_MM
    if not (np.all(np.isfinite(quat)) and abs(np.linalg.norm(quat) - 1.0) < _UNIT_QUATERNION_SLACK):
        raise InputError(f"{where}: orientation {quat.tolist()} is not a unit quaternion")
    if not np.all(np.isfinite(centre)):
        raise InputError(f"{where}: position {centre.tolist()} mm is not finite")
    return Pose.from_centre(quaternion_to_matrix(quat / np.linalg.norm(quat)).T, centre)


def _poses_of(msg, msgtype: str, time_ns: int, camera_frame: str | None, topic: str, where: str) -> list[StampedPose]:
    """The camera poses one message holds (none if it is about other frames)."""
    if msgtype == "geometry_msgs/msg/PoseStamped":
        return [StampedPose(_stamp_ns(msg.header, time_ns), _pose_from(msg.pose.position, msg.pose.orientation,
                                                                          where))]
    if msgtype in ("geometry_msgs/msg/PoseWithCovarianceStamped", "nav_msgs/msg/Odometry"):
        if msgtype == "nav_msgs/msg/Odometry" and camera_frame and msg.child_frame_id != camera_frame:
            return []
        p = msg.pose.pose
        cov = np.asarray(msg.pose.covariance, float).reshape(6, 6)
        return [StampedPose(_stamp_ns(msg.header, time_ns), _pose_from(p.position, p.orientation, where), cov)]
    transforms = msg.transforms if msgtype == "tf2_msgs/msg/TFMessage" else [msg]
    if msgtype == "tf2_msgs/msg/TFMessage" and not camera_frame:
        raise InputError(f"{topic}: a tf stream needs the camera's frame id (--camera-frame)")
    out = []
    for t in transforms:
        if camera_frame and t.child_frame_id.lstrip("/") != camera_frame.lstrip("/"):
            continue
        out.append(StampedPose(_stamp_ns(t.header, time_ns),
                               _pose_from(t.transform.translation, t.transform.rotation, where)))
    return out


def decode_image(msg, msgtype: str, where: str) -> np.ndarray:
    """(H, W, 3) uint8 RGB or (H, W) uint8/uint16 of an Image or CompressedImage message."""
    if msgtype == "sensor_msgs/msg/CompressedImage":
        img = decode_image_data(np.asarray(msg.data, np.uint8), where, cv2.IMREAD_UNCHANGED)
        if img.ndim == 3 and img.shape[2] < 3 or img.dtype not in (np.uint8, np.uint16):
            raise InputError(f"{where}: compressed image ({msg.format!r}) is {img.dtype} with shape {img.shape}")
        return img if img.ndim == 2 else cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2RGB)
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "mono16": 1, "8UC1": 1, "8UC3": 3}
    if msg.encoding not in channels:
        raise InputError(f"{where}: image encoding {msg.encoding!r} not supported "
                         f"(supported: {', '.join(channels)})")
    dtype = np.dtype(">u2" if msg.is_bigendian else "<u2") if msg.encoding == "mono16" else np.dtype(np.uint8)
    c = channels[msg.encoding]
    row = msg.width * c * dtype.itemsize
    data = np.asarray(msg.data, np.uint8)
    if msg.step < row or len(data) < msg.step * msg.height:
        raise InputError(f"{where}: image data shorter than height x step ({len(data)} bytes)")
    rows = data[: msg.step * msg.height].reshape(msg.height, msg.step)[:, :row]
    img = np.ascontiguousarray(rows).view(dtype).reshape(msg.height, msg.width, c) if c > 1 else \
        np.ascontiguousarray(rows).view(dtype).reshape(msg.height, msg.width).astype(dtype.newbyteorder("="))
    if msg.encoding.startswith("bgr"):
        img = img[..., 2::-1]
    elif c == 4:
        img = img[..., :3]
    return np.ascontiguousarray(img)


# ROS distortion_model -> the coefficients of D in order (REP 104 / image_geometry)
ROS_DISTORTION_MODELS = {
    "plumb_bob": ("k1", "k2", "p1", "p2", "k3"),
    "rational_polynomial": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "equidistant": ("k1", "k2", "k3", "k4"),
}


def camera_from_info(msg, where: str) -> Camera:
    """A Camera from a CameraInfo message, by its ``distortion_model``: ``equidistant`` is the fisheye
    (OPENCV_FISHEYE, D = k1..k4); ``rational_polynomial`` is FULL_OPENCV; ``plumb_bob`` (D = k1, k2, p1, p2,
    k3) is scope3d's ``pinhole_radial_k1k2`` when p1, p2 and k3 are zero (as every import so far), OPENCV
    when only k3 is, FULL_OPENCV otherwise. A message without the name (an empty one) is read as plumb_bob,
    or rational_polynomial when D has 8 values; a D shorter than the model's is padded with zeros (ROS
    leaves D empty for a camera without distortion)."""
    # a damaged bag's message definition can turn K into one number or D into text: refused, not reshaped
    try:
        k = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), float)
        d = np.asarray(getattr(msg, "d", getattr(msg, "D", [])), float).ravel()
    except (TypeError, ValueError):
        raise InputError(f"{where}: camera info's K or D is not numbers") from None
    if k.size != 9:
        raise InputError(f"{where}: camera info's K has {k.size} values, not 9")
    k = k.reshape(3, 3)
    if not np.all(np.isfinite(k)) or not np.all(np.isfinite(d)):
        raise InputError(f"{where}: camera info's K or D has NaN or infinite values")
    if not k[0, 0] > 0 or not k[1, 1] > 0:
        raise InputError(f"{where}: camera info has no focal length (uncalibrated camera)")
    # a camera holds no skew: one that moves pixels by more than rounding is refused, not dropped
    try:
        size = int(msg.width), int(msg.height)
    except (TypeError, ValueError):
        size = (0, 0)  # no image size: refused below as no camera
    skew_px = calibration_shift_px(k, without_skew(k), *size) if min(size) > 0 else 0.0
    if not skew_px <= SAME_CALIBRATION_PX:
        raise InputError(f"{where}: camera info's K must be [[fx 0 cx] [0 fy cy] [0 0 1]] (no skew): its skew and "
                         f"third row move pixels by up to {skew_px:.3g} px, rounding by at most {SAME_CALIBRATION_PX} px")
    name = str(getattr(msg, "distortion_model", "") or "")
    if not name:
        name = "rational_polynomial" if len(d) == 8 else "plumb_bob"
    if name not in ROS_DISTORTION_MODELS:
        raise InputError(f"{where}: distortion model {name!r} is not supported "
                         f"(supported: {', '.join(ROS_DISTORTION_MODELS)})")
    names = ROS_DISTORTION_MODELS[name]
    if len(d) > len(names):
        raise InputError(f"{where}: {name} has {len(names)} distortion coefficients, D has {len(d)}")
    coeffs = dict(zip(names, list(d) + [0.0] * (len(names) - len(d))))
    if name == "equidistant":
        model = "OPENCV_FISHEYE"
    elif name == "rational_polynomial" or coeffs["k3"] != 0.0:
        model = "FULL_OPENCV"
    elif coeffs["p1"] != 0.0 or coeffs["p2"] != 0.0:
        model = "OPENCV"
    else:
        model = DEFAULT_MODEL
    lens = lens_model(model)
    head = {"fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2]}
    params = [float(head[n]) if n in head else float(coeffs.get(n, 0.0)) for n in lens.param_names]
    # ROS's pixel centres are at integer coordinates, as scope3d's are: cx, cy carry over unchanged
    try:
        return Camera.from_params(int(msg.width), int(msg.height), model, params)
    except ValueError as exc:
        raise InputError(f"{where}: camera info is no camera ({exc})") from None


def camera_info_fields(camera: Camera) -> dict:
    """The sensor_msgs/CameraInfo fields of a camera (width, height, distortion_model, d, k, r, p): the
    fisheye as ``equidistant``, FULL_OPENCV as ``rational_polynomial``, the others as ``plumb_bob``
    (:func:`camera_from_info` reads them back as the same model). The circular mask has no field."""
    p = dict(zip(camera.param_names, map(float, camera.params)))
    if camera.lens.is_fisheye:
        name = "equidistant"
    elif camera.model == "FULL_OPENCV":
        name = "rational_polynomial"
    else:
        name = "plumb_bob"
    d = [p.get(n, 0.0) for n in ROS_DISTORTION_MODELS[name]]
    return {"width": camera.width, "height": camera.height, "distortion_model": name, "d": d,
            "k": [camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0],
            "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            "p": [camera.fx, 0.0, camera.cx, 0.0, 0.0, camera.fy, camera.cy, 0.0, 0.0, 0.0, 1.0, 0.0]}


def pair_by_time(image_ns: np.ndarray, pose_ns: np.ndarray, slop_ns: int) -> list[tuple[int, int]]:
    """(image index, pose index) pairs, each index used once, gaps within ``slop_ns``, smallest gap first;
    sorted by image index. image_ns : (M,) int ns; pose_ns : (P,) int ns."""
    order = np.argsort(pose_ns, kind="stable")
    sorted_ns = pose_ns[order]
    candidates = []
    for i, t in enumerate(image_ns):
        lo = np.searchsorted(sorted_ns, t - slop_ns, side="left")
        hi = np.searchsorted(sorted_ns, t + slop_ns, side="right")
        candidates.extend((abs(int(sorted_ns[j]) - int(t)), i, int(order[j])) for j in range(lo, hi))
    used_images, used_poses, pairs = set(), set(), []
    for _, i, j in sorted(candidates):
        if i not in used_images and j not in used_poses:
            used_images.add(i)
            used_poses.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def tolerance_from_covariance(cov: np.ndarray, sigmas: float, where: str = "pose") -> PoseTolerance:
    """Box half-widths from a ROS pose covariance (m², rad²): ``sigmas`` standard deviations per position
    axis (mm); orientation: ROS states it about the parent's axes and scope3d's box is about the camera's,
    so every axis gets the largest of the three (a box that holds the other whatever the rotation)."""
    var = np.diag(np.asarray(cov, float).reshape(6, 6))
    if np.any(var < 0) or not np.all(np.isfinite(var)):
        raise InputError(f"{where}: pose covariance has a negative or non-finite variance")
    position_mm = sigmas * np.sqrt(var[:3]) * M_TO_MM
    try:
        return PoseTolerance(position_mm, np.full(3, sigmas * np.sqrt(var[3:].max())))
    except ValueError as exc:  # a variance finite in m² whose box is infinite in mm
        raise InputError(f"{where}: pose covariance gives no tolerance ({exc})") from None


def _one_line(exc: BaseException) -> str:
    return " ".join(f"{type(exc).__name__}: {exc}".split())[:300]


def _messages(reader, connections: list, bag: Path, topic: str) -> Iterator[tuple[int, int, object, str]]:
    """(index on the topic, bag time ns, message, message type) of every message of ``connections``.
    What the rosbags library fails to read or deserialise is the bag's fault: one InputError naming the
    bag, the topic and the message (the library raises many kinds of error on a damaged bag)."""
    messages = reader.messages(connections=connections)
    index = 0
    while True:
        try:
            item = next(messages)
        except StopIteration:
            return
        except (InputError, MemoryError):
            raise
        except Exception as exc:  # noqa: BLE001 - see the docstring
            raise InputError(f"{bag}: {topic} message {index} cannot be read ({_one_line(exc)})") from None
        conn, time_ns, raw = item
        try:
            message = reader.deserialize(raw, conn.msgtype)
        except (InputError, MemoryError):
            raise
        except Exception as exc:  # noqa: BLE001
            raise InputError(f"{bag}: {topic} message {index} does not deserialise ({_one_line(exc)})") from None
        yield index, time_ns, message, conn.msgtype
        index += 1


def import_rosbag(bag: str | Path, out_dir: str | Path, *, options: RosbagOptions, 
                  camera: Camera | None = None, finish=None) -> Path:
    """Write the bag's synchronised images and poses as a scope3d dataset folder (see
    :func:`scope3d.io.dataset.write_dataset`); returns ``out_dir``. camera : the intrinsics when the
    bag has no CameraInfo topic (``options.camera_info_topic``). finish : see
    :func:`scope3d.io.dataset.write_dataset`. Frames are decoded one at a time (only
    the paired ones), so a long bag never sits in memory. Raises InputError naming the bag for a missing
    topic, an unsupported message type, no intrinsics, or streams that never meet within the slop."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from scope3d.io.dataset import write_dataset

    bag = Path(bag)
    if not bag.exists():
        raise InputError(f"{bag}: no such bag")
    try:
        reader = AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except MemoryError:
        raise
    except Exception as exc:  # noqa: BLE001 - AnyReaderError mostly; a damaged bag raises many kinds of error
        raise InputError(f"{bag}: not a readable ROS 1 or ROS 2 bag ({_one_line(exc)})") from None
    try:
        # a damaged metadata.yaml can hold a mapping where a name belongs (found by the long fuzz run:
        # TypeError, unhashable dict, from the dict of topics)
        if not all(isinstance(c.topic, str) and isinstance(c.msgtype, str) for c in reader.connections):
            raise InputError(f"{bag}: a topic or message type in its metadata is not a name (damaged bag)")
        topics = {c.topic: c.msgtype for c in reader.connections}
        for topic, allowed in ((options.image_topic, IMAGE_TYPES), (options.pose_topic, POSE_TYPES)):
            if topic not in topics:
                raise InputError(f"{bag}: no topic {topic!r} (topics: {', '.join(sorted(topics)) or 'none'})")
            if topics[topic] not in allowed:
                raise InputError(f"{bag}: topic {topic!r} holds {topics[topic]}, not one of {', '.join(allowed)}")
        if camera is None:
            camera = _read_camera_info(reader, bag, options, topics)

        poses: list[StampedPose] = []
        pose_conns = [c for c in reader.connections if c.topic == options.pose_topic]
        for index, time_ns, msg, msgtype in _messages(reader, pose_conns, bag, options.pose_topic):
            poses.extend(_poses_of(msg, msgtype, time_ns, options.camera_frame, options.pose_topic,
                                   f"{bag}: {options.pose_topic} message {index}"))
        if not poses:
            raise InputError(f"{bag}: topic {options.pose_topic!r} has no pose of frame "
                             f"{options.camera_frame!r}" if options.camera_frame else
                             f"{bag}: topic {options.pose_topic!r} has no message")
        image_conns = [c for c in reader.connections if c.topic == options.image_topic]
        image_ns = np.array([_stamp_ns(msg.header, time_ns)
                             for _, time_ns, msg, _ in _messages(reader, image_conns, bag, options.image_topic)],
                            dtype=np.int64)
        if len(image_ns) == 0:
            raise InputError(f"{bag}: topic {options.image_topic!r} has no message")
        pose_ns = np.array([p.stamp_ns for p in poses], dtype=np.int64)
        pairs = pair_by_time(image_ns, pose_ns, int(round(options.slop_s * 1e9)))
        if not pairs:
            gap = float(np.min(np.abs(image_ns[:, None] - pose_ns[None, :]))) / 1e9
            raise InputError(f"{bag}: images on {options.image_topic!r} and poses on {options.pose_topic!r} never "
                             f"come within the slop of {options.slop_s:g} s of each other (closest {gap:.3g} s)")

        pose_of_image = dict(pairs)
        measured = []
        for i, j in pairs:
            p = poses[j]
            if options.tolerance is not None:
                tol = options.tolerance
            elif p.covariance is not None:
                tol = tolerance_from_covariance(p.covariance, options.covariance_sigmas,
                                                f"{bag}: {options.pose_topic} pose {j}")
            else:
                tol = PoseTolerance.exact()
            # the stream's frame is the flange's with a hand-eye: cam_from_world = cam_from_flange @ flange_from_world
            pose = p.pose if options.flange_from_cam is None else options.flange_from_cam.inverse() @ p.pose
            measured.append(MeasuredPose(pose, tol))
        with tempfile.TemporaryDirectory(prefix="scope3d-rosbag-") as tmp:
            frames = []
            for index, _time_ns, msg, msgtype in _messages(reader, image_conns, bag, options.image_topic):
                if index not in pose_of_image:
                    continue
                img = decode_image(msg, msgtype, f"{bag}: {options.image_topic} message {index}")
                if img.shape[:2] != (camera.height, camera.width):
                    raise InputError(f"{bag}: {options.image_topic} message {index} is {img.shape[1]}x"
                                     f"{img.shape[0]} px, the camera {camera.width}x{camera.height}")
                if img.dtype != np.uint8:  # mono16 -> 8 bits, scope3d's frames are 8-bit
                    img = (img >> 8).astype(np.uint8)
                path = Path(tmp) / f"{len(frames):04d}.png"
                if not cv2.imwrite(str(path), img if img.ndim == 2 else img[..., ::-1]):
                    raise InputError(f"{path}: could not write a frame")
                frames.append(path)
            return write_dataset(out_dir, camera, frames, measured, metadata={
                "source": {"rosbag": str(bag), "image_topic": options.image_topic, "pose_topic": options.pose_topic,
                           "camera_frame": options.camera_frame, "slop_s": options.slop_s,
                           "flange_from_cam": None if options.flange_from_cam is None else
                           {"rotation": options.flange_from_cam.rotation.tolist(),
                            "translation_mm": options.flange_from_cam.translation.tolist()},
                           "images_in_bag": int(len(image_ns)), "images_paired": len(pairs),
                           "image_stamps_ns": [int(image_ns[i]) for i, _ in pairs],
                           "pose_gaps_s": [float(abs(image_ns[i] - pose_ns[j]) / 1e9) for i, j in pairs]}},
                finish=finish)
    finally:
        reader.close()


def _read_camera_info(reader, bag: Path, options: RosbagOptions, topics: dict) -> Camera:
    if not options.camera_info_topic:
        raise InputError(f"{bag}: no intrinsics: give a camera-info topic or a camera.json")
    if topics.get(options.camera_info_topic) != CAMERA_INFO_TYPE:
        raise InputError(f"{bag}: no {CAMERA_INFO_TYPE} topic {options.camera_info_topic!r}")
    conns = [c for c in reader.connections if c.topic == options.camera_info_topic]
    for _, _time_ns, msg, _ in _messages(reader, conns, bag, options.camera_info_topic):
        return camera_from_info(msg, f"{bag}: {options.camera_info_topic}")
    raise InputError(f"{bag}: topic {options.camera_info_topic!r} has no message")
