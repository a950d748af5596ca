"""Compiled kernels of axial stereo: the log-polar resampling maps (:meth:`scope3d.mvs.axial.AxialPair.polar_maps`)
and the reliability tests of every grid cell (:func:`scope3d.mvs.confidence.reliability`). A kernel module of
:mod:`scope3d.utils.aot` (compiled at install; numba's JIT where that could not run). It imports only numpy
and numba (setup.py compiles it without importing scope3d).
"""
from __future__ import annotations

import numpy as np
from numba import njit

# Exported at install with the exact argument types AxialPair._compute_polar_maps passes (C-contiguous)
AOT_SIGNATURES = {
    "polar_maps": "void(f8[::1], f8[::1], f8[:, ::1], f8[::1], f8[::1], i8, i8, f4[:, ::1], f4[:, ::1])",
    "reliability_tests": "void(u1[:, ::1], u1[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], b1[:, ::1], f4[::1], i8, "
                         "i8, i8, b1[:, :, ::1], b1[:, ::1])",
}


@njit(cache=True, nogil=True)
def polar_maps(cos_sin, radii, camera_from_virtual, intrinsics, image, row_lo, row_hi, map_u, map_v):
    """Pixels of the camera that sees every log-polar grid direction, in one pass over the grid.

    cos_sin : (2 A,) cos and sin of the A grid angles, interleaved; radii : (R,) normalised radii;
    camera_from_virtual : (3, 3) rotation; intrinsics : (fx, fy, cx, cy, k1, k2); image : (width, height,
    mask radius px or -1 for none, mask centre u, mask centre v). Fills map_u, map_v (A, R) float32 with
    the distorted pixel of direction ``camera_from_virtual @ (rho cos t, rho sin t, 1)``, or -1 where the
    direction is behind the camera or lands outside the image (or its circular field): the same
    arithmetic as :meth:`scope3d.sensor.camera.Camera.project` and ``in_image`` per element, without
    their (A R, 3) float64 temporaries. Only rows [row_lo, row_hi) of the maps are filled.
    """
    fx, fy, cx, cy, k1, k2 = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3], intrinsics[4], intrinsics[5]
    width, height, mask_radius, mu, mv = image[0], image[1], image[2], image[3], image[4]
    r = camera_from_virtual
    for a in range(row_lo, row_hi):
        c, s = cos_sin[2 * a], cos_sin[2 * a + 1]
        for j in range(map_u.shape[1]):
            x, y = radii[j] * c, radii[j] * s
            dz = r[2, 0] * x + r[2, 1] * y + r[2, 2]
            u = -1.0
            v = -1.0
            if dz > 0:
                xn = (r[0, 0] * x + r[0, 1] * y + r[0, 2]) / dz
                yn = (r[1, 0] * x + r[1, 1] * y + r[1, 2]) / dz
                r2 = xn * xn + yn * yn
                factor = 1.0 + k1 * r2 + k2 * r2 * r2
                pu = fx * (xn * factor) + cx
                pv = fy * (yn * factor) + cy
                inside = -0.5 <= pu <= width - 0.5 and -0.5 <= pv <= height - 0.5
                if inside and mask_radius >= 0:
                    inside = np.sqrt((pu - mu) ** 2 + (pv - mv) ** 2) <= mask_radius
                if inside:
                    u, v = pu, pv
            map_u[a, j] = u
            map_v[a, j] = v


@njit(cache=True, nogil=True)
def _reflect(index, length):
    """OpenCV's BORDER_REFLECT (``fedcba|abcdefgh|hgfedcb``) index, reflected as often as needed."""
    if length == 1:
        return 0
    while index < 0 or index >= length:
        index = -index - 1 if index < 0 else 2 * length - index - 1
    return index


@njit(cache=True, nogil=True)
def _add_row(columns, front, rear, row, sign):
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
                _add_row(columns, front, rear, _reflect(r, height), 1.0)
        else:
            _add_row(columns, front, rear, _reflect(y + half, height), 1.0)
            _add_row(columns, front, rear, _reflect(y - half - 1, height), -1.0)
        for q in range(4):
            column = columns[q]
            for x in range(width):
                padded[half + x] = column[x]
            for k in range(half):
                padded[half - 1 - k] = column[_reflect(-1 - k, width)]
                padded[half + width + k] = column[_reflect(width + k, width)]
            for x in range(width):
                sums[x] = padded[x]
            for k in range(1, window):
                for x in range(width):
                    sums[x] += padded[x + k]
            mean = means[q]
            for x in range(width):
                mean[x] = np.float32(sums[x] * inverse)
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
