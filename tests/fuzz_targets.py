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
        line_of = data.count(b"\n", 0, spans[i][0])
        same = [s for s in spans if data.count(b"\n", 0, s[0]) == line_of]
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
    spans, start = [], None
    for i, c in enumerate(data):
        sep = c in b" \t\r\n,:[]{}\""
        if start is None and not sep:
            start = i
        elif start is not None and sep:
            spans.append((start, i))
            start = None
    if start is not None:
        spans.append((start, len(data)))
    return spans


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
    from scope3d.estimators.bundle.synthetic import make_scene

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
    return targets


def huge_header(target: Target) -> bytes:
    """The target's seed with a header that claims about 10^9 elements (rows, points, observations)."""
    seed = target.seed
    if target.name == "image png":
        return _png_claiming_huge_size(seed)
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
    if target.name in ("camera.json", "dataset.json"):
        return seed.replace(b"{", b'{"pad": [' + b"0," * 100000 + b'0], "deep": ' + b"[" * 100000 + b"]" * 100000
                            + b",", 1)
    if target.name.startswith("colmap"):
        return seed + b"\n1 " + b"0 " * 200000 + b"\n"
    return seed * 1000


def _replace_ply_count(seed: bytes) -> bytes:
    head, sep, rest = seed.partition(b"element vertex ")
    count_end = rest.index(b"\n")
    return head + sep + HUGE_COUNT + rest[count_end:]


__all__ = ["FuzzCrash", "MUTATIONS", "Target", "build_targets", "huge_header", "mutate"]
