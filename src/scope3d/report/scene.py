"""What the report's 3D view shows, gathered from a run folder: the job's clouds and meshes (decimated
for the page), their colourings (height, error against the true surface, texture), the cameras'
frusta along the trajectory, the fluorescent targets, and for the explorer (click a spot, see the frames
that saw it) every camera's pose and intrinsics with a small picture of its frame. Lengths in mm, world
frame of the run."""
from __future__ import annotations

import base64
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.plane import principal_axes
from scope3d.geometry.pose import Pose
from scope3d.io.ply import read_ply
from scope3d.scene.mesh import Mesh, SampledSurface
from scope3d.sensor.camera import Camera
from scope3d.sensor.camera_models import DEFAULT_MODEL

# The geometry files a job may leave, in the order the view lists them; ``texture_from`` names a file
# holding the same vertices coloured by reflectance only (the map's mesh.ply carries the fluorescence
# overlay, mesh_reflectance.ply the plain texture).
GEOMETRY_FILES = ("wall.obj", "mesh.ply", "cloud.ply", "points.ply")
TEXTURE_FROM = {"mesh.ply": "mesh_reflectance.ply"}
# A textured mesh (OBJ + MTL + atlas) stands for the same geometry's PLY: the panorama's wall.obj is its
# mesh.ply with the frames' texture.
SUPERSEDES = {"wall.obj": "mesh.ply"}


@dataclass(frozen=True)
class ReportOptions:
    """How the page is built.

    max_points : int, vertices drawn per layer at most; a larger cloud is thinned to a seeded random
        subset (the full PLY stays linked). max_faces : int, triangles drawn per mesh at most; a larger
        mesh is drawn as its (thinned) vertices. seed : int, the thinning's seed (same page for the same
        run). frustum_depth_fraction : float, frustum depth as a fraction of the scene's diagonal.
    error_scale_percentile : float, top of the error colour scale (percentile of the errors, so one far
        outlier does not wash the rest out).
    thumbnail_px : int, longest side of each frame's picture in the explorer (JPEG in the page).
    max_texture_px : int, longest side of a textured mesh's atlas in the page (JPEG, quality 85; the full
        atlas stays linked), which bounds what a texture adds to the page (~1-2 MB at 2048 px).
    max_thumbnails : int, frames with a picture at most (evenly spread over the run; the others are listed
        by name only), which bounds the page's size for videos of thousands of frames.
    """

    max_points: int = 200_000
    max_faces: int = 400_000
    seed: int = 0
    frustum_depth_fraction: float = 0.08
    error_scale_percentile: float = 95.0
    thumbnail_px: int = 160
    max_thumbnails: int = 400
    max_texture_px: int = 2048

    def __post_init__(self) -> None:
        if self.max_points < 1 or self.max_faces < 1:
            raise ValueError("max_points and max_faces must be >= 1")
        if self.thumbnail_px < 16 or self.max_thumbnails < 0 or self.max_texture_px < 16:
            raise ValueError("thumbnail_px and max_texture_px must be >= 16 and max_thumbnails >= 0")
        if not 0 < self.frustum_depth_fraction <= 1:
            raise ValueError("frustum_depth_fraction must be in (0, 1]")
        if not 0 < self.error_scale_percentile <= 100:
            raise ValueError("error_scale_percentile must be in (0, 100]")


@dataclass
class Layer:
    """One geometry file as drawn. positions : (N, 3) float64 mm world; faces : (F, 3) int or None
    (points); colours : colouring name -> (N, 3) uint8 RGB; n_file : vertices in the file (N < n_file
    when thinned); error_mm : (N,) distances to the true surface or None; uv : (N, 2) texture coordinates
    (OBJ's: v up) and texture_jpeg : the atlas (JPEG bytes), for a textured mesh, else None."""

    name: str
    positions: np.ndarray
    faces: np.ndarray | None
    colours: dict[str, np.ndarray]
    n_file: int
    n_faces_file: int
    error_mm: np.ndarray | None = None
    uv: np.ndarray | None = None
    texture_jpeg: bytes | None = None

    @property
    def textured(self) -> bool:
        """Whether the layer carries a texture atlas (drawn for the "texture" colouring)."""
        return self.texture_jpeg is not None


