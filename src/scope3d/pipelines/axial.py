"""Axial-stereo dense metrology of an internal surface (reference ch. 7 and sec. 9.2), as one job.

Read top to bottom like the method section::

    pairs/references <- choose frames              (two-view: I, J; multi-view: every stride)
    depth            <- stereo.reconstruct_pair    (polar resampling, SGM or SAD, mask, eq. 7.3)
                        or stereo.reconstruct_reference (multi-baseline fusion)
    cloud, mesh      <- grid points and grid-neighbour triangles
    evaluation       <- distance to the true mesh when the dataset has one
    files            <- cloud.ply, mesh.ply, depth.png, error_histogram.png, report.json

``run(options, dataset, out_dir) -> AxialResult`` is what the CLI (``scope3d axial``) calls.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.io.dataset import Dataset, check_jobs_take
from scope3d.io.ply import write_ply
from scope3d.mvs.axial import PolarGridOptions
from scope3d.mvs.confidence import ConfidenceOptions
from scope3d.mvs.dense_matching import SgmOptions
from scope3d.mvs.multiview import MultiViewOptions, reconstruct_reference, reference_frames
from scope3d.mvs.two_view import ImageDepth, TwoViewOptions, grid_mesh_faces, reconstruct_pair, to_image
from scope3d.scene.mesh import Mesh, PointCloud
from scope3d.utils.atomic import atomic_directory
from scope3d.utils.figures import new_figure, save_figure
from scope3d.utils.jsonio import write_json
from scope3d.utils.progress import Progress, advance, stage

METHODS = ("sgm", "sad", "multiview")


def _default_two_view() -> TwoViewOptions:
    # Defaults for a forward-looking scope in a bore: the nearest wall is ~ r / tan(fov / 2) away (4.7 mm
    # for an M8 hole and 70 deg), so 3 mm bounds the search; tall refinement windows follow the rings.
    # Measured on the M8 phantom (benchmarks/bench_axial.py, docs/axial_stereo.md): 7x7 SGM blocks beat
    # 5x5 on the turned wall, and a single refinement step beats iterating to convergence there (the
    # converged Lucas-Kanade fixed point is pulled off by what is not a pure shift between the views:
    # view-dependent specular highlights and shading, disparity gradients across thread flanks).
    # Points are kept when their predicted range sigma (eq. 7.3 propagated, sigma_d >= 0.02 column) is
    # within the 0.05 mm accuracy target of issue 5.
    return TwoViewOptions(
        min_depth_mm=3.0,
        grid=PolarGridOptions(min_radius_px=30.0),
        sgm=SgmOptions(block_size=7, refine_window_px=5, refine_window_rows=21, refine_iterations=1),
        confidence=ConfidenceOptions(max_normalised_cost=0.8, disparity_sigma_floor_px=0.02, max_range_sigma_mm=0.05),
    )


@dataclass(frozen=True)
class AxialOptions:
    """What to reconstruct and how.

    method : "sgm" | "sad" (two-view) or "multiview" (fusion along the hole, sec. 9.2).
    frames : (I, J) for two-view; None = the middle two consecutive frames.
    use_true_poses : use the dataset's ground-truth poses instead of the measured ones (benchmarks).
    two_view : options of every pair; multiview : fusion options (its own ``two_view`` is replaced by
        ``two_view`` here so that one place holds them).
    max_mesh_edge_ratio : grid triangles with an edge longer than this fraction of the range are depth
        jumps and are dropped.
    evaluation_step_mm : sampling of the true mesh for the error figures.
    """

    method: str = "sgm"
    frames: tuple[int, int] | None = None
    use_true_poses: bool = False
    two_view: TwoViewOptions = field(default_factory=_default_two_view)
    multiview: MultiViewOptions = field(default_factory=MultiViewOptions)
    max_mesh_edge_ratio: float = 0.05
    evaluation_step_mm: float = 0.05

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown axial method {self.method!r} (use one of {', '.join(METHODS)})")
        if self.frames is not None and len(self.frames) != 2:
            raise ValueError("AxialOptions.frames must be two frame indices")


@dataclass(frozen=True)
class AxialResult:
    """cloud : coloured PointCloud (mm, world); mesh : grid-neighbour Mesh; depths : per reference frame
    ImageDepth; report : the dict written to report.json; out_dir : where the files are."""

    cloud: PointCloud
    mesh: Mesh
    depths: list[ImageDepth]
    report: dict
    out_dir: Path | None

    @property
    def points(self) -> np.ndarray:
        """(N, 3) mm world, the cloud's points."""
        return self.cloud.points

    @property
    def colors(self) -> np.ndarray | None:
        """(N, 3) uint8 RGB, each point's colour."""
        return self.cloud.colors

    def summary(self) -> str:
        r = self.report
        line = f"axial {r['method']}: {r['n_points']} points in {r['time_s']:.2f} s"
        err = r.get("surface_error_mm")
        if err and err.get("n"):
            line += f"; distance to true surface mean {err['mean']:.4f} mm, median {err['median']:.4f}, p95 {err['p95']:.4f}"
        return line


