"""Compiled window-statistics passes of dense matching: the sub-pixel disparity refinement
(:func:`scope3d.mvs.dense_matching.refine_subpixel`) and the axial pair's reliability tests
(:func:`scope3d.mvs.confidence.reliability`), which share the box means below. A kernel module of :mod:`scope3d.utils.aot` (compiled at install; numba's JIT where that could not run). It imports
only numpy and numba (setup.py compiles it without importing scope3d).

The refinement warps the right image and its row gradient by every pixel's disparity and then needs seven
window means of their products. With OpenCV that was a two-channel Lanczos-4 ``cv2.remap`` (an 8 x 8 kernel,
of which 7 rows have weight 0 since every row stays on its row) and nine ``cv2.boxFilter`` calls on
frame-sized products, each its own pass. Here the warp is OpenCV's own one-dimensional Lanczos-4 (its
weights, read from ``cv2.remap`` by the caller, and its 1/32-pixel quantisation of the position) and each
window mean is a running column sum in float64 of the float32 products, as ``cv2.boxFilter`` sums them
(BORDER_REFLECT), scaled and rounded to float32 once. The float32 arithmetic that follows is the order
of NumPy's expressions in the refinement before these kernels, so the results are the same bits
(tests/test_stereo_kernels.py checks it against the OpenCV and NumPy computation).

Every pass writes the rows ``[row_lo, row_hi)`` of its outputs only, so that threads can share a frame by
blocks of rows (the functions release the GIL).
"""
from __future__ import annotations

import numpy as np
from numba import njit

# Exported at install with the exact argument types dense_matching.refine_subpixel and confidence.reliability pass
# (C-contiguous)
AOT_SIGNATURES = {
    "reliability_tests": "void(u1[:, ::1], u1[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], b1[:, ::1], f4[::1], i8, "
                         "i8, i8, b1[:, :, ::1], b1[:, ::1])",
    "left_statistics": "void(f4[:, ::1], i8, i8, i8, i8, f4[:, ::1], f4[:, ::1])",
    "warp_rows": "void(f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], i8, i8, f4[:, ::1], f4[:, ::1])",
    "step_pass": "void(f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], i8, i8, i8, i8, "
                 "f4[:, ::1])",
    "fit_pass": "void(f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], i8, i8, "
                "f4, f4, f4, f4, i8, i8, f4[:, ::1], f4[:, ::1], f4[:, ::1])",
}

LANCZOS_TAPS = 8  # cv2.INTER_LANCZOS4: 4 source pixels either side
LANCZOS_STEPS = 32  # OpenCV's INTER_TAB_SIZE: remap positions are rounded to 1/32 pixel (as dense_matching's table)
# the window sums, in this order: warped w, its gradient g, w w, g g, l w (l the left image), g l, g w
_N_SUMS_STEP = 7
_N_SUMS_FIT = 5


@njit(cache=True, nogil=True)
def _reflect(index, length):
    """OpenCV's BORDER_REFLECT (``fedcba|abcdefgh|hgfedcb``) index, reflected as often as needed."""
    if length == 1:
        return 0
    while index < 0 or index >= length:
        if index < 0:
            index = -index - 1
        else:
            index = 2 * length - index - 1
    return index


@njit(cache=True, nogil=True)
def left_statistics(left, window_cols, window_rows, row_lo, row_hi, mean_left, var_left):
    """Window mean of ``left`` (H, W) float32 and its variance floored at 1e-6, rows [row_lo, row_hi).

    ``mean(l)`` and ``mean(l^2)`` as ``cv2.boxFilter(..., normalize=True)`` with BORDER_REFLECT (float64
    running sums of the float32 values and squares, each mean rounded to float32 once), then
    ``max(mean(l^2) - mean(l)^2, 1e-6)`` in float32 as NumPy computes it.
    """
    height, width = left.shape
    half_r, half_c = window_rows // 2, window_cols // 2
    inverse = 1.0 / (window_cols * window_rows)
    tiny = np.float32(1e-6)
    columns = np.zeros((2, width))
    padded = np.empty(width + window_cols - 1)
    sums = np.empty(width)
    means = np.empty((2, width), np.float32)
    for y in range(row_lo, row_hi):
        if y == row_lo:
            for r in range(y - half_r, y + half_r + 1):
                _add_left_row(columns, left[_reflect(r, height)], 1.0)
        else:
            _add_left_row(columns, left[_reflect(y + half_r, height)], 1.0)
            _add_left_row(columns, left[_reflect(y - half_r - 1, height)], -1.0)
        for q in range(2):
            _horizontal_means(columns[q], half_c, window_cols, inverse, padded, sums, means[q])
        for x in range(width):
            mu = means[0, x]
            mean_left[y, x] = mu
            var_left[y, x] = max(means[1, x] - mu * mu, tiny)


