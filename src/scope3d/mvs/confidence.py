"""Which axial-stereo depths to trust.

Axial stereo fails in three predictable places, and each has a measurable symptom:

* **near the epipole** (image centre) the disparity tends to 0 and depth error grows as
  ``Z^2 * step / b`` (eq. 7.3 divides by the disparity): masked by ``min_disparity_px`` and, better, by the
  predicted range standard deviation ``max_range_sigma_mm``;
* **the dark rim** of the scanning-fibre image (reference sec. 7.4: "a very noisy rim since the outer scans
  ... were dark"): masked by ``min_intensity`` on the window mean in both images;
* **low texture / mismatches**: a window whose gradient along the epipolar line is weak cannot fix the
  shift (``min_gradient``), and a window whose contrast-normalised residual is large did not match
  (``max_normalised_cost``); left-right inconsistent matches are already removed by the matcher.

All tests are on the polar grid of :mod:`scope3d.mvs.axial` (rows = epipolar lines).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from scope3d.mvs.axial import AxialPair
from scope3d.utils.aot import load_kernels
from scope3d.utils.row_blocks import run_by_row_blocks

_kernels = load_kernels("scope3d.mvs.refine_kernels")

#: the tests of :func:`reliability`, in the order the compiled pass writes them (``Reliability.reasons``)
REASONS = ("outside_view", "no_match", "near_epipole", "ill_conditioned", "dark", "low_texture", "poor_match")


@dataclass(frozen=True)
class ConfidenceOptions:
    """Thresholds of the reliability mask; every one is named with its unit.

    min_disparity_px : float, columns. Relative range error is about ``sigma_d / d``; at 1.5 columns and
        0.1 column of noise it is 7 %.
    max_range_sigma_mm : float, predicted 1-sigma range error (mm) above which a point is dropped.
    disparity_sigma_floor_px : float, columns. The refinement's Cramér-Rao sigma ignores interpolation and
        model error; a floor of 0.05 column (typical sub-pixel accuracy of SGM plus refinement on
        textured images) keeps the prediction honest.
    min_intensity : float, grey levels (0-255): mean over the window in both images (the dark rim).
    min_gradient : float, grey levels per column: RMS row gradient over the window (texture along the
        epipolar line; 1 grey level per column is at the noise level of 8-bit images).
    max_normalised_cost : float, mean absolute residual over the window divided by the window's grey
        standard deviation (0 = perfect match, ~1.1 = unrelated windows).
    window_px : int, odd, the window of the intensity and gradient statistics.
    erode_px : int, shrink the valid region by this many pixels: disparities next to holes and
        occlusion edges are the least reliable.
    """

    min_disparity_px: float = 1.5
    max_range_sigma_mm: float = 0.1
    disparity_sigma_floor_px: float = 0.05
    min_intensity: float = 20.0
    min_gradient: float = 1.0
    max_normalised_cost: float = 0.35
    window_px: int = 7
    erode_px: int = 1

    def __post_init__(self) -> None:
        if self.window_px < 1 or self.window_px % 2 == 0:
            raise ValueError("ConfidenceOptions.window_px must be a positive odd number")
        for name in ("min_disparity_px", "max_range_sigma_mm", "disparity_sigma_floor_px", "min_intensity",
                     "min_gradient", "max_normalised_cost"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"ConfidenceOptions.{name} must be non-negative")
        if self.erode_px < 0:
            raise ValueError("ConfidenceOptions.erode_px must be non-negative")


@dataclass(frozen=True)
class Reliability:
    """Per-cell reliability on the polar grid, each (n_angles, n_radii).

    mask : bool, keep. confidence : float32 in (0, 1], ``1 / (1 + (sigma / max_range_sigma)^2)``, 0 where
    masked. range_sigma_mm : float32 predicted 1-sigma range error. reasons : dict name -> bool mask of
    the cells each test rejected (for reports and pictures).
    """

    mask: np.ndarray
    confidence: np.ndarray
    range_sigma_mm: np.ndarray
    reasons: dict


def reliability(
    front_polar: np.ndarray,
    rear_polar: np.ndarray,
    disparity: np.ndarray,
    cost: np.ndarray,
    disparity_sigma: np.ndarray,
    pair: AxialPair,
    valid: np.ndarray,
    *,
    options: ConfidenceOptions = ConfidenceOptions(),
) -> Reliability:
    """Combine the tests of the module docstring into one mask and a confidence.

    front_polar, rear_polar : (A, R) uint8 polar images (front = matcher's left).
    disparity, cost, disparity_sigma : (A, R) float32 from the matcher (NaN = no match).
    pair : the :class:`~scope3d.mvs.axial.AxialPair` of the grid; the range sigma is its
        :meth:`~scope3d.mvs.axial.AxialPair.range_sigma` at ``max(disparity_sigma, floor)``.
    valid : (A, R) bool, grid cells seen by both cameras.

    The window statistics (mean, standard deviation and RMS row gradient of the front image, mean of the
    rear one, over ``window_px`` boxes) and every test run in one compiled pass over the grid
    (``refine_kernels.reliability_tests``), on blocks of rows shared by the cores: the same bits as
    cv2.boxFilter, cv2.Sobel and NumPy's expressions of each test (tests/test_stereo_kernels.py).
    """
    shape = np.shape(disparity)
    for name, array in (("front_polar", front_polar), ("rear_polar", rear_polar), ("valid", valid)):
        if np.shape(array) != shape:
            raise ValueError(f"reliability: {name} is {np.shape(array)}, the disparity {shape}")
    d = np.ascontiguousarray(disparity, dtype=np.float32)
    disparity_sigma = np.asarray(disparity_sigma, dtype=np.float32)
    floor = options.disparity_sigma_floor_px
    range_sigma = np.empty(shape, np.float32)
    reasons = np.empty((len(REASONS),) + shape, bool)
    mask = np.empty(shape, bool)
    thresholds = np.array([options.min_disparity_px, options.max_range_sigma_mm, options.min_intensity,
                           options.min_gradient, options.max_normalised_cost], np.float32)
    images = (np.ascontiguousarray(front_polar, dtype=np.uint8), np.ascontiguousarray(rear_polar, dtype=np.uint8))
    cost = np.ascontiguousarray(cost, dtype=np.float32)
    valid = np.ascontiguousarray(valid, dtype=bool)

    def block(row_lo: int, row_hi: int) -> None:
        # the range sigma in NumPy (its exp and expm1 are faster than the compiled ones, the same bits), then
        # the tests; NumPy's loops and the kernel release the GIL, so blocks overlap on the cores
        rows = slice(row_lo, row_hi)
        sigma_d = np.fmax(disparity_sigma[rows], floor)
        sigma_d = np.where(np.isfinite(sigma_d), sigma_d, floor)
        range_sigma[rows] = pair.range_sigma(d[rows], sigma_d)
        _kernels.reliability_tests(*images, d, cost, range_sigma, valid, thresholds, options.window_px, row_lo,
                                   row_hi, reasons, mask)

    run_by_row_blocks(block, shape[0], (), ())
    if options.erode_px:
        k = 2 * options.erode_px + 1
        mask = cv2.erode(mask.astype(np.uint8), np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT,
                         borderValue=0).astype(bool)
    confidence = np.zeros(shape, np.float32)
    with np.errstate(invalid="ignore", over="ignore"):
        confidence[mask] = 1.0 / (1.0 + (range_sigma[mask] / options.max_range_sigma_mm) ** 2)
    return Reliability(mask, confidence, range_sigma, dict(zip(REASONS, reasons)))
