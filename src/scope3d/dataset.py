"""Datasets on disk: frames, reported poses with tolerances, camera intrinsics, optional ground truth.

Folder layout (all lengths in millimetres, angles in degrees in files)::

    DATASET/
      dataset.json        {"format": "scope3d-dataset", "version": 1, "length_unit": "mm", "name": ..., "scene": {...}}
      camera.json         {"width", "height", "fx", "fy", "cx", "cy", "k1", "k2", "mask_radius_px" (or null)}
      poses.csv           one row per frame, in frame order (columns below)
      frames/             reflectance images named in poses.csv (PNG, grey or colour)
      fluorescence/       optional: fluorescence images with the same names
      ground_truth/       optional, written by the phantom lab
        poses.csv         the true poses (tolerance columns 0)
        surface.ply       the true surface, a triangle mesh in mm
        depth/NAME.npy    optional (H, W) float32 z-depth in mm of each frame, NaN where no surface
        scene.json        scene parameters (targets, thread profile, ...)

``poses.csv`` columns::

    image, x_mm, y_mm, z_mm, qw, qx, qy, qz, tol_x_mm, tol_y_mm, tol_z_mm, tol_rx_deg, tol_ry_deg, tol_rz_deg

``x, y, z`` is the camera centre in the world; ``(qw, qx, qy, qz)`` is the camera's orientation in the
world (the rotation ``world_from_cam``, a unit quaternion), as a robot or tracker reports it. The
``tol_*_mm`` columns bound the true centre per world axis; ``tol_r*_deg`` bound a small rotation about
the camera's own x, y, z axes (``R_true = exp([w]x) R_measured`` for ``cam_from_world``). Tolerance 0
means exact, ``inf`` means unknown. ``dataset.json``'s ``length_unit`` may be ``mm``, ``cm``, ``m`` or
``um``; lengths are converted to mm when loading.
"""
from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .atomic import atomic_directory, atomic_file
from .camera import Camera
from .errors import InputError
from .geometry import matrix_to_quaternion, quaternion_to_matrix
from .mesh import Mesh, read_ply, write_ply
from .pose import MeasuredPose, Pose, PoseTolerance

POSE_COLUMNS = (
    "image", "x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz",
    "tol_x_mm", "tol_y_mm", "tol_z_mm", "tol_rx_deg", "tol_ry_deg", "tol_rz_deg",
)
LENGTH_UNITS_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "um": 1e-3}
CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "k1", "k2")
_QUATERNION_NORM_TOLERANCE = 1e-3


@dataclass(frozen=True)
class GroundTruth:
    """What the phantom lab knows exactly. poses : true ``cam_from_world`` per frame; surface : mesh in mm."""

    poses: list[Pose] | None = None
    surface_path: Path | None = None
    depth_paths: list[Path] | None = None
    scene: dict = field(default_factory=dict)

    def surface(self) -> Mesh:
        if self.surface_path is None:
            raise InputError("dataset has no ground-truth surface")
        mesh = read_ply(self.surface_path)
        if not isinstance(mesh, Mesh):
            raise InputError(f"{self.surface_path}: ground-truth surface must be a triangle mesh")
        return mesh

    def depth(self, index: int) -> np.ndarray:
        """(H, W) float32 true z-depth (mm) of frame ``index``, NaN where the ray hits nothing."""
        if not self.depth_paths:
            raise InputError("dataset has no ground-truth depth maps")
        return np.load(self.depth_paths[index])


@dataclass(frozen=True)
class Dataset:
    """A loaded dataset. Images are read on demand with :meth:`frame` and :meth:`fluorescence_frame`."""

    root: Path
    camera: Camera
    frame_paths: list[Path]
    poses: list[MeasuredPose]
    fluorescence_paths: list[Path] | None = None
    ground_truth: GroundTruth | None = None
    metadata: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frame_paths)

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.frame_paths]

    def frame(self, index: int, *, grey: bool = False) -> np.ndarray:
        """(H, W, 3) uint8 RGB, or (H, W) uint8 with ``grey=True``."""
        return read_image(self.frame_paths[index], grey=grey)

    def fluorescence_frame(self, index: int) -> np.ndarray:
        """(H, W) uint8 fluorescence intensity (the green emission channel)."""
        if not self.fluorescence_paths:
            raise InputError(f"{self.root}: dataset has no fluorescence frames")
        img = read_image(self.fluorescence_paths[index])
        return img[..., 1]


