"""Dense matching along image rows: semi-global matching, the reference's SAD block matcher, and a
sub-pixel refinement shared by both.

Both matchers take a *rectified* pair, ``left`` and ``right`` (H, W) uint8, in which a scene point at
column ``x`` of ``left`` is at column ``x - d`` of ``right`` on the same row, ``d >= 0``. In axial stereo
these are the front and rear images resampled on the log-polar grid (:mod:`scope3d.mvs.axial`); in
lateral stereo, the left and right images of an ordinary rectified pair. Disparities are float32 columns
with NaN where there is no match.

* :func:`sgm_disparity` -- OpenCV's StereoSGBM (Hirschmüller's semi-global matching with the
  Birchfield-Tomasi cost and a parabola sub-pixel step), followed by :func:`refine_subpixel`.
* :func:`sad_disparity` -- the reference's matcher (sec. 7.2.2 and 7.4): sum of absolute differences
  over a 7x7 block, winner-take-all, parabola fit through the three costs around the minimum [136].
* :func:`refine_subpixel` -- one-dimensional Lucas-Kanade on each window: removes the "pixel locking"
  bias of parabola fits and returns each disparity's standard deviation from the residual.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from scope3d.utils.aot import load_kernels
from scope3d.utils.row_blocks import run_by_row_blocks

_kernels = load_kernels("scope3d.mvs.refine_kernels")

# Lanczos-4 resampling in the refinement: linear (and, less so, cubic) interpolation low-passes by a
# shift-dependent amount and pulls sub-pixel estimates toward integers, the very bias the refinement
# removes (measured on band-limited textures: cubic leaves ~0.07 px, Lanczos-4 ~0.01 px).
_INTERP = cv2.INTER_LANCZOS4


@dataclass(frozen=True)
class SgmOptions:
    """Semi-global matching (cv2.StereoSGBM) settings.

    num_disparities : int, search range in columns ``[min_disparity, min_disparity + num_disparities)``;
        rounded up to a multiple of 16 as OpenCV requires.
    block_size : int, odd, matching window in pixels (the cost is summed over it).
    p1, p2 : float, smoothness penalties per unit of block area and channel, OpenCV's suggested
        ``8 * bs^2`` and ``32 * bs^2`` (small changes of 1 column vs jumps at depth edges).
    uniqueness_ratio : int, percent by which the best cost must beat the second best.
    max_lr_difference_px : int, left-right consistency tolerance in columns (OpenCV disp12MaxDiff).
    speckle_window : int, connected blobs of disparity smaller than this (pixels) are removed; 0 = off.
    speckle_range : int, disparity variation (columns) allowed inside one blob.
    refine_window_px : int, odd window width (columns) of :func:`refine_subpixel`; 0 disables it.
    refine_window_rows : int, odd window height (rows); 0 = square. In axial stereo rows are polar
        angles, along which a turned or threaded bore changes slowly, so a tall window gathers more
        texture without mixing depths.
    refine_iterations : int.
    wrap_rows : bool, treat the first and last rows as neighbours (the polar angle wraps around), so
        that the vertical aggregation paths do not start cold at theta = 0.
    """

    num_disparities: int = 64
    min_disparity: int = 0
    block_size: int = 5
    p1: float = 8.0
    p2: float = 32.0
    uniqueness_ratio: int = 5
    max_lr_difference_px: int = 1
    speckle_window: int = 100
    speckle_range: int = 2
    refine_window_px: int = 7
    refine_window_rows: int = 0
    refine_iterations: int = 3
    wrap_rows: bool = False

    def __post_init__(self) -> None:
        if self.num_disparities < 1:
            raise ValueError("SgmOptions.num_disparities must be at least 1")
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise ValueError("SgmOptions.block_size must be a positive odd number")
        for name in ("refine_window_px", "refine_window_rows"):
            value = getattr(self, name)
            if value < 0 or (value and value % 2 == 0):
                raise ValueError(f"SgmOptions.{name} must be 0 or a positive odd number")
        if not (0 <= self.p1 < self.p2):
            raise ValueError("SgmOptions needs 0 <= p1 < p2")


@dataclass(frozen=True)
class SadOptions:
    """The reference's block matcher (sec. 7.4): 7x7 SAD, winner-take-all, parabola sub-pixel fit.

    left_right_check : bool, also match right-to-left and drop disparities that disagree by more than
        ``max_lr_difference_px`` (not in the reference; doubles the time).
    """

    num_disparities: int = 64
    min_disparity: int = 0
    block_size: int = 7
    left_right_check: bool = True
    max_lr_difference_px: float = 1.0

    def __post_init__(self) -> None:
        if self.num_disparities < 2:
            raise ValueError("SadOptions.num_disparities must be at least 2")
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise ValueError("SadOptions.block_size must be a positive odd number")


@dataclass(frozen=True)
class Disparity:
    """A disparity map and its per-pixel quality.

    disparity : (H, W) float32 columns, ``x_right = x_left - disparity``; NaN = no match.
    cost : (H, W) float32, mean absolute grey-level residual over the window at the match (0-255 scale);
        NaN where no match.
    sigma : (H, W) float32 columns, first-order standard deviation of the disparity (from the residual and
        the texture along the row), NaN where unknown.
    """

    disparity: np.ndarray
    cost: np.ndarray
    sigma: np.ndarray


def _check_pair(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    left = np.asarray(left)
    right = np.asarray(right)
    if left.ndim != 2 or right.ndim != 2:
        raise ValueError(f"matching needs two single-channel images, got shapes {left.shape} and {right.shape}")
    if left.shape != right.shape:
        raise ValueError(f"images differ in size: {left.shape} vs {right.shape}")
    if left.dtype != np.uint8 or right.dtype != np.uint8:
        raise ValueError("matching needs uint8 images")
    return left, right


def sgm_disparity(left: np.ndarray, right: np.ndarray, *, options: SgmOptions = SgmOptions()) -> Disparity:
    """Semi-global matching with sub-pixel refinement.

    left, right : (H, W) uint8 rectified pair (see module docstring). Returns :class:`Disparity`.
    """
    left, right = _check_pair(left, right)
    pad = 0
    if options.wrap_rows:
        pad = min(32, left.shape[0])
        left = np.concatenate([left[-pad:], left, left[:pad]])
        right = np.concatenate([right[-pad:], right, right[:pad]])
    nd = int(np.ceil(options.num_disparities / 16.0) * 16)
    area = options.block_size * options.block_size
    sgbm = cv2.StereoSGBM_create(
        minDisparity=options.min_disparity,
        numDisparities=nd,
        blockSize=options.block_size,
        P1=int(round(options.p1 * area)),
        P2=int(round(options.p2 * area)),
        disp12MaxDiff=options.max_lr_difference_px,
        uniquenessRatio=options.uniqueness_ratio,
        speckleWindowSize=options.speckle_window,
        speckleRange=options.speckle_range,  # OpenCV multiplies by 16 itself
        preFilterCap=63,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    raw = sgbm.compute(left, right)
    disparity = raw.astype(np.float32) / 16.0
    disparity[raw <= (options.min_disparity - 1) * 16] = np.nan
    if options.refine_window_px:
        result = refine_subpixel(left, right, disparity, window_px=options.refine_window_px,
                                 window_rows=options.refine_window_rows or options.refine_window_px,
                                 iterations=options.refine_iterations,
                                 max_shift_px=1.0, search_range=(options.min_disparity, options.min_disparity + nd))
    else:
        cost = np.full(disparity.shape, np.nan, np.float32)
        result = Disparity(disparity, cost, cost.copy())
    if pad:
        result = Disparity(*(a[pad:-pad] for a in (result.disparity, result.cost, result.sigma)))
    return result


def refine_subpixel(
    left: np.ndarray,
    right: np.ndarray,
    disparity: np.ndarray,
    *,
    window_px: int = 7,
    window_rows: int | None = None,
    iterations: int = 3,
    max_shift_px: float = 1.0,
    search_range: tuple[float, float] | None = None,
) -> Disparity:
    """Refine disparities by 1-D Lucas-Kanade over a window, and estimate their uncertainty.

    Each pixel's window in ``left`` is compared with ``right`` shifted by the current disparity ``d``
    (``W(x) = right(x - d)``), after removing each window's mean and matching its contrast
    (``a = std(left) / std(W)``), which makes the step insensitive to the brightness change of a scope
    that carries its own light (a surface brightens as the scope approaches). The Gauss-Newton step
    for the zero-mean residual ``e = (L - mean L) - a (W - mean W)`` with Jacobian ``J = a (g - mean g)``,
    ``g`` the row gradient of ``W``, is ``delta = -sum(J e) / sum(J^2)``; both sums are exact per window,
    from box filters of products.

    left, right : (H, W) uint8 or float; disparity : (H, W) float columns, NaN = none.
    window_px, window_rows : window width and height (odd; height defaults to the width).
    max_shift_px : a refinement moving a disparity farther than this from its start is rejected (NaN):
        the window then has no reliable minimum nearby.
    search_range : (lo, hi) columns; results outside are rejected.
    Returns :class:`Disparity` with ``cost`` the RMS zero-mean residual in grey levels,
    ``std(L) sqrt(2 (1 - zncc))``, and ``sigma = sqrt(mean(e^2) / sum(J^2))`` (columns), the Cramér-Rao
    bound of the shift for white noise.
    """
    left_f = np.ascontiguousarray(left, dtype=np.float32)
    right_f = np.ascontiguousarray(right, dtype=np.float32)
    start = np.ascontiguousarray(disparity, dtype=np.float32)
    known = np.isfinite(start)
    d = np.where(known, start, 0.0).astype(np.float32)
    grad = cv2.Sobel(right_f, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)  # central difference, grey levels / column
    window_rows = window_rows or window_px
    # Every pixel's window in ``right`` is warped by that pixel's disparity, then the products' window means
    # give the step (refine_kernels.py: one compiled pass per warp and one per set of means, on blocks of
    # rows shared by the cores; the same bits as cv2.remap + cv2.boxFilter + NumPy, at ~1/3 of their CPU).
    weights = _lanczos_weights()
    warped, warped_grad = np.empty_like(left_f), np.empty_like(left_f)
    lowest, highest = (-np.inf, np.inf) if search_range is None else (search_range[0] - 0.5, search_range[1] - 0.5)
    height = left_f.shape[0]
    mu_l, var_l = np.empty_like(left_f), np.empty_like(left_f)
    run_by_row_blocks(_kernels.left_statistics, height, (left_f, window_px, window_rows), (mu_l, var_l))
    window = (left_f, warped, warped_grad, mu_l, var_l)
    for _ in range(max(iterations, 1)):
        run_by_row_blocks(_kernels.warp_rows, height, (right_f, grad, d, weights), (warped, warped_grad))
        stepped = np.empty_like(d)
        run_by_row_blocks(_kernels.step_pass, height, (*window, d, window_px, window_rows), (stepped,))
        d = stepped
    run_by_row_blocks(_kernels.warp_rows, height, (right_f, grad, d, weights), (warped, warped_grad))
    out = Disparity(np.empty_like(d), np.empty_like(d), np.empty_like(d))
    run_by_row_blocks(_kernels.fit_pass, height,
                      (*window, d, start, window_px, window_rows, np.float32(max_shift_px), np.float32(lowest),
                       np.float32(highest), np.float32(window_px * window_rows)),
                      (out.disparity, out.cost, out.sigma))
    return out


def _lanczos_weights() -> np.ndarray:
    """(32, 8) float32: the weights cv2.remap's INTER_LANCZOS4 gives the 8 pixels around a position at
    each 1/32-pixel phase (OpenCV's INTER_TAB_SIZE, which refine_kernels.warp_rows assumes), read from
    OpenCV itself by resampling an impulse, so that the compiled warp is OpenCV's to the bit."""
    steps, taps = 32, 8
    impulse = np.zeros((1, 4 * taps), np.float32)
    centre = 2 * taps
    impulse[0, centre] = 1.0
    # the output at position p = centre + (taps / 2 - 1) - k + phase / steps weighs the impulse with tap k
    positions = centre + (taps // 2 - 1) - np.arange(taps)[None, :] + np.arange(steps)[:, None] / steps
    weights = cv2.remap(impulse, positions.astype(np.float32).reshape(1, -1), np.zeros((1, steps * taps), np.float32),
                        _INTERP, borderMode=cv2.BORDER_REPLICATE)
    return np.ascontiguousarray(weights.reshape(steps, taps))


def sad_disparity(left: np.ndarray, right: np.ndarray, *, options: SadOptions = SadOptions()) -> Disparity:
    """The reference's 7x7 SAD block matcher with a parabola sub-pixel fit, vectorised over pixels.

    For each candidate disparity the absolute difference image is box-filtered once; a running minimum
    keeps the best disparity and the costs one column either side for the parabola
    ``d* = d + (c- - c+) / (2 (c- - 2 c0 + c+))`` [136]. Memory is O(H W), not O(H W D).

    left, right : (H, W) uint8 rectified pair. Returns :class:`Disparity` (``sigma`` is NaN: SAD has
    no uncertainty model; ``cost`` is the mean absolute difference at the minimum).
    """
    left, right = _check_pair(left, right)
    forward = _sad_wta(left.astype(np.float32), right.astype(np.float32), options)
    if options.left_right_check:
        # Right-to-left: flip both images horizontally so the same code applies.
        backward = _sad_wta(right[:, ::-1].astype(np.float32), left[:, ::-1].astype(np.float32), options)
        back = backward.disparity[:, ::-1]
        h, w = left.shape
        xs = np.arange(w)[None, :] - np.nan_to_num(forward.disparity, nan=0.0)
        xi = np.clip(np.round(xs).astype(int), 0, w - 1)
        other = back[np.arange(h)[:, None], xi]
        bad = ~(np.abs(other - forward.disparity) <= options.max_lr_difference_px)
        forward = Disparity(np.where(bad, np.nan, forward.disparity).astype(np.float32),
                            np.where(bad, np.nan, forward.cost).astype(np.float32), forward.sigma)
    return forward


def _sad_wta(left: np.ndarray, right: np.ndarray, options: SadOptions) -> Disparity:
    h, w = left.shape
    ksize = (options.block_size, options.block_size)
    best = np.full((h, w), np.inf, np.float32)
    best_d = np.full((h, w), -1, np.int32)
    c_minus = np.full((h, w), np.inf, np.float32)
    c_plus = np.full((h, w), np.inf, np.float32)
    previous = np.full((h, w), np.inf, np.float32)
    lo = options.min_disparity
    for d in range(lo, lo + options.num_disparities):
        diff = np.full((h, w), 255.0, np.float32)  # no right pixel: worst cost
        if d >= 0:
            diff[:, d:] = np.abs(left[:, d:] - right[:, : w - d])
        else:
            diff[:, : w + d] = np.abs(left[:, : w + d] - right[:, -d:])
        cost = cv2.boxFilter(diff, cv2.CV_32F, ksize, normalize=True, borderType=cv2.BORDER_REFLECT)
        follow = best_d == d - 1
        c_plus[follow] = cost[follow]
        better = cost < best
        best[better] = cost[better]
        best_d[better] = d
        c_minus[better] = previous[better]
        c_plus[better] = np.inf
        previous = cost
    denom = c_minus - 2.0 * best + c_plus
    with np.errstate(invalid="ignore", divide="ignore"):
        offset = np.where(np.isfinite(denom) & (denom > 0), 0.5 * (c_minus - c_plus) / denom, np.nan)
    disparity = (best_d + offset).astype(np.float32)  # NaN at the ends of the range: no parabola
    cost = np.where(np.isfinite(disparity), best, np.nan).astype(np.float32)
    return Disparity(disparity, cost, np.full((h, w), np.nan, np.float32))
