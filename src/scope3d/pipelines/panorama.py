"""Organ panorama jobs (reference ch. 2): plan a scan of a cavity.

``plan_scan(options, surface, out_dir)`` reads as the method of sec. 2.3.2::

    wall      <- a phantom's mesh or a PLY mesh
    plan      <- spiral of perpendicular views at the stand-off, lateral overlap F (sfm.scan_planning)
    coverage  <- ray casting every view onto the wall (with and without the bending limit)
    files     <- plan.json (n_views, coverage_fraction, poses), plan.png

The CLI (``scope3d plan-scan``) calls the same function.
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.io.ply import read_ply
from scope3d.io.scan_plan import write_scan_plan
from scope3d.phantoms.raycast import RayCaster
from scope3d.phantoms.scenes import SCENES, build_scene
from scope3d.scene.mesh import Mesh
from scope3d.sfm.scan_planning import ScanPlan, ScanPlanOptions, plan_spiral_scan
from scope3d.utils.figures import new_figure, save_figure
from scope3d.utils.jsonio import write_json
from scope3d.utils.progress import stage


def load_surface(surface: str | Path) -> tuple[Mesh, RayCaster, str]:
    """A phantom name (``bladder``...) or a PLY mesh file -> (mesh, ray caster, description)."""
    if str(surface) in SCENES:
        scene = build_scene(str(surface))
        return scene.mesh, scene.caster, f"phantom {surface}"
    path = Path(surface)
    if not path.is_file():
        raise InputError(f"{surface}: neither a phantom ({', '.join(SCENES)}) nor a PLY file")
    mesh = read_ply(path)
    if not isinstance(mesh, Mesh) or len(mesh.faces) == 0:
        raise InputError(f"{path}: the PLY file has no faces; the scan planner needs a surface mesh")
    return mesh, RayCaster(mesh), str(path)


def plan_scan(options: ScanPlanOptions, surface: str | Path, out_dir: str | Path) -> ScanPlan:
    """Plan a spiral scan of ``surface`` and write ``plan.json``, ``plan.png`` and ``report.json`` (the plan's
    figures: views, coverage, options) into ``out_dir``."""
    mesh, caster, source = load_surface(surface)
    try:
        plan = plan_spiral_scan(mesh, options, caster=caster)
    except ValueError as exc:
        raise InputError(f"{surface}: {exc}") from None
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    info = {
        "surface": source,
        "coverage_fraction": plan.coverage.fraction,
        "coverage_fraction_without_bend_limit": plan.coverage_unlimited.fraction,
        "coverage_lost_to_bend_limit": plan.coverage_unlimited.fraction - plan.coverage.fraction,
        "n_planned_views": plan.n_planned,
        "n_sections": int(len(np.unique(plan.sections))),
        "coverage_method": "face centroids inside some view's circular field, within max_range_mm, not occluded "
                           "(ray cast on the mesh); area-weighted",
        "options": asdict(plan.options),
        "camera": {"width": plan.camera.width, "height": plan.camera.height, "fx": plan.camera.fx,
                   "mask_radius_px": plan.camera.mask_radius_px},
    }
    write_scan_plan(out / "plan.json", plan.poses, plan.sections, options.fov_deg,
                    wall_points_mm=plan.wall_points_mm, bend_deg=plan.bend_deg, info=info)
    plot_plan(plan, mesh, out / "plan.png")
    # the plan's figures without its views (those are plan.json's): what the job's report shows
    write_json(out / "report.json", {"job": "plan-scan", **info, "n_views": len(plan.poses),
                                     "fov_deg": options.fov_deg})
    return plan


def plot_plan(plan: ScanPlan, mesh: Mesh, path: str | Path) -> None:
    """The wall's face centroids (grey: unseen, blue: seen) and the views' wall points joined in scan order."""
    fig = new_figure((6.0, 5.5), dpi=110)
    ax = fig.add_subplot(projection="3d")
    centroids = mesh.vertices[mesh.faces].mean(axis=1)
    stride = max(1, len(centroids) // 6000)
    sub = np.arange(0, len(centroids), stride)
    seen = plan.coverage.seen_faces[sub]
    ax.scatter(*centroids[sub][~seen].T, s=1, c="0.75", alpha=0.4, label="not seen")
    ax.scatter(*centroids[sub][seen].T, s=1, c="tab:blue", alpha=0.15, label="seen")
    for k in np.unique(plan.sections):
        w = plan.wall_points_mm[plan.sections == k]
        ax.plot(*w.T, "-o", ms=2, lw=1)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title(f"{plan.n_views} views, coverage {plan.coverage.fraction:.1%}", fontsize=10)
    ax.set_box_aspect(np.ptp(mesh.vertices, axis=0))
    save_figure(fig, path)


# --- 2-D mosaic ----------------------------------------------------------------------------------


def _sections(dataset) -> np.ndarray:
    """Scan section (spiral turn) per frame from the phantom's trajectory, else one section."""
    gt = dataset.ground_truth
    traj = (gt.scene.get("trajectory") or {}) if gt is not None else {}
    sections = traj.get("sections")
    if isinstance(sections, list) and len(sections) == len(dataset):
        return np.asarray(sections, dtype=int)
    return np.zeros(len(dataset), dtype=int)


