"""Compiled descriptor distances of candidate pairs (:func:`scope3d.feature.matching.pair_squared_distances`):
a kernel module of :mod:`scope3d.utils.aot` (compiled at install; numba's JIT where that could not run).
It imports only numpy and numba (setup.py compiles it without importing scope3d).
"""
from __future__ import annotations

import numpy as np
from numba import njit

# Exported at install with the exact argument types pair_squared_distances passes (C-contiguous)
AOT_SIGNATURES = {
    "candidate_squared_distances": "void(f4[:, ::1], f4[:, ::1], i8[::1], i8[::1], f4[::1])",
    "best_two_per_query": "Tuple((i8[::1], f4[::1], f4[::1]))(i8[::1], i8[::1], f4[::1], i8)",
}


@njit(cache=True, nogil=True)
def candidate_squared_distances(desc_a, desc_b, a, b, out):
    """``out[k] = |desc_a[a[k]] - desc_b[b[k]]|^2`` for every candidate pair k: desc_a (Na, D), desc_b
    (Nb, D) float32, a, b (C,) int64, out (C,) float32."""
    # Reads the two descriptor rows in place: gathering them first (desc[a], desc[b]) moved
    # 2 x 512 bytes per candidate through memory and cost 10x the arithmetic.
    for k in range(a.shape[0]):
        ra, rb = a[k], b[k]
        acc = np.float32(0.0)
        for c in range(desc_a.shape[1]):
            d = desc_a[ra, c] - desc_b[rb, c]
            acc += d * d
        out[k] = acc


@njit(cache=True, nogil=True)
def best_two_per_query(query, candidate, d2, n_queries):
    """For candidate pairs ``(query[k], candidate[k])`` at squared distances ``d2[k]`` (C,) in any order:
    per query q < n_queries, its best candidate (least ``(d2, candidate)``: ties go to the lower index;
    -1 without any), that best ``d2`` and the second least ``d2`` of its pairs (inf with fewer than two).
    One pass, where sorting the pairs by (query, d2, candidate) cost ~20x more."""
    best = np.full(n_queries, -1, np.int64)
    best_d2 = np.full(n_queries, np.inf, np.float32)
    second_d2 = np.full(n_queries, np.inf, np.float32)
    for k in range(query.shape[0]):
        q, c, d = query[k], candidate[k], d2[k]
        if best[q] < 0 or d < best_d2[q] or (d == best_d2[q] and c < best[q]):
            second_d2[q] = best_d2[q]
            best[q], best_d2[q] = c, d
        elif d < second_d2[q]:
            second_d2[q] = d
    return best, best_d2, second_d2
