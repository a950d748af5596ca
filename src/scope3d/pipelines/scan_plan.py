"""Plan a scan of a cavity (reference sec. 2.3.2), ``scope3d plan-scan``. :func:`run` reads as the method::

    wall      <- a phantom's mesh or a PLY mesh
    plan      <- spiral of perpendicular views at the stand-off, lateral overlap F (sfm.scan_planning)
    coverage  <- ray casting every view onto the wall (with and without the bending limit)
    files     <- plan.json (n_views, coverage_fraction, poses), plan.png, report.json
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
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
from scope3d.utils.progress import Progress, stage


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


@dataclass
class ScanPlanResult:
    """plan : the planned scan (views, sections, coverage); report : report.json as written (the plan's
    figures without its views)."""

    plan: ScanPlan
    report: dict

    def summary(self) -> str:
        return self.plan.summary()


def run(options: ScanPlanOptions, surface: str | Path, out_dir: str | Path, *,
        progress: Progress | None = None) -> ScanPlanResult:
    """Plan a spiral scan of ``surface`` and write ``plan.json``, ``plan.png`` and ``report.json`` (the plan's
    figures: views, coverage, options) into ``out_dir``. progress : told the one stage (planning has no
    count to show)."""
    stage(progress, "plan-scan", None)
    mesh, caster, source = load_surface(surface)
    try:
        plan = plan_spiral_scan(mesh, options=options, caster=caster)
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
    report = {"job": "plan-scan", **info, "n_views": len(plan.poses), "fov_deg": options.fov_deg}
    write_json(out / "report.json", report)
    return ScanPlanResult(plan, report)


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