@njit(cache=True, nogil=True)
def _add_left_row(columns, row, sign):
    for x in range(row.shape[0]):
        columns[0, x] += sign * row[x]
    for x in range(row.shape[0]):
        columns[1, x] += sign * (row[x] * row[x])


@njit(cache=True, nogil=True)
def _horizontal_means(column, half_c, window_cols, inverse, padded, sums, mean):
    """``mean[x] = float32(sum(column[x - half_c : x + half_c + 1]) * inverse)``, the ends reflected."""
    width = column.shape[0]
    for x in range(width):
        padded[half_c + x] = column[x]
    for k in range(half_c):
        padded[half_c - 1 - k] = column[_reflect(-1 - k, width)]
        padded[half_c + width + k] = column[_reflect(width + k, width)]
    for x in range(width):
        sums[x] = padded[x]
    for k in range(1, window_cols):
        for x in range(width):
            sums[x] += padded[x + k]
    for x in range(width):
        mean[x] = np.float32(sums[x] * inverse)


@njit(cache=True, nogil=True)
def warp_rows(image, gradient, disparity, weights, row_lo, row_hi, warped, warped_gradient):
    """``image`` and ``gradient`` (H, W) float32 resampled at ``(x - disparity[y, x], y)`` along each row.

    weights : (32, 8) float32 Lanczos-4 weights of the 32 sub-pixel phases (OpenCV's table). The position
    is rounded to 1/32 pixel (half to even) and the 8 taps around it are clamped to the row
    (BORDER_REPLICATE); the weighted sum runs left to right in float32, as ``cv2.remap`` with
    ``INTER_LANCZOS4`` computes it for an integer row coordinate. Fills rows [row_lo, row_hi) of
    ``warped`` and ``warped_gradient`` (H, W) float32.
    """
    width = image.shape[1]
    steps = np.float32(LANCZOS_STEPS)
    for y in range(row_lo, row_hi):
        for x in range(width):
            scaled = (np.float32(x) - disparity[y, x]) * steps  # exact: a float32 times a power of two
            fixed = np.int64(np.rint(np.float64(scaled)))  # float32 -> float64 is exact; half to even
            phase = fixed & (LANCZOS_STEPS - 1)
            start = (fixed >> 5) - 3  # floor(fixed / 32) - 3
            value = np.float32(0.0)
            grad = np.float32(0.0)
            if 0 <= start and start + LANCZOS_TAPS <= width:
                for k in range(LANCZOS_TAPS):
                    value += image[y, start + k] * weights[phase, k]
                    grad += gradient[y, start + k] * weights[phase, k]
            else:
                for k in range(LANCZOS_TAPS):
                    col = min(max(start + k, 0), width - 1)
                    value += image[y, col] * weights[phase, k]
                    grad += gradient[y, col] * weights[phase, k]
            warped[y, x] = value
            warped_gradient[y, x] = grad


@njit(cache=True, nogil=True)
def _add_row(columns, n_sums, left, warped, gradient, row, sign):
    """Add (sign 1) or subtract (sign -1) one image row's float32 products to the float64 column sums
    (one loop per sum: plain loops over a row are what LLVM vectorises)."""
    width = left.shape[1]
    l, w, g = left[row], warped[row], gradient[row]
    for x in range(width):
        columns[0, x] += sign * w[x]
    for x in range(width):
        columns[1, x] += sign * g[x]
    for x in range(width):
        columns[2, x] += sign * (w[x] * w[x])
    for x in range(width):
        columns[3, x] += sign * (g[x] * g[x])
    for x in range(width):
        columns[4, x] += sign * (l[x] * w[x])
    if n_sums == _N_SUMS_STEP:
        for x in range(width):
            columns[5, x] += sign * (g[x] * l[x])
        for x in range(width):
            columns[6, x] += sign * (g[x] * w[x])


