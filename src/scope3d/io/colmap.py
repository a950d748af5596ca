"""COLMAP sparse models in text form (``cameras.txt``, ``images.txt``, ``points3D.txt``), both ways.

The text format is documented at https://colmap.github.io/format.html. Conventions, and how they map to
scope3d's:

* ``images.txt`` stores ``QW QX QY QZ TX TY TZ`` of ``cam_from_world`` (``x_cam = R x_world + t``), the
  same direction as :class:`scope3d.geometry.pose.Pose`; the translation is in the model's length unit (scope3d
  writes mm).
* COLMAP puts the pixel origin at the top-left *corner* of the image (the centre of the top-left pixel is
  (0.5, 0.5)); scope3d puts it at the centre of the top-left pixel. Principal points and keypoints are
  therefore shifted by +0.5 px when written and by -0.5 px when read.
* A ``pinhole_radial_k1k2`` camera (scope3d's default model) is written as ``RADIAL`` (``f, cx, cy, k1,
  k2``) when ``fx == fy``, else as ``OPENCV`` (``fx, fy, cx, cy, k1, k2, p1, p2``) with ``p1 = p2 = 0``,
  so the two radial terms survive; a camera of a COLMAP-named model (:mod:`scope3d.sensor.camera_models`:
  ``PINHOLE``, ``OPENCV``, ``FULL_OPENCV``, ``OPENCV_FISHEYE``) under its own name with its parameters.
  The circular mask of a scanning-fibre endoscope has no COLMAP equivalent and is dropped.
* The reader accepts ``SIMPLE_PINHOLE``, ``PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``,
  ``FULL_OPENCV`` and ``OPENCV_FISHEYE``. A camera the default model represents (no p1, p2, k3..k6, or
  those zero) is read as ``pinhole_radial_k1k2``, as it always was; the others keep their model.
  Anything else is an InputError.
* Quaternions may be printed with few digits: one whose norm is within rounding of 1
  (:data:`scope3d.geometry.rotation.ROTATION_ROUNDING_TOLERANCE`) is normalised, and ``import_colmap`` records the
  largest normalisation in ``dataset.json`` (``source.quaternion_normalised_max``); others are refused.
* IDs are 1-based in the files and become 0-based list indices in :class:`SparseModel` (in file order
  for cameras and points, in image-ID order for images).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import matrix_to_quaternion, normalised_quaternion, quaternion_to_matrix
from scope3d.io.dataset import write_dataset
from scope3d.io.images import read_image
from scope3d.sensor.camera import SAME_CALIBRATION_PX, Camera, calibration_shift_px
from scope3d.sensor.camera_models import DEFAULT_MODEL, MODELS
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.utils.atomic import atomic_directory

# COLMAP's pixel origin is the image corner; scope3d's is the centre of the top-left pixel.
_COLMAP_PIXEL_OFFSET = 0.5
# Extra distortion terms (p1, p2, k3...) below this are treated as zero when reading OPENCV models.
_NEGLIGIBLE_DISTORTION = 1e-12


@dataclass
class SparseModel:
    """A sparse reconstruction: cameras, posed images and 3D points with their tracks.

    Lengths in mm, world frame; pixels in scope3d's convention (origin at the centre of the top-left
    pixel, u right, v down). Build one directly or with :meth:`from_observations`.

    cameras : list of C :class:`Camera`.
    image_names : list of M str, file names of the images (relative to an image folder).
    poses : list of M :class:`Pose`, ``cam_from_world`` of each image.
    image_cameras : (M,) int, index into ``cameras`` of each image's camera; default all 0.
    points3d : (N, 3) float64, mm, world frame.
    colors : (N, 3) uint8 RGB; default grey 128.
    errors : (N,) float64, mean reprojection error of each point in px; NaN = not computed.
    keypoints : list of M (P_j, 2) float64 arrays, pixels, the 2D points of each image; default empty.
    tracks : list of N (K_i, 2) int64 arrays, rows ``(image index, keypoint index in that image)``:
        the observations of each 3D point. A keypoint belongs to at most one track.
    """

    cameras: list[Camera]
    image_names: list[str]
    poses: list[Pose]
    image_cameras: np.ndarray | None = None
    points3d: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    colors: np.ndarray | None = None
    errors: np.ndarray | None = None
    keypoints: list[np.ndarray] | None = None
    tracks: list[np.ndarray] | None = None

    def __post_init__(self) -> None:
        m = len(self.image_names)
        if len(self.poses) != m:
            raise ValueError(f"{m} image names but {len(self.poses)} poses")
        if not self.cameras:
            raise ValueError("a sparse model needs at least one camera")
        if len(set(self.image_names)) != m:
            raise ValueError("image names must be unique")
        cams = np.zeros(m, np.int64) if self.image_cameras is None else np.asarray(self.image_cameras, np.int64)
        if cams.shape != (m,) or (m and (cams.min() < 0 or cams.max() >= len(self.cameras))):
            raise ValueError(f"image_cameras must be ({m},) indices into {len(self.cameras)} cameras")
        self.image_cameras = cams
        pts = np.asarray(self.points3d, dtype=float).reshape(-1, 3)
        if not np.all(np.isfinite(pts)):
            raise ValueError("points3d has NaN or infinite values")
        n = len(pts)
        self.points3d = pts
        self.colors = (np.full((n, 3), 128, np.uint8) if self.colors is None
                       else np.asarray(self.colors, np.uint8).reshape(n, 3))
        self.errors = np.full(n, np.nan) if self.errors is None else np.asarray(self.errors, float).reshape(n)
        self.keypoints = ([np.zeros((0, 2)) for _ in range(m)] if self.keypoints is None
                          else [np.asarray(k, float).reshape(-1, 2) for k in self.keypoints])
        if len(self.keypoints) != m:
            raise ValueError(f"{m} images but {len(self.keypoints)} keypoint arrays")
        self.tracks = ([np.zeros((0, 2), np.int64) for _ in range(n)] if self.tracks is None
                       else [np.asarray(t, np.int64).reshape(-1, 2) for t in self.tracks])
        if len(self.tracks) != n:
            raise ValueError(f"{n} points but {len(self.tracks)} tracks")
        # checked as arrays: a 1,000-image map's ~10^6 observations as Python tuples in a set took ~10^8 bytes
        obs, owner = _observations(self.tracks)
        sizes = np.array([len(k) for k in self.keypoints], np.int64)
        image, kp = obs[:, 0], obs[:, 1]
        bad = (image < 0) | (image >= m)
        bad[~bad] = (kp[~bad] < 0) | (kp[~bad] >= sizes[image[~bad]])
        if bad.any():
            first = int(np.argmax(bad))
            raise ValueError(f"track of point {owner[first]} refers to keypoint {kp[first]} of image {image[first]}, "
                             "which does not exist")
        key = np.r_[0, np.cumsum(sizes)][image] + kp
        _, first_seen = np.unique(key, return_index=True)
        repeated = np.ones(len(key), bool)
        repeated[first_seen] = False
        if repeated.any():
            first = int(np.argmax(repeated))
            raise ValueError(f"keypoint {kp[first]} of image {image[first]} is in two tracks")

    @classmethod
    def from_observations(
        cls,
        cameras: Camera | list[Camera],
        image_names: list[str],
        poses: list[Pose],
        points3d: np.ndarray,
        image_indices: np.ndarray,
        point_indices: np.ndarray,
        pixels: np.ndarray,
        *,
        image_cameras: np.ndarray | None = None,
        colors: np.ndarray | None = None,
        errors: np.ndarray | None = None,
    ) -> "SparseModel":
        """Build a model from bundle-adjustment style observations.

        image_indices, point_indices : (K,) int, which image saw which point; pixels : (K, 2) float,
        where (scope3d pixel convention). Each observation becomes a keypoint of its image.
        """
        cameras = [cameras] if isinstance(cameras, Camera) else list(cameras)
        image_indices = np.asarray(image_indices, np.int64).reshape(-1)
        point_indices = np.asarray(point_indices, np.int64).reshape(-1)
        pixels = np.asarray(pixels, float).reshape(-1, 2)
        if not (len(image_indices) == len(point_indices) == len(pixels)):
            raise ValueError("image_indices, point_indices and pixels must have the same length")
        n = len(np.asarray(points3d).reshape(-1, 3))
        m = len(image_names)
        if len(image_indices) and (image_indices.min() < 0 or image_indices.max() >= m
                                   or point_indices.min() < 0 or point_indices.max() >= n):
            raise ValueError("observation indices out of range")
        # image j's keypoints are its observations in row order; a track lists its observations by image,
        # then keypoint (both sorts stable)
        by_image = np.argsort(image_indices, kind="stable")
        starts = np.r_[0, np.cumsum(np.bincount(image_indices, minlength=m))]
        keypoints = [pixels[by_image[starts[j]:starts[j + 1]]] for j in range(m)]
        kp_of_row = np.empty(len(by_image), np.int64)
        kp_of_row[by_image] = np.arange(len(by_image)) - np.repeat(starts[:-1], np.diff(starts))
        order = by_image[np.argsort(point_indices[by_image], kind="stable")]
        obs = np.column_stack([image_indices[order], kp_of_row[order]])
        tracks = np.split(obs, np.cumsum(np.bincount(point_indices, minlength=n))[:-1])
        return cls(cameras, list(image_names), list(poses), image_cameras, points3d, colors, errors, keypoints, tracks)

    def observations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All observations as (image_indices (K,), point_indices (K,), pixels (K, 2))."""
        images, points, pixels = [], [], []
        for i, track in enumerate(self.tracks):
            for image, kp in track:
                images.append(image)
                points.append(i)
                pixels.append(self.keypoints[image][kp])
        return (np.array(images, np.int64), np.array(points, np.int64), np.array(pixels, float).reshape(-1, 2))


