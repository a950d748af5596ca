"""Datasets on disk: frames, reported poses with tolerances, camera intrinsics, optional ground truth.

Folder layout (all lengths in millimetres, angles in degrees in files; see ``docs/datasets.md``)::

    DATASET/
      dataset.json        {"format": "scope3d-dataset", "version": 1, "length_unit": "mm", "name": ...}
                          optional: "scene": NAME, "source": {...} (provenance of an import),
                          "bounding_box_mm": [[xmin, ymin, zmin], [xmax, ymax, zmax]]
      camera.json         {"width", "height", "fx", "fy", "cx", "cy", "k1", "k2", "mask_radius_px" (or null)}
                          (pixels; "model" and "fov_deg" are written for people and ignored when read)
      poses.csv           one row per frame, in frame order (columns below)
      frames/             reflectance images named in poses.csv (PNG, grey or colour), nothing else
      fluorescence/       optional: fluorescence images with the same names
      ground_truth/       optional, written by the phantom lab
        poses.csv         the true poses (tolerance columns 0)
        surface.ply       the true surface, a triangle mesh in mm
        depth/NAME.npy    optional (H, W) float32 z-depth in mm of each frame (NAME = image stem), NaN where no surface
        scene.json        scene parameters (targets, thread profile, ...)

``poses.csv`` columns::

    image, x_mm, y_mm, z_mm, qw, qx, qy, qz, tol_x_mm, tol_y_mm, tol_z_mm, tol_rx_deg, tol_ry_deg, tol_rz_deg

``image`` is a plain file name in ``frames/``, unique. ``x, y, z`` is the camera centre in the world;
``(qw, qx, qy, qz)`` is the camera's orientation in the world (the rotation ``world_from_cam``, a unit
quaternion), as a robot or tracker reports it. The ``tol_*_mm`` columns bound the true centre per world
axis; ``tol_r*_deg`` bound a small rotation about the camera's own x, y, z axes (``R_true = exp([w]x)
R_measured`` for ``cam_from_world``). Tolerance 0 means exact, ``inf`` means unknown; NaN is an error
everywhere. ``dataset.json``'s ``length_unit`` may be ``mm``, ``cm``, ``m`` or ``um``; lengths (positions
and position tolerances) are converted to mm when loading. Pixels: origin at the centre of the top-left
pixel, u right, v down (:mod:`scope3d.sensor.camera`). An optional last column ``time_s`` gives each
frame's time in seconds, strictly increasing (a video's frames: :attr:`Dataset.times_s`).
"""
from __future__ import annotations

import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.io.camera_json import camera_to_dict, read_camera_json
from scope3d.io.images import read_image, write_image
from scope3d.io.json_object import read_json_object
from scope3d.io.ply import read_ply, write_ply
from scope3d.io.poses_csv import _read_pose_rows, format_poses_csv, read_poses_csv
from scope3d.scene.mesh import Mesh
from scope3d.sensor.camera import Camera, fov_from_focal
from scope3d.sensor.camera_models import DEFAULT_MODEL
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.utils.atomic import atomic_directory
from scope3d.utils.jsonio import write_json

LENGTH_UNITS_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "um": 1e-3}


