"""Fuzz targets for every file reader: a valid seed file per reader, byte-level mutations, and the one rule
every outcome must satisfy. Shared by ``tests/test_fuzz_readers.py`` (short hypothesis runs) and
``benchmarks/bench_fuzz.py`` (long hypothesis and atheris runs).

A target builds its seed files once in a folder (``build(root) -> Target``); ``Target.run(data)`` writes
``data`` over the mutated file and calls the reader. The only acceptable outcomes are a normal return or
one :class:`InputError` whose single-line message names the mutated file (or, for a reader of a whole
folder, that folder). Anything else (another exception type, a multi-line message, a message naming
no file) is a crash, raised as :class:`FuzzCrash`.
"""
from __future__ import annotations

import bisect
import json
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from scope3d.errors import InputError

# --- mutations -------------------------------------------------------------------------------------

# Replacements for one token: huge, tiny, non-finite, negative, integer overflow, empty, not a number.
NASTY_TOKENS = (
    b"1e308", b"-1e308", b"1e999", b"-1e999", b"nan", b"NaN", b"inf", b"-inf", b"Infinity", b"1000000000",
    b"-1", b"0", b"-0", b"99999999999999999999999999", b"1" * 5000, b"0x10", b"", b"1.5", b"1,5", b"--5",
    b"\xff\xfe", b"\xc3(", b"\x00", b"null", b"true", b"[]", b"{}", b'"x"', b"1e-320", b"4294967296",
)
# A header count that, believed, would allocate about 10^9 elements.
HUGE_COUNT = b"1000000000"


def mutate(data: bytes, kind: str, a: float, b: float, pick: int) -> bytes:
    """One mutation of ``data``. ``a``, ``b`` in [0, 1) choose positions; ``pick`` chooses a replacement.

    kind : truncate, bitflip, swap_tokens (swapped columns), swap_lines, nasty_token (huge numbers,
    NaN/inf, ...), non_utf8 (a stray byte), empty, huge_count (the first integer becomes 10^9),
    delete_line, duplicate_line, insert_bytes.
    """
    n = len(data)
    if kind == "empty":
        return b""
    if kind == "truncate":
        return data[: int(a * n)]
    if kind == "bitflip":
        if not n:
            return data
        i = int(a * n)
        return data[:i] + bytes([data[i] ^ (1 << (pick % 8))]) + data[i + 1 :]
    if kind == "non_utf8":
        i = int(a * (n + 1))
        return data[:i] + bytes([(0x80, 0xFF, 0xFE, 0xC3, 0xE9)[pick % 5]]) + data[i:]
    if kind == "insert_bytes":
        i = int(a * (n + 1))
        return data[:i] + bytes((pick * 37 + k * 101) % 256 for k in range(1 + pick % 16)) + data[i:]
    lines = data.split(b"\n")
    if kind in ("swap_lines", "delete_line", "duplicate_line"):
        i, j = int(a * len(lines)), int(b * len(lines))
        if kind == "swap_lines":
            lines[i], lines[j] = lines[j], lines[i]
        elif kind == "delete_line":
            del lines[i]
        else:
            lines.insert(j, lines[i])
        return b"\n".join(lines)
    spans = _token_spans(data)
    if not spans:
        return data
    if kind == "swap_tokens":  # two fields of one line: a swapped column
        i = int(a * len(spans))
        line_start = data.rfind(b"\n", 0, spans[i][0]) + 1
        line_end = data.find(b"\n", spans[i][0]) % (n + 1)  # -1 (the last line) becomes n
        starts = [start for start, _ in spans]
        same = spans[bisect.bisect_left(starts, line_start) : bisect.bisect_left(starts, line_end)]
        j = same[int(b * len(same))]
        (s0, e0), (s1, e1) = sorted([spans[i], j])
        if s0 == s1:
            return data
        return data[:s0] + data[s1:e1] + data[e0:s1] + data[s0:e0] + data[e1:]
    if kind == "nasty_token":
        s, e = spans[int(a * len(spans))]
        return data[:s] + NASTY_TOKENS[pick % len(NASTY_TOKENS)] + data[e:]
    if kind == "huge_count":
        for s, e in spans:
            if data[s:e].isdigit():
                return data[:s] + HUGE_COUNT + data[e:]
        return data
    raise ValueError(f"unknown mutation {kind}")


