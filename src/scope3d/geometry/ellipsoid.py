"""Ellipsoids through points: the algebraic least-squares ellipsoid (:func:`fit_ellipsoid`) with the standard
errors of its semi-axes, so that a caller can tell a fit the points determine from one they do not (a cap of
a cavity's wall fixes no far side).

Units: those of the points (mm in the package).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Ellipsoid:
    """``(X - centre) @ axes`` divided by ``semi_axes`` has unit norm on the surface. centre : (3,);
    axes : (3, 3) rotation whose columns are the principal directions, longest semi-axis first;
    semi_axes : (3,) decreasing; semi_axes_sigma : (3,) their standard errors from the fit's residuals
    (inf when the points do not determine them)."""

    centre: np.ndarray
    axes: np.ndarray
    semi_axes: np.ndarray
    semi_axes_sigma: np.ndarray


def _quadric_design(points: np.ndarray) -> np.ndarray:
    x, y, z = points.T
    return np.c_[x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, 2 * x, 2 * y, 2 * z]


def ellipsoid_from_quadric(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Centre, axes (columns, longest first, right-handed) and semi-axes of the quadric
    ``a x² + b y² + c z² + 2d xy + 2e xz + 2f yz + 2g x + 2h y + 2i z = 1`` (q : (9,)), None when it is no
    ellipsoid (its quadratic form not definite, or the centre outside it)."""
    m = np.array([[q[0], q[3], q[4]], [q[3], q[1], q[5]], [q[4], q[5], q[2]]])
    g = q[6:9]
    try:
        centre = -np.linalg.solve(m, g)
    except np.linalg.LinAlgError:
        return None
    k = 1.0 + centre @ m @ centre  # (X - c)^T M (X - c) = k on the surface
    w, v = np.linalg.eigh(m / k) if k != 0 else (np.full(3, -1.0), np.eye(3))
    if not np.all(w > 0):
        return None
    order = np.argsort(w)  # smallest eigenvalue: longest axis
    axes = v[:, order]
    if np.linalg.det(axes) < 0:
        axes[:, 2] = -axes[:, 2]
    return centre, axes, 1.0 / np.sqrt(w[order])


def fit_ellipsoid(points: np.ndarray, *, inside: np.ndarray | None = None, trim_sigmas: float = 3.0,
                  rounds: int = 3) -> Ellipsoid | None:
    """Least-squares ellipsoid through points (N, 3), N >= 9: the quadric of :func:`ellipsoid_from_quadric`, linear in
    its 9 coefficients; points whose algebraic residual exceeds ``trim_sigmas`` robust standard deviations are
    dropped and the fit repeated (``rounds`` times; a map's few far-triangulated points would otherwise tilt
    it). inside : a point inside the surface (default the points' median), the origin of the fit's coordinates:
    the constant 1 of the quadric needs the origin off the surface. The semi-axes' standard errors propagate the
    coefficients' covariance (residual variance x (AᵀA)⁻¹) through the semi-axes by central differences. None
    when no ellipsoid fits."""
    X = np.asarray(points, float)
    if len(X) < 9:
        return None
    shift = np.median(X, axis=0) if inside is None else np.asarray(inside, float)
    scale = float(np.median(np.linalg.norm(X - shift, axis=1))) or 1.0
    P = (X - shift) / scale  # conditioning: coefficients of order one
    keep = np.ones(len(P), bool)
    for _ in range(rounds + 1):
        a = _quadric_design(P[keep])
        q, *_ = np.linalg.lstsq(a, np.ones(len(a)), rcond=None)
        r = _quadric_design(P) @ q - 1.0
        mad = 1.4826 * float(np.median(np.abs(r[keep] - np.median(r[keep]))))
        new = np.abs(r) <= trim_sigmas * max(mad, 1e-12)
        if new.sum() < 9 or np.array_equal(new, keep):
            break
        keep = new
    a = _quadric_design(P[keep])
    q, *_ = np.linalg.lstsq(a, np.ones(len(a)), rcond=None)
    shape = ellipsoid_from_quadric(q)
    if shape is None:
        return None
    centre, axes, semi = shape
    residual = a @ q - 1.0
    dof = max(len(a) - 9, 1)
    try:
        cov = np.linalg.inv(a.T @ a) * float(residual @ residual) / dof
    except np.linalg.LinAlgError:
        cov = np.full((9, 9), np.inf)
    jac = np.zeros((3, 9))
    for j in range(9):
        h = 1e-6 * max(abs(q[j]), 1e-3)
        plus, minus = ellipsoid_from_quadric(q + h * np.eye(9)[j]), ellipsoid_from_quadric(q - h * np.eye(9)[j])
        if plus is None or minus is None:
            jac[:, j] = np.inf
            continue
        jac[:, j] = (plus[2] - minus[2]) / (2 * h)
    with np.errstate(invalid="ignore"):
        sigma = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", jac, cov, jac), 0.0))
    sigma = np.where(np.isfinite(sigma), sigma, np.inf)
    return Ellipsoid(centre * scale + shift, axes, semi * scale, sigma * scale)