def _poses(dataset: Dataset, use_true: bool):
    if use_true:
        if dataset.ground_truth is None or dataset.ground_truth.poses is None:
            raise InputError(f"{dataset.root}: no ground-truth poses (use the measured poses)")
        return list(dataset.ground_truth.poses)
    return [m.pose for m in dataset.poses]


def _check_frame(dataset: Dataset, index: int) -> int:
    if not -len(dataset) <= index < len(dataset):
        raise InputError(f"frame {index} does not exist (the dataset has {len(dataset)} frames, 0..{len(dataset) - 1})")
    return index % len(dataset)


def check_dataset(options: AxialOptions, dataset: Dataset) -> None:
    """What the job refuses before any work (``scope3d check --for axial`` runs it too): raises InputError."""
    check_jobs_take(dataset.camera, dataset.root / "camera.json", "axial")
    _poses(dataset, options.use_true_poses)
    if options.method in ("sgm", "sad"):
        if len(dataset) < 2:
            raise InputError(f"{dataset.root}: axial stereo needs at least two frames")
        for index in options.frames or ():
            _check_frame(dataset, index)
    elif not reference_frames(len(dataset), options=_multiview_options(options)):
        raise InputError(f"{dataset.root}: {len(dataset)} frames are too few for multi-view with offsets "
                         f"{options.multiview.baseline_offsets}")


def _multiview_options(options: AxialOptions) -> MultiViewOptions:
    return MultiViewOptions(**{**{k: getattr(options.multiview, k) for k in options.multiview.__dataclass_fields__},
                               "two_view": options.two_view})