# --- writing ------------------------------------------------------------------------------------


def _observations(tracks: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Every track's rows (image, keypoint) stacked, (K, 2) int64, and the point each belongs to, (K,)."""
    lengths = np.array([len(t) for t in tracks], np.int64)
    obs = np.concatenate(tracks).astype(np.int64, copy=False) if len(tracks) else np.zeros((0, 2), np.int64)
    return obs.reshape(-1, 2), np.repeat(np.arange(len(tracks)), lengths)


def write_colmap_text(model: SparseModel, out_dir: str | Path) -> Path:
    """Write ``cameras.txt``, ``images.txt`` and ``points3D.txt`` into ``out_dir`` (atomically).

    Readable by COLMAP (``colmap gui``, ``model_converter``) and ``pycolmap.Reconstruction(out_dir)``.
    Lengths are written as they are in the model (mm).
    """
    out_dir = Path(out_dir)
    with atomic_directory(out_dir) as tmp:
        lines = ["# Camera list with one line of data per camera:",
                 "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
                 f"# Number of cameras: {len(model.cameras)}"]
        lines += [camera_line(i + 1, cam) for i, cam in enumerate(model.cameras)]
        (tmp / "cameras.txt").write_text("\n".join(lines) + "\n")

        # the point each keypoint belongs to (-1: none), per image, as arrays (a dict of ~10^6 tuples was ~10^8 bytes)
        obs, owner = _observations(model.tracks)
        offsets = np.r_[0, np.cumsum([len(k) for k in model.keypoints])]
        point_of = np.full(offsets[-1], -1, np.int64)
        point_of[offsets[obs[:, 0]] + obs[:, 1]] = owner
        n_obs = len(obs)
        lines = ["# Image list with two lines of data per image:",
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)",
                 f"# Number of images: {len(model.image_names)}, mean observations per image: "
                 f"{n_obs / max(len(model.image_names), 1):g}"]
        for j, (name, pose) in enumerate(zip(model.image_names, model.poses)):
            if any(c.isspace() for c in name):
                raise ValueError(f"image name {name!r} contains white space, which COLMAP's text format cannot hold")
            qx, qy, qz, qw = matrix_to_quaternion(pose.rotation)
            values = [qw, qx, qy, qz, *pose.translation]
            lines.append(f"{j + 1} " + " ".join(_num(v) for v in values) + f" {model.image_cameras[j] + 1} {name}")
            kps = model.keypoints[j] + _COLMAP_PIXEL_OFFSET
            # POINT3D_ID -1 for a keypoint in no track, as COLMAP writes it
            ids = np.where(point_of[offsets[j]:offsets[j + 1]] >= 0, point_of[offsets[j]:offsets[j + 1]] + 1, -1)
            lines.append(" ".join(f"{_num(u)} {_num(v)} {int(p)}" for (u, v), p in zip(kps, ids)))
        (tmp / "images.txt").write_text("\n".join(lines) + "\n")

        mean_track = n_obs / max(len(model.points3d), 1)
        lines = ["# 3D point list with one line of data per point:",
                 "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
                 f"# Number of points: {len(model.points3d)}, mean track length: {mean_track:g}"]
        for i, (xyz, rgb, err, track) in enumerate(zip(model.points3d, model.colors, model.errors, model.tracks)):
            err_text = "-1" if not math.isfinite(err) else _num(err)  # COLMAP's "not computed"
            lines.append(
                f"{i + 1} " + " ".join(_num(v) for v in xyz) + " " + " ".join(str(int(c)) for c in rgb)
                + f" {err_text} " + " ".join(f"{int(image) + 1} {int(kp)}" for image, kp in track)
            )
        (tmp / "points3D.txt").write_text("\n".join(lines) + "\n")
    return out_dir