def read_image(path: str | Path, *, grey: bool = False) -> np.ndarray:
    """Read an image as RGB uint8 (H, W, 3), or grey (H, W). A missing or corrupt file is an InputError."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: image file is missing")
    flag = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR
    img = cv2.imread(str(path), flag)
    if img is None:
        raise InputError(f"{path}: not a readable image (corrupt or unsupported format)")
    if img.dtype != np.uint8:
        img = cv2.convertScaleAbs(img, alpha=255.0 / max(float(img.max()), 1.0))
    return img if grey else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def write_image(path: str | Path, image: np.ndarray) -> None:
    """Write an RGB (H, W, 3) or grey (H, W) uint8 image; the format follows the suffix."""
    path = Path(path)
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(path.suffix or ".png", img)
    if not ok:
        raise InputError(f"{path}: cannot encode image")
    with atomic_file(path, "wb") as fh:
        fh.write(buf.tobytes())


# --- poses.csv --------------------------------------------------------------------------------


def format_poses_csv(names: list[str], poses: list[MeasuredPose]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(POSE_COLUMNS)
    for name, measured in zip(names, poses):
        c = measured.pose.centre
        q = matrix_to_quaternion(measured.pose.rotation.T)  # world_from_cam, (x, y, z, w)
        tol = measured.tolerance
        writer.writerow(
            [name, *(f"{v:.12g}" for v in c), *(f"{v:.12g}" for v in (q[3], q[0], q[1], q[2]))]
            + [f"{v:.9g}" for v in tol.position_mm]
            + [f"{v:.9g}" for v in tol.orientation_deg]
        )
    return out.getvalue()


def write_poses_csv(path: str | Path, names: list[str], poses: list[MeasuredPose]) -> None:
    with atomic_file(path) as fh:
        fh.write(format_poses_csv(names, poses))


def read_poses_csv(path: str | Path, length_scale_to_mm: float = 1.0) -> tuple[list[str], list[MeasuredPose]]:
    """Parse ``poses.csv``. Every problem is an InputError naming the file and the row (1 = header)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: pose file is missing")
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise InputError(f"{path}: pose file is empty")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in POSE_COLUMNS if c not in header]
    if missing:
        raise InputError(f"{path} row 1: missing column(s) {', '.join(missing)}")
    col = {name: header.index(name) for name in POSE_COLUMNS}
    names, poses = [], []
    for row_number, row in enumerate(rows[1:], start=2):
        if not row or all(not cell.strip() for cell in row):
            continue
        where = f"{path} row {row_number}"
        if len(row) < len(header):
            raise InputError(f"{where}: expected {len(header)} values, found {len(row)}")
        values = {}
        for name in POSE_COLUMNS[1:]:
            text = row[col[name]].strip()
            try:
                values[name] = float(text)
            except ValueError:
                raise InputError(f"{where}: {name} = {text!r} is not a number") from None
            if math.isnan(values[name]) or (math.isinf(values[name]) and not name.startswith("tol_")):
                raise InputError(f"{where}: {name} is {text} (NaN or infinite)")
            if name.startswith("tol_") and values[name] < 0:
                raise InputError(f"{where}: {name} = {text} is negative (lower bound above upper bound)")
        q = np.array([values["qx"], values["qy"], values["qz"], values["qw"]])
        if abs(np.linalg.norm(q) - 1.0) > _QUATERNION_NORM_TOLERANCE:
            raise InputError(f"{where}: quaternion (qw, qx, qy, qz) is not unit length (norm {np.linalg.norm(q):.4g})")
        world_from_cam = quaternion_to_matrix(q / np.linalg.norm(q))
        centre = np.array([values["x_mm"], values["y_mm"], values["z_mm"]]) * length_scale_to_mm
        tolerance = PoseTolerance.from_degrees(
            np.array([values["tol_x_mm"], values["tol_y_mm"], values["tol_z_mm"]]) * length_scale_to_mm,
            [values["tol_rx_deg"], values["tol_ry_deg"], values["tol_rz_deg"]],
        )
        names.append(row[col["image"]].strip())
        poses.append(MeasuredPose(Pose.from_centre(world_from_cam.T, centre), tolerance))
    if not poses:
        raise InputError(f"{path}: pose file has a header but no rows")
    return names, poses