def reconstruct(options: AxialOptions, dataset: Dataset, *, progress: Progress | None = None,
                ) -> tuple[list[ImageDepth], list[np.ndarray], dict]:
    """The depth stage: returns per-reference ImageDepth, their colour images (H, W, 3) and timings.

    progress : tqdm-like or None, advanced by one per multi-view reference frame.
    """
    check_dataset(options, dataset)
    poses = _poses(dataset, options.use_true_poses)
    cam = dataset.camera
    t0 = time.perf_counter()
    if options.method in ("sgm", "sad"):
        i, j = options.frames if options.frames is not None else (len(dataset) // 2 - 1, len(dataset) // 2)
        i, j = _check_frame(dataset, i), _check_frame(dataset, j)
        tv = TwoViewOptions(**{**{k: getattr(options.two_view, k) for k in options.two_view.__dataclass_fields__},
                               "method": options.method})
        res = reconstruct_pair(cam, dataset.frame(i, grey=True), dataset.frame(j, grey=True), poses[i], poses[j],
                               options=tv)
        depth = to_image(res.pair, res.range_mm, res.reliability.confidence)
        front = j if not res.pair.swapped else i
        timing = {"pairs": 1, "timings_s": {"per_pair": res.time_s["total"], "stages": res.time_s},
                  "frames": [i, j], "front_frame": front, "baseline_mm": res.pair.baseline_mm,
                  "axis_angle_deg": float(np.rad2deg(res.pair.axis_angle_rad))}
        return [depth], [dataset.frame(front)], timing
    mv = _multiview_options(options)
    refs = reference_frames(len(dataset), options=mv)
    stage(progress, "axial multiview", len(refs))
    depths, colours = [], []
    for ref in refs:
        fused = reconstruct_reference(cam, lambda k: dataset.frame(k, grey=True), poses, ref, options=mv)
        depths.append(fused.depth)
        colours.append(dataset.frame(ref))
        advance(progress)
    n_pairs = len(refs) * len(mv.baseline_offsets)
    elapsed = time.perf_counter() - t0
    return depths, colours, {"pairs": n_pairs, "references": refs, "timings_s": {"per_pair": elapsed / n_pairs}}


def build_geometry(depths: list[ImageDepth], colours: list[np.ndarray], max_edge_ratio: float) -> tuple[PointCloud, Mesh]:
    """Stack every reference's valid pixels into one coloured cloud and grid-neighbour mesh."""
    points, cols, faces = [], [], []
    offset = 0
    for depth, colour in zip(depths, colours):
        valid = depth.valid
        index = np.full(valid.shape, -1, np.int64)
        index[valid] = np.arange(np.count_nonzero(valid)) + offset
        f = grid_mesh_faces(depth.points_world, np.where(valid, depth.range_mm, np.nan), max_edge_ratio=max_edge_ratio)
        faces.append(index.reshape(-1)[f])
        points.append(depth.points_world[valid])
        cols.append(colour[valid])
        offset += int(np.count_nonzero(valid))
    pts = np.concatenate(points) if points else np.zeros((0, 3))
    rgb = np.concatenate(cols) if cols else np.zeros((0, 3), np.uint8)
    tri = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
    return PointCloud(pts, rgb), Mesh(pts, tri, rgb)


def evaluate(cloud: PointCloud, dataset: Dataset, step_mm: float) -> tuple[dict | None, np.ndarray | None]:
    """Distance of every point to the true mesh (when the dataset has one): summary dict and (N,) mm."""
    gt = dataset.ground_truth
    if gt is None or gt.surface_path is None or len(cloud) == 0:
        return None, None
    from scope3d.metrology.evaluation import distance_summary
    from scope3d.scene.mesh import SampledSurface

    distances = SampledSurface(gt.surface(), step_mm).distances(cloud.points)
    return distance_summary(distances), distances


def save_depth_png(path: Path, depth: ImageDepth, *, title: str) -> None:
    """z-depth map (mm) with a colour bar; pixels without depth are white."""
    z = np.where(depth.valid, depth.z_depth_mm, np.nan)
    fig = new_figure((5.6, 4.8), dpi=110)
    ax = fig.add_subplot()
    finite = z[np.isfinite(z)]
    lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0, 1))
    im = ax.imshow(z, cmap="turbo", vmin=lo, vmax=hi)
    fig.colorbar(im, ax=ax, label="z-depth (mm)")
    ax.set_title(title)
    ax.set_axis_off()
    fig.tight_layout()
    save_figure(fig, path)


def run(options: AxialOptions, dataset: Dataset, out_dir: str | Path | None, *,
        progress: Progress | None = None) -> AxialResult:
    """Reconstruct, evaluate and (when ``out_dir`` is given) write the job's files, atomically: ``out_dir`` is
    replaced as a whole once the new folder is complete. progress : tqdm-like or None
    (:mod:`scope3d.utils.progress`)."""
    t0 = time.perf_counter()
    depths, colours, timing = reconstruct(options, dataset, progress=progress)
    cloud, mesh = build_geometry(depths, colours, options.max_mesh_edge_ratio)
    elapsed = time.perf_counter() - t0
    summary, distances = evaluate(cloud, dataset, options.evaluation_step_mm)
    report = {
        "method": options.method,
        "dataset": str(dataset.root),
        "poses": "true" if options.use_true_poses else "measured",
        "n_points": int(len(cloud)),
        "n_faces": int(len(mesh.faces)),
        "time_s": elapsed,
        **timing,
        "options": asdict(options),
    }
    if summary is not None:
        report["surface_error_mm"] = summary
    if out_dir is not None:
        with atomic_directory(Path(out_dir)) as out:  # the previous complete folder until this one is
            _write_files(out, options, cloud, mesh, depths, distances, report)
    return AxialResult(cloud, mesh, depths, report, Path(out_dir) if out_dir is not None else None)


def _write_files(out: Path, options: AxialOptions, cloud: PointCloud, mesh: Mesh, depths: list[ImageDepth],
                 distances: np.ndarray | None, report: dict) -> None:
    write_ply(out / "cloud.ply", cloud)
    write_ply(out / "mesh.ply", mesh)
    save_depth_png(out / "depth.png", depths[len(depths) // 2], title=f"axial {options.method}: depth")
    if distances is not None:
        from scope3d.metrology.evaluation import save_error_histogram_png

        save_error_histogram_png(out / "error_histogram.png", distances,
                                 title=f"axial {options.method}: distance to the true surface")
    write_json(out / "report.json", report)
