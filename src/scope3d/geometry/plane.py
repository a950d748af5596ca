"""Least-squares planes: principal axes of a point set, the best-fit plane, distances from it."""
from __future__ import annotations

import numpy as np


def principal_axes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid and principal axes of points (N, 3) mm.

    Returns centroid (3,) mm and axes (3, 3) (with fewer than 3 points, (N, 3)): rows are unit
    directions of decreasing spread about the centroid (the SVD's right singular vectors, signs as it
    gives them); the last row is the normal of the least-squares plane through the centroid.
    """
    pts = np.asarray(points, float).reshape(-1, 3)
    centroid = pts.mean(axis=0)
    return centroid, np.linalg.svd(pts - centroid, full_matrices=False)[2]


def fit_plane(points: np.ndarray, towards: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Best-fit plane by PCA. points : (N, 3) mm. towards : (3,) a direction the normal should face
    (e.g. the mean viewing direction reversed). Returns origin (3,) and axes (3, 3), rows e_s, e_t, n."""
    pts = np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3:
        raise ValueError(f"need at least 3 points of shape (N, 3) to fit a plane, got {pts.shape}")
    origin = np.median(pts, axis=0)
    e_s, e_t, n = principal_axes(pts)[1]
    if towards is not None and np.dot(n, towards) < 0:
        n = -n
    e_t = np.cross(n, e_s)  # right-handed (e_s, e_t, n)
    return origin, np.stack([e_s, e_t, n])


def plane_residuals(points: np.ndarray) -> np.ndarray:
    """(N,) signed distances (mm) of points (N, 3) mm from their least-squares plane (through the
    centroid; the sign follows the SVD's normal, so it is arbitrary). Fewer than 3 points: zeros."""
    centroid, axes = principal_axes(points)
    return (np.asarray(points, float).reshape(-1, 3) - centroid) @ axes[-1]


def plane_rms(points: np.ndarray) -> float:
    """RMS distance (mm) of points (N, 3) mm from their least-squares plane, 0 for a flat sheet: the
    smallest singular value of the centred points over sqrt(N)."""
    pts = np.asarray(points, float).reshape(-1, 3)
    return float(np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)[-1] / np.sqrt(len(pts)))