MUTATIONS = ("truncate", "bitflip", "swap_tokens", "swap_lines", "nasty_token", "non_utf8", "empty",
             "huge_count", "delete_line", "duplicate_line", "insert_bytes")


def _token_spans(data: bytes) -> list[tuple[int, int]]:
    """(start, end) of every run of bytes that is not white space, a comma, a quote or a bracket."""
    # one regular expression, not a Python loop over the bytes: the loop was most of a mutation's time on
    # the larger seeds (a 28 kB ROS 2 bag: 2 ms of the 17 ms an input took)
    return [match.span() for match in _TOKEN.finditer(data)]


_TOKEN = re.compile(rb'[^ \t\r\n,:\[\]{}"]+')


# --- the outcome rule ------------------------------------------------------------------------------


class FuzzCrash(AssertionError):
    """A reader's outcome on a mutated file that the rule does not accept."""


@dataclass
class Target:
    """One reader under test. ``path`` is the file mutated; ``call`` reads it (or its folder)."""

    name: str
    path: Path
    seed: bytes
    call: Callable[[], object]
    names: Path  # what an InputError's message must name: the file, or the folder the reader was given

    def run(self, data: bytes) -> str:
        """Write ``data`` as the file, read it; 'ok' or 'refused', else raise FuzzCrash."""
        self.path.write_bytes(data)
        try:
            self.call()
        except InputError as exc:
            message = str(exc)
            if "\n" in message or str(self.names) not in message:
                raise FuzzCrash(f"{self.name}: InputError not one line naming {self.names}: {message!r}") from exc
            return "refused"
        except Exception as exc:  # the crash the rule forbids
            raise FuzzCrash(f"{self.name}: {type(exc).__name__}: {exc}") from exc
        return "ok"

    def restore(self) -> None:
        self.path.write_bytes(self.seed)


# --- seed files ------------------------------------------------------------------------------------


def _tiny_dataset(root: Path) -> Path:
    from scope3d.geometry.pose import Pose
    from scope3d.geometry.rotation import look_at
    from scope3d.io.dataset import write_dataset
    from scope3d.sensor.camera import Camera
    from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance

    rng = np.random.default_rng(0)
    camera = Camera(32, 24, 30.0, 31.0, 15.5, 11.5, k1=-0.1, k2=0.01, mask_radius_px=12.0)
    tol = PoseTolerance.from_degrees([0.25, 0.25, 0.5], [0.1, 0.1, 0.2])
    measured = []
    for i in range(3):
        centre = np.array([50.0 * np.sin(0.3 * i), 5.0, -50.0 * np.cos(0.3 * i)])
        measured.append(MeasuredPose(Pose.from_centre(look_at(centre, np.zeros(3)), centre), tol))
    frames = [rng.integers(0, 255, (24, 32, 3), dtype=np.uint8) for _ in range(3)]
    return write_dataset(root, camera, frames, measured)


def _tiny_bal_text() -> bytes:
    from scope3d.phantoms.bundle_scene import make_scene

    scene = make_scene(3, 4, observations_per_point=2, seed=0)
    lines = [f"3 4 {len(scene.camera_index)}"]
    for c, p, (u, v) in zip(scene.camera_index, scene.point_index, scene.observations_px):
        lines.append(f"{c} {p} {u - 320:.6e} {240 - v:.6e}")
    for rot, t in zip(scene.rotations, scene.translations):
        from scope3d.geometry.rotation import matrix_to_rotvec

        flip = np.array([1.0, -1.0, -1.0])
        w = matrix_to_rotvec(flip[:, None] * rot)
        lines += [f"{x:.16e}" for x in (*w, *(flip * t), 500.0, 0.0, 0.0)]
    lines += [f"{x:.16e}" for x in scene.points.ravel()]
    return ("\n".join(lines) + "\n").encode()


BOUNDS_SEED = b"""# gauge
camera 0 all fixed
camera * k1,k2 -1e-6 1e-6
camera 1-2 translation +- 0.05
point 0,2 x,y -100 100
depth 3 0 0 0 0 0 1 1 50
shell * 0 0 0 1 500
"""