def camera_line(camera_id: int, cam: Camera) -> str:
    """One ``cameras.txt`` line: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...`` (principal point shifted to
    COLMAP's pixel corner origin)."""
    cx, cy = cam.cx + _COLMAP_PIXEL_OFFSET, cam.cy + _COLMAP_PIXEL_OFFSET
    if cam.model == DEFAULT_MODEL and cam.fx == cam.fy:
        name, params = "RADIAL", [cam.fx, cx, cy, cam.k1, cam.k2]
    elif cam.model == DEFAULT_MODEL:
        name, params = "OPENCV", [cam.fx, cam.fy, cx, cy, cam.k1, cam.k2, 0.0, 0.0]
    else:
        name, params = cam.lens.colmap_name, [cam.fx, cam.fy, cx, cy, *cam.params[4:]]
    return f"{camera_id} {name} {cam.width} {cam.height} " + " ".join(_num(v) for v in params)


def _num(value: float) -> str:
    # repr is the shortest text that reads back as the same float64: no precision is lost.
    return repr(float(value))


# --- reading ------------------------------------------------------------------------------------

# model name -> (parameter names in COLMAP order)
_CAMERA_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}


def read_colmap_text(model_dir: str | Path, *, length_scale_to_mm: float = 1.0, points: bool = True) -> SparseModel:
    """Read a COLMAP text model. ``points3D.txt`` is optional (an empty point set without it).

    length_scale_to_mm : the model's length unit in mm (1 if it was written by scope3d; 1000 for a
    model in metres). points : False skips ``points3D.txt`` (cameras and poses only: most of a large
    model's reading time is its points). Problems are InputErrors naming the file and line.
    """
    return _read_model(Path(model_dir), length_scale_to_mm, read_points=points)[0]


