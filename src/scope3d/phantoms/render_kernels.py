"""Compiled per-pixel sensor model of the renderer (:func:`scope3d.phantoms.render.render_frame`): a kernel
module of :mod:`scope3d.utils.aot` (compiled at install; numba's JIT where that could not run). It imports
only numpy and numba (setup.py compiles it without importing scope3d).
"""
from __future__ import annotations

import numpy as np
from numba import njit

# Exported at install with the exact argument types render._to_image passes (C-contiguous)
AOT_SIGNATURES = {
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