@dataclass(frozen=True)
class FrameView:
    """One camera of the run as the explorer uses it. name : the frame's file name; pose : cam_from_world
    (mm); thumbnail : JPEG bytes of the frame, longest side ``ReportOptions.thumbnail_px``, or None."""

    name: str
    pose: Pose
    thumbnail: bytes | None


@dataclass
class ViewScene:
    """Everything the viewer draws; see :func:`gather_scene`. frusta : (S, 2, 3) mm line segments;
    trajectory : (M, 3) mm camera centres in frame order; targets / true_targets : dicts from report.json;
    up : (3,) unit height direction; scales : colouring name -> (low, high, unit) of its colour bar.
    camera : the run's intrinsics (None without cameras); frames : the explorer's cameras, in frame order.
    inside : True for a closed cavity seen from within (the organ panorama): the page offers the view from
    inside, like a virtual globe."""

    layers: list[Layer]
    frusta: np.ndarray
    trajectory: np.ndarray
    targets: list[dict]
    true_targets: list[dict]
    up: np.ndarray
    scales: dict[str, tuple[float, float, str]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    camera: Camera | None = None
    frames: list[FrameView] = field(default_factory=list)
    inside: bool = False


def colour_map(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """(N,) values -> (N, 3) uint8 RGB on matplotlib's turbo scale between low and high (clipped)."""
    from matplotlib import colormaps

    span = high - low if high > low else 1.0
    t = np.clip((np.asarray(values, float) - low) / span, 0.0, 1.0)
    return (colormaps["turbo"](t)[:, :3] * 255 + 0.5).astype(np.uint8)


def colour_stops(count: int = 9) -> list[str]:
    """CSS colours of the turbo scale at ``count`` even stops (the legend's gradient)."""
    rgb = colour_map(np.linspace(0, 1, count), 0.0, 1.0)
    return [f"rgb({r},{g},{b})" for r, g, b in rgb]


def _thin(n: int, limit: int, seed: int) -> np.ndarray | None:
    """Sorted indices of a seeded random subset of ``limit`` of ``n`` items, or None if n <= limit."""
    if n <= limit:
        return None
    return np.sort(np.random.default_rng(seed).choice(n, size=limit, replace=False))


def _read_geometry(path: Path, options: ReportOptions) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None,
                                                               int, int, np.ndarray | None]:
    """positions, faces (None = drawn as points), colours of a PLY as drawn, the file's vertex and face
    counts, and the kept vertex indices (None = all). A mesh over either budget is drawn as its
    vertices, thinned to ``max_points``."""
    geometry = read_ply(path)
    if isinstance(geometry, Mesh):
        vertices, faces, colours = geometry.vertices, geometry.faces, geometry.vertex_colors
    else:
        vertices, faces, colours = geometry.points, None, geometry.colors
    n_vertices, n_faces = len(vertices), 0 if faces is None else len(faces)
    if faces is not None and (n_faces == 0 or n_faces > options.max_faces or n_vertices > options.max_points):
        faces = None
    keep = _thin(n_vertices, options.max_points, options.seed) if faces is None else None
    if keep is not None:
        vertices = vertices[keep]
        colours = None if colours is None else colours[keep]
    return vertices, faces, colours, n_vertices, n_faces, keep


def _read_textured(path: Path, options: ReportOptions):
    """A textured OBJ as drawn: (positions, faces, uv, atlas JPEG, vertices and faces in the file), its
    corners unwelded where they have different texture coordinates (WebGL has one index per vertex); None
    when it is over the face budget or has no texture (the mesh's PLY is drawn instead)."""
    import cv2

    from scope3d.io.obj import read_textured_obj

    vertices, faces, uv, face_uv, image = read_textured_obj(path)
    if image is None or len(faces) == 0 or len(faces) > options.max_faces:
        return None
    pairs, corner = np.unique(np.stack([faces.ravel(), face_uv.ravel()], axis=1), axis=0, return_inverse=True)
    if len(pairs) > options.max_points:
        return None
    factor = options.max_texture_px / max(image.shape[:2])
    if factor < 1:
        image = cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA)
    ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])
    if not ok:
        return None
    return vertices[pairs[:, 0]], corner.reshape(-1, 3), uv[pairs[:, 1]], jpeg.tobytes(), len(vertices), len(faces)


