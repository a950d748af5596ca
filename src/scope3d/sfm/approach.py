"""The tool's approach path to a target on the mapped surface, kept a safety distance off it (reference
sec. 5.1, Fig. 5.1: "an optimal surgical path of the tool can be designed ... and re-adjusted along the way
towards the residual tumor").

:func:`plan_approach` plans from the tool's current position to a goal a safety distance above the
target along the surface normal there, through a pre-goal on that normal (the last stretch is a straight
descent onto the target, the direction an instrument meets tissue), and pushes every point of the path
that comes closer than the safety distance to the map's points away from them, smoothing between pushes.
Re-planning is planning again from the newly localized position (:func:`replan`): the map and the goal
do not move, so the path converges as the tool follows it.

Clearance is measured to the map's sparse points, less half their typical spacing (a surface between
points can be that much closer than the nearest point). The tool tip is taken at the scope's centre; a
hand-eye offset moves both the same way.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from scope3d.geometry.plane import fit_plane
from scope3d.utils.figures import new_figure, save_figure


@dataclass(frozen=True)
class ApproachOptions:
    """safety_distance_mm : the path keeps at least this clearance from the mapped surface, and stops this
        far from the target (default 2 mm).
    descent_mm : length of the straight final descent along the target's normal (default 4 mm).
    step_mm : spacing of the path's points (default 0.25 mm).
    normal_radius_mm : points within this radius of the target give its normal (default 3 mm).
    max_iterations : push-and-smooth rounds (default 200).
    """

    safety_distance_mm: float = 2.0
    descent_mm: float = 4.0
    step_mm: float = 0.25
    normal_radius_mm: float = 3.0
    max_iterations: int = 200

    def __post_init__(self) -> None:
        if not (self.safety_distance_mm > 0 and self.descent_mm >= 0 and self.step_mm > 0 and self.normal_radius_mm > 0):
            raise ValueError("safety distance, step and normal radius must be positive, descent non-negative")
        if self.max_iterations < 0:
            raise ValueError("max_iterations must be >= 0")


@dataclass
class ApproachPath:
    """waypoints_mm : (N, 3) from the start to the goal. clearance_mm : (N,) to the mapped surface.
    goal_mm : (3,), target_mm : (3,), normal : (3,) unit, out of the surface at the target.
    feasible : every waypoint between the start and the final descent keeps the safety distance."""

    waypoints_mm: np.ndarray
    clearance_mm: np.ndarray
    goal_mm: np.ndarray
    target_mm: np.ndarray
    normal: np.ndarray
    feasible: bool

    @property
    def length_mm(self) -> float:
        return float(np.sum(np.linalg.norm(np.diff(self.waypoints_mm, axis=0), axis=1)))


def _polyline(points: np.ndarray, step_mm: float) -> np.ndarray:
    out = [points[0]]
    for a, b in zip(points[:-1], points[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step_mm)))
        out.extend(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.array(out)


def target_normal(surface_points_mm: np.ndarray, target_mm: np.ndarray, towards_mm: np.ndarray, radius_mm: float
                  ) -> np.ndarray:
    """Unit normal of the map's points near ``target_mm`` (least principal axis), pointing to ``towards_mm``."""
    near = surface_points_mm[np.linalg.norm(surface_points_mm - target_mm, axis=1) <= radius_mm]
    if len(near) < 3:
        raise ValueError(f"fewer than 3 map points within {radius_mm} mm of the target: no normal there")
    return fit_plane(near, towards=towards_mm - target_mm)[1][2]