PAR_SEED = b"""2
a.png 1520.4 0 302.32 0 1525.9 246.87 0 0 1 0.877582561890 -0.479425538604 0 0.479425538604 0.877582561890 0 0 0 1 0.02 0.01 0.61
b.png 1520.4 0 302.32 0 1525.9 246.87 0 0 1 1 0 0 0 1 0 0 0 1 0 0 0.6
"""

README_SEED = b"""templeSparseRing
The bounding box of the object is (-0.073568 0.021728 -0.012445) - (0.028855 0.181892 0.062736)
"""


def _ply_seed(binary: bool, mesh: bool) -> bytes:
    import tempfile

    from scope3d.io.ply import write_ply
    from scope3d.scene.mesh import Mesh, PointCloud

    rng = np.random.default_rng(1)
    pts = rng.normal(size=(6, 3))
    if not binary:
        header = ["ply", "format ascii 1.0", "element vertex 4", "property float x", "property float y",
                  "property float z", "property uchar red", "property uchar green", "property uchar blue",
                  "element face 2", "property list uchar int vertex_indices", "end_header"]
        body = ["0 0 0 255 0 0", "1 0 0 0 255 0", "0 1 0 0 0 255", "1 1 0.5 9 9 9", "3 0 1 2", "4 0 1 3 2"]
        return ("\n".join(header + body) + "\n").encode()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "s.ply"
        if mesh:
            write_ply(path, Mesh(pts, np.array([[0, 1, 2], [2, 3, 4], [3, 4, 5]])))
        else:
            write_ply(path, PointCloud(pts, rng.integers(0, 255, (6, 3), dtype=np.uint8)))
        return path.read_bytes()


def _colmap_seed(root: Path) -> Path:
    from scope3d.geometry.pose import Pose
    from scope3d.geometry.rotation import look_at
    from scope3d.io.colmap import SparseModel, write_colmap_text
    from scope3d.sensor.camera import Camera

    rng = np.random.default_rng(2)
    camera = Camera(64, 48, 60.0, 60.0, 31.5, 23.5, k1=-0.05)
    poses = []
    for i in range(3):
        centre = np.array([5.0 * i, 0.0, -50.0])
        poses.append(Pose.from_centre(look_at(centre, np.zeros(3)), centre))
    points = rng.normal(size=(4, 3))
    image_idx = np.repeat(np.arange(3), 4)
    point_idx = np.tile(np.arange(4), 3)
    pixels = rng.uniform(0, 40, (12, 2))
    model = SparseModel.from_observations(camera, ["a.png", "b.png", "c.png"], poses, points, image_idx,
                                          point_idx, pixels)
    return write_colmap_text(model, root)


def _png_seed() -> bytes:
    rng = np.random.default_rng(3)
    ok, buf = cv2.imencode(".png", rng.integers(0, 255, (12, 16, 3), dtype=np.uint8))
    return buf.tobytes()


def _jpeg_seed() -> bytes:
    board = np.kron((np.indices((3, 4)).sum(axis=0) % 2) * 255, np.ones((4, 4))).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", board, [cv2.IMWRITE_JPEG_QUALITY, 90])
    return buf.tobytes()


def _jpeg_claiming_huge_size(seed: bytes) -> bytes:
    """The seed JPEG with its frame header (SOF0) saying 60,000 x 60,000 pixels (3.6 Gpx)."""
    at = seed.index(b"\xff\xc0") + 5  # marker, length (2), precision (1): then height, width
    return seed[:at] + struct.pack(">HH", 60000, 60000) + seed[at + 4:]


def _png_claiming_huge_size(seed: bytes) -> bytes:
    """The seed PNG with its IHDR saying 10^5 x 10^5 pixels (40 GB of RGB), its CRC made right again."""
    import zlib

    ihdr = bytearray(seed[8 : 8 + 25])
    ihdr[8:16] = struct.pack(">II", 100000, 100000)
    ihdr[21:25] = struct.pack(">I", zlib.crc32(bytes(ihdr[4:21])) & 0xFFFFFFFF)
    return seed[:8] + bytes(ihdr) + seed[33:]