def _height_axis(points: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Unit normal of the points' least-squares plane, facing the cameras (world +z when unknown)."""
    if len(points) < 3:
        return np.array([0.0, 0.0, 1.0])
    centroid, axes = principal_axes(points)
    n = axes[-1]
    towards = (centres.mean(axis=0) - centroid) if len(centres) else np.array([0.0, 0.0, 1.0])
    return -n if np.dot(n, towards) < 0 else n


# a frustum's edge is drawn to a z-depth: a wide lens's corner ray is cut at this angle from the axis
_FRUSTUM_MAX_ANGLE_RAD = np.deg2rad(75.0)


def _corners_in_field(camera: Camera, corners_px: np.ndarray) -> np.ndarray:
    """Each corner pulled towards the principal point until the lens sees through it and its ray lies within
    75 deg of the axis (a fisheye's image corners lie past its field, or past 90 deg, where a z-depth has
    no point): bisection along the diagonal, to 1e-6 of its length."""
    centre = np.array([camera.cx, camera.cy])

    def inside(px: np.ndarray) -> np.ndarray:
        rays = camera.unproject(px)
        return camera.sees_pixels(px) & (rays[:, 2] >= np.cos(_FRUSTUM_MAX_ANGLE_RAD))

    lo, hi = np.zeros(len(corners_px)), np.ones(len(corners_px))
    ok = inside(corners_px)
    hi[ok] = lo[ok] = 1.0
    for _ in range(20):
        mid = 0.5 * (lo + hi)
        good = inside(centre + mid[:, None] * (corners_px - centre))
        lo, hi = np.where(good, mid, lo), np.where(good, hi, mid)
    return centre + lo[:, None] * (corners_px - centre)


def camera_frusta(camera: Camera, poses: list[Pose], depth_mm: float) -> np.ndarray:
    """(8 M, 2, 3) mm line segments: each camera's four edges from its centre to the image corners at
    z-depth ``depth_mm``, and the four edges of that far rectangle."""
    corners_px = np.array([[-0.5, -0.5], [camera.width - 0.5, -0.5], [camera.width - 0.5, camera.height - 0.5],
                           [-0.5, camera.height - 0.5]])
    if camera.model != DEFAULT_MODEL:
        corners_px = _corners_in_field(camera, corners_px)
    corners_cam = camera.unproject(corners_px, np.full(4, depth_mm))
    segments = []
    for pose in poses:
        world_from_cam = pose.inverse()
        corners = world_from_cam.transform(corners_cam)
        centre = pose.centre
        for k in range(4):
            segments.append([centre, corners[k]])
            segments.append([corners[k], corners[(k + 1) % 4]])
    return np.array(segments, float).reshape(-1, 2, 3)


def gather_scene(run_dir: Path, report: dict, options: ReportOptions) -> ViewScene:
    """Read the run folder's geometry, cameras and targets; colour every layer by height, by error
    against the dataset's true surface (when the dataset named in report.json is there with one) and by
    its texture. Missing pieces become notes on the page, never errors: a report is written for any run."""
    notes: list[str] = []
    dataset = _dataset(run_dir, report, notes)
    camera, names, poses = _cameras(run_dir, dataset, notes)
    truth = None
    if dataset is not None and dataset.ground_truth is not None and dataset.ground_truth.surface_path is not None:
        from scope3d.metrology.evaluation import EvaluationOptions

        # sampled once for every layer, as the map's evaluation samples it (seeded: the same distances)
        truth = SampledSurface(dataset.ground_truth.surface(), EvaluationOptions().sample_step_mm)

    layers: list[Layer] = []
    drawn: set[str] = set()
    for name in GEOMETRY_FILES:
        path = run_dir / name
        if not path.is_file() or any(drawn_name in drawn and SUPERSEDES[drawn_name] == name for drawn_name in SUPERSEDES):
            continue
        if path.suffix == ".obj":
            textured = _read_textured(path, options)
            if textured is None:
                notes.append(f"{name}: over the page's budget or without its texture; its mesh is drawn untextured")
                continue
            positions, faces, uv, jpeg, n_file, n_faces = textured
            layer = Layer(name, positions, faces, {}, n_file, n_faces, uv=uv, texture_jpeg=jpeg)
            layers.append(layer)
            drawn.add(name)
            if truth is not None and len(positions):
                from scope3d.metrology.evaluation import surface_distances

                layer.error_mm = surface_distances(positions, truth)
            continue
        positions, faces, colours, n_file, n_faces, keep = _read_geometry(path, options)
        texture = colours
        twin = run_dir / TEXTURE_FROM.get(name, "")
        if name in TEXTURE_FROM and twin.is_file():
            plain = read_ply(twin)
            plain_colours = plain.vertex_colors if isinstance(plain, Mesh) else plain.colors
            if plain_colours is not None and len(plain_colours) == n_file:
                texture = plain_colours if keep is None else plain_colours[keep]
        layer = Layer(name, positions, faces, {}, n_file, n_faces)
        if texture is not None:
            layer.colours["texture"] = texture
        if colours is not None and texture is not colours:
            layer.colours["multimodal"] = colours
        if truth is not None and len(positions):
            from scope3d.metrology.evaluation import surface_distances

            layer.error_mm = surface_distances(positions, truth)
        layers.append(layer)
        if n_file > len(positions):
            notes.append(f"{name}: {len(positions):,} of {n_file:,} vertices drawn (seeded random subset, seed "
                         f"{options.seed}); the full file is linked below")
    if not layers:
        notes.append("no cloud or mesh in this run folder")

    all_points = np.concatenate([layer.positions for layer in layers]) if layers else np.zeros((0, 3))
    centres = np.array([p.centre for p in poses]) if poses else np.zeros((0, 3))
    up = _height_axis(all_points, centres)
    scales: dict[str, tuple[float, float, str]] = {}
    if len(all_points):
        h = all_points @ up
        scales["height"] = (float(np.percentile(h, 1)), float(np.percentile(h, 99)), "mm")
    errors = [layer.error_mm for layer in layers if layer.error_mm is not None]
    if errors:
        top = float(np.percentile(np.concatenate(errors), options.error_scale_percentile))
        scales["error"] = (0.0, max(top, 1e-6), "mm")
    for layer in layers:
        if "height" in scales:
            layer.colours["height"] = colour_map(layer.positions @ up, *scales["height"][:2])
        if layer.error_mm is not None:
            layer.colours["error"] = colour_map(layer.error_mm, *scales["error"][:2])

    extent = np.concatenate([all_points, centres]) if len(centres) else all_points
    diagonal = float(np.linalg.norm(np.ptp(extent, axis=0))) if len(extent) else 1.0
    frusta = camera_frusta(camera, poses, options.frustum_depth_fraction * diagonal) if camera and poses \
        else np.zeros((0, 2, 3))
    targets = checked_targets(report, "targets", "centroid_mm", run_dir / "report.json")
    truth_targets = [t for t in checked_targets(report, "targets_vs_truth", "true_centre_mm", run_dir / "report.json")
                     if "true_centre_mm" in t]
    frames = frame_views(names, poses, dataset, options, notes)
    return ViewScene(layers, frusta, centres, targets, truth_targets, up, scales, notes, camera, frames,
                     inside=report.get("job") == "panorama")


def frame_views(names: list[str], poses: list[Pose], dataset, options: ReportOptions,
                notes: list[str]) -> list[FrameView]:
    """The explorer's cameras: each pose with a small JPEG of its frame when the dataset is at hand (at most
    ``max_thumbnails``, evenly spread; a frame that cannot be read is listed without one, with a note)."""
    import cv2

    paths = {p.name: p for p in dataset.frame_paths} if dataset is not None else {}
    pictured = set()
    if paths and options.max_thumbnails:
        count = min(len(names), options.max_thumbnails)
        pictured = set(np.unique(np.linspace(0, len(names) - 1, count).round().astype(int)).tolist())
    frames, unreadable = [], []
    for i, (name, pose) in enumerate(zip(names, poses)):
        thumbnail = None
        if i in pictured and name in paths:
            image = cv2.imread(str(paths[name]), cv2.IMREAD_COLOR)
            if image is None:
                unreadable.append(name)
            else:
                factor = options.thumbnail_px / max(image.shape[:2])
                small = cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA) \
                    if factor < 1 else image
                ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 80])
                thumbnail = jpeg.tobytes() if ok else None
        frames.append(FrameView(name, pose, thumbnail))
    if unreadable:
        notes.append(f"{len(unreadable)} frame(s) could not be read for the explorer, e.g. {unreadable[0]}")
    if len(names) > len(pictured) and pictured:
        notes.append(f"explorer: pictures of {len(pictured)} of {len(names)} frames (evenly spread); the others "
                     "are listed by name")
    return frames


