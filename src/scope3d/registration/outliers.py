"""Statistical outlier removal (reference sec. 8.3): a point whose mean distance to its k nearest
neighbours is more than ``n_sigmas`` standard deviations above the cloud's mean of that distance is an
outlier (the filter PCL and Open3D call statistical outlier removal)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class OutlierOptions:
    """neighbours : int, k (default 30, as in the reference); n_sigmas : float, cut (default 3)."""

    neighbours: int = 30
    n_sigmas: float = 3.0

    def __post_init__(self) -> None:
        if self.neighbours < 1 or not self.n_sigmas > 0:
            raise ValueError("need neighbours >= 1 and n_sigmas > 0")


def statistical_inliers(points: np.ndarray, *, options: OutlierOptions = OutlierOptions()) -> np.ndarray:
    """points : (N, 3) float64 mm -> (N,) bool, True for the points kept. A cloud of no more than
    ``neighbours`` points is kept whole (no statistics to judge by)."""
    points = np.asarray(points, float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    if len(points) <= options.neighbours:
        return np.ones(len(points), bool)
    dist, _ = cKDTree(points).query(points, k=options.neighbours + 1)
    mean = dist[:, 1:].mean(axis=1)  # the first neighbour is the point itself
    return mean <= mean.mean() + options.n_sigmas * mean.std()