def build_targets(root: Path) -> dict[str, Target]:
    """Every reader's target, with its seed files written under ``root``."""
    from scope3d.estimators.bundle import apply_bounds_file, bal_to_problem, read_bal
    from scope3d.io.camera_json import read_camera_json
    from scope3d.io.colmap import read_colmap_text
    from scope3d.io.dataset import load_dataset
    from scope3d.io.images import read_image
    from scope3d.io.middlebury import read_middlebury_bounding_box, read_middlebury_par
    from scope3d.io.ply import read_ply
    from scope3d.io.poses_csv import read_poses_csv

    root.mkdir(parents=True, exist_ok=True)
    targets = {}

    def add(name, path, seed, call, names=None):
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(seed)
        targets[name] = Target(name, path, seed, call, names or path)

    ds = _tiny_dataset(root / "dataset")
    add("dataset.json", ds / "dataset.json", (ds / "dataset.json").read_bytes(),
        lambda: load_dataset(ds, check_images=True))
    add("poses.csv", root / "poses" / "poses.csv", (ds / "poses.csv").read_bytes(),
        lambda: read_poses_csv(root / "poses" / "poses.csv"))
    add("camera.json", root / "camera" / "camera.json", (ds / "camera.json").read_bytes(),
        lambda: read_camera_json(root / "camera" / "camera.json"))
    bal_path = root / "bal" / "problem.txt"
    add("bal", bal_path, _tiny_bal_text(), lambda: bal_to_problem(read_bal(bal_path)))
    bounds_problem_bal = read_bal(bal_path)
    bounds_path = root / "bounds" / "bounds.txt"
    add("bounds", bounds_path, BOUNDS_SEED,
        lambda: apply_bounds_file(bal_to_problem(bounds_problem_bal), bounds_path))
    colmap = _colmap_seed(root / "colmap")
    for file in ("cameras.txt", "images.txt", "points3D.txt"):
        add(f"colmap {file}", colmap / file, (colmap / file).read_bytes(), lambda: read_colmap_text(colmap),
            names=colmap)
    for name, binary, mesh in (("ply ascii", False, True), ("ply binary cloud", True, False),
                               ("ply binary mesh", True, True)):
        path = root / name.replace(" ", "_") / "m.ply"
        add(name, path, _ply_seed(binary, mesh), lambda p=path: read_ply(p))
    par = root / "middlebury" / "set_par.txt"
    add("middlebury par", par, PAR_SEED, lambda: read_middlebury_par(par))
    readme = root / "middlebury" / "README.txt"
    add("middlebury readme", readme, README_SEED, lambda: read_middlebury_bounding_box(readme))
    png = root / "image" / "f.png"
    add("image png", png, _png_seed(), lambda: (read_image(png), read_image(png, grey=True)))
    jpeg = root / "image" / "board.jpg"  # calibration boards and scope frames come as JPEG too
    add("image jpeg", jpeg, _jpeg_seed(), lambda: (read_image(jpeg), read_image(jpeg, grey=True)))
    _add_later_readers(root, add)
    return targets


# --- the readers that landed later: tracker, ROS bags, video, scan plans, intrinsic bounds, quadrants, map
# points, the hand-eye robot poses, report.json ----------------------------------------------------------


def _tracker_rows() -> list[list]:
    """An NDI Track table: a header, three tool rows (one with the tool missing and garbage in its pose
    fields, as NDI writes it) and three markers (one missing in the last row)."""
    header = ["Port", "Tool", "Frame", "Face", "State", "Q0", "Qx", "Qy", "Qz", "Tx", "Ty", "Tz", "Error",
              "Markers"] + ["State", "Tx", "Ty", "Tz"] * 3
    rows = [header]
    for k in range(3):
        ok = k != 1
        pose = [0.7071, 0.0, 0.7071, 0.0, 10.5 + k, -3.25, 1200.0] if ok else [1e28, -3e27, 0, 0, 123456.0, 0, 0]
        row = [1, "plate", 1000 + k, 1, "OK" if ok else "Missing", *pose, 0.12, 3]
        for m in range(3):
            row += ["Missing", "nan", "", "-1e30"] if (k == 2 and m == 0) else ["OK", 10.0 * m, 5.0 - k, 1190.0 + m]
        rows.append(row)
    return rows


