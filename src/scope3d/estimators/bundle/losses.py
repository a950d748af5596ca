"""Robust losses on an observation's squared reprojection error, in Ceres's convention.

The cost of one observation with residual ``r`` (2,) pixels is ``0.5 * rho(s)`` with ``s = |r|^2``.
``rho(s) = s`` is plain least squares; the scale ``a`` (pixels) is where a loss starts to discount:

* Huber:  ``rho(s) = s`` if ``s <= a^2`` else ``2 a sqrt(s) - a^2``.
* Cauchy: ``rho(s) = a^2 log(1 + s / a^2)``.

The solver uses them by iteratively reweighted least squares: each observation's residual and Jacobian
rows are multiplied by ``sqrt(rho'(s))``, which gives the exact gradient ``rho'(s) J^T r`` of the robust
cost and a Gauss-Newton model that drops the ``rho''`` term (Triggs et al. 2000, sec. 4.3, "simple
sqrt-weighting"); steps are accepted on the true robust cost.
"""
from __future__ import annotations

import numpy as np

LOSS_NAMES = ("none", "huber", "cauchy")


def loss_rho(name: str, squared_px2: np.ndarray, scale_px: float) -> np.ndarray:
    """rho(s) for s = squared_px2 (K,) pixels^2; returns (K,) pixels^2."""
    s = np.asarray(squared_px2, dtype=float)
    a2 = scale_px * scale_px
    if name == "none":
        return s
    if name == "huber":
        return np.where(s <= a2, s, 2.0 * scale_px * np.sqrt(s) - a2)
    if name == "cauchy":
        return a2 * np.log1p(s / a2)
    raise ValueError(f"unknown loss {name!r}; choose one of {LOSS_NAMES}")


def loss_weight(name: str, squared_px2: np.ndarray, scale_px: float) -> np.ndarray | None:
    """sqrt(rho'(s)) per observation (K,), or None for plain least squares (all weights 1)."""
    s = np.asarray(squared_px2, dtype=float)
    if name == "none":
        return None
    if name == "huber":
        a2 = scale_px * scale_px
        return np.sqrt(np.where(s <= a2, 1.0, scale_px / np.sqrt(np.maximum(s, a2))))
    if name == "cauchy":
        return np.sqrt(1.0 / (1.0 + s / (scale_px * scale_px)))
    raise ValueError(f"unknown loss {name!r}; choose one of {LOSS_NAMES}")
