"""Robust rigid 3-D-3-D registration from correspondences (reference sec. 8.2.2, eqs. 8.1-8.2).

Given points ``P`` in a source frame and their correspondences ``Q`` in a target frame, find ``R, t`` with
``R P + t = Q`` (eq. 8.1): centring both sets removes ``t`` and the rotation solves ``min |R Y1 - Y2|^2``
(eq. 8.2) by SVD (the Umeyama/Kabsch solution of :func:`scope3d.geometry.similarity.fit_similarity`,
its scale ignored). RANSAC on minimal 3-point samples rejects wrong feature matches.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.similarity import fit_similarity


def fit_rigid(source: np.ndarray, target: np.ndarray) -> Pose:
    """Least-squares rigid transform ``target_from_source`` (eqs. 8.1-8.2).

    source, target : (N, 3) float64 mm, N >= 3 corresponding points, not all on a line.
    Returns a :class:`Pose` (``x_target = R x_source + t``)."""
    source, target = np.asarray(source, float), np.asarray(target, float)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3 or len(source) < 3:
        raise ValueError(f"need two (N, 3) arrays with N >= 3, got {source.shape} and {target.shape}")
    sim = fit_similarity(source, target)
    return Pose(sim.rotation, sim.target - sim.rotation @ sim.origin)


@dataclass(frozen=True)
class RansacOptions:
    """RANSAC for a rigid fit.

    threshold_mm : float, inlier distance after the transform (default 0.05 mm: ~3-4 sigma of a sparse
        side-view reconstruction's point error, ~0.01-0.015 mm at 5 mm range).
    confidence : float, probability of drawing one all-inlier sample (default 0.999).
    max_trials : int (default 2000). min_inliers : int, fewer inliers is a failure (default 6).
    min_spread_mm : float, a minimal sample whose points are closer than this to each other or to a line
        is skipped (default 0.2 mm: degenerate rotation).
    """

    threshold_mm: float = 0.05
    confidence: float = 0.999
    max_trials: int = 2000
    min_inliers: int = 6
    min_spread_mm: float = 0.2

    def __post_init__(self) -> None:
        if not (self.threshold_mm > 0 and 0 < self.confidence < 1 and self.max_trials >= 1):
            raise ValueError("need threshold_mm > 0, confidence in (0, 1) and max_trials >= 1")
        if self.min_inliers < 3 or self.min_spread_mm < 0:
            raise ValueError("need min_inliers >= 3 and min_spread_mm >= 0")


@dataclass
class RigidFit:
    """target_from_source : Pose; inliers : (N,) bool; rms_mm : inliers' residual RMS; trials : samples drawn."""

    target_from_source: Pose
    inliers: np.ndarray
    rms_mm: float
    trials: int

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def ransac_rigid(source: np.ndarray, target: np.ndarray, *, options: RansacOptions = RansacOptions(), 
                 seed: int = 0) -> RigidFit | None:
    """RANSAC + SVD rigid fit (minimal samples of 3, the largest consensus refitted by least squares and
    its inliers re-selected until stable). source, target : (N, 3) mm corresponding points.
    Returns None when no transform has ``options.min_inliers`` inliers."""
    source, target = np.asarray(source, float), np.asarray(target, float)
    n = len(source)
    if source.shape != target.shape or n < 3:
        return None
    rng = np.random.default_rng(seed)
    best = np.zeros(n, bool)
    trials, needed = 0, options.max_trials
    thr2 = options.threshold_mm**2
    while trials < min(needed, options.max_trials):
        trials += 1
        idx = rng.choice(n, 3, replace=False)
        a = source[idx]
        e1, e2 = a[1] - a[0], a[2] - a[0]
        if min(np.linalg.norm(e1), np.linalg.norm(e2)) < options.min_spread_mm or \
                np.linalg.norm(np.cross(e1, e2)) < options.min_spread_mm * max(np.linalg.norm(e1), np.linalg.norm(e2)):
            continue
        pose = fit_rigid(a, target[idx])
        inl = np.sum((pose.transform(source) - target) ** 2, axis=1) < thr2
        if inl.sum() > best.sum():
            best = inl
            w = best.mean()
            needed = int(np.ceil(np.log(1 - options.confidence) / np.log(max(1 - w**3, 1e-12)))) if w < 1 else 1
    if best.sum() < options.min_inliers:
        return None
    for _ in range(10):
        pose = fit_rigid(source[best], target[best])
        inl = np.sum((pose.transform(source) - target) ** 2, axis=1) < thr2
        if inl.sum() < options.min_inliers or np.array_equal(inl, best):
            break
        best = inl
    pose = fit_rigid(source[best], target[best])
    res = np.linalg.norm(pose.transform(source[best]) - target[best], axis=1)
    return RigidFit(pose, best, float(np.sqrt(np.mean(res**2))), trials)