def _tracker_csv_seed() -> bytes:
    return ("\n".join(",".join(str(c) for c in row) for row in _tracker_rows()) + "\n").encode()


def _tracker_xlsx_seed() -> bytes:
    import io

    import openpyxl

    book = openpyxl.Workbook()
    for row in _tracker_rows():
        book.active.append(row)
    buffer = io.BytesIO()
    book.save(buffer)
    return buffer.getvalue()


def _rosbag_seed(path: Path, *, ros1: bool) -> Path:
    """A bag with two 16 x 12 frames (one raw bgr8, one PNG-compressed on a second topic), camera info and
    three PoseStamped samples, stamped so that each frame has a pose within 5 ms."""
    from rosbags.typesys import Stores, get_typestore

    from scope3d.geometry.rotation import look_at, matrix_to_quaternion

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types = store.types
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import Writer

        writer = Writer(path, version=8)
    t0 = 1_700_000_000 * 1_000_000_000

    def header(ns):
        stamp = types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        return types["std_msgs/msg/Header"](stamp=stamp, frame_id="scope", **({"seq": 0} if ros1 else {}))

    rng = np.random.default_rng(4)
    with writer:
        c_img = writer.add_connection("/image", "sensor_msgs/msg/Image", typestore=store)
        c_info = writer.add_connection("/info", "sensor_msgs/msg/CameraInfo", typestore=store)
        c_pose = writer.add_connection("/pose", "geometry_msgs/msg/PoseStamped", typestore=store)
        for k in range(3):
            ns = t0 + k * 50_000_000
            centre = np.array([0.01 * k, 0.0, -0.05])
            x, y, z, w = matrix_to_quaternion(look_at(centre, np.zeros(3)).T)  # world_from_cam
            pose = types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](x=centre[0], y=centre[1], z=centre[2]),
                orientation=types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))
            msg = types["geometry_msgs/msg/PoseStamped"](header=header(ns), pose=pose)
            writer.write(c_pose, ns, serialize(msg, "geometry_msgs/msg/PoseStamped"))
        for k in range(2):
            ns = t0 + k * 50_000_000 + 2_000_000
            frame = rng.integers(0, 255, (12, 16, 3), dtype=np.uint8)
            msg = types["sensor_msgs/msg/Image"](header=header(ns), height=12, width=16, encoding="bgr8",
                                                 is_bigendian=0, step=48, data=frame.ravel())
            writer.write(c_img, ns, serialize(msg, "sensor_msgs/msg/Image"))
            k_matrix = np.array([20.0, 0, 7.5, 0, 20.0, 5.5, 0, 0, 1])
            fields = {"D" if ros1 else "d": np.zeros(5), "K" if ros1 else "k": k_matrix,
                      "R" if ros1 else "r": np.eye(3).ravel(), "P" if ros1 else "p": np.zeros(12)}
            info = types["sensor_msgs/msg/CameraInfo"](
                header=header(ns), height=12, width=16, distortion_model="plumb_bob", binning_x=0, binning_y=0,
                roi=types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                             do_rectify=False), **fields)
            writer.write(c_info, ns, serialize(info, "sensor_msgs/msg/CameraInfo"))
    return path


def _video_seed(root: Path) -> bytes:
    from scope3d.io.video import write_video

    rng = np.random.default_rng(5)
    base = rng.integers(0, 255, (24, 40, 3), dtype=np.uint8)
    path = write_video(root / "seed.mp4", [np.roll(base, 2 * k, axis=1)[:, :32].copy() for k in range(4)], 10.0)
    data = path.read_bytes()
    path.unlink()
    return data


def _plan_seed(root: Path) -> bytes:
    from scope3d.geometry.pose import Pose
    from scope3d.geometry.rotation import look_at
    from scope3d.io.scan_plan import write_scan_plan

    poses = [Pose.from_centre(look_at(np.array([c, 1.0, -20.0]), np.zeros(3)), np.array([c, 1.0, -20.0]))
             for c in (0.0, 4.0, 8.0)]
    path = root / "seed_plan.json"
    write_scan_plan(path, poses, [0, 0, 1], 70.0, wall_points_mm=np.zeros((3, 3)), bend_deg=[0.0, 5.0, 10.0],
                    info={"coverage_fraction": 0.5, "standoff_mm": 20.0})
    data = path.read_bytes()
    path.unlink()
    return data


