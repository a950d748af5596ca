"""Procedural, world-anchored textures for the phantoms, precomputed as images and sampled bilinearly.

A texture is an image laid on a plane of the world (or on an unrolled cylinder) with a known origin
and texel size in millimetres, so that a surface point always gets the same colour whatever camera
sees it: this is what makes features match across views, as on the printed and painted phantoms of
the reference (sec. 4.2: "near-realistic surgical features"; sec. 2.2: vessels drawn in red and blue
ink inside the bladder phantom).

Everything here is vectorised: textures are generated with array operations and a few hundred
``cv2.polylines`` calls (one per vessel), and sampled with ``cv2.remap``.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from scope3d.utils.sample_image import sample_image


@dataclass(frozen=True)
class TextureMap:
    """An image pinned to world coordinates.

    image : (H, W, C) uint8; texel (row i, column j) covers the square centred on
        ``origin_mm + (j, i) * mm_per_texel`` in the texture's (u, v) plane.
    origin_mm : (2,) float, (u, v) of the centre of texel (0, 0), mm.
    mm_per_texel : float, mm.
    wrap_u : bool, the texture repeats along u (an unrolled cylinder; the seam is a visible, world-anchored
        line); otherwise edges are clamped.

    Coarser mip levels are read where their texels are: ``cv2.pyrDown`` centres its output texel ``i`` on
    input texel ``2 i``, so level ``k``'s texel ``i`` is centred on level 0's ``i 2^k``, and every level
    shows the pattern at the same place in the world (two views reading one point at different levels see
    it at the same place: no sub-pixel disparity error from the pyramid).
    """

    image: np.ndarray
    origin_mm: tuple[float, float]
    mm_per_texel: float
    wrap_u: bool = False

    def __post_init__(self) -> None:
        img = np.asarray(self.image)
        if img.ndim == 2:
            img = img[..., None]
        if img.dtype != np.uint8 or img.ndim != 3:
            raise ValueError("texture image must be (H, W) or (H, W, C) uint8")
        object.__setattr__(self, "image", np.ascontiguousarray(img))
        if self.mm_per_texel <= 0:
            raise ValueError("texel size must be positive")

    @property
    def channels(self) -> int:
        return self.image.shape[2]

    def level(self, k: int) -> np.ndarray:
        """Mip level k: the image low-passed and halved k times (Gaussian pyramid), built on first use."""
        pyramid = self.__dict__.setdefault("_pyramid", [self.image])
        while len(pyramid) <= k:
            prev = pyramid[-1]
            nxt = cv2.pyrDown(prev)
            pyramid.append(nxt.reshape(nxt.shape[0], nxt.shape[1], -1))
        return pyramid[k]

    def sample(self, uv_mm: np.ndarray, footprint_mm: np.ndarray | float | None = None) -> np.ndarray:
        """Filtered lookup. uv_mm : (N, 2) mm in the texture plane -> (N, C) float32 in [0, 1].

        footprint_mm : (N,) or scalar, size of the pixel on the surface (mm). The texture is read from the
            mip level whose texel matches it, so that a distant view shows the average colour instead of
            aliasing (which would make the same point look different in two views). None = full resolution.
        """
        uv = np.asarray(uv_mm, dtype=float).reshape(-1, 2)
        n = len(uv)
        if n == 0:
            return np.zeros((0, self.channels), np.float32)
        if footprint_mm is None:
            return self._sample_level(uv, 0)
        ratio = np.broadcast_to(np.asarray(footprint_mm, dtype=float), (n,)) / self.mm_per_texel
        levels = np.clip(np.floor(np.log2(np.maximum(ratio, 1e-9)) + 0.5), 0, 8).astype(np.intp)
        counts = np.bincount(levels, minlength=9)
        if np.count_nonzero(counts) == 1:
            return self._sample_level(uv, int(levels[0]))
        # Group the points by level with one sort instead of a boolean mask over all points per level;
        # each point's lookup is independent of the others, so the grouping changes no value.
        order = np.argsort(levels, kind="stable")
        out = np.empty((n, self.channels), np.float32)
        start = 0
        for k in np.flatnonzero(counts):
            idx = order[start:start + counts[k]]
            out[idx] = self._sample_level(uv[idx], int(k))
            start += counts[k]
        return out

    def _sample_level(self, uv: np.ndarray, k: int) -> np.ndarray:
        n = len(uv)
        image = self.level(k)
        scale = 2**k
        # level-0 texel coordinates, then level k's: pyrDown centres its texel (i, j) on level 0's (i 2^k, j 2^k)
        cols = (uv[:, 0] - self.origin_mm[0]) / self.mm_per_texel / scale
        rows = (uv[:, 1] - self.origin_mm[1]) / self.mm_per_texel / scale
        if self.wrap_u:
            cols = np.mod(cols, image.shape[1])
        border = cv2.BORDER_WRAP if self.wrap_u else cv2.BORDER_REPLICATE
        out = sample_image(image, np.column_stack([cols, rows]), border=border).reshape(n, -1)
        return out.astype(np.float32) / 255.0


# --- noise -----------------------------------------------------------------------------------


def smooth_noise(shape: tuple[int, int], feature_texels: float, rng: np.random.Generator) -> np.ndarray:
    """Band-limited noise with blobs about ``feature_texels`` across. -> (H, W) float32, zero mean, unit std."""
    h, w = shape
    gh = max(int(np.ceil(h / feature_texels)) + 3, 4)
    gw = max(int(np.ceil(w / feature_texels)) + 3, 4)
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    # Resize a slightly larger grid and crop so that the edges are not stretched differently.
    big = cv2.resize(grid, (int(gw * feature_texels), int(gh * feature_texels)), interpolation=cv2.INTER_CUBIC)
    out = big[:h, :w]
    return (out - out.mean()) / (out.std() + 1e-9)


def fractal_noise(
    shape: tuple[int, int], largest_texels: float, octaves: int, rng: np.random.Generator, persistence: float = 0.55
) -> np.ndarray:
    """Sum of ``octaves`` layers of :func:`smooth_noise`, each half the size of the previous. -> (H, W) float32."""
    out = np.zeros(shape, np.float32)
    amplitude, size = 1.0, float(largest_texels)
    for _ in range(octaves):
        if size < 1.5:
            break
        out += amplitude * smooth_noise(shape, size, rng)
        amplitude *= persistence
        size /= 2.0
    return (out - out.mean()) / (out.std() + 1e-9)


# --- vessel networks -------------------------------------------------------------------------


def vessel_mask(
    shape: tuple[int, int],
    mm_per_texel: float,
    rng: np.random.Generator,
    *,
    density_per_cm2: float,
    width_mm: tuple[float, float],
    segment_mm: float,
    max_depth: int = 3,
) -> np.ndarray:
    """Branching random-walk vessels drawn with anti-aliased lines. -> (H, W) float32 coverage in [0, 1].

    density_per_cm2 : trunk vessels started per cm² of texture.
    width_mm : (thinnest, thickest) vessel width; branches are thinner than their parent.
    segment_mm : length of one straight piece of a vessel; vessels wander by about 20° per piece.
    """
    h, w = shape
    canvas = np.zeros(shape, np.uint8)
    area_cm2 = h * w * mm_per_texel**2 / 100.0
    n_trunks = max(1, int(round(density_per_cm2 * area_cm2)))
    shift = 4  # sub-texel precision of cv2 drawing, 1/16 texel
    stack = []
    for _ in range(n_trunks):
        start = rng.uniform([0, 0], [w, h])
        stack.append((start, rng.uniform(0, 2 * np.pi), width_mm[1] * rng.uniform(0.6, 1.0), 0))
    seg_px = segment_mm / mm_per_texel
    while stack:
        pos, heading, width, depth = stack.pop()
        n_seg = int(rng.integers(8, 30))
        turns = np.cumsum(rng.normal(0.0, 0.35, n_seg)) + heading
        steps = seg_px * np.stack([np.cos(turns), np.sin(turns)], axis=1)
        pts = np.vstack([pos, pos + np.cumsum(steps, axis=0)])
        thickness = max(1, int(round(width / mm_per_texel)))
        cv2.polylines(canvas, [np.round(pts * (1 << shift)).astype(np.int32)], False, 255, thickness,
                      cv2.LINE_AA, shift)
        if depth < max_depth and width * 0.6 >= width_mm[0]:
            for k in rng.choice(n_seg, size=int(rng.integers(1, 4)), replace=False):
                side = rng.choice([-1.0, 1.0])
                stack.append((pts[k + 1], turns[k] + side * rng.uniform(0.5, 1.2), width * rng.uniform(0.45, 0.7),
                              depth + 1))
    return canvas.astype(np.float32) / 255.0


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)


def tissue_texture(
    size_mm: tuple[float, float],
    mm_per_texel: float,
    seed: int,
    *,
    vessel_width_mm: tuple[float, float] = (0.05, 0.35),
    vessel_density_per_cm2: float = 0.7,
    speckle_mm: float = 0.12,
    background_rgb: tuple[float, float, float] = (0.86, 0.58, 0.52),
    dot_contrast: float = 0.45,
) -> np.ndarray:
    """Cortex-like reflectance: mottled pink tissue, a branching network of red and blue vessels, and small
    dark speckles (capillary dots, darkening by up to ``dot_contrast``) that give SIFT features at the
    endoscope's pixel footprint.

    size_mm : (width, height) of the textured area; mm_per_texel : texel size.
    Returns (H, W, 3) uint8 RGB albedo with H = ceil(height / mm_per_texel).
    """
    rng = np.random.default_rng(seed)
    w = int(np.ceil(size_mm[0] / mm_per_texel))
    h = int(np.ceil(size_mm[1] / mm_per_texel))
    shape = (h, w)
    mottle = fractal_noise(shape, 4.0 / mm_per_texel, 6, rng)
    fine = smooth_noise(shape, speckle_mm / mm_per_texel, rng)
    base = np.asarray(background_rgb, np.float32)
    rgb = base * (1.0 + 0.10 * mottle[..., None])
    # Capillary dots: where band-limited noise peaks, the tissue is darker and redder.
    dots = np.clip((fine - 1.3) / 0.8, 0.0, 1.0)
    rgb = rgb * (1.0 - dot_contrast * dots[..., None] * np.array([0.6, 1.0, 1.0], np.float32))
    arteries = vessel_mask(shape, mm_per_texel, rng, density_per_cm2=vessel_density_per_cm2,
                           width_mm=vessel_width_mm, segment_mm=0.6)
    veins = vessel_mask(shape, mm_per_texel, rng, density_per_cm2=vessel_density_per_cm2 * 0.5,
                        width_mm=vessel_width_mm, segment_mm=0.8)
    red = np.array([0.55, 0.10, 0.10], np.float32)
    blue = np.array([0.30, 0.18, 0.42], np.float32)
    rgb = rgb * (1.0 - arteries[..., None]) + red * arteries[..., None]
    rgb = rgb * (1.0 - veins[..., None]) + blue * veins[..., None]
    return _to_uint8(rgb)


def printed_texture(size_mm: tuple[float, float], mm_per_texel: float, seed: int) -> np.ndarray:
    """A printed photograph of tissue on white paper: the tissue pattern with higher contrast and a paper
    background. -> (H, W, 3) uint8."""
    tissue = tissue_texture(size_mm, mm_per_texel, seed, background_rgb=(0.93, 0.80, 0.74),
                            vessel_density_per_cm2=1.0)
    return tissue


def machined_texture(
    size_mm: tuple[float, float], mm_per_texel: float, seed: int, *, along_mm: float = 2.0, across_mm: float = 0.02,
    periodic_u: bool = False,
) -> np.ndarray:
    """Brushed/turned metal: noise stretched along u (the tool path), fine across it. -> (H, W, 1) uint8.

    along_mm, across_mm : typical length of a tool mark along and across the cut.
    periodic_u : make the last column continue into the first (for a texture wrapped round a bore).
    """
    rng = np.random.default_rng(seed)
    w = max(1, int(round(size_mm[0] / mm_per_texel)))  # exactly one period when periodic_u
    h = int(np.ceil(size_mm[1] / mm_per_texel))
    band = max(2, w // 8) if periodic_u else 0
    wb = w + band
    # Anisotropic noise: isotropic noise on a grid squeezed along u, then stretched back.
    ratio = max(along_mm / across_mm, 1.0)
    squeezed_w = max(int(np.ceil(wb / ratio * 4)), 8)
    marks = smooth_noise((h, squeezed_w), across_mm / mm_per_texel, rng)
    marks = cv2.resize(marks, (wb, h), interpolation=cv2.INTER_LINEAR)
    blotch = fractal_noise((h, wb), 1.0 / mm_per_texel, 4, rng)
    grain = rng.standard_normal((h, wb)).astype(np.float32)
    grey = 0.58 + 0.10 * marks + 0.03 * blotch + 0.02 * grain
    if band:
        # Cross-fade the first columns with the ones just past the end, so column w-1 runs into column 0.
        fade = (np.arange(band, dtype=np.float32) / band)[None, :]
        grey[:, :band] = fade * grey[:, :band] + (1 - fade) * grey[:, w:w + band]
        grey = grey[:, :w]
    return _to_uint8(grey[..., None])