def read_colmap_cameras(path: str | Path) -> list[Camera]:
    """The cameras of a ``cameras.txt``, in file order (problems are InputErrors naming the file and line)."""
    return _read_cameras(Path(path))[0]


def _read_model(model_dir: Path, length_scale_to_mm: float, *, read_points: bool = True) -> tuple[SparseModel, float]:
    """:func:`read_colmap_text`, also returning the largest ``| |q| - 1 |`` of the quaternions it normalised."""
    if not model_dir.is_dir():
        raise InputError(f"{model_dir}: COLMAP model folder does not exist")
    if not (model_dir / "cameras.txt").is_file() and (model_dir / "cameras.bin").is_file():
        raise InputError(f"{model_dir}: binary COLMAP model; convert it first with "
                         "'colmap model_converter --output_type TXT'")
    cameras, camera_index = _read_cameras(model_dir / "cameras.txt")
    names, poses, image_cameras, keypoints, _, image_index, normalised = _read_images(
        model_dir / "images.txt", camera_index, length_scale_to_mm
    )
    points_path = model_dir / "points3D.txt"
    points, colors, errors, tracks = np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), []
    if read_points and points_path.is_file():
        points, colors, errors, tracks, _ = _read_points(points_path, image_index, keypoints,
                                                                 length_scale_to_mm)
    try:
        model = SparseModel(cameras, names, poses, np.array(image_cameras), points, colors, errors, keypoints, tracks)
    except ValueError as exc:
        raise InputError(f"{points_path}: {exc}") from None
    return model, normalised