def _intrinsic_bounds_seed(root: Path) -> bytes:
    from scope3d.io.intrinsic_bounds import write_intrinsic_bounds

    path = root / "seed_bounds.json"
    write_intrinsic_bounds(path, np.array([228.6, 228.1, 159.5, 119.5, -0.1, 0.01]),
                           np.array([0.09, 0.08, 0.3, 0.3, 1e-3, 1e-4]), 3.0, source="fuzz seed")
    data = path.read_bytes()
    path.unlink()
    return data


QUADRANT_FRAMES = ["0000.png", "0001.png", "0002.png", "0003.png"]
QUADRANTS_SEED = (b'{"angle_step_deg": 90, "step_mm": 0.1, "side_view_deg": 45, "quadrants": ['
                  b'{"index": 0, "angle_deg": 0, "frames": ["0000.png", "0001.png"]}, '
                  b'{"index": 1, "angle_deg": 90.0, "frames": ["0002.png", "0003.png"]}]}\n')


def _map_points_seed(root: Path) -> bytes:
    from scope3d.io.map_points import MapPoints, write_map_points

    rng = np.random.default_rng(6)
    path = root / "seed_map_points.npz"
    write_map_points(path, MapPoints(rng.normal(size=(3, 3)), rng.uniform(0, 200, (3, 128)).astype(np.float32),
                                     np.array([2, 3, 2], np.int32), rng.integers(0, 255, (3, 3), dtype=np.uint8)))
    data = path.read_bytes()
    path.unlink()
    return data


REPORT_SEED = json.dumps({
    "dataset": "no_such_dataset", "pose_mode": "bcba", "n_frames": 3, "n_points": 2, "time_s": 1.5,
    "mean_reprojection_error_px": 0.41, "surface_error_mm": {"direct": {"mean": 0.2, "within_1mm_fraction": 0.97}},
    "targets": [{"label": 1, "centroid_mm": [1.0, 2.0, 3.0], "size_mm": 2.5, "area_mm2": 4.0}],
    "targets_vs_truth": [{"name": "#1", "true_centre_mm": [1.0, 2.0, 3.1], "true_size_mm": 2.4}],
    "timings_s": {"features": 0.5, "bundle": 1.0}, "unused_frames": ["0002.png"],
}, indent=1).encode()