# The fields of a target entry the page computes with or formats as numbers, and those it shows as labels.
_TARGET_NUMBERS = ("size_mm", "area_mm2", "true_size_mm", "centroid_error_mm")
_TARGET_LABELS = ("label", "name", "shape", "found_label")


def checked_targets(report: dict, key: str, centre_key: str, path: Path) -> list[dict]:
    """``report[key]`` (a list of target dicts) with the fields the page uses checked: ``centre_key`` a finite
    3-vector when present, sizes and errors numbers or null, labels plain values. A damaged entry is one
    InputError naming the file and the entry (report.json is scope3d's own output: nothing to guess)."""
    entries = report.get(key) or []
    if not isinstance(entries, list):
        raise InputError(f"{path}: {key} must be a list, found {type(entries).__name__}")
    for i, t in enumerate(entries):
        where = f"{path}: {key}[{i}]"
        if not isinstance(t, dict):
            raise InputError(f"{where}: expected an object, found {type(t).__name__}")
        if centre_key in t:
            c = t[centre_key]
            if (not isinstance(c, list) or len(c) != 3
                    or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and _finite(v) for v in c)):
                raise InputError(f"{where}: {centre_key} must be three finite numbers, found {c!r:.80}")
        for name in _TARGET_NUMBERS:
            v = t.get(name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not _finite(v, True)):
                raise InputError(f"{where}: {name} must be a number, found {v!r:.80}")
        for name in _TARGET_LABELS:
            if isinstance(t.get(name), (list, dict)):
                raise InputError(f"{where}: {name} must be a plain value, found {t[name]!r:.80}")
    if key == "targets_vs_truth" and any("name" not in t for t in entries if "true_centre_mm" in t):
        raise InputError(f"{path}: {key}: every true target needs a name")
    return entries


