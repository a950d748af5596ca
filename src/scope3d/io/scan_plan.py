"""``plan.json``: a planned scan (``scope3d plan-scan``), read back by the phantom lab (``--plan``).

Layout (lengths in mm, angles in degrees)::

    {"kind": "scope3d scan plan", "version": 1,
     "n_views": N, "coverage_fraction": f, "standoff_mm": s, "overlap": F, "fov_deg": a, ...,
     "views": [{"index": i, "section": k, "centre_mm": [x, y, z], "view_direction": [dx, dy, dz],
                "cam_from_world": {"quaternion_xyzw": [...], "translation_mm": [...]},
                "wall_point_mm": [...], "bend_deg": b}, ...]}

``section`` is the spiral turn a view belongs to (0 = the first turn), used to draw the scope's path.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.io.json_object import read_json_object
from scope3d.utils.jsonio import write_json

PLAN_KIND = "scope3d scan plan"


@dataclass(frozen=True)
class PlanFile:
    """poses : ``cam_from_world`` per view (mm). sections : (N,) int. fov_deg : the planning camera's field
    of view across its circular field. info : every other top-level entry of the file."""

    poses: list[Pose]
    sections: np.ndarray
    fov_deg: float
    info: dict


def write_scan_plan(path: str | Path, poses: list[Pose], sections, fov_deg: float, *, wall_points_mm=None,
                    bend_deg=None, info: dict | None = None) -> None:
    """Write ``plan.json`` atomically. wall_points_mm : (N, 3) or None; bend_deg : (N,) or None;
    info : extra top-level entries (``n_views``, ``coverage_fraction``, options...)."""
    views = []
    for i, pose in enumerate(poses):
        v = {"index": i, "section": int(sections[i]), "centre_mm": pose.centre.tolist(),
             "view_direction": pose.rotation[2].tolist(),
             "cam_from_world": {"quaternion_xyzw": pose.quaternion.tolist(), "translation_mm": pose.translation.tolist()}}
        if wall_points_mm is not None:
            v["wall_point_mm"] = np.asarray(wall_points_mm[i], float).tolist()
        if bend_deg is not None:
            v["bend_deg"] = float(bend_deg[i])
        views.append(v)
    write_json(path, {"kind": PLAN_KIND, "version": 1, **(info or {}), "fov_deg": float(fov_deg),
                      "n_views": len(poses), "views": views})


def read_scan_plan(path: str | Path) -> PlanFile:
    """Read ``plan.json``. Every problem is an InputError naming the file (and the view)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: scan plan is missing")
    data = read_json_object(path)
    if data.get("kind") != PLAN_KIND:
        raise InputError(f"{path}: not a scope3d scan plan (kind {PLAN_KIND!r} missing)")
    views = data.get("views")
    if not isinstance(views, list) or not views:
        raise InputError(f"{path}: the plan has no views")
    try:
        fov = float(data["fov_deg"])
    except (KeyError, TypeError, ValueError, OverflowError):
        raise InputError(f"{path}: fov_deg missing or not a number") from None
    if not 0 < fov < 180:
        raise InputError(f"{path}: fov_deg must be in (0, 180), got {fov}")
    poses, sections = [], []
    for i, v in enumerate(views):
        try:
            q = np.asarray(v["cam_from_world"]["quaternion_xyzw"], float).reshape(4)
            t = np.asarray(v["cam_from_world"]["translation_mm"], float).reshape(3)
            if not abs(np.linalg.norm(q) - 1.0) < 1e-6:
                raise ValueError("quaternion is not unit")
            poses.append(Pose.from_quaternion(q, t))
            section = int(v.get("section", 0))
            if not -2**63 <= section < 2**63:  # -1e308 is a (huge) int, which the int64 array cannot hold
                raise ValueError(f"section {v['section']} is beyond int64")
            sections.append(section)
        except (KeyError, TypeError, ValueError, OverflowError) as exc:  # "section": Infinity
            raise InputError(f"{path}: view {i}: bad pose ({exc})") from None
    info = {k: val for k, val in data.items() if k not in ("views", "fov_deg", "kind", "version")}
    return PlanFile(poses, np.asarray(sections, dtype=int), fov, info)