def _add_later_readers(root: Path, add) -> None:
    from scope3d.io.intrinsic_bounds import read_intrinsic_bounds
    from scope3d.io.map_points import read_map_points
    from scope3d.io.quadrants import read_quadrants
    from scope3d.io.rosbag import RosbagOptions, import_rosbag
    from scope3d.io.scan_plan import read_scan_plan
    from scope3d.io.tracker import read_tracker
    from scope3d.io.video import DecodeCheck, probe_video, read_video
    from scope3d.pipelines.hand_eye import robot_flange_poses
    from scope3d.report import build_page

    csv = root / "tracker" / "ndi.csv"
    add("tracker csv", csv, _tracker_csv_seed(), lambda: read_tracker(csv))
    xlsx = root / "tracker" / "ndi.xlsx"
    add("tracker xlsx", xlsx, _tracker_xlsx_seed(), lambda: read_tracker(xlsx))

    options = RosbagOptions(image_topic="/image", pose_topic="/pose", camera_info_topic="/info", slop_s=0.005)
    (root / "rosbag").mkdir(parents=True, exist_ok=True)
    bag1 = _rosbag_seed(root / "rosbag" / "seed.bag", ros1=True)
    add("rosbag ros1", bag1, bag1.read_bytes(), lambda: import_rosbag(bag1, root / "rosbag" / "out1", options=options))
    bag2 = _rosbag_seed(root / "rosbag" / "seed2", ros1=False)
    storage = next(p for p in bag2.iterdir() if p.name != "metadata.yaml")
    for name, file in (("rosbag2 metadata.yaml", bag2 / "metadata.yaml"), ("rosbag2 storage", storage)):
        add(name, file, file.read_bytes(), lambda: import_rosbag(bag2, root / "rosbag" / "out2", options=options),
            names=bag2)

    video = root / "video" / "v.mp4"
    (root / "video").mkdir(parents=True, exist_ok=True)
    add("video mp4", video, _video_seed(root / "video"),
        lambda: (probe_video(video), list(read_video(video, check=DecodeCheck()))))
    plan = root / "plan" / "plan.json"
    (root / "plan").mkdir(parents=True, exist_ok=True)
    add("scan plan", plan, _plan_seed(root / "plan"), lambda: read_scan_plan(plan))
    bounds = root / "intrinsic_bounds" / "intrinsic_bounds.json"
    (root / "intrinsic_bounds").mkdir(parents=True, exist_ok=True)
    add("intrinsic bounds", bounds, _intrinsic_bounds_seed(root / "intrinsic_bounds"),
        lambda: read_intrinsic_bounds(bounds))
    quadrants = root / "quadrants" / "quadrants.json"
    add("quadrants", quadrants, QUADRANTS_SEED, lambda: read_quadrants(quadrants.parent, QUADRANT_FRAMES))
    points = root / "map" / "map_points.npz"
    (root / "map").mkdir(parents=True, exist_ok=True)
    add("map points", points, _map_points_seed(root / "map"), lambda: read_map_points(points))
    robot = root / "hand_eye" / "robot_poses.csv"
    add("hand-eye robot poses", robot, (root / "dataset" / "poses.csv").read_bytes(), lambda: robot_flange_poses(robot))
    report = root / "report" / "report.json"
    add("report.json", report, REPORT_SEED, lambda: build_page(report.parent))
    _add_robot_log_readers(root, add)


ROBOT_LOG_SEED = (b"t,x,y,z,qx,qy,qz,qw\n"
                  + b"".join(b"%.4f,%.6f,0.0125,-0.002,0.0,0.0,%.9f,%.9f\n" % (i / 250, 0.001 * i, np.sin(i / 50),
                                                                             np.cos(i / 50)) for i in range(12)))
MATRIX_LOG_SEED = (b"stamp," + b",".join(b"m%d%d" % (i, j) for i in range(4) for j in range(4)) + b"\n"
                   + b"".join(b"%d,1,0,0,%d,0,1,0,2,0,0,1,3,0,0,0,1\n" % (1000 * i, i) for i in range(6)))
FRAME_TIMES_SEED = b"image,t\n" + b"".join(b"f%d.png,%.4f\n" % (i, i / 30) for i in range(6))
HAND_EYE_SEED = (b'{"flange_from_cam": {"rotation": [[0, -1, 0], [1, 0, 0], [0, 0, 1]], "translation_mm": [1.5, -2, 40]},'
                 b' "rms_px": 0.2}')


def _add_robot_log_readers(root: Path, add) -> None:
    """The readers of ``scope3d import frames``: a robot's pose log in two layouts, a frame-time table and
    hand_eye.json."""
    from scope3d.io.hand_eye_json import read_hand_eye_json
    from scope3d.io.robot_log import PoseLogFormat, read_frame_times, read_pose_log

    log = root / "robot_log" / "log.csv"
    add("robot log", log, ROBOT_LOG_SEED, lambda: read_pose_log(log, PoseLogFormat(length_unit="m")))
    matrix = root / "robot_log" / "matrix.csv"
    add("robot log matrix44", matrix, MATRIX_LOG_SEED, lambda: read_pose_log(
        matrix, PoseLogFormat("matrix44", columns={"t": "stamp"}, time_unit="ms", drop_bad_rows=True)))
    times = root / "robot_log" / "frame_times.csv"
    add("frame times", times, FRAME_TIMES_SEED, lambda: read_frame_times(times))
    hand_eye = root / "robot_log" / "hand_eye.json"
    add("hand_eye.json", hand_eye, HAND_EYE_SEED, lambda: read_hand_eye_json(hand_eye))


