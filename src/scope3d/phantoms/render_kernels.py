"""Compiled per-ray and per-pixel passes of the renderer (:func:`scope3d.phantoms.render.render_frame`): the
rays' rotation, the shading, the depth and the sensor model. A kernel module of :mod:`scope3d.utils.aot`
(compiled at install; numba's JIT where that could not run). It imports only numpy and numba (setup.py
compiles it without importing scope3d).
"""
from __future__ import annotations

import numpy as np
from numba import njit

# Exported at install with the exact argument types render.py passes (C-contiguous)
AOT_SIGNATURES = {
    "rotate_rows": "void(f8[:, ::1], f8[:, ::1], f8[:, ::1])",
    "depth_along": "void(f8[:, ::1], b1[::1], f8[::1], f8[::1], f8[::1])",
    "incidence": "void(f8[:, ::1], f8[:, ::1], f8[::1], f8, f8, f8[::1], f4[::1], f8[::1])",
    "shade": "void(f4[:, ::1], i2[::1], f4[::1], f8[::1], f8[::1], f4, f8, f8, f8, f8, i8[::1], f4[:, ::1], "
             "f4[::1], i2[::1])",
    "noisy_uint8": "void(f4[:, ::1], b1, b1[:, ::1], f4[:, :, ::1], f4, f4, f4, u1[:, :, ::1])",
}


@njit(cache=True, nogil=True)
def noisy_uint8(values, packed, valid, normal, gain, shot2, read2, out):
    """Exposure, the sensor's read and shot noise and 8-bit quantisation, in one pass over the frame.

    values : float32 radiance, (M, C) at the valid pixels in row-major order when ``packed``, else (H W, C)
        at every pixel; gain : float32 radiance -> intensity (1 = full scale); valid (H, W) bool; normal
        (H, W, C) float32 standard normal draws; shot2, read2 the squared noise levels (float32). Fills
        ``out`` (H, W, C) uint8 with ``round(255 (x + sqrt(read2 + shot2 max(x, 0)) normal))``, ``x = gain
        value``, clipped to [0, 255] inside the valid pixels, 0 outside: float32 operations in the order
        NumPy's whole-frame expressions take (``render._to_image`` before this kernel; the same bits),
        without their frame-sized temporaries and passes.
    """
    zero, full = np.float32(0.0), np.float32(255.0)
    row = 0
    for i in range(valid.shape[0]):
        for j in range(valid.shape[1]):
            if not packed:
                row = i * valid.shape[1] + j
            if not valid[i, j]:
                for k in range(out.shape[2]):
                    out[i, j, k] = 0
                continue
            for k in range(out.shape[2]):
                x = values[row, k] * gain
                noisy = max(x, zero) * shot2
                noisy = np.sqrt(noisy + read2)
                noisy = noisy * normal[i, j, k]
                noisy = (noisy + x) * full
                level = np.rint(np.float64(noisy))  # float32 -> float64 is exact: round half to even as NumPy
                out[i, j, k] = np.uint8(min(max(level, 0.0), 255.0))
            if packed:
                row += 1


@njit(cache=True, nogil=True)
def incidence(normals, directions, distance, footprint_scale, root_focal, cos_i, falloff, footprint):
    """Per hit (M rows): how squarely the light at the eye meets the surface, and the pixel's size there.

    normals, directions (M, 3) unit, distance (M,) mm along the rays; footprint_scale the fraction of a
    pixel a ray stands for, root_focal ``sqrt(fx fy)`` px. Fills cos_i ``|n . d|`` (M,) float64, falloff
    ``float32(cos_i / d^2)`` and footprint ``footprint_scale d / root_focal / sqrt(max(cos_i, 0.1))`` mm:
    NumPy's whole-array expressions in ``render._shade`` before this kernel, operation by operation (the
    same bits), without their (M,) temporaries.
    """
    for h in range(normals.shape[0]):
        c = abs(normals[h, 0] * directions[h, 0] + normals[h, 1] * directions[h, 1]
                + normals[h, 2] * directions[h, 2])
        d = distance[h]
        cos_i[h] = c
        falloff[h] = np.float32(c / (d * d))
        widen = c if (c >= 0.1 or c != c) else 0.1  # np.maximum's: NaN propagates
        footprint[h] = footprint_scale * d / root_focal / np.sqrt(widen)


@njit(cache=True, nogil=True)
def shade(albedo, target, falloff, cos_i, distance, target_factor, specular, shininess, efficiency, background,
          rows, reflect, fluor, target_out):
    """Radiance of M hits (Lambertian albedo plus the Blinn-Phong lobe) written to rows ``rows`` of the
    frame's arrays.

    albedo (M, 3) float32; target (M,) int16 id (0: no target); falloff (M,) float32, cos_i and distance
    (M,) float64 from :func:`incidence`; target_factor float32 (albedo kept on a target); specular,
    shininess the material's; efficiency, background the fluorescence of a target and of the rest.
    Writes reflect (N, 3) float32 ``albedo (x target_factor on a target) x falloff + float32(specular
    cos_i^shininess / d^2)``, fluor (N,) float32 ``float32(falloff x efficiency or background)`` and
    target_out (N,) int16 at the rows: float32 and float64 operations as NumPy's whole-array expressions
    in ``render._shade`` took them (the same bits).
    """
    for h in range(albedo.shape[0]):
        r = rows[h]
        on_target = target[h] > 0
        f = falloff[h]
        spec = np.float32(0.0)
        if specular > 0:
            d = distance[h]
            spec = np.float32(specular * cos_i[h] ** shininess / (d * d))
        for k in range(3):
            a = albedo[h, k]
            if on_target:
                a = a * target_factor
            value = a * f
            if specular > 0:
                value = value + spec
            reflect[r, k] = value
        fluor[r] = np.float32(np.float64(f) * (efficiency if on_target else background))
        target_out[r] = target[h]


@njit(cache=True, nogil=True)
def rotate_rows(a, b, out):
    """``out = a @ b`` for (N, 3) ``a`` and (3, 3) ``b``, each entry summed as ``a0 b0k + a1 b1k + a2 b2k``
    (the renderer's column-by-column NumPy product before this kernel: the same bits; BLAS may sum in
    another order), in one pass."""
    for r in range(a.shape[0]):
        a0, a1, a2 = a[r, 0], a[r, 1], a[r, 2]
        for k in range(3):
            out[r, k] = a0 * b[0, k] + a1 * b[1, k] + a2 * b[2, k]


@njit(cache=True, nogil=True)
def depth_along(points, hit, centre, axis, depth):
    """z-depth (N,) of the hit points (N, 3) mm: ``(point - centre) . axis`` summed in that order where
    ``hit``, NaN elsewhere (the renderer's NumPy expression before this kernel: the same bits)."""
    for r in range(points.shape[0]):
        if hit[r]:
            depth[r] = ((points[r, 0] - centre[0]) * axis[0] + (points[r, 1] - centre[1]) * axis[1]
                        + (points[r, 2] - centre[2]) * axis[2])
        else:
            depth[r] = np.nan