def _data_lines(path: Path):
    """(line number, stripped text) for every line, comments included (images.txt needs blank lines)."""
    if not path.is_file():
        raise InputError(f"{path}: file is missing")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    return list(enumerate(text.splitlines(), start=1))


def _floats(path: Path, number: int, tokens: list[str], what: str) -> list[float]:
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        raise InputError(f"{path} line {number}: {what} must be numbers") from None
    if not all(math.isfinite(v) for v in values):
        raise InputError(f"{path} line {number}: {what} has NaN or infinite values")
    return values


def _read_cameras(path: Path) -> tuple[list[Camera], dict[int, int]]:
    cameras, index = [], {}
    for number, line in _data_lines(path):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path} line {number}"
        tokens = line.split()
        if len(tokens) < 4:
            raise InputError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...")
        model = tokens[1]
        if model not in _CAMERA_MODELS:
            raise InputError(f"{where}: camera model {model} is not supported "
                             f"(use one of {', '.join(_CAMERA_MODELS)})")
        names = _CAMERA_MODELS[model]
        if len(tokens) != 4 + len(names):
            raise InputError(f"{where}: {model} has {len(names)} parameters, found {len(tokens) - 4}")
        try:
            camera_id, width, height = int(tokens[0]), int(tokens[2]), int(tokens[3])
        except ValueError:
            raise InputError(f"{where}: CAMERA_ID, WIDTH and HEIGHT must be integers") from None
        p = dict(zip(names, _floats(path, number, tokens[4:], "camera parameters")))
        fx = p.get("fx", p.get("f"))
        fy = p.get("fy", p.get("f"))
        if camera_id in index:
            raise InputError(f"{where}: camera {camera_id} is defined twice")
        p.update(fx=fx, fy=fy, cx=p["cx"] - _COLMAP_PIXEL_OFFSET, cy=p["cy"] - _COLMAP_PIXEL_OFFSET)
        extra = [k for k in ("p1", "p2", "k3", "k4", "k5", "k6") if abs(p.get(k, 0.0)) > _NEGLIGIBLE_DISTORTION]
        kind = model if model == "OPENCV_FISHEYE" or extra else DEFAULT_MODEL
        names = MODELS[kind].param_names
        try:
            cameras.append(Camera.from_params(width, height, kind, [p.get(n, 0.0) for n in names]))
        except ValueError as exc:
            raise InputError(f"{where}: {exc}") from None
        index[camera_id] = len(cameras) - 1
    if not cameras:
        raise InputError(f"{path}: no cameras")
    return cameras, index