def _size(target: dict, key: str) -> float:
    """A target's drawn size (mm): its ``key`` where finite, else 1 mm (checked_targets lets null and NaN
    through: a size the map could not measure; float(None) raised TypeError, found by the long fuzz run)."""
    value = target.get(key)
    return float(value) if value is not None and np.isfinite(float(value)) else 1.0


def _finite(value, nan_ok: bool = False) -> bool:
    try:
        return np.isfinite(float(value)) or (nan_ok and np.isnan(float(value)))
    except OverflowError:  # an integer beyond float64
        return False


def _dataset(run_dir: Path, report: dict, notes: list[str]):
    """The dataset named in report.json (absolute, or relative to the run folder, or else to the working
    folder; "." is the run folder itself, as for a job whose output is a dataset)."""
    from scope3d.io.dataset import load_dataset

    name = report.get("dataset")
    if not name:
        return None
    if not isinstance(name, str):
        notes.append(f"dataset {name!r:.80} not read: not a path")
        return None
    for candidate in (run_dir / name, Path(name)):
        try:
            found = (candidate / "dataset.json").is_file() or (candidate / "poses.csv").is_file()
        except OSError:  # a name longer than the file system allows (ENAMETOOLONG; found by the long fuzz run)
            found = False
        if found:
            try:
                return load_dataset(candidate)
            except InputError as exc:
                notes.append(f"dataset {name} not read: {exc}")
                return None
    notes.append(f"dataset {name} not found: no cameras from it, no errors against ground truth")
    return None


def _cameras(run_dir: Path, dataset, notes: list[str]) -> tuple[Camera | None, list[str], list[Pose]]:
    """The adjusted cameras of the run's COLMAP model (sparse/) when there is one, else the dataset's
    measured poses: intrinsics, frame names and cam_from_world poses."""
    sparse = run_dir / "sparse"
    if (sparse / "images.txt").is_file():
        from scope3d.io.colmap import read_colmap_text

        try:
            model = read_colmap_text(sparse, points=False)  # the cameras only: the points are in points.ply
            camera = model.cameras[0]
            # COLMAP's files have no circular field of view: the dataset's camera holds it
            if dataset is not None and (dataset.camera.width, dataset.camera.height) == (camera.width, camera.height):
                camera = replace(camera, mask_radius_px=dataset.camera.mask_radius_px)
            return camera, list(model.image_names), list(model.poses)
        except InputError as exc:
            notes.append(f"sparse model not read: {exc}")
    if dataset is not None:
        return dataset.camera, dataset.names, [m.pose for m in dataset.poses]
    return None, [], []


