"""Robust scales and weights, one copy for every layer: a standard deviation from the median absolute
deviation (:func:`robust_sigma`), a scale of residual norms from their median (:func:`robust_norm_sigma`), a
spread as a fraction of the values' size (:func:`relative_spread`), and the Huber loss's reweighting
(:func:`huber_weights`).
"""
from __future__ import annotations

import numpy as np

#: the median absolute deviation of a Gaussian times this is its standard deviation (1 / Phi^-1(3/4))
MAD_TO_SIGMA = 1.4826


def robust_sigma(values: np.ndarray, *, about: float | None = None) -> float:
    """A Gaussian's standard deviation from a sample with outliers: :data:`MAD_TO_SIGMA` times the median
    absolute deviation of ``values`` about their median (``about`` None), or about ``about`` (0 for
    residuals known to be centred, or for values that are already absolute deviations)."""
    values = np.asarray(values)
    deviation = np.abs(values - np.median(values)) if about is None else np.abs(values - about)
    return MAD_TO_SIGMA * float(np.median(deviation))


def relative_spread(values: np.ndarray, *, about: float | None = None) -> float:
    """Median absolute deviation of positive ``values`` about their median (``about`` None) or about
    ``about``, over that centre: a unitless spread (0 when every value is equal), e.g. of a wall's distances
    from a sphere's centre or from a camera, or of the views' star scales about their combined scale."""
    values = np.asarray(values, float)
    centre = float(np.median(values)) if about is None else float(about)
    return float(np.median(np.abs(values - centre)) / centre)


def robust_norm_sigma(norms: np.ndarray, floor: float) -> float:
    """Robust scale of residual norms (median / 1.1774: the median of a 2-D Gaussian's norm; close for
    3-D too), at least ``floor``."""
    return max(float(np.median(norms)) / 1.1774, floor) if len(norms) else floor


def huber_weights(r: np.ndarray, scale: float) -> np.ndarray:
    """IRLS weights of the Huber loss for residual norms ``r`` at ``scale`` (1 inside, scale / r beyond)."""
    return np.where(r <= scale, 1.0, scale / np.maximum(r, 1e-300))
