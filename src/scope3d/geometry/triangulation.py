"""Points from rays: the least-squares (midpoint) triangulation that every view count shares."""
from __future__ import annotations

import numpy as np


def triangulate_midpoint(origins: np.ndarray, directions: np.ndarray, group: np.ndarray, n_points: int) -> np.ndarray:
    """For each group of rays, the point with the least sum of squared distances to them.

    origins : (M, 3) mm, a point of each ray (its camera centre); directions : (M, 3) unit vectors;
    group : (M,) int in [0, n_points), the point each ray belongs to. With two rays this is the midpoint
    of their common perpendicular; with more, the solution of ``(sum P_k) X = sum P_k c_k``,
    ``P_k = I - d_k d_k^T`` (a 3x3 system per point).
    Returns (n_points, 3) mm; NaN where a group's rays are (nearly) parallel or too few
    (``|det(sum P_k)| <= 1e-12``: two rays closer than ~1e-6 rad).
    """
    c = np.asarray(origins, dtype=float).reshape(-1, 3)
    d = np.asarray(directions, dtype=float).reshape(-1, 3)
    # argmin_X sum_k |(I - d_k d_k^T)(X - c_k)|^2  ->  (sum P_k) X = sum P_k c_k
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    A = np.zeros((n_points, 3, 3))
    b = np.zeros((n_points, 3))
    np.add.at(A, group, proj)
    np.add.at(b, group, np.einsum("mij,mj->mi", proj, c))
    ok = np.abs(np.linalg.det(A)) > 1e-12
    X = np.full((n_points, 3), np.nan)
    X[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    return X
