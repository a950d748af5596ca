"""Key frames of a video: keep a frame when the view has moved enough since the last key frame.

A scope's video repeats itself: at 30 fps the reference's bladder scan gave 19,753 frames for 529 planned
views (sec. 2.3.2), and the scope dwells at each. Mapping needs views that overlap well but are not
copies. The criterion here is cheap (about 2 ms of CPU per 608 x 608 frame, on top of decoding it) and
general (no features, so it works on pale, sparsely textured walls too):

1. Each frame is turned grey, shrunk to ``working_width_px`` (area averaging: sensor noise falls by the
   shrink factor) and high-passed (minus a Gaussian blur), which removes the tip light's falloff and the
   vignetting, both of which move with the camera and would otherwise pin the match at zero shift.
2. Phase correlation (``cv2.phaseCorrelate``, a windowed FFT cross-power spectrum) against the last key
   frame gives the image translation ``(dx, dy)`` and the peak's height ``response`` (about 1 for the same
   view, falling with the overlap and towards the noise floor for views that no longer match by a shift).
   The window is a Hann window, or for a circular field of view (an endoscope's) a disc tapered inside the
   field's edge, so the fixed black border and its edge never take part.
3. The frame becomes the next key frame when ``hypot(dx / W, dy / H) >= min_shift_fraction`` (it has
   moved by that fraction of the image) or ``response < min_response`` (rolled, zoomed, cut away, or
   moved beyond phase correlation's reach of half the image).

The first frame is always a key frame; a static stretch, however long, adds none.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class KeyframeOptions:
    """How far the view must move before a frame becomes a key frame.

    min_shift_fraction : float in (0, 1). A frame is kept when its translation from the last key frame
        reaches this fraction of the image size (``hypot(dx / W, dy / H)``). Default 0.2: a wall point then
        stays in view for about ``1 / 0.2 = 5`` consecutive key frames along the motion, so tracks are long
        enough (three views or more) for triangulation and bundle adjustment, with the 50 % lateral overlap
        of a planned spiral (sec. 2.3.2) still giving neighbours across turns.
    min_response : float in [0, 1). A frame is kept when the phase-correlation peak with the last key
        frame falls below this: the two views no longer match by a translation. Default 0.1, between the
        peak of unrelated views (-0.03 to 0.03) and that of the same view moved by a fifth of the image
        (0.45 to 0.74), measured on 304-px views of a dense and a pale tissue texture, with and without a
        circular field (``benchmarks/results/video_import.json``). It then catches a roll of 10-20
        degrees (peak 0.08-0.27 at 10, at most 0.03 at 20) or a zoom of about 1.25 (0.08-0.17): moves
        that shift the field's edge by 0.1-0.15 of the image, the same order as ``min_shift_fraction``.
    working_width_px : int, frames are shrunk to this width (height in proportion) before the comparison.
        At 128 px shifts come out to a fraction of 1/128 of the image (median error 0.8 px of a 608-px
        frame in the benchmark), far finer than the threshold needs.
    highpass_sigma_px : float, Gaussian blur subtracted at the working size (removes shading larger than
        about 4 sigma: lighting falloff, vignetting).
    """

    min_shift_fraction: float = 0.2
    min_response: float = 0.1
    working_width_px: int = 128
    highpass_sigma_px: float = 3.0

    def __post_init__(self) -> None:
        if not 0 < self.min_shift_fraction < 1:
            raise ValueError(f"min_shift_fraction must be in (0, 1), got {self.min_shift_fraction}")
        if not 0 <= self.min_response < 1:
            raise ValueError(f"min_response must be in [0, 1), got {self.min_response}")
        if not 16 <= self.working_width_px <= 2048:
            raise ValueError(f"working_width_px must be 16-2048, got {self.working_width_px}")
        if not (math.isfinite(self.highpass_sigma_px) and 0.5 <= self.highpass_sigma_px <= self.working_width_px / 4):
            raise ValueError(f"highpass_sigma_px must be 0.5 to working_width_px / 4, got {self.highpass_sigma_px}")


@dataclass(frozen=True)
class KeyframeDecision:
    """keep : bool, the frame is a key frame. shift_px : (2,) float, translation (dx, dy) of the image
    content from the last key frame to this one (a camera panning right moves it left: dx < 0), pixels
    of the full frame (NaN for the first frame). shift_fraction : float,
    ``hypot(dx / W, dy / H)``. response : float, phase-correlation peak (1 for the first frame)."""

    keep: bool
    shift_px: tuple[float, float]
    shift_fraction: float
    response: float


class KeyframeSelector:
    """Streaming key-frame choice: call :meth:`offer` with each frame in order.

    field_radius_px : radius of the circular field of view in full-frame pixels, centred in the frame
    (an endoscope's ``Camera.mask_radius_px``), or None for a rectangular field.
    """

    def __init__(self, options: KeyframeOptions = KeyframeOptions(), *, field_radius_px: float | None = None):
        if field_radius_px is not None and not (math.isfinite(field_radius_px) and field_radius_px > 0):
            raise ValueError(f"field_radius_px must be positive, got {field_radius_px}")
        self.options = options
        self.field_radius_px = field_radius_px
        self._size: tuple[int, int] | None = None  # full-frame (W, H)
        self._window: np.ndarray | None = None
        self._key: np.ndarray | None = None
        self._last: np.ndarray | None = None  # the frame last measured, until kept
        self.n_offered = 0
        self.n_kept = 0

    def _prepare(self, image: np.ndarray) -> np.ndarray:
        """(h, w) float32 high-passed grey at the working size."""
        image = np.asarray(image)
        if image.ndim not in (2, 3) or image.dtype not in (np.uint8, np.uint16, np.float32):
            raise ValueError(f"expected an (H, W) or (H, W, 3) image, got {image.shape} {image.dtype}")
        height, width = image.shape[:2]
        if self._size is None:
            self._start(width, height)
        elif (width, height) != self._size:
            raise ValueError(f"frame is {width}x{height}, the first was {self._size[0]}x{self._size[1]}")
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        w, h = self._window.shape[1], self._window.shape[0]
        small = cv2.resize(grey, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
        return small - cv2.GaussianBlur(small, (0, 0), self.options.highpass_sigma_px)

    def _start(self, width: int, height: int) -> None:
        o = self.options
        w = min(o.working_width_px, width)
        h = max(8, int(round(height * w / width)))
        self._size = (width, height)
        if self.field_radius_px is None:
            self._window = cv2.createHanningWindow((w, h), cv2.CV_32F)
            return
        # the disc of the field, shrunk by the high-pass's reach (3 sigma) so the black border's edge,
        # which the high-pass turns into a bright ring, stays out; tapered over 4 sigma
        scale = w / width
        y, x = np.mgrid[0:h, 0:w].astype(np.float32)
        r = np.hypot(x - (w - 1) / 2, y - (h - 1) / 2)
        inner = self.field_radius_px * scale - 3 * o.highpass_sigma_px
        taper = 4 * o.highpass_sigma_px
        if inner <= taper:
            raise ValueError(f"field radius {self.field_radius_px} px is too small for the working size")
        edge = np.clip((inner - r) / taper, 0.0, 1.0)
        self._window = (0.5 - 0.5 * np.cos(np.pi * edge)).astype(np.float32)

    def offer(self, image: np.ndarray) -> KeyframeDecision:
        """Decide on the next frame ((H, W, 3) RGB or (H, W) grey); a kept frame becomes the reference."""
        decision = self.measure(image)
        if decision.keep:
            self.keep()
        return decision

    def measure(self, image: np.ndarray) -> KeyframeDecision:
        """The decision on the next frame, not acted on: :meth:`keep` makes it the reference. For a caller with
        rules of its own (the live mapper also keeps a frame when tracking thins out, and refuses one that
        adds no baseline): the next shift is then measured from the frame it actually kept."""
        prepared = self._prepare(image)
        self.n_offered += 1
        self._last = prepared
        if self._key is None:
            return KeyframeDecision(True, (math.nan, math.nan), math.nan, 1.0)
        (dx, dy), response = cv2.phaseCorrelate(self._key, prepared, self._window)
        scale = self._size[0] / self._window.shape[1]
        shift_fraction = float(math.hypot(dx / self._window.shape[1], dy / self._window.shape[0]))
        keep = shift_fraction >= self.options.min_shift_fraction or response < self.options.min_response
        return KeyframeDecision(bool(keep), (float(dx * scale), float(dy * scale)), shift_fraction, float(response))

    def keep(self) -> None:
        """Make the frame last measured the key frame, whatever its decision said."""
        if self._last is None:
            raise ValueError("no frame measured since the last key frame")
        self._key, self._last = self._last, None
        self.n_kept += 1