@njit(cache=True, nogil=True)
def _window_means(left, warped, gradient, window_cols, window_rows, n_sums, y, row_lo, columns, padded, sums, means):
    """The first ``n_sums`` window means of row ``y`` into ``means`` (n_sums, W) float32.

    columns : (7, W) float64, the sums over the window's rows of every column, brought from row ``y - 1``
    to row ``y`` (or started afresh at ``row_lo``); padded : (W + window_cols - 1,) and sums : (W,) float64
    scratch. Each mean is ``float32(sum * (1 / n))`` of the float32 products summed in float64 with
    BORDER_REFLECT, as ``cv2.boxFilter(..., normalize=True)`` computes it (the sums of float32 products
    are exact in float64 but for products of very different magnitudes, so the order does not matter).
    """
    height, width = left.shape
    half_r, half_c = window_rows // 2, window_cols // 2
    if y == row_lo:
        columns[:, :] = 0.0
        for r in range(y - half_r, y + half_r + 1):
            _add_row(columns, n_sums, left, warped, gradient, _reflect(r, height), 1.0)
    else:
        _add_row(columns, n_sums, left, warped, gradient, _reflect(y + half_r, height), 1.0)
        _add_row(columns, n_sums, left, warped, gradient, _reflect(y - half_r - 1, height), -1.0)
    inverse = 1.0 / (window_cols * window_rows)
    for q in range(n_sums):
        _horizontal_means(columns[q], half_c, window_cols, inverse, padded, sums, means[q])


@njit(cache=True, nogil=True)
def step_pass(left, warped, gradient, mean_left, var_left, disparity, window_cols, window_rows, row_lo, row_hi,
              new_disparity):
    """One Gauss-Newton step of every pixel's disparity, from window statistics of the zero-mean,
    gain-normalised residual between ``left`` and the warped right image.

    left, warped, gradient : (H, W) float32, the left image, the right image warped by the current
    disparity and its warped row gradient; mean_left, var_left : (H, W) float32 window mean and variance
    (floored at 1e-6) of ``left``; disparity : (H, W) float32 current disparity (0 where unknown);
    window_cols, window_rows : odd window size. Fills rows [row_lo, row_hi) of ``new_disparity`` (H, W)
    float32 with ``d + clip(-mean(J e) / mean(J^2), -1/2, 1/2)`` (no step where ``mean(J^2) <= 1e-9``),
    J and e as in ``refine_subpixel``. The column sums restart at ``row_lo``, so a frame cut into the same
    blocks gives the same bits whichever thread runs which block.
    """
    width = left.shape[1]
    columns = np.empty((_N_SUMS_STEP, width))
    padded = np.empty(width + window_cols - 1)
    sums = np.empty(width)
    means = np.empty((_N_SUMS_STEP, width), np.float32)
    for y in range(row_lo, row_hi):
        _window_means(left, warped, gradient, window_cols, window_rows, _N_SUMS_STEP, y, row_lo, columns, padded, sums,
                      means)
        _step_row(means, mean_left[y], var_left[y], disparity[y], new_disparity[y])


# error_model="numpy": a division by 0 gives inf or NaN as in NumPy instead of a check that raises, which
# keeps the row loops free of branches (vectorised); every division here is guarded or has a floored divisor
@njit(cache=True, nogil=True, error_model="numpy")
def _step_row(means, mean_left, var_left, disparity, new_disparity):
    """:func:`step_pass` on one row, from its window means (7, W) float32."""
    tiny, zero, half, min_jj = np.float32(1e-6), np.float32(0.0), np.float32(0.5), np.float32(1e-9)
    for x in range(means.shape[1]):
        mu_l, var_l = mean_left[x], var_left[x]
        mu_w, mu_g = means[0, x], means[1, x]
        var_w = max(means[2, x] - mu_w * mu_w, tiny)
        var_g = max(means[3, x] - mu_g * mu_g, zero)
        a = np.sqrt(var_l / var_w)
        jj = a * a * var_g  # mean of J^2
        cov_gl = means[5, x] - mu_g * mu_l
        cov_gw = means[6, x] - mu_g * mu_w
        je = a * (cov_gl - a * cov_gw)  # mean of J e
        step = -je / jj
        # Damped: a step beyond half a column leaves the linear range of the interpolated gradient
        step = half if step > half else step  # NaN passes, as through np.clip
        step = -half if step < -half else step
        new_disparity[x] = disparity[x] + (step if jj > min_jj else zero)


