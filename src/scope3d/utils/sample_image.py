"""Bilinear (or other) reads of an image at any number of points with ``cv2.remap``.

``cv2.remap`` asserts that its maps are under SHRT_MAX (32767) on each side, so a flat list of points read
as one column fails once it holds 32767 of them (a frame seen by many mesh vertices, a depth map's pixels
projected into another frame). The points are laid out as an image of ``ROW`` columns, read in blocks of
fewer than 32767 rows.
"""
from __future__ import annotations

import cv2
import numpy as np

ROW = 4096  # columns of the points' layout: small enough for any count's rows to stay few
_MAX_ROWS = 32766  # rows per cv2.remap call, under SHRT_MAX


def sample_image(image: np.ndarray, xy: np.ndarray, *, interpolation: int = cv2.INTER_LINEAR,
                 border: int = cv2.BORDER_REPLICATE, border_value: float = 0.0) -> np.ndarray:
    """``image`` (H, W) or (H, W, C), any dtype cv2.remap takes, read at ``xy`` ((N, 2) float pixels, x = column,
    pixel centres at integers). Returns (N,) or (N, C) of ``image``'s dtype; points outside follow ``border``
    (``border_value`` with ``cv2.BORDER_CONSTANT``)."""
    xy = np.asarray(xy, np.float32).reshape(-1, 2)
    n = len(xy)
    channels = image.shape[2:] if image.ndim == 3 else ()
    if n == 0:
        return np.zeros((0, *channels), image.dtype)
    rows = -(-n // ROW)
    grid = np.zeros((rows * ROW, 2), np.float32)
    grid[:n] = xy
    grid = grid.reshape(rows, ROW, 2)
    parts = [cv2.remap(image, grid[r:r + _MAX_ROWS, :, 0].copy(), grid[r:r + _MAX_ROWS, :, 1].copy(), interpolation,
                       borderMode=border, borderValue=border_value)
             for r in range(0, rows, _MAX_ROWS)]
    return np.concatenate(parts).reshape(rows * ROW, *channels)[:n]
