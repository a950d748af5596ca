"""A surgical tool in the scope's view (reference sec. 5.2: the scope rides along the tool, which hides a
sector of every frame).

The tool is rigid with the scope, so it covers the same pixels in every frame: :func:`tool_mask` draws
its outline once in image coordinates, and :func:`paint_tool` lays it over a rendered frame as a
matt metal shaft lit from the scope tip (bright along its near edge, darker across), with the frame's
own sensor noise left on it so that it looks like part of the image, not a pasted patch.
"""
from __future__ import annotations

import numpy as np

from scope3d.sensor.camera import Camera

#: The shaft enters from the bottom edge of the view, 22 % of the image wide, its rounded tip 40 % of the
#: way up from the bottom: about the sector the reference's Fig. 5.3(b) loses.
TOOL_WIDTH_FRACTION = 0.22
TOOL_REACH_FRACTION = 0.40
TOOL_OFFSET_FRACTION = 0.12  # shaft centre right of the image centre


def tool_mask(camera: Camera) -> np.ndarray:
    """(H, W) bool, True where the tool hides the scene."""
    h, w = camera.height, camera.width
    v, u = np.mgrid[0:h, 0:w].astype(float)
    half = TOOL_WIDTH_FRACTION * w / 2.0
    centre_u = (w - 1) / 2.0 + TOOL_OFFSET_FRACTION * w
    tip_v = (h - 1) * (1.0 - TOOL_REACH_FRACTION) + half
    shaft = (np.abs(u - centre_u) <= half) & (v >= tip_v)
    tip = np.hypot(u - centre_u, v - tip_v) <= half
    return shaft | tip


def paint_tool(image: np.ndarray, mask: np.ndarray, *, seed: int, frame_index: int) -> np.ndarray:
    """``image`` (H, W, 3) uint8 with the tool painted where ``mask``; the shading follows a cylinder lit
    along the view, ~2 grey levels of noise per frame (``default_rng([seed, frame_index, 1])``)."""
    out = image.copy()
    h, w = mask.shape
    cols = np.flatnonzero(mask.any(axis=0))
    if len(cols) == 0:
        return out
    u = np.arange(w, dtype=float)
    x = np.clip((u - cols.mean()) / max((cols.max() - cols.min()) / 2.0, 1.0), -1.0, 1.0)
    shade = 0.25 + 0.45 * np.sqrt(1.0 - x * x)  # Lambert across a cylinder facing the light
    tone = np.array([0.78, 0.80, 0.84])  # steel, slightly blue
    value = 255.0 * shade[None, :, None] * tone[None, None, :]
    rng = np.random.default_rng([seed, frame_index, 1])
    noisy = np.broadcast_to(value, (h, w, 3)) + rng.normal(0.0, 2.0, (h, w, 1))
    out[mask] = np.clip(np.rint(noisy[mask]), 0, 255).astype(np.uint8)
    return out
