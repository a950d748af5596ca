"""Spheres through points: the least-squares sphere, algebraic or robust (:func:`fit_sphere`), and how much
points spread about their sphere's centre (:func:`wall_spread`, the shape a cavity's wall seen from inside has).

Units: those of the points (mm in the package).
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from scope3d.utils.robust import relative_spread, robust_sigma


def fit_sphere(points: np.ndarray, *, robust: bool = False) -> tuple[np.ndarray, float]:
    """Least-squares sphere (centre (3,), radius) through points (N, 3), N >= 4.

    The algebraic fit (``|X|^2 = 2 c.X + (r^2 - |c|^2)``, linear in c and the constant) measures each
    point's misfit in squared radii, so a point triangulated far off weighs with its distance squared.
    robust : refine it geometrically, the misfit being each point's distance to the sphere
    ``|X - c| - r``, under a soft-L1 loss whose scale is the residuals' robust spread
    (:func:`scope3d.utils.robust.robust_sigma`), re-estimated over three rounds. Why: the start's
    triangulation of the 30 mm default spiral (planned poses) has 1 % of its points 100-240 mm from the
    cavity's centre; the algebraic sphere sat 28.7 mm off the true centre (radius 52 mm) and the shell about
    it cut the near end's real wall, the robust one is 0.5 mm off (radius 38 mm)."""
    X = np.asarray(points, float)
    A = np.c_[2.0 * X, np.ones(len(X))]
    sol = np.linalg.lstsq(A, np.einsum("ij,ij->i", X, X), rcond=None)[0]
    centre = sol[:3]
    radius = float(np.sqrt(max(sol[3] + centre @ centre, 0.0)))
    if not robust:
        return centre, radius

    def misfit(p):
        return np.linalg.norm(X - p[:3], axis=1) - p[3]

    def jacobian(p):
        d = X - p[:3]
        return np.c_[-d / np.maximum(np.linalg.norm(d, axis=1), 1e-300)[:, None], -np.ones(len(X))]

    p = np.r_[centre, radius]
    for _ in range(3):
        r = misfit(p)
        scale = max(robust_sigma(r), 1e-9 * max(abs(p[3]), 1.0))
        p = least_squares(misfit, p, jac=jacobian, loss="soft_l1", f_scale=scale).x
    return p[:3], float(abs(p[3]))


def wall_spread(points: np.ndarray) -> float:
    """Spread of the points' (N, 3) distances from the centre of their fitted sphere (:func:`fit_sphere`):
    median absolute deviation over the median; inf with fewer than four points. A wall seen from inside a
    cavity is at nearly one distance from its centre (the maps kept on the bladder phantoms, 608 and 256
    px: 0.04-0.06); an all-pair map fallen into another minimum scatters them (0.08-0.22 measured). No
    threshold: :func:`scope3d.sfm.cavity_map_choice.choose_map` only compares two maps of the same frames."""
    if len(points) < 4:
        return float("inf")
    return relative_spread(np.linalg.norm(np.asarray(points, float) - fit_sphere(points)[0], axis=1))
