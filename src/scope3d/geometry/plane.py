"""Least-squares planes."""
from __future__ import annotations

import numpy as np


def fit_plane(points: np.ndarray, towards: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Best-fit plane by PCA. points : (N, 3) mm. towards : (3,) a direction the normal should face
    (e.g. the mean viewing direction reversed). Returns origin (3,) and axes (3, 3), rows e_s, e_t, n."""
    pts = np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3:
        raise ValueError(f"need at least 3 points of shape (N, 3) to fit a plane, got {pts.shape}")
    origin = np.median(pts, axis=0)
    _, _, vt = np.linalg.svd(pts - pts.mean(axis=0), full_matrices=False)
    e_s, e_t, n = vt[0], vt[1], vt[2]
    if towards is not None and np.dot(n, towards) < 0:
        n = -n
    e_t = np.cross(n, e_s)  # right-handed (e_s, e_t, n)
    return origin, np.stack([e_s, e_t, n])