@njit(cache=True, nogil=True)
def fit_pass(left, warped, gradient, mean_left, var_left, disparity, start, window_cols, window_rows,
             max_shift, lowest, highest, samples, row_lo, row_hi, out_disparity, out_cost, out_sigma):
    """The refinement's result from the window statistics at the final disparity.

    left, warped, gradient, mean_left, var_left, window_cols, window_rows : as :func:`step_pass`;
    disparity : (H, W) float32 final disparity; start : (H, W) float32 the matcher's, NaN = none;
    max_shift, lowest, highest : float32, a disparity farther than ``max_shift`` from its start or outside
    [lowest, highest] is rejected; samples : float32, pixels per window. Fills rows [row_lo, row_hi) of
    ``out_disparity``, ``out_cost = sqrt(mean(e^2))`` and ``out_sigma = sqrt(mean(e^2) / (samples
    mean(J^2)))`` (H, W) float32, NaN where rejected.
    """
    width = left.shape[1]
    columns = np.empty((_N_SUMS_FIT, width))
    padded = np.empty(width + window_cols - 1)
    sums = np.empty(width)
    means = np.empty((_N_SUMS_FIT, width), np.float32)
    for y in range(row_lo, row_hi):
        _window_means(left, warped, gradient, window_cols, window_rows, _N_SUMS_FIT, y, row_lo, columns, padded, sums,
                      means)
        _fit_row(means, mean_left[y], var_left[y], disparity[y], start[y], max_shift, lowest, highest, samples,
                 out_disparity[y], out_cost[y], out_sigma[y])


@njit(cache=True, nogil=True, error_model="numpy")
def _fit_row(means, mean_left, var_left, disparity, start, max_shift, lowest, highest, samples, out_disparity,
             out_cost, out_sigma):
    """:func:`fit_pass` on one row, from its window means (5, W) float32."""
    tiny, zero, two, nan = np.float32(1e-6), np.float32(0.0), np.float32(2.0), np.float32(np.nan)
    for x in range(means.shape[1]):
        d, d0 = disparity[x], start[x]
        keep = np.isfinite(d0) & (not abs(d - d0) > max_shift) & (not d < lowest) & (not d > highest)
        mu_l, var_l = mean_left[x], var_left[x]
        mu_w, mu_g = means[0, x], means[1, x]
        var_w = max(means[2, x] - mu_w * mu_w, tiny)
        var_g = max(means[3, x] - mu_g * mu_g, zero)
        cov_lw = means[4, x] - mu_l * mu_w
        a = np.sqrt(var_l / var_w)
        jj = a * a * var_g  # mean of J^2
        ee = max(var_l - two * a * cov_lw + a * a * var_w, zero)  # mean of e^2
        out_disparity[x] = d if keep else nan
        out_cost[x] = np.sqrt(ee) if keep else nan
        out_sigma[x] = np.sqrt(ee / (samples * jj)) if keep else nan  # inf or NaN where mean(J^2) is 0, as NumPy


@njit(cache=True, nogil=True)
def _add_polar_row(columns, front, rear, row, sign):
    """Add (sign 1) or subtract (sign -1) one row to the column sums of the window statistics: front,
    front^2, (front row gradient)^2, rear. The row gradient is cv2.Sobel's ksize=1 central difference times
    1/2 (BORDER_REFLECT_101); every term is a multiple of 1/4 below 2^16, so the float64 sums are exact."""
    width = front.shape[1]
    f, r = front[row], rear[row]
    for x in range(width):
        value = np.float64(f[x])
        columns[0, x] += sign * value
        columns[1, x] += sign * (value * value)
        columns[3, x] += sign * np.float64(r[x])
    if width < 2:  # cv2.Sobel's difference of a one-pixel row is 0
        return
    for x in range(width):
        right = f[x + 1] if x + 1 < width else f[width - 2]
        left = f[x - 1] if x > 0 else f[1]
        g = 0.5 * (np.float64(right) - np.float64(left))
        columns[2, x] += sign * (g * g)


