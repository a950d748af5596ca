"""Triangles of a vertex grid: two per cell, the one copy behind every grid mesh (phantom surfaces of
revolution, fitted height fields, depth images)."""
from __future__ import annotations

import numpy as np


def grid_faces(
    n_rows: int,
    n_cols: int,
    *,
    wrap: bool = False,
    anti_diagonal: bool = False,
    clockwise: bool = False,
    keep: np.ndarray | tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Two triangles per cell of a row-major grid of ``n_rows`` x ``n_cols`` vertices.

    Vertex ``(r, c)`` has index ``r * n_cols + c``. A cell's corners are ``00 = (r, c)``, ``01 = (r, c + 1)``,
    ``10 = (r + 1, c)``, ``11 = (r + 1, c + 1)``; it is split along ``00-11`` (default) or, with
    ``anti_diagonal``, along ``01-10``. Triangles wind counter-clockwise in the (column, row) plane, i.e.
    their normals point along column x row: ``(00, 01, 11), (00, 11, 10)`` or ``(00, 01, 10), (01, 11, 10)``;
    ``clockwise`` reverses them to ``(a, c, b)``. ``wrap`` joins the last column to the first (a closed
    ring: ``n_cols`` cells per row instead of ``n_cols - 1``).
    keep : optional (n_rows - 1, cells per row) bool, the cells to triangulate, or a pair of such masks,
        one for each cell's first triangle and one for its second.
    Returns (F, 3) int64: every kept cell's first triangle (row-major), then every kept second triangle.
    """
    cols = n_cols if wrap else n_cols - 1
    r, c = np.meshgrid(np.arange(max(n_rows - 1, 0)), np.arange(max(cols, 0)), indexing="ij")
    c1 = (c + 1) % n_cols if wrap else c + 1
    v00, v01 = r * n_cols + c, r * n_cols + c1
    v10, v11 = (r + 1) * n_cols + c, (r + 1) * n_cols + c1
    first, second = ((v00, v01, v10), (v01, v11, v10)) if anti_diagonal else ((v00, v01, v11), (v00, v11, v10))
    if clockwise:
        first, second = (first[0], first[2], first[1]), (second[0], second[2], second[1])
    keep_first, keep_second = keep if isinstance(keep, tuple) else (keep, keep)
    out = []
    for tri, sel in ((first, keep_first), (second, keep_second)):
        f = np.stack(tri, axis=-1).reshape(-1, 3)
        out.append(f if sel is None else f[np.asarray(sel, bool).reshape(-1)])
    return np.concatenate(out).astype(np.int64)