def encode(array: np.ndarray, dtype) -> str:
    """Base64 of the array's little-endian bytes (what the viewer decodes into a typed array)."""
    return base64.b64encode(np.ascontiguousarray(array, dtype=np.dtype(dtype).newbyteorder("<")).tobytes()).decode()


def scene_payload(scene: ViewScene) -> dict:
    """The JSON the viewer reads: positions relative to the scene's centre (float32 keeps 0.1 µm there),
    colours as RGB bytes, faces as uint32, segments, targets, up axis."""
    pts = [layer.positions for layer in scene.layers] + [scene.trajectory]
    stacked = np.concatenate([p for p in pts if len(p)]) if any(len(p) for p in pts) else np.zeros((1, 3))
    centre = 0.5 * (stacked.min(axis=0) + stacked.max(axis=0))
    radius = float(np.linalg.norm(stacked - centre, axis=1).max()) or 1.0
    layers = []
    for layer in scene.layers:
        layers.append({
            "name": layer.name, "count": int(len(layer.positions)), "file_count": layer.n_file,
            "positions": encode(layer.positions - centre, np.float32),
            "faces": None if layer.faces is None else encode(layer.faces, np.uint32),
            "n_faces": 0 if layer.faces is None else int(len(layer.faces)),
            "colours": {k: encode(v, np.uint8) for k, v in layer.colours.items()},
            "uv": None if layer.uv is None else encode(layer.uv, np.float32),
            "texture": None if layer.texture_jpeg is None else
            "data:image/jpeg;base64," + base64.b64encode(layer.texture_jpeg).decode(),
        })
    return {
        "centre_mm": centre.tolist(), "radius_mm": radius, "up": scene.up.tolist(), "layers": layers,
        "frusta": encode(scene.frusta.reshape(-1, 3) - centre, np.float32) if len(scene.frusta) else None,
        "trajectory": encode(scene.trajectory - centre, np.float32) if len(scene.trajectory) > 1 else None,
        "targets": [{"label": t.get("label"), "centre": (np.asarray(t["centroid_mm"], float) - centre).tolist(),
                     "size_mm": _size(t, "size_mm")} for t in scene.targets if "centroid_mm" in t],
        "true_targets": [{"name": t.get("name"), "centre": (np.asarray(t["true_centre_mm"], float) - centre).tolist(),
                          "size_mm": _size(t, "true_size_mm")} for t in scene.true_targets],
        "explorer": explorer_payload(scene, centre),
    }


def explorer_payload(scene: ViewScene, centre: np.ndarray) -> dict | None:
    """What the explorer projects a clicked spot with: the intrinsics (pinhole + k1, k2 and the circular
    field) and, per frame, R and t of cam_from_world taken to the page's centred coordinates
    (x_cam = R (p + centre) + t = R p + t'), with its picture as a data URI. None without cameras."""
    camera = scene.camera
    if camera is None or not scene.frames:
        return None
    frames = []
    for frame in scene.frames:
        rotation = frame.pose.rotation
        frames.append({
            "name": frame.name, "R": rotation.ravel().tolist(),
            "t": (rotation @ centre + frame.pose.translation).tolist(),
            "picture": None if frame.thumbnail is None else
            "data:image/jpeg;base64," + base64.b64encode(frame.thumbnail).decode(),
        })
    return {"camera": {"width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy,
                       "cx": camera.cx, "cy": camera.cy, "model": camera.model,
                       "param_names": list(camera.param_names), "params": camera.params.tolist(),
                       "fisheye": camera.lens.is_fisheye, "max_half_angle_rad": camera.max_half_angle_rad,
                       "mask_radius_px": camera.mask_radius_px},
            "frames": frames, "inside": scene.inside, "centre_mm": centre.tolist()}
