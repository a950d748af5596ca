"""Compiled passes of the sub-pixel disparity refinement (:func:`scope3d.mvs.dense_matching.refine_subpixel`): a
kernel module of :mod:`scope3d.utils.aot` (compiled at install; numba's JIT where that could not run). It imports
only numpy and numba (setup.py compiles it without importing scope3d).

The refinement warps the right image and its row gradient by every pixel's disparity and then needs seven
window means of their products. With OpenCV that was a two-channel Lanczos-4 ``cv2.remap`` (an 8 x 8 kernel,
of which 7 rows have weight 0 since every row stays on its row) and nine ``cv2.boxFilter`` calls on
frame-sized products, each its own pass. Here the warp is OpenCV's own one-dimensional Lanczos-4 (its
weights, read from ``cv2.remap`` by the caller, and its 1/32-pixel quantisation of the position) and each
window mean is a running column sum in float64 of the float32 products, as ``cv2.boxFilter`` sums them
(BORDER_REFLECT), scaled and rounded to float32 once. The float32 arithmetic that follows is the order
of NumPy's expressions in the refinement before these kernels, so the results are the same bits
(tests/test_refine_kernels.py checks it against the OpenCV and NumPy computation).

Every pass writes the rows ``[row_lo, row_hi)`` of its outputs only, so that threads can share a frame by
blocks of rows (the functions release the GIL).
"""
from __future__ import annotations

import numpy as np
from numba import njit

# Exported at install with the exact argument types dense_matching.refine_subpixel passes (C-contiguous)
AOT_SIGNATURES = {
    "warp_rows": "void(f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], i8, i8, f4[:, ::1], f4[:, ::1])",
    "window_pass": "void(f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], i8, i8, b1, "
                   "i8, i8, f4[:, ::1], f4[:, ::1])",
}

LANCZOS_TAPS = 8  # cv2.INTER_LANCZOS4: 4 source pixels either side
LANCZOS_STEPS = 32  # OpenCV's INTER_TAB_SIZE: remap positions are rounded to 1/32 pixel


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
            for k in range(LANCZOS_TAPS):
                col = min(max(start + k, 0), width - 1)
                value += image[y, col] * weights[phase, k]
                grad += gradient[y, col] * weights[phase, k]
            warped[y, x] = value
            warped_gradient[y, x] = grad


@njit(cache=True, nogil=True)
def window_pass(left, warped, gradient, mean_left, var_left, disparity, window_cols, window_rows, with_step,
                row_lo, row_hi, out_a, out_b):
    """Window statistics of the zero-mean, gain-normalised residual between ``left`` and the warped right image.

    left, warped, gradient : (H, W) float32, the left image, the right image warped by the current
    disparity and its warped row gradient; mean_left, var_left : (H, W) float32 window mean and
    variance (floored) of ``left``; disparity : (H, W) float32 current disparity (0 where unknown).
    window_cols, window_rows : odd window size. Every window mean is ``float32(sum * (1 / n))`` of the
    float32 products summed in float64 with BORDER_REFLECT, as ``cv2.boxFilter(..., normalize=True)``.

    With ``with_step`` the Gauss-Newton step is taken: ``out_a`` gets the new disparity
    ``d + clip(-mean(J e) / mean(J^2), -1/2, 1/2)`` (no step where ``mean(J^2) <= 1e-9``). Without,
    ``out_a`` gets ``mean(J^2)`` and ``out_b`` ``mean(e^2)`` (J and e as in ``refine_subpixel``). Only rows
    [row_lo, row_hi) of the outputs are written; the column sums restart at ``row_lo``, so a frame cut into
    the same blocks gives the same bits whichever thread runs which block.
    """
    height, width = left.shape
    half_r, half_c = window_rows // 2, window_cols // 2
    n_sums = 7 if with_step else 5
    # column sums over the window's rows, padded by the window's half width on both sides (reflected)
    columns = np.zeros((n_sums, width + 2 * half_c))
    inverse = 1.0 / (window_cols * window_rows)
    tiny = np.float32(1e-6)
    zero = np.float32(0.0)
    two = np.float32(2.0)
    half = np.float32(0.5)
    min_jj = np.float32(1e-9)
    for y in range(row_lo, row_hi):
        if y == row_lo:
            for q in range(n_sums):
                for x in range(width):
                    columns[q, half_c + x] = 0.0
            for r in range(y - half_r, y + half_r + 1):
                _add_row(columns, left, warped, gradient, _reflect(r, height), half_c, 1.0, n_sums)
        else:
            _add_row(columns, left, warped, gradient, _reflect(y + half_r, height), half_c, 1.0, n_sums)
            _add_row(columns, left, warped, gradient, _reflect(y - half_r - 1, height), half_c, -1.0, n_sums)
        for q in range(n_sums):
            for k in range(half_c):
                columns[q, half_c - 1 - k] = columns[q, half_c + _reflect(-1 - k, width)]
                columns[q, half_c + width + k] = columns[q, half_c + _reflect(width + k, width)]
        for x in range(width):
            s_w = 0.0
            s_g = 0.0
            s_ww = 0.0
            s_gg = 0.0
            s_lw = 0.0
            s_gl = 0.0
            s_gw = 0.0
            for k in range(window_cols):
                s_w += columns[0, x + k]
                s_g += columns[1, x + k]
                s_ww += columns[2, x + k]
                s_gg += columns[3, x + k]
                s_lw += columns[4, x + k]
                if with_step:
                    s_gl += columns[5, x + k]
                    s_gw += columns[6, x + k]
            mu_l = mean_left[y, x]
            var_l = var_left[y, x]
            mu_w = np.float32(s_w * inverse)
            mu_g = np.float32(s_g * inverse)
            var_w = max(np.float32(s_ww * inverse) - mu_w * mu_w, tiny)
            var_g = max(np.float32(s_gg * inverse) - mu_g * mu_g, zero)
            cov_lw = np.float32(s_lw * inverse) - mu_l * mu_w
            a = np.sqrt(var_l / var_w)
            jj = a * a * var_g  # mean of J^2
            if with_step:
                cov_gl = np.float32(s_gl * inverse) - mu_g * mu_l
                cov_gw = np.float32(s_gw * inverse) - mu_g * mu_w
                je = a * (cov_gl - a * cov_gw)  # mean of J e
                step = zero
                if jj > min_jj:
                    step = -je / jj
                    # Damped: a step beyond half a column leaves the linear range of the interpolated gradient
                    if step > half:  # NaN passes, as through np.clip
                        step = half
                    elif step < -half:
                        step = -half
                out_a[y, x] = disparity[y, x] + step
            else:
                out_a[y, x] = jj
                out_b[y, x] = max(var_l - two * a * cov_lw + a * a * var_w, zero)  # mean of e^2


@njit(cache=True, nogil=True)
def _add_row(columns, left, warped, gradient, row, offset, sign, n_sums):
    """Add (sign 1) or remove (sign -1) one image row's float32 products to the float64 column sums."""
    for x in range(left.shape[1]):
        l = left[row, x]
        w = warped[row, x]
        g = gradient[row, x]
        columns[0, offset + x] += sign * w
        columns[1, offset + x] += sign * g
        columns[2, offset + x] += sign * (w * w)
        columns[3, offset + x] += sign * (g * g)
        columns[4, offset + x] += sign * (l * w)
        if n_sums == 7:
            columns[5, offset + x] += sign * (g * l)
            columns[6, offset + x] += sign * (g * w)
