"""Multi-view axial stereo (reference sec. 9.2): fuse several pairs along the hole into one dense cloud.

Depth error of one pair grows as ``Z^2 * step / b`` (eq. 7.3), so the cure is more baseline and more
looks. For each *reference* frame ``j`` (the front camera of its pairs), pairs ``(j - s, j)`` are
reconstructed for every offset ``s`` in ``baseline_offsets`` (multi-baseline stereo, Okutomi-Kanade),
all on the reference's own pixel grid, where a range along a pixel ray means the same thing whatever the
pair. Per pixel the estimates are fused robustly:

1. the median of the available ranges is the anchor;
2. estimates within ``max(consistency_sigmas * sigma_k, consistency_floor_mm)`` of it are consistent
   (``sigma_k`` the pair's predicted range error); the rest are mismatches (repeated thread rings,
   occlusions that differ between baselines);
3. the fused range is the inverse-variance weighted mean of the consistent ones, kept only when at least
   ``min_consistent`` agree, with sigma ``1 / sqrt(sum 1 / sigma_k^2)``.

References every ``reference_stride`` frames cover the hole; their clouds are concatenated.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.mvs.two_view import ImageDepth, TwoViewOptions, reconstruct_pair, to_image
from scope3d.sensor.camera import Camera


@dataclass(frozen=True)
class MultiViewOptions:
    """baseline_offsets : frame offsets ``s`` of the rear frames behind each reference (1 = consecutive).
    reference_stride : a reference every this many frames.
    min_consistent : estimates that must agree for a pixel to be kept (2 rejects single-pair mismatches).
    consistency_sigmas, consistency_floor_mm : agreement test of the module docstring.
    two_view : options of every pair.
    """

    baseline_offsets: tuple[int, ...] = (1, 2, 3, 4)
    reference_stride: int = 4
    min_consistent: int = 2
    consistency_sigmas: float = 3.0
    consistency_floor_mm: float = 0.03
    two_view: TwoViewOptions = field(default_factory=TwoViewOptions)

    def __post_init__(self) -> None:
        if not self.baseline_offsets or min(self.baseline_offsets) < 1:
            raise ValueError("MultiViewOptions.baseline_offsets must be positive frame offsets")
        if self.reference_stride < 1 or self.min_consistent < 1:
            raise ValueError("MultiViewOptions.reference_stride and min_consistent must be at least 1")
        if self.min_consistent > len(self.baseline_offsets):
            raise ValueError("MultiViewOptions.min_consistent exceeds the number of baselines")


@dataclass(frozen=True)
class FusedDepth:
    """One reference frame's fused depth on its pixel grid; arrays (H, W).

    depth : ImageDepth (range, z-depth, world points, confidence) of the fused result.
    range_sigma_mm : float32 predicted 1-sigma range error, NaN = none.
    n_consistent : int16 number of agreeing pairs.
    reference : frame index.
    """

    depth: ImageDepth
    range_sigma_mm: np.ndarray
    n_consistent: np.ndarray
    reference: int


def fuse_ranges(ranges_mm: np.ndarray, sigmas_mm: np.ndarray, *,
                options: MultiViewOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust per-pixel fusion (module docstring).

    ranges_mm, sigmas_mm : (K, H, W) float, NaN = no estimate. Returns fused range (H, W) mm (NaN where
    fewer than ``min_consistent`` agree), its sigma (H, W) mm, and the count (H, W) int16.
    """
    r = np.asarray(ranges_mm, dtype=float)
    s = np.asarray(sigmas_mm, dtype=float)
    known = np.isfinite(r) & np.isfinite(s) & (s > 0)
    r = np.where(known, r, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: no estimate, handled below
        anchor = np.nanmedian(r, axis=0)
    tol = np.maximum(options.consistency_sigmas * s, options.consistency_floor_mm)
    consistent = known & (np.abs(r - anchor) <= tol)
    w = np.where(consistent, 1.0 / np.where(known, s, 1.0) ** 2, 0.0)
    wsum = w.sum(axis=0)
    count = consistent.sum(axis=0).astype(np.int16)
    with np.errstate(all="ignore"):
        fused = (np.where(consistent, r, 0.0) * w).sum(axis=0) / wsum
        sigma = 1.0 / np.sqrt(wsum)
    keep = count >= options.min_consistent
    return np.where(keep, fused, np.nan), np.where(keep, sigma, np.nan), count


def reference_frames(n_frames: int, *, options: MultiViewOptions) -> list[int]:
    """Frames that get a fused depth map: from the first with all its rear frames, every stride."""
    first = max(options.baseline_offsets)
    return list(range(first, n_frames, options.reference_stride))


def reconstruct_reference(
    camera: Camera,
    frames: Callable[[int], np.ndarray],
    poses: Sequence[Pose],
    reference: int,
    *,
    options: MultiViewOptions = MultiViewOptions(),
) -> FusedDepth:
    """Fuse the pairs ``(reference - s, reference)`` for every baseline offset ``s``.

    frames : callable index -> (H, W) uint8 grey frame; poses : cam_from_world per frame.
    """
    ranges, sigmas = [], []
    pair = None
    front = frames(reference)
    for s in options.baseline_offsets:
        if reference - s < 0:
            continue
        res = reconstruct_pair(camera, frames(reference - s), front, poses[reference - s], poses[reference],
                               options=options.two_view)
        pair = res.pair
        rng = to_image(res.pair, res.range_mm).range_mm
        sig = res.pair.from_polar(np.where(np.isfinite(res.range_mm), res.reliability.range_sigma_mm, np.nan),
                                  res.pair.pose_front)
        ranges.append(rng)
        sigmas.append(sig)
    if pair is None:
        raise ValueError(f"reference frame {reference} has no frame behind it at the requested offsets")
    fused, sigma, count = fuse_ranges(np.stack(ranges), np.stack(sigmas), options=options)
    max_sigma = options.two_view.confidence.max_range_sigma_mm
    confidence = np.where(np.isfinite(fused), 1.0 / (1.0 + (sigma / max_sigma) ** 2), 0.0)
    depth = _image_depth(camera, poses[reference], fused, confidence)
    return FusedDepth(depth, sigma.astype(np.float32), count, reference)


def _image_depth(camera: Camera, pose: Pose, range_mm: np.ndarray, confidence: np.ndarray) -> ImageDepth:
    """ImageDepth of a range map (H, W) on the pixel grid of the camera at ``pose``."""
    rays = camera.unproject(camera.pixel_grid().reshape(-1, 2)).reshape(range_mm.shape + (3,))
    with np.errstate(invalid="ignore"):
        z = (range_mm * rays[..., 2]).astype(np.float32)
    pts = pose.centre + (rays * range_mm[..., None]) @ pose.rotation
    return ImageDepth(z, range_mm.astype(np.float32), pts, confidence.astype(np.float32), pose)
