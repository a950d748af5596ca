"""Rigid point-to-plane ICP (Chen & Medioni) with Huber weights.

The reference aligned each reconstruction to the CAD model with ICP (sec. 4.5) to measure its shape
error; metrology starts it from eight perturbed poses (:func:`scope3d.metrology.evaluation.icp_from_initial_poses`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.scene.mesh import SampledSurface
from scope3d.utils.robust import robust_sigma


@dataclass(frozen=True)
class IcpOptions:
    """iterations : int, at most this many linearised steps (default 100).
    tolerance_mm : float, stop when a step moves the points by less than this (default 1e-3 mm).
    max_distance_mm : float, correspondences farther than this are ignored (default 5 mm: beyond the
        misalignment ICP is asked to remove, a far point is an outlier).
    trim_fraction : float in [0, 0.5), the worst fraction of correspondences ignored each iteration
        (default 0: trimming lets ICP slide along a symmetry by dropping the points that resist).
    huber_sigmas : float, residuals beyond this many robust sigmas are Huber-weighted (default 2).
    min_decrease_sigma2 : float >= 0, also stop when a step would lower the weighted sum of squared
        residuals by less than this many squared robust sigmas of the residuals (default 1): a step whose
        length in the pose's own standard errors (its Mahalanobis length under the normal matrix) is below
        one is the correspondences' noise, not misalignment. Along a near-symmetry (a dome's axis) such
        steps never end: the 1 µm test alone ran every start of the dome phantom's evaluation to the
        iteration cap, turning the map tens of degrees about the dome's axis. Stopped there, the next
        step would move the weighted mean of squares by about sigma² / N (one point's share of the sum).
        0: the step test alone.
    """

    iterations: int = 100
    tolerance_mm: float = 1e-3
    max_distance_mm: float = 5.0
    trim_fraction: float = 0.0
    huber_sigmas: float = 2.0
    min_decrease_sigma2: float = 1.0

    def __post_init__(self) -> None:
        if self.iterations < 1 or not 0 <= self.trim_fraction < 0.5:
            raise ValueError("need iterations >= 1 and trim_fraction in [0, 0.5)")
        if not self.min_decrease_sigma2 >= 0:
            raise ValueError(f"need min_decrease_sigma2 >= 0, got {self.min_decrease_sigma2}")
        if not (self.tolerance_mm > 0 and self.max_distance_mm > 0 and self.huber_sigmas > 0):
            raise ValueError("need tolerance_mm, max_distance_mm and huber_sigmas > 0")


@dataclass
class IcpResult:
    """rotation (3, 3), translation (3,) mm: aligned = R @ x + t; mean_distance_mm after alignment
    (over the points within ``max_distance_mm``); iterations; history of mean distances (mm)."""

    rotation: np.ndarray
    translation: np.ndarray
    mean_distance_mm: float
    iterations: int
    history: list

    def apply(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, float) @ self.rotation.T + self.translation


def _cross(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """Row-wise a x b of (N, 3) arrays into ``out`` (N, 3): np.cross's arithmetic without its per-call
    overhead (ICP calls it every iteration)."""
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]


def icp_point_to_plane(
    points: np.ndarray, target: SampledSurface, options: IcpOptions = IcpOptions(),
    *, rotation: np.ndarray | None = None, translation: np.ndarray | None = None,
) -> IcpResult:
    """Rigid point-to-plane ICP of ``points`` (N, 3) onto the sampled true surface, from an initial
    transform (default identity). Each iteration solves min Σ (n·(R x + t - q))² linearised in a small
    rotation ``w`` about the points' centroid, over the best (1 - trim) correspondences."""
    x = np.asarray(points, float)
    R = np.eye(3) if rotation is None else np.asarray(rotation, float)
    t = np.zeros(3) if translation is None else np.asarray(translation, float)
    history = []
    it = 0
    for it in range(1, options.iterations + 1):
        y = x @ R.T + t
        # approximate neighbours are enough for a point-to-plane step: the plane of a sample a little
        # farther away differs by its curvature only (the final distances are exact)
        q, n, _ = target.nearest(y, eps=0.5, max_distance_mm=options.max_distance_mm)
        r = np.einsum("ij,ij->i", y - q, n)
        ok = np.isfinite(r)
        if ok.sum() < 6:
            break
        keep = ok.copy()
        if options.trim_fraction:
            keep[ok] = np.abs(r[ok]) <= np.quantile(np.abs(r[ok]), 1 - options.trim_fraction)
        history.append(float(np.mean(np.abs(r[ok]))))
        yk, nk, rk = (y, n, r) if keep.all() else (y[keep], n[keep], r[keep])
        abs_r = np.abs(rk)
        # Huber weights (scale: 2 robust sigmas of the residuals) rather than dropping the worst: a point
        # sliding off the surface's edge keeps a bounded pull, so ICP cannot slide along a symmetry (a
        # dome's axis) by shedding the points that would resist it
        sigma = max(robust_sigma(abs_r, about=0.0), 1e-6)
        w = np.minimum(1.0, options.huber_sigmas * sigma / np.maximum(abs_r, 1e-12))
        c = yk.mean(axis=0)
        A = np.empty((len(yk), 6))
        _cross(yk - c, nk, A[:, :3])
        A[:, 3:] = nk
        Aw = A * w[:, None]
        # 6x6 normal equations (tiny Tikhonov term: a rotationally symmetric target leaves a null space)
        AwtA = Aw.T @ A
        AtA = AwtA + 1e-9 * np.eye(6) * max(float(np.trace(AwtA)), 1.0)
        gradient = -Aw.T @ rk
        sol = np.linalg.solve(AtA, gradient)
        # what the linearised step takes off the weighted sum of squares (its Mahalanobis length², ~ sigma²)
        decrease = float(sol @ gradient)
        dR = rotvec_to_matrix(sol[:3])
        # rotate about the centroid c, then translate
        R = dR @ R
        t = dR @ (t - c) + c + sol[3:]
        step = np.linalg.norm(sol[:3]) * np.sqrt(np.mean(np.sum((y - c) ** 2, axis=1))) + np.linalg.norm(sol[3:])
        # stop on a small step, or one within the pose's own uncertainty (the mean residual itself is no
        # test: it moves by ~0.5 % from step to step with the samples the approximate search returns)
        if step < options.tolerance_mm or decrease < options.min_decrease_sigma2 * sigma**2:
            break
    y = x @ R.T + t
    q, n, d = target.nearest(y, max_distance_mm=options.max_distance_mm)
    ok = np.isfinite(d)
    final = np.minimum(np.abs(np.einsum("ij,ij->i", y[ok] - q[ok], n[ok])), d[ok])
    return IcpResult(R, t, float(final.mean()) if ok.any() else float("inf"), it, history)
