"""Compiled kernel of axial stereo: the log-polar resampling maps (:meth:`scope3d.mvs.axial.AxialPair.polar_maps`;
the reliability tests' window statistics are in :mod:`scope3d.mvs.refine_kernels`). A kernel module of
:mod:`scope3d.utils.aot` (compiled at install; numba's JIT where that could not run). It imports only numpy
and numba (setup.py compiles it without importing scope3d).
"""
from __future__ import annotations

import numpy as np
from numba import njit

# Exported at install with the exact argument types AxialPair._compute_polar_maps passes (C-contiguous)
AOT_SIGNATURES = {
    "polar_maps": "void(f8[::1], f8[::1], f8[:, ::1], f8[::1], f8[::1], i8, i8, f4[:, ::1], f4[:, ::1])",
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