def load_dataset(root: str | Path, *, check_images: bool = False) -> Dataset:
    """Load and validate a dataset folder; lengths are returned in mm whatever ``length_unit`` says.

    Always checked: the JSON and CSV files parse, every value is finite (tolerances may be ``inf``),
    tolerances are non-negative, quaternions are unit, every pose row has its image and every image has
    its pose row, fluorescence and ground-truth files match the frames. With ``check_images`` every
    image is also decoded once and its size compared with ``camera.json``, every ground-truth depth map
    is opened and its shape checked, and the ground-truth surface is parsed (what ``scope3d check`` does).
    The first problem found is raised as an :class:`InputError` naming the file (and the row).
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: dataset folder does not exist")
    meta_path = root / "dataset.json"
    metadata = read_json_object(meta_path) if meta_path.is_file() else {}
    fmt = metadata.get("format", "scope3d-dataset")
    if fmt != "scope3d-dataset":
        raise InputError(f"{meta_path}: format is {fmt!r}, expected 'scope3d-dataset'")
    version = metadata.get("version", 1)
    if version != 1:
        raise InputError(f"{meta_path}: dataset version {version!r} is not supported (this scope3d reads version 1)")
    unit = metadata.get("length_unit", "mm")
    if not isinstance(unit, str) or unit not in LENGTH_UNITS_TO_MM:
        raise InputError(f"{meta_path}: unknown length_unit {unit!r} (use one of {', '.join(LENGTH_UNITS_TO_MM)})")
    scale = LENGTH_UNITS_TO_MM[unit]
    camera = read_camera_json(root / "camera.json")
    poses_path = root / "poses.csv"
    names, poses, row_numbers, times_s = _read_pose_rows(poses_path, scale)
    frames_dir = root / "frames"
    if not frames_dir.is_dir():
        raise InputError(f"{frames_dir}: frames folder is missing")
    frame_paths = [frames_dir / n for n in names]
    for p, row in zip(frame_paths, row_numbers):
        if not p.is_file():
            raise InputError(f"{poses_path} row {row}: image {p.relative_to(root)} is missing")
    on_disk = {q.name for q in frames_dir.iterdir() if q.is_file() and not q.name.startswith(".")}
    extra = sorted(on_disk - set(names))
    if extra:
        raise InputError(
            f"{poses_path}: {len(names)} pose rows but {len(on_disk)} frames "
            f"(no pose row for frames/{extra[0]})"
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
            _check_size(p, read_image(p), camera)
        if ground_truth is not None:
            _check_ground_truth_files(ground_truth, camera)
    return Dataset(root, camera, frame_paths, poses, fluorescence_paths, ground_truth, metadata, times_s)


def _check_size(path: Path, image: np.ndarray, camera: Camera) -> np.ndarray:
    if image.shape[:2] != (camera.height, camera.width):
        raise InputError(
            f"{path}: image is {image.shape[1]}x{image.shape[0]}, camera.json says {camera.width}x{camera.height}"
        )
    return image


def _load_ground_truth(gt_dir: Path, names: list[str], scale: float) -> GroundTruth | None:
    if not gt_dir.is_dir():
        return None
    poses = None
    if (gt_dir / "poses.csv").is_file():
        gt_names, measured = read_poses_csv(gt_dir / "poses.csv", scale)
        if gt_names != names:
            first = next((i for i, (a, b) in enumerate(zip(gt_names, names)) if a != b), min(len(gt_names), len(names)))
            raise InputError(
                f"{gt_dir / 'poses.csv'}: frames differ from poses.csv ({len(gt_names)} vs {len(names)} rows, "
                f"first difference at data row {first + 1})"
            )
        poses = [m.pose for m in measured]
    surface = gt_dir / "surface.ply"
    depth_dir = gt_dir / "depth"
    depth_paths = None
    if depth_dir.is_dir():
        depth_paths = [depth_dir / (Path(n).stem + ".npy") for n in names]
        for p in depth_paths:
            if not p.is_file():
                raise InputError(f"{p}: ground-truth depth map is missing (every frame needs one)")
    scene_path = gt_dir / "scene.json"
    scene = read_json_object(scene_path) if scene_path.is_file() else {}
    return GroundTruth(poses, surface if surface.is_file() else None, depth_paths, scene)


def _check_ground_truth_files(gt: GroundTruth, camera: Camera) -> None:
    """Open every ground-truth file once (depth maps memory-mapped: only their headers are read)."""
    for p in gt.depth_paths or []:
        try:
            depth = np.load(p, mmap_mode="r", allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise InputError(f"{p}: not a readable .npy depth map ({exc})") from None
        if depth.shape != (camera.height, camera.width):
            raise InputError(f"{p}: depth map has shape {depth.shape}, expected ({camera.height}, {camera.width})")
    if gt.surface_path is not None:
        gt.surface()


def check_jobs_take(camera: Camera, where: str | Path, job: str) -> None:
    """A job that takes scope3d's radial model only, so far (issue 32: ``map``, ``localize``, ``panorama`` and
    ``mosaic`` take every model of :mod:`scope3d.sensor.camera_models`; ``axial`` and ``thread-scan`` call
    this): an InputError naming ``where`` for a camera of another model, so that a fisheye's parameters are
    never read as radial ones. Its ``check_dataset`` (or ``run``) calls it before any work."""
    if camera.model != DEFAULT_MODEL:
        raise InputError(f"{where}: a {camera.model} camera; scope3d {job} takes {DEFAULT_MODEL} cameras only so "
                         "far (map, localize, panorama and mosaic take every model; calibrate with --model radial "
                         "for the others)")


def write_dataset(
    out_dir: str | Path,
    camera: Camera,
    frames: Sequence[np.ndarray | str | Path],
    poses: list[MeasuredPose],
    *,
    names: list[str] | None = None,
    fluorescence: Sequence[np.ndarray | str | Path] | None = None,
    true_poses: list[Pose] | None = None,
    true_surface: Mesh | None = None,
    true_depths: list[np.ndarray] | None = None,
    scene: dict | None = None,
    metadata: dict | None = None,
    extra_images: dict[str, np.ndarray] | None = None,
    finish: Callable[[Path], None] | None = None,
    move_frames: bool = False,
    times_s: Sequence[float] | None = None,
) -> Path:
    """Write a dataset folder atomically (built beside ``out_dir``, then renamed into place).

    frames : list of (H, W, 3) uint8 RGB or (H, W) uint8 arrays, or paths of image files. A path whose
        suffix matches the frame's name is copied byte for byte (no re-encoding); any other is decoded
        and written in the name's format, so large sets never need to be held in memory at once.
    poses : measured ``cam_from_world`` per frame, mm. names : plain file names, default ``0000.png``...
    fluorescence : like ``frames``. true_depths : (H, W) z-depth in mm per frame, NaN where no surface.
    metadata : merged into ``dataset.json`` (e.g. ``{"source": {...}}`` provenance).
    extra_images : file name -> image, written at the top of the folder with the rest (contact sheets),
        so that the folder appears complete or not at all.
    finish : called with the folder being built once everything above is in it, before it is put in place
        (a job's report.json and report.html): what it writes appears with the dataset or not at all.
    move_frames : frames given as paths of the caller's own temporary files, just written whole in the
        name's format: moved into the dataset, neither copied nor decoded again to check them (an import's
        own PNGs; a user's files are always copied and checked).
    times_s : each frame's time, seconds, strictly increasing: ``poses.csv``'s ``time_s`` column (a video's
        frames), in the ground truth's poses.csv too.

    If anything fails, ``out_dir`` is left as it was (absent, or the previous dataset).
    """
    n = len(frames)
    if len(poses) != n:
        raise ValueError(f"{n} frames but {len(poses)} poses")
    names = list(names) if names is not None else [f"{i:04d}.png" for i in range(n)]
    if len(names) != n:
        raise ValueError(f"{n} frames but {len(names)} names")
    if len(set(names)) != n:
        raise ValueError("frame names must be unique")
    bad = [name for name in names if not name or "/" in name or "\\" in name or name.startswith(".")]
    if bad:
        raise ValueError(f"frame name {bad[0]!r} must be a plain file name")
    if times_s is not None:
        times_s = np.asarray(times_s, dtype=float)
        if not (np.all(np.isfinite(times_s)) and np.all(np.diff(times_s) > 0)):
            raise ValueError("frame times must be finite and strictly increasing")
    for label, items in (("fluorescence frames", fluorescence), ("true poses", true_poses), ("depth maps", true_depths),
                         ("frame times", times_s)):
        if items is not None and len(items) != n:
            raise ValueError(f"{n} frames but {len(items)} {label}")
    out_dir = Path(out_dir)
    with atomic_directory(out_dir) as tmp:
        meta = {"format": "scope3d-dataset", "version": 1, "length_unit": "mm", "name": out_dir.name}
        meta.update(metadata or {})
        if scene is not None:
            meta["scene"] = scene.get("name", "custom")
        write_json(tmp / "dataset.json", meta)
        write_json(tmp / "camera.json", camera_to_dict(camera))
        (tmp / "poses.csv").write_text(format_poses_csv(names, poses, times_s=times_s))
        (tmp / "frames").mkdir()
        for name, img in zip(names, frames):
            if move_frames and isinstance(img, (str, Path)) and Path(img).suffix.lower() == Path(name).suffix.lower():
                shutil.move(img, tmp / "frames" / name)
            else:
                _write_frame(tmp / "frames" / name, img)
        if fluorescence is not None:
            (tmp / "fluorescence").mkdir()
            for name, img in zip(names, fluorescence):
                _write_frame(tmp / "fluorescence" / name, img)
        if any(x is not None for x in (true_poses, true_surface, true_depths, scene)):
            gt = tmp / "ground_truth"
            gt.mkdir()
            if true_poses is not None:
                exact = [MeasuredPose(p, PoseTolerance.exact()) for p in true_poses]
                (gt / "poses.csv").write_text(format_poses_csv(names, exact, times_s=times_s))
            if true_surface is not None:
                write_ply(gt / "surface.ply", true_surface)
            if true_depths is not None:
                (gt / "depth").mkdir()
                for name, depth in zip(names, true_depths):
                    np.save(gt / "depth" / (Path(name).stem + ".npy"), np.asarray(depth, dtype=np.float32))
            if scene is not None:
                write_json(gt / "scene.json", scene)
        for name, image in (extra_images or {}).items():
            write_image(tmp / name, image)
        if finish is not None:
            finish(tmp)
    return out_dir


def _write_frame(dest: Path, image: np.ndarray | str | Path) -> None:
    if isinstance(image, (str, Path)):
        source = Path(image)
        if source.suffix.lower() == dest.suffix.lower():
            read_image(source)  # refuse to copy a corrupt file into a dataset
            shutil.copyfile(source, dest)
            return
        image = read_image(source)
    write_image(dest, image)


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
    """A loaded dataset. Images are read on demand with :meth:`frame` and :meth:`fluorescence_frame`.
    times_s : (n,) each frame's time in seconds (``poses.csv``'s ``time_s`` column), or None without one."""

    root: Path
    camera: Camera
    frame_paths: list[Path]
    poses: list[MeasuredPose]
    fluorescence_paths: list[Path] | None = None
    ground_truth: GroundTruth | None = None
    metadata: dict = field(default_factory=dict)
    times_s: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.frame_paths)

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.frame_paths]

    def frame(self, index: int, *, grey: bool = False) -> np.ndarray:
        """(H, W, 3) uint8 RGB, or (H, W) uint8 with ``grey=True``; a frame of another size than
        ``camera.json`` says is an InputError naming it (checked here too: ``load_dataset`` decodes
        no image unless asked)."""
        return _check_size(self.frame_paths[index], read_image(self.frame_paths[index], grey=grey), self.camera)

    def summary(self) -> str:
        """Several lines saying what the dataset holds (what ``scope3d check`` prints)."""
        cam = self.camera
        centres = np.array([m.pose.centre for m in self.poses])
        span = centres.max(axis=0) - centres.min(axis=0)
        lines = [
            f"dataset       {self.root} ({self.metadata.get('name', self.root.name)})",
            f"frames        {len(self)} images of {cam.width}x{cam.height} px ({self.names[0]} .. {self.names[-1]})",
            f"camera        fx {cam.fx:.6g} fy {cam.fy:.6g} cx {cam.cx:.6g} cy {cam.cy:.6g} px, "
            + (f"k1 {cam.k1:.4g} k2 {cam.k2:.4g}; field of view {cam.fov_deg:.1f} x "
               f"{fov_from_focal(cam.height, cam.fy):.1f} deg; " if cam.model == DEFAULT_MODEL else
               f"{cam.model} " + " ".join(f"{n} {v:.4g}" for n, v in zip(cam.param_names[4:], cam.params[4:]))
               + f"; field of view {cam.fov_deg:.1f} deg across the width; ")
            + (f"circular mask radius {cam.mask_radius_px:.6g} px" if cam.mask_radius_px else "no circular mask"),
            f"poses         camera centres span {span[0]:.4g} x {span[1]:.4g} x {span[2]:.4g} mm; "
            f"tolerance {_tolerance_summary([m.tolerance for m in self.poses])}",
            f"fluorescence  {'yes' if self.fluorescence_paths else 'no'}",
            f"ground truth  {self._ground_truth_summary()}",
        ]
        source = self.metadata.get("source")
        if isinstance(source, dict) and source.get("format"):
            lines.append(f"source        {source['format']}: {source.get('path', '?')}")
        return "\n".join(lines)

    def _ground_truth_summary(self) -> str:
        gt = self.ground_truth
        if gt is None:
            return "none"
        parts = []
        if gt.poses is not None:
            parts.append("true poses")
        if gt.surface_path is not None:
            parts.append("surface mesh")
        if gt.depth_paths:
            parts.append(f"{len(gt.depth_paths)} depth maps")
        if gt.scene:
            parts.append(f"scene {gt.scene.get('name', '(unnamed)')}")
        return ", ".join(parts) or "empty folder"

    def fluorescence_frame(self, index: int) -> np.ndarray:
        """(H, W) uint8 fluorescence intensity (the green emission channel)."""
        if not self.fluorescence_paths:
            raise InputError(f"{self.root}: dataset has no fluorescence frames")
        img = _check_size(self.fluorescence_paths[index], read_image(self.fluorescence_paths[index]), self.camera)
        return img[..., 1]


def _tolerance_summary(tolerances: list[PoseTolerance]) -> str:
    """One phrase: exact, unknown, or the range of half-widths over all frames."""
    if all(t.is_exact for t in tolerances):
        return "exact (0) for every frame"
    pos = np.array([t.position_mm for t in tolerances])
    rot = np.array([t.orientation_deg for t in tolerances])
    if np.all(np.isinf(pos)) and np.all(np.isinf(rot)):
        return "unknown (inf) for every frame"

    def span(values: np.ndarray, unit: str) -> str:
        lo, hi = float(values.min()), float(values.max())
        return f"+-{lo:.4g} {unit}" if lo == hi else f"+-{lo:.4g}..{hi:.4g} {unit}"

    return f"position {span(pos, 'mm')} per axis, orientation {span(rot, 'deg')} per axis"