def huge_header(target: Target) -> bytes:
    """The target's seed with a header that claims about 10^9 elements (rows, points, observations)."""
    seed = target.seed
    if target.name == "image png":
        return _png_claiming_huge_size(seed)
    if target.name == "image jpeg":
        return _jpeg_claiming_huge_size(seed)
    if target.name.startswith("ply"):
        return _replace_ply_count(seed)
    if target.name == "bal":
        return b"1000000000 1000000000 1000000000" + seed[seed.index(b"\n") :]
    if target.name == "middlebury par":
        return HUGE_COUNT + seed[seed.index(b"\n") :]
    if target.name == "bounds":
        return seed + b"point 0-999999999999 x,y,z fixed\ncamera 0-1000000000000 f fixed\n"
    if target.name == "poses.csv":
        return seed + b"\n" * 1000 + b"x" + b"," * 100000 + b"\n"
    if target.name == "tracker csv":  # a row announcing 10^9 markers
        lines = seed.split(b"\n")
        cells = lines[1].split(b",")
        cells[13] = HUGE_COUNT
        return b"\n".join([lines[0], b",".join(cells), *lines[2:]])
    if target.name == "tracker xlsx":
        return _xlsx_claiming_a_million_rows(seed)
    if target.name == "rosbag ros1":  # the bag header's chunk and connection counts
        for field in (b"chunk_count=", b"conn_count="):
            at = seed.index(field) + len(field)
            seed = seed[:at] + struct.pack("<I", 10**9) + seed[at + 4:]
        return seed
    if target.name == "rosbag2 metadata.yaml":
        return re.sub(rb"message_count: \d+", b"message_count: " + HUGE_COUNT, seed)
    if target.name == "rosbag2 storage":  # SQLite's page count (advisory: SQLite trusts the file's size)
        return seed[:28] + struct.pack(">I", 10**9) + seed[32:]
    if target.name == "video mp4":  # the sample table claims 10^9 frames
        at = seed.index(b"stsz") + 12
        return seed[:at] + struct.pack(">I", 10**9) + seed[at + 4:]
    if target.name == "map points":
        return _npz_claiming_a_billion_points(seed)
    if target.name in ("camera.json", "dataset.json", "scan plan", "intrinsic bounds", "quadrants", "report.json",
                       "hand_eye.json"):
        return seed.replace(b"{", b'{"pad": [' + b"0," * 100000 + b'0], "deep": ' + b"[" * 100000 + b"]" * 100000
                            + b",", 1)
    if target.name.startswith("colmap"):
        return seed + b"\n1 " + b"0 " * 200000 + b"\n"
    return seed * 1000


def _xlsx_claiming_a_million_rows(seed: bytes) -> bytes:
    """The seed workbook with its sheet's ``<dimension>`` saying A1:XFD1048576: believed, every row is
    padded to 16,384 cells and a million empty rows are added (1.7 * 10^10 cells from a 5 kB file)."""
    import io
    import zipfile

    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(seed)) as source, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as dest:
        for info in source.infolist():
            data = source.read(info)
            if info.filename.startswith("xl/worksheets/"):
                data = re.sub(rb'<dimension ref="[^"]*"', b'<dimension ref="A1:XFD1048576"', data)
            dest.writestr(info.filename, data)
    return out.getvalue()


def _npz_claiming_a_billion_points(seed: bytes) -> bytes:
    """The map points' archive with ``xyz_mm.npy``'s header saying (10^9, 3): 24 GB of float64."""
    import io
    import zipfile

    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(seed)) as source, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as dest:
        for info in source.infolist():
            data = source.read(info)
            if info.filename == "xyz_mm.npy":
                head = data[: data.index(b"\n") + 1]
                claimed = head.replace(b"(3, 3)", b"(1000000000, 3)")
                claimed = claimed.replace(b" " * 9 + b"\n", b"\n", 1)  # keep the header's length
                data = claimed + data[len(head):]
            dest.writestr(info.filename, data)
    return out.getvalue()


def _replace_ply_count(seed: bytes) -> bytes:
    head, sep, rest = seed.partition(b"element vertex ")
    count_end = rest.index(b"\n")
    return head + sep + HUGE_COUNT + rest[count_end:]


__all__ = ["FuzzCrash", "MUTATIONS", "Target", "build_targets", "huge_header", "mutate"]
