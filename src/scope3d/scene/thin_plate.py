"""The smoothing thin-plate spline in the plane: the height field of :mod:`scope3d.scene.surface`.

``h(x) = sum_i w_i phi(|x - c_i|) + a_0 + a_1 x + a_2 y`` with ``phi(r) = r² log r``, the weights and the
affine part solving ``[[K + smoothing I, P], [P^T, 0]] [w; a] = [h; 0]`` (``K_ij = phi(|c_i - c_j|)``,
``P`` the affine monomials of the centres): the same spline as
``scipy.interpolate.RBFInterpolator(kernel="thin_plate_spline", smoothing=...)``, whose weights scipy keeps
private. Kept here because the map evaluates the spline at every vertex of its grid (10^5 - 10^6 of them,
against ~2,500 centres), which needs the weights: :meth:`ThinPlateSpline.__call__` sums every centre's term
exactly (``phi(r) = ½ r² log r²`` in blocks of points, one logarithm per point and centre; the work is
points x centres, no faster than scipy's), :meth:`ThinPlateSpline.tiled` sums only the near centres exactly
and interpolates the far ones' smooth sum (4-5x less work on a map's grid, within a fraction of a
micrometre). Far centres cannot simply be dropped: ``r² log r`` grows with the distance, and only the
weights' moment conditions make their sum small.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from scipy.interpolate import RectBivariateSpline

#: Vertices evaluated at once: a (rows x centres) float64 block, 5 MB with 2,500 centres (stays in cache).
_BLOCK_ROWS = 256


@dataclass(frozen=True)
class ThinPlateSpline:
    """A fitted smoothing thin-plate spline in the plane.

    centres : (M, 2) mm, shifted by ``shift``; weights : (M,) kernel weights; affine : (3,) coefficients of
    1, x and y in the scaled coordinates ``(x - shift) / scale``; shift, scale : (2,) mm.
    """

    centres: np.ndarray
    weights: np.ndarray
    affine: np.ndarray
    shift: np.ndarray
    scale: np.ndarray

    @classmethod
    def fit(cls, centres: np.ndarray, values: np.ndarray, smoothing: float = 0.0) -> "ThinPlateSpline":
        """Solve for the spline through ``values`` (M,) at ``centres`` (M, 2) mm, ``smoothing`` >= 0 added to
        the kernel matrix's diagonal (scipy's ``smoothing``). Centres are shifted to their box's middle and
        the affine part uses coordinates scaled to [-1, 1], as scipy does, for the system's conditioning."""
        c = np.asarray(centres, float)
        h = np.asarray(values, float)
        if c.ndim != 2 or c.shape[1] != 2 or h.shape != (len(c),):
            raise ValueError(f"centres must be (M, 2) and values (M,), got {c.shape} and {h.shape}")
        if len(c) < 3 or smoothing < 0:
            raise ValueError(f"need at least 3 centres and smoothing >= 0, got {len(c)} and {smoothing}")
        lo, hi = c.min(axis=0), c.max(axis=0)
        shift = 0.5 * (lo + hi)
        scale = 0.5 * (hi - lo)
        scale[scale == 0] = 1.0
        c = c - shift
        m = len(c)
        lhs = np.zeros((m + 3, m + 3))
        lhs[:m, :m] = _kernel(c, c)
        lhs[np.arange(m), np.arange(m)] += smoothing
        poly = np.column_stack([np.ones(m), c / scale])
        lhs[:m, m:] = poly
        lhs[m:, :m] = poly.T
        rhs = np.r_[h, np.zeros(3)]
        # symmetric indefinite (a saddle-point system): LDL^T
        coef = scipy.linalg.solve(lhs, rhs, assume_a="sym", check_finite=False)
        return cls(c, coef[:m], coef[m:], shift, scale)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Heights (N,) at ``points`` (N, 2) mm, every centre's term summed exactly."""
        x = np.asarray(points, float) - self.shift
        return self._affine(x) + _kernel_sum(x, self.centres, self.weights)

    def tiled(self, points: np.ndarray, *, tile_mm: float = 12.8, margin_mm: float = 6.4,
              lattice_mm: float = 0.8) -> np.ndarray:
        """Heights (N,) at ``points`` (N, 2) mm, for many points: per square tile of ``tile_mm``, the
        centres within ``margin_mm`` of the tile's points summed exactly at every point, the far centres'
        sum evaluated exactly on a ``lattice_mm`` lattice over the tile and interpolated bicubically.

        Why that is accurate: the far sum ``f = sum_far w_i phi(|x - c_i|)`` has no centre within
        ``margin_mm`` of the tile, where the k-th derivatives of ``phi`` fall as r^(2-k) (up to log r):
        an interpolating cubic spline's error is of order lattice^4 times f's fourth derivatives, at most
        ``lattice^4 sum|w_i| / margin^2`` (a loose bound: the weights' moment conditions cancel most of
        the far sum and its derivatives). Measured against :meth:`__call__` (tests/test_thin_plate.py,
        docs/performance.md): below a micrometre at the defaults. Cost per tile: its points times its near
        centres plus its lattice nodes times the far centres, instead of points times all centres."""
        x = np.asarray(points, float) - self.shift
        out = self._affine(x)
        if len(x) == 0:
            return out
        key = np.floor((x - x.min(axis=0)) / tile_mm).astype(np.int64)
        _, tile = np.unique(key, axis=0, return_inverse=True)
        tile = tile.ravel()
        order = np.argsort(tile, kind="stable")
        bounds = np.r_[0, np.cumsum(np.bincount(tile))]
        for lo, hi in zip(bounds[:-1], bounds[1:]):  # per-tile loop
            sel = order[lo:hi]
            p = x[sel]
            box_lo, box_hi = p.min(axis=0), p.max(axis=0)
            gap = np.maximum(np.maximum(box_lo - self.centres, self.centres - box_hi), 0.0)
            near = np.hypot(gap[:, 0], gap[:, 1]) <= margin_mm
            value = _kernel_sum(p, self.centres[near], self.weights[near])
            if not near.all():
                # the lattice covers the tile's box with one node to spare on each side (a bicubic needs
                # four nodes per axis, also for a tile that is a single row of points)
                cells = np.maximum(np.ceil((box_hi - box_lo) / lattice_mm), 1).astype(int)
                gs = box_lo[0] + lattice_mm * np.arange(-1, cells[0] + 2)
                gt = box_lo[1] + lattice_mm * np.arange(-1, cells[1] + 2)
                nodes = np.stack(np.meshgrid(gs, gt, indexing="ij"), axis=-1).reshape(-1, 2)
                far = _kernel_sum(nodes, self.centres[~near], self.weights[~near]).reshape(len(gs), len(gt))
                value += RectBivariateSpline(gs, gt, far, kx=3, ky=3, s=0).ev(p[:, 0], p[:, 1])
            out[sel] += value
        return out

    def _affine(self, x: np.ndarray) -> np.ndarray:
        return np.column_stack([np.ones(len(x)), x / self.scale]) @ self.affine


def _kernel_sum(x: np.ndarray, centres: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(N,) ``sum_i weights_i phi(|x - centres_i|)`` at the points x (N, 2), in blocks of rows."""
    out = np.zeros(len(x))
    if len(centres):
        for lo in range(0, len(x), _BLOCK_ROWS):
            out[lo:lo + _BLOCK_ROWS] = _kernel(x[lo:lo + _BLOCK_ROWS], centres) @ weights
    return out


def _kernel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) matrix of ``phi(r) = r² log r = ½ r² log r²`` between the points (·, 2) mm."""
    r2 = np.subtract.outer(a[:, 0], b[:, 0])
    r2 *= r2
    dy = np.subtract.outer(a[:, 1], b[:, 1])
    dy *= dy
    r2 += dy
    # phi(0) = 0: r² log r² -> 0; a floor far below any real squared distance gives ~1e-297 instead of NaN
    np.maximum(r2, 1e-300, out=r2)
    dy = np.log(r2, out=dy)
    r2 *= dy
    r2 *= 0.5
    return r2