def plan_approach(surface_points_mm: np.ndarray, target_mm: np.ndarray, start_mm: np.ndarray,
                  *,
                  options: ApproachOptions = ApproachOptions()) -> ApproachPath:
    """Plan from ``start_mm`` to a safety distance above ``target_mm`` (see the module docstring).

    surface_points_mm : (N, 3) the map's points (mm, world). target_mm, start_mm : (3,).
    """
    pts = np.asarray(surface_points_mm, float)
    target, start = np.asarray(target_mm, float), np.asarray(start_mm, float)
    normal = target_normal(pts, target, start, options.normal_radius_mm)
    goal = target + options.safety_distance_mm * normal
    pre_goal = goal + options.descent_mm * normal
    tree = cKDTree(pts)
    spacing = float(np.median(tree.query(pts, k=2)[0][:, 1]))

    def clearance(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d, i = tree.query(p)
        return d - spacing / 2.0, i

    to_pre_goal = _polyline(np.stack([start, pre_goal]), options.step_mm)
    path = _polyline(np.stack([start, pre_goal, goal]), options.step_mm)
    descent = np.arange(len(path)) >= len(to_pre_goal) - 1  # the straight final stretch, pre-goal included
    free = ~descent
    free[0] = False  # the start is where the tool is
    for _ in range(options.max_iterations):
        c, nearest = clearance(path)
        low = free & (c < options.safety_distance_mm)
        if not np.any(low):
            break
        # smooth (the pushes leave kinks), then push out by the shortfall plus a quarter step along the
        # direction away from the nearest point: the round ends on the push, so the check sees its result
        smooth = path.copy()
        smooth[1:-1] = 0.25 * path[:-2] + 0.5 * path[1:-1] + 0.25 * path[2:]
        path[free] = smooth[free]
        for _ in range(20):  # pushed away from one point, a waypoint can come near the next one
            c, nearest = clearance(path)
            low = free & (c < options.safety_distance_mm)
            if not np.any(low):
                break
            away = path[low] - pts[nearest[low]]
            away /= np.maximum(np.linalg.norm(away, axis=1, keepdims=True), 1e-12)
            path[low] += away * (options.safety_distance_mm - c[low] + options.step_mm / 4)[:, None]
    c, _ = clearance(path)
    # the start is where the tool is (it may already be closer); the descent ends at the goal by design
    feasible = bool(np.all(c[free] >= options.safety_distance_mm - 1e-9))
    return ApproachPath(path, c, goal, target, normal, feasible)


def replan(path: ApproachPath, surface_points_mm: np.ndarray, position_mm: np.ndarray,
           *,
           options: ApproachOptions = ApproachOptions()) -> ApproachPath:
    """The path again from ``position_mm`` (the newly localized tool) to the same target."""
    return plan_approach(surface_points_mm, path.target_mm, position_mm, options=options)


def save_approach_png(path, surface_points_mm: np.ndarray, plans: list[ApproachPath], *,
                      travelled_mm: np.ndarray | None = None, title: str = "approach path over the map") -> None:
    """The map's points from the side and from above, each plan (first dark, re-plans lighter), the
    travelled path, the target and the goal."""
    fig = new_figure((11.0, 4.6), dpi=100)
    axes = fig.subplots(1, 2)
    pts = np.asarray(surface_points_mm)
    for ax, (a, b, label) in zip(axes, ((0, 2, "side: x, z (mm)"), (0, 1, "above: x, y (mm)"))):
        ax.scatter(pts[:, a], pts[:, b], s=1, c=pts[:, 2], cmap="copper", alpha=0.5)
        for k, plan in enumerate(plans):
            w = plan.waypoints_mm
            ax.plot(w[:, a], w[:, b], "-", color=(0.1, 0.3 + 0.6 * k / max(len(plans), 1), 0.9), lw=1.5,
                    label="plan" if k == 0 else ("re-plans" if k == 1 else None))
        if travelled_mm is not None:
            ax.plot(travelled_mm[:, a], travelled_mm[:, b], "k.", ms=3, label="localized tool")
        t, g = plans[0].target_mm, plans[0].goal_mm
        ax.plot(t[a], t[b], "g*", ms=12, label="target")
        ax.plot(g[a], g[b], "rx", ms=8, label=f"goal ({plans[0].goal_mm[2] - t[2]:+.1f} mm z)")
        ax.set_title(label, fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
    axes[0].legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)