def _read_images(path: Path, camera_index: dict[int, int], scale: float):
    lines = _data_lines(path)
    entries = []  # (image_id, name, pose, camera index, keypoints, point3D ids)
    i = 0
    while i < len(lines):
        number, line = lines[i]
        line = line.strip()
        i += 1
        if not line or line.startswith("#"):
            continue
        where = f"{path} line {number}"
        tokens = line.split()
        if len(tokens) < 10:
            raise InputError(f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        try:
            image_id, camera_id = int(tokens[0]), int(tokens[8])
        except ValueError:
            raise InputError(f"{where}: IMAGE_ID and CAMERA_ID must be integers") from None
        qw, qx, qy, qz, tx, ty, tz = _floats(path, number, tokens[1:8], "QW QX QY QZ TX TY TZ")
        try:
            q, normalised = normalised_quaternion([qx, qy, qz, qw])
        except ValueError as exc:
            raise InputError(f"{where}: quaternion is {exc}") from None
        if camera_id not in camera_index:
            raise InputError(f"{where}: camera {camera_id} is not in cameras.txt")
        # The name is the rest of the line (COLMAP writes it last; it cannot contain white space).
        name = " ".join(tokens[9:])
        try:
            pose = Pose(quaternion_to_matrix(q), np.array([tx, ty, tz]) * scale)
        except ValueError as exc:  # finite in the model's unit, beyond float64 in mm
            raise InputError(f"{where}: translation in mm: {exc}") from None
        # The next line holds the 2D points, and may be empty: it is read whatever it holds.
        points_line = lines[i][1].strip() if i < len(lines) else ""
        points_number = lines[i][0] if i < len(lines) else number + 1
        i += 1
        tokens2 = points_line.split()
        if len(tokens2) % 3:
            raise InputError(f"{path} line {points_number}: POINTS2D must be triples X Y POINT3D_ID")
        values = _floats(path, points_number, tokens2, "POINTS2D")
        arr = np.array(values, float).reshape(-1, 3)
        if np.any(arr[:, 2] != np.round(arr[:, 2])):
            raise InputError(f"{path} line {points_number}: POINT3D_ID must be integers")
        entries.append((image_id, name, pose, camera_index[camera_id], arr[:, :2] - _COLMAP_PIXEL_OFFSET,
                        arr[:, 2].astype(np.int64), number, normalised))
    if not entries:
        raise InputError(f"{path}: no images")
    ids = [e[0] for e in entries]
    if len(set(ids)) != len(ids):
        dup = next(e for e in entries if ids.count(e[0]) > 1)
        raise InputError(f"{path} line {dup[6]}: image {dup[0]} is defined twice")
    entries.sort(key=lambda e: e[0])
    image_index = {e[0]: j for j, e in enumerate(entries)}
    return ([e[1] for e in entries], [e[2] for e in entries], [e[3] for e in entries],
            [e[4] for e in entries], [e[5] for e in entries], image_index, max(e[7] for e in entries))


def _read_points(path: Path, image_index: dict[int, int], keypoints: list[np.ndarray], scale: float):
    points, colors, errors, tracks, ids = [], [], [], [], []
    for number, line in _data_lines(path):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path} line {number}"
        tokens = line.split()
        if len(tokens) < 8 or (len(tokens) - 8) % 2:
            raise InputError(f"{where}: expected POINT3D_ID X Y Z R G B ERROR then (IMAGE_ID POINT2D_IDX) pairs")
        x, y, z, r, g, b, err = _floats(path, number, tokens[1:8], "X Y Z R G B ERROR")
        if not all(0 <= c <= 255 and c == round(c) for c in (r, g, b)):
            raise InputError(f"{where}: R G B must be whole numbers from 0 to 255")
        try:
            track = np.array([int(t) for t in tokens[8:]], np.int64).reshape(-1, 2)
            ids.append(int(tokens[0]))
        except (ValueError, OverflowError):  # OverflowError: beyond int64
            raise InputError(f"{where}: POINT3D_ID and track entries must be integers") from None
        for image_id, kp in track:
            if image_id not in image_index:
                raise InputError(f"{where}: track refers to image {image_id}, which is not in images.txt")
            if not 0 <= kp < len(keypoints[image_index[image_id]]):
                raise InputError(f"{where}: track refers to 2D point {kp} of image {image_id}, which has "
                                 f"{len(keypoints[image_index[image_id]])}")
        track[:, 0] = [image_index[i] for i in track[:, 0]]
        points.append((x * scale, y * scale, z * scale))
        colors.append((r, g, b))
        errors.append(np.nan if err < 0 else err)
        tracks.append(track)
    return (np.array(points, float).reshape(-1, 3), np.array(colors, np.uint8).reshape(-1, 3),
            np.array(errors, float), tracks, ids)