# --- camera.json ------------------------------------------------------------------------------


def camera_to_dict(camera: Camera) -> dict:
    return {
        "model": "pinhole_radial_k1k2",
        "width": camera.width, "height": camera.height,
        "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
        "k1": camera.k1, "k2": camera.k2, "mask_radius_px": camera.mask_radius_px,
        "fov_deg": camera.fov_deg,
    }


def read_camera_json(path: str | Path) -> Camera:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: camera intrinsics file is missing")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    missing = [k for k in CAMERA_KEYS if k not in data]
    if missing:
        raise InputError(f"{path}: missing key(s) {', '.join(missing)}")
    try:
        values = {k: float(data[k]) for k in CAMERA_KEYS}
    except (TypeError, ValueError):
        raise InputError(f"{path}: intrinsics must be numbers") from None
    bad = [k for k, v in values.items() if not math.isfinite(v)]
    if bad:
        raise InputError(f"{path}: {', '.join(bad)} is NaN or infinite")
    try:
        return Camera(
            int(values["width"]), int(values["height"]), values["fx"], values["fy"], values["cx"], values["cy"],
            values["k1"], values["k2"], data.get("mask_radius_px"),
        )
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None


# --- whole datasets ---------------------------------------------------------------------------


def load_dataset(root: str | Path, *, check_images: bool = False) -> Dataset:
    """Load and validate a dataset folder. With ``check_images`` every image is decoded once."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: dataset folder does not exist")
    meta_path = root / "dataset.json"
    metadata = {}
    if meta_path.is_file():
        try:
            metadata = json.loads(meta_path.read_text())
        except json.JSONDecodeError as exc:
            raise InputError(f"{meta_path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    unit = metadata.get("length_unit", "mm")
    if unit not in LENGTH_UNITS_TO_MM:
        raise InputError(f"{meta_path}: unknown length_unit {unit!r} (use one of {', '.join(LENGTH_UNITS_TO_MM)})")
    scale = LENGTH_UNITS_TO_MM[unit]
    camera = read_camera_json(root / "camera.json")
    names, poses = read_poses_csv(root / "poses.csv", scale)
    frame_paths = [root / "frames" / n for n in names]
    for i, p in enumerate(frame_paths):
        if not p.is_file():
            raise InputError(f"{root / 'poses.csv'} row {i + 2}: image {p.relative_to(root)} is missing")
    frames_dir = root / "frames"
    extra = sorted(set(q.name for q in frames_dir.iterdir() if not q.name.startswith(".")) - set(names))
    if extra:
        raise InputError(
            f"{root / 'poses.csv'}: {len(names)} pose rows but {len(names) + len(extra)} frames "
            f"(no pose for frames/{extra[0]})"
        )
    fluo_dir = root / "fluorescence"
    fluorescence_paths = None
    if fluo_dir.is_dir():
        fluorescence_paths = [fluo_dir / n for n in names]
        for p in fluorescence_paths:
            if not p.is_file():
                raise InputError(f"{p}: fluorescence image is missing (every frame needs one)")
    ground_truth = _load_ground_truth(root / "ground_truth", names, scale)
    if check_images:
        for p in frame_paths + (fluorescence_paths or []):
            img = read_image(p)
            if img.shape[:2] != (camera.height, camera.width):
                raise InputError(f"{p}: image is {img.shape[1]}x{img.shape[0]}, camera.json says {camera.width}x{camera.height}")
    return Dataset(root, camera, frame_paths, poses, fluorescence_paths, ground_truth, metadata)


def _load_ground_truth(gt_dir: Path, names: list[str], scale: float) -> GroundTruth | None:
    if not gt_dir.is_dir():
        return None
    poses = None
    if (gt_dir / "poses.csv").is_file():
        gt_names, measured = read_poses_csv(gt_dir / "poses.csv", scale)
        if gt_names != names:
            raise InputError(f"{gt_dir / 'poses.csv'}: frames differ from poses.csv ({len(gt_names)} vs {len(names)} rows)")
        poses = [m.pose for m in measured]
    surface = gt_dir / "surface.ply"
    depth_dir = gt_dir / "depth"
    depth_paths = [depth_dir / (Path(n).stem + ".npy") for n in names] if depth_dir.is_dir() else None
    scene = json.loads((gt_dir / "scene.json").read_text()) if (gt_dir / "scene.json").is_file() else {}
    return GroundTruth(poses, surface if surface.is_file() else None, depth_paths, scene)


def write_dataset(
    out_dir: str | Path,
    camera: Camera,
    frames: list[np.ndarray],
    poses: list[MeasuredPose],
    *,
    names: list[str] | None = None,
    fluorescence: list[np.ndarray] | None = None,
    true_poses: list[Pose] | None = None,
    true_surface: Mesh | None = None,
    true_depths: list[np.ndarray] | None = None,
    scene: dict | None = None,
    metadata: dict | None = None,
) -> Path:
    """Write a dataset folder atomically (built beside ``out_dir``, then renamed into place).

    frames : list of (H, W, 3) uint8 RGB or (H, W) uint8; fluorescence likewise; true_depths : (H, W) mm.
    """
    if len(frames) != len(poses):
        raise ValueError(f"{len(frames)} frames but {len(poses)} poses")
    names = names or [f"{i:04d}.png" for i in range(len(frames))]
    out_dir = Path(out_dir)
    with atomic_directory(out_dir) as tmp:
        meta = {"format": "scope3d-dataset", "version": 1, "length_unit": "mm", "name": out_dir.name}
        meta.update(metadata or {})
        if scene is not None:
            meta["scene"] = scene.get("name", "custom")
        (tmp / "dataset.json").write_text(json.dumps(meta, indent=2) + "\n")
        (tmp / "camera.json").write_text(json.dumps(camera_to_dict(camera), indent=2) + "\n")
        (tmp / "poses.csv").write_text(format_poses_csv(names, poses))
        (tmp / "frames").mkdir()
        for name, img in zip(names, frames):
            write_image(tmp / "frames" / name, img)
        if fluorescence is not None:
            (tmp / "fluorescence").mkdir()
            for name, img in zip(names, fluorescence):
                write_image(tmp / "fluorescence" / name, img)
        if any(x is not None for x in (true_poses, true_surface, true_depths, scene)):
            gt = tmp / "ground_truth"
            gt.mkdir()
            if true_poses is not None:
                exact = [MeasuredPose(p, PoseTolerance.exact()) for p in true_poses]
                (gt / "poses.csv").write_text(format_poses_csv(names, exact))
            if true_surface is not None:
                write_ply(gt / "surface.ply", true_surface)
            if true_depths is not None:
                (gt / "depth").mkdir()
                for name, depth in zip(names, true_depths):
                    np.save(gt / "depth" / (Path(name).stem + ".npy"), np.asarray(depth, dtype=np.float32))
            if scene is not None:
                (gt / "scene.json").write_text(json.dumps(scene, indent=2, default=_json_default) + "\n")
    return out_dir


def _json_default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    raise TypeError(f"cannot serialise {type(obj).__name__}")