@njit(cache=True, nogil=True)
def reliability_tests(front, rear, disparity, cost, range_sigma, valid, thresholds, window, row_lo, row_hi, reasons,
                      keep):
    """Every test of :func:`scope3d.mvs.confidence.reliability` at each cell, in one pass (before the erosion).

    front, rear : (A, R) uint8 polar images; disparity, cost : (A, R) float32 from the matcher (NaN =
    none); range_sigma : (A, R) float32 predicted range sigma (mm, NaN = none); valid : (A, R) bool, seen
    by both cameras; thresholds : float32 (min disparity, max range sigma, min intensity, min gradient,
    max normalised cost), compared in float32 as NumPy compares a float32 array with a Python float;
    window : odd size of the image statistics, box means with BORDER_REFLECT as cv2.boxFilter. Fills rows
    [row_lo, row_hi) of reasons (7, A, R) bool, in the order of ``confidence.REASONS`` (outside view, no
    match, near the epipole, ill-conditioned, dark, low texture, poor match), and keep (A, R) bool (no
    test failed).
    """
    height, width = front.shape
    half = window // 2
    inverse = 1.0 / (window * window)
    columns = np.zeros((4, width))
    padded = np.empty(width + window - 1)
    sums = np.empty(width)
    means = np.empty((4, width), np.float32)
    for y in range(row_lo, row_hi):
        if y == row_lo:
            for r in range(y - half, y + half + 1):
                _add_polar_row(columns, front, rear, _reflect(r, height), 1.0)
        else:
            _add_polar_row(columns, front, rear, _reflect(y + half, height), 1.0)
            _add_polar_row(columns, front, rear, _reflect(y - half - 1, height), -1.0)
        for q in range(4):
            _horizontal_means(columns[q], half, window, inverse, padded, sums, means[q])
        _row_tests(means, front.shape[1], disparity[y], cost[y], range_sigma[y], valid[y], thresholds, reasons[:, y],
                   keep[y])


# error_model="numpy" (a callee keeps its own; ahead of time the exported functions get numba's default): a flat
# window's normalised cost divides by a zero deviation and gives inf or NaN as in NumPy instead of raising
@njit(cache=True, nogil=True, error_model="numpy")
def _row_tests(means, width, disparity, cost, range_sigma, valid, thresholds, reasons, keep):
    """:func:`reliability_tests` on one row, from its window means (4, W) float32."""
    min_disparity, max_range_sigma, min_intensity = thresholds[0], thresholds[1], thresholds[2]
    min_gradient, max_cost = thresholds[3], thresholds[4]
    zero = np.float32(0.0)
    for x in range(width):
        mean_f = means[0, x]
        std_f = np.sqrt(max(means[1, x] - mean_f * mean_f, zero))
        grad_f = np.sqrt(max(means[2, x], zero))
        mean_r = means[3, x]
        d = disparity[x]
        normalised_cost = cost[x] / std_f
        outside = not valid[x]
        no_match = not np.isfinite(d)
        near_epipole = not d >= min_disparity
        ill_conditioned = not range_sigma[x] <= max_range_sigma
        dark = not (mean_f >= min_intensity and mean_r >= min_intensity)
        low_texture = not grad_f >= min_gradient
        poor_match = np.isfinite(normalised_cost) and normalised_cost > max_cost
        reasons[0, x] = outside
        reasons[1, x] = no_match
        reasons[2, x] = near_epipole
        reasons[3, x] = ill_conditioned
        reasons[4, x] = dark
        reasons[5, x] = low_texture
        reasons[6, x] = poor_match
        keep[x] = not (outside or no_match or near_epipole or ill_conditioned or dark or low_texture or poor_match)