# --- import into a dataset -------------------------------------------------------------------------


def import_colmap(
    model_dir: str | Path,
    images_dir: str | Path,
    out_dir: str | Path,
    *,
    tolerance: PoseTolerance | None = None,
    length_scale_to_mm: float = 1.0,
    finish=None,
) -> Path:
    """Turn a COLMAP text model and its image folder into a scope3d dataset (atomically). finish : see
    :func:`scope3d.io.dataset.write_dataset`.

    Every image of ``images.txt`` becomes a frame, in image-ID order, with its ``cam_from_world`` pose
    reported with ``tolerance`` (default exact: COLMAP's poses are taken as given). The model must have
    one camera (or several identical ones): a scope3d dataset has one. Image names with sub-folders are
    flattened (``a/b.png`` -> ``a_b.png``); images that are not PNG are re-encoded as PNG (lossless).
    The 3D points are not part of a dataset and are not imported. ``dataset.json`` records the
    provenance, with the largest normalisation ``| |q| - 1 |`` of a rounded quaternion.
    """
    model_dir, images_dir = Path(model_dir), Path(images_dir)
    if not images_dir.is_dir():
        raise InputError(f"{images_dir}: image folder does not exist")
    model, normalised = _read_model(model_dir, length_scale_to_mm)
    used = sorted(set(model.image_cameras.tolist()))
    camera = model.cameras[used[0]]
    # cameras that differ only by the rounding of K (per-image cameras of one physical camera, each from a
    # decomposed projection matrix) are one: within SAME_CALIBRATION_PX at every pixel, the first one's K
    k_shift = 0.0
    for c in used[1:]:
        other = model.cameras[c]
        shift = calibration_shift_px(other.K, camera.K, camera.width, camera.height)
        if replace(other, fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy) != camera \
                or not shift <= SAME_CALIBRATION_PX:
            raise InputError(f"{model_dir / 'cameras.txt'}: camera #{c + 1} (in the file's order) differs from #{used[0] + 1} "
                             f"(model, size, distortion, or K by {shift:.3g} px, rounding {SAME_CALIBRATION_PX} px "
                             f"at most); the images use {len(used)} different cameras, a scope3d dataset has one")
        k_shift = max(k_shift, shift)
    tolerance = PoseTolerance.exact() if tolerance is None else tolerance
    sources, names = [], []
    seen = {}
    for name in model.image_names:
        source = images_dir / name
        if not source.is_file():
            raise InputError(f"{model_dir / 'images.txt'}: image {name} is not in {images_dir}")
        flat = name.replace("\\", "/").replace("/", "_")
        flat = flat if flat.lower().endswith(".png") else str(Path(flat).with_suffix(".png"))
        if flat in seen:
            raise InputError(f"{model_dir / 'images.txt'}: images {seen[flat]} and {name} would both be "
                             f"stored as frames/{flat}")
        seen[flat] = name
        _check_image_size(source, camera)
        sources.append(source)
        names.append(flat)
    poses = [MeasuredPose(p, tolerance) for p in model.poses]
    metadata = {
        "source": {
            "format": "colmap-text",
            "path": str(model_dir.resolve()),
            "images": str(images_dir.resolve()),
            "length_scale_to_mm": length_scale_to_mm,
            "num_points3D": int(len(model.points3d)),
            "quaternion_normalised_max": normalised,
            "camera_k_shift_max_px": k_shift,
            "original_names": list(model.image_names),
        }
    }
    return write_dataset(out_dir, camera, sources, poses, names=names, metadata=metadata, finish=finish)


def _check_image_size(path: Path, camera: Camera) -> None:
    img = read_image(path)
    if img.shape[:2] != (camera.height, camera.width):
        raise InputError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, the camera is "
                         f"{camera.width}x{camera.height}")