def _planar_truth(datasets) -> tuple[np.ndarray, np.ndarray] | None:
    """(origin, normal) of the true surface when every dataset has true poses and the same flat surface."""
    planes = []
    for ds in datasets:
        gt = ds.ground_truth
        if gt is None or gt.poses is None or gt.surface_path is None:
            return None
        v = gt.surface().vertices
        centre = v.mean(axis=0)
        _, s, vt = np.linalg.svd(v - centre, full_matrices=False)
        if s[2] > 1e-9 * max(s[0], 1.0):
            return None
        planes.append((centre, vt[2]))
    o, n = planes[0]
    if any(abs(np.dot(n2, o2 - o)) > 1e-6 or abs(abs(np.dot(n2, n)) - 1) > 1e-9 for o2, n2 in planes[1:]):
        return None
    return o, n


def make_mosaic(options, datasets: list, out_dir: str | Path, *, progress=None):
    """2-D mosaic of one or more datasets (reference sec. 2.3.3) into ``out_dir``: ``mosaic.png`` (with the
    scope's path per scan section), ``coverage.png``, ``report.json``. Returns the report.

    options : :class:`~scope3d.registration.mosaic.MosaicOptions`. Frames of all datasets are matched
    together (a 15 mm and a 30 mm scan fill each other's gaps, sec. 2.4.2); frame 0 of the first dataset
    is the mosaic's frame. ``alignment_error_px`` is measured where the truth is a plane.
    Returns (report dict, :class:`~scope3d.registration.mosaic.Mosaic`).
    """
    import time

    from scope3d.io.images import write_image
    from scope3d.registration import mosaic as mos

    t0, c0 = time.perf_counter(), time.process_time()
    frames, cameras, sections, owner, true_poses = [], [], [], [], []
    for k, ds in enumerate(datasets):
        frames += [ds.frame(i) for i in range(len(ds))]
        cameras += [ds.camera] * len(ds)
        sections += list(_sections(ds) + 1000 * k)
        owner += [k] * len(ds)
        if ds.ground_truth is not None and ds.ground_truth.poses is not None:
            true_poses += list(ds.ground_truth.poses)
    if len(frames) < 2:
        raise InputError("a mosaic needs at least two frames")
    stage(progress, "mosaic: matching pairs", len(frames) * (len(frames) - 1) // 2)
    links = mos.link_frames(frames, cameras, options, progress=progress)
    try:
        result = mos.align_globally(len(frames), links, [(c.width, c.height) for c in cameras], options)
    except ValueError as exc:
        raise InputError(f"{datasets[0].root}: {exc} (frames without overlap)") from None
    mos.blend(result, frames, cameras, options)
    centres = mos.frame_centres(result, cameras)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_image(out / "mosaic.png", result.image)
    write_image(out / "mosaic_path.png", mos.draw_path(result.image, centres, np.asarray(sections)))
    write_image(out / "coverage.png", (result.coverage * 255).astype(np.uint8))
    report = {
        "n_frames": len(frames),
        "n_registered": int(result.registered.sum()),
        "n_linked_pairs": len(result.links),
        "datasets": [str(ds.root) for ds in datasets],
        "frames_per_dataset": [len(ds) for ds in datasets],
        "registered_per_dataset": [int(result.registered[np.asarray(owner) == k].sum()) for k in range(len(datasets))],
        "coverage_fraction": mos.coverage_fraction(result.coverage),
        "coverage_definition": "mosaic pixels seen by some frame over the convex hull of them (holes = missed areas)",
        "residual_px": {"mean": float(result.residual_px.mean()), "p95": float(np.percentile(result.residual_px, 95))},
        "canvas_px": list(result.image.shape[1::-1]),
        "time_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
    }
    plane = _planar_truth(datasets) if len(true_poses) == len(frames) else None
    if plane is not None:
        truth = mos.true_plane_homographies(cameras, true_poses, *plane)
        err = mos.alignment_errors_px(result, truth, cameras)
        report["alignment_error_px"] = {"mean": float(err.mean()), "p95": float(np.percentile(err, 95)),
                                        "unit": "pixels of the first frame (the mosaic's frame)"}
    else:
        report["alignment_error_px"] = None
        report["alignment_error_note"] = "no planar ground truth (a curved wall has no exact 2-D mosaic)"
    write_json(out / "report.json", report)
    return report, result
