"""What the report's 3D view shows, gathered from a run folder: the job's clouds and meshes (decimated
for the page), their colourings (height, error against the true surface, texture), the cameras'
frusta along the trajectory and the fluorescent targets. Lengths in mm, world frame of the run."""
from __future__ import annotations

import base64
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.plane import principal_axes
from scope3d.geometry.pose import Pose
from scope3d.io.ply import read_ply
from scope3d.scene.mesh import Mesh, SampledSurface
from scope3d.sensor.camera import Camera

# The geometry files a job may leave, in the order the view lists them; ``texture_from`` names a file
# holding the same vertices coloured by reflectance only (the map's mesh.ply carries the fluorescence
# overlay, mesh_reflectance.ply the plain texture).
GEOMETRY_FILES = ("mesh.ply", "cloud.ply", "points.ply")
TEXTURE_FROM = {"mesh.ply": "mesh_reflectance.ply"}


@dataclass(frozen=True)
class ReportOptions:
    """How the page is built.

    max_points : int, vertices drawn per layer at most; a larger cloud is thinned to a seeded random
        subset (the full PLY stays linked). max_faces : int, triangles drawn per mesh at most; a larger
        mesh is drawn as its (thinned) vertices. seed : int, the thinning's seed (same page for the same
        run). frustum_depth_fraction : float, frustum depth as a fraction of the scene's diagonal.
    error_scale_percentile : float, top of the error colour scale (percentile of the errors, so one far
        outlier does not wash the rest out).
    """

    max_points: int = 200_000
    max_faces: int = 400_000
    seed: int = 0
    frustum_depth_fraction: float = 0.08
    error_scale_percentile: float = 95.0

    def __post_init__(self) -> None:
        if self.max_points < 1 or self.max_faces < 1:
            raise ValueError("max_points and max_faces must be >= 1")
        if not 0 < self.frustum_depth_fraction <= 1:
            raise ValueError("frustum_depth_fraction must be in (0, 1]")
        if not 0 < self.error_scale_percentile <= 100:
            raise ValueError("error_scale_percentile must be in (0, 100]")


@dataclass
class Layer:
    """One geometry file as drawn. positions : (N, 3) float64 mm world; faces : (F, 3) int or None
    (points); colours : colouring name -> (N, 3) uint8 RGB; n_file : vertices in the file (N < n_file
    when thinned); error_mm : (N,) distances to the true surface or None."""

    name: str
    positions: np.ndarray
    faces: np.ndarray | None
    colours: dict[str, np.ndarray]
    n_file: int
    n_faces_file: int
    error_mm: np.ndarray | None = None


@dataclass
class ViewScene:
    """Everything the viewer draws; see :func:`gather_scene`. frusta : (S, 2, 3) mm line segments;
    trajectory : (M, 3) mm camera centres in frame order; targets / true_targets : dicts from report.json;
    up : (3,) unit height direction; scales : colouring name -> (low, high, unit) of its colour bar."""

    layers: list[Layer]
    frusta: np.ndarray
    trajectory: np.ndarray
    targets: list[dict]
    true_targets: list[dict]
    up: np.ndarray
    scales: dict[str, tuple[float, float, str]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


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


def _height_axis(points: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Unit normal of the points' least-squares plane, facing the cameras (world +z when unknown)."""
    if len(points) < 3:
        return np.array([0.0, 0.0, 1.0])
    centroid, axes = principal_axes(points)
    n = axes[-1]
    towards = (centres.mean(axis=0) - centroid) if len(centres) else np.array([0.0, 0.0, 1.0])
    return -n if np.dot(n, towards) < 0 else n


def camera_frusta(camera: Camera, poses: list[Pose], depth_mm: float) -> np.ndarray:
    """(8 M, 2, 3) mm line segments: each camera's four edges from its centre to the image corners at
    z-depth ``depth_mm``, and the four edges of that far rectangle."""
    corners_px = np.array([[-0.5, -0.5], [camera.width - 0.5, -0.5], [camera.width - 0.5, camera.height - 0.5],
                           [-0.5, camera.height - 0.5]])
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
    camera, poses = _cameras(run_dir, dataset, notes)
    truth = None
    if dataset is not None and dataset.ground_truth is not None and dataset.ground_truth.surface_path is not None:
        from scope3d.metrology.evaluation import EvaluationOptions

        # sampled once for every layer, as the map's evaluation samples it (seeded: the same distances)
        truth = SampledSurface(dataset.ground_truth.surface(), EvaluationOptions().sample_step_mm)

    layers: list[Layer] = []
    for name in GEOMETRY_FILES:
        path = run_dir / name
        if not path.is_file():
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
    truth_targets = [t for t in report.get("targets_vs_truth") or [] if "true_centre_mm" in t]
    return ViewScene(layers, frusta, centres, list(report.get("targets") or []), truth_targets, up, scales, notes)


def _dataset(run_dir: Path, report: dict, notes: list[str]):
    """The dataset named in report.json (absolute, or relative to the run folder or the working folder)."""
    from scope3d.io.dataset import load_dataset

    name = report.get("dataset")
    if not name:
        return None
    for candidate in (Path(name), run_dir / name):
        if (candidate / "dataset.json").is_file() or (candidate / "poses.csv").is_file():
            try:
                return load_dataset(candidate)
            except InputError as exc:
                notes.append(f"dataset {name} not read: {exc}")
                return None
    notes.append(f"dataset {name} not found: no cameras from it, no errors against ground truth")
    return None


def _cameras(run_dir: Path, dataset, notes: list[str]) -> tuple[Camera | None, list[Pose]]:
    """The adjusted cameras of the run's COLMAP model (sparse/) when there is one, else the dataset's
    measured poses."""
    sparse = run_dir / "sparse"
    if (sparse / "images.txt").is_file():
        from scope3d.io.colmap import read_colmap_text

        try:
            model = read_colmap_text(sparse, points=False)  # the cameras only: the points are in points.ply
            return model.cameras[0], list(model.poses)
        except InputError as exc:
            notes.append(f"sparse model not read: {exc}")
    if dataset is not None:
        return dataset.camera, [m.pose for m in dataset.poses]
    return None, []


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
        })
    return {
        "centre_mm": centre.tolist(), "radius_mm": radius, "up": scene.up.tolist(), "layers": layers,
        "frusta": encode(scene.frusta.reshape(-1, 3) - centre, np.float32) if len(scene.frusta) else None,
        "trajectory": encode(scene.trajectory - centre, np.float32) if len(scene.trajectory) > 1 else None,
        "targets": [{"label": t.get("label"), "centre": (np.asarray(t["centroid_mm"], float) - centre).tolist(),
                     "size_mm": float(t.get("size_mm", 1.0))} for t in scene.targets if "centroid_mm" in t],
        "true_targets": [{"name": t.get("name"), "centre": (np.asarray(t["true_centre_mm"], float) - centre).tolist(),
                          "size_mm": float(t.get("true_size_mm", 1.0))} for t in scene.true_targets],
    }
