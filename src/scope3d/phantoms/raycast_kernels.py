"""Compiled per-ray maths of the ray caster (:class:`scope3d.phantoms.raycast.RayCaster`): a kernel module of
:mod:`scope3d.utils.aot` (compiled at install; numba's JIT where that could not run). It imports only numpy
and numba (setup.py compiles it without importing scope3d).
"""
from __future__ import annotations

import numpy as np
from numba import njit

# Exported at install with the exact argument types RayCaster.cast passes (C-contiguous float64 / int64)
AOT_SIGNATURES = {
    "embree_rays": "void(f8[:, ::1], f8[:, ::1], f8[::1], f8, f4[:, ::1], f4[:, ::1])",
    "refine_hits": "void(f8[:, ::1], f8[:, ::1], i8[::1], i8[::1], f8[:, :, ::1], f8[:, :, ::1], f8[:, ::1], b1, "
                   "f8[::1], i8[::1], f8[:, ::1], f8[:, ::1], f8[:, ::1])",
}


@njit(cache=True, nogil=True)
def refine_hits(origins, directions, ray_idx, tri_idx, v0_e1_e2, face_vertex_normals, face_normals,
                vertex_normals, distance, triangle, barycentric, points, normals):
    """The hits of rays ``ray_idx`` on faces ``tri_idx`` (Embree's answer) in double precision.

    origins, directions (N, 3) mm and unit; v0_e1_e2 (F, 3, 3) each face's first vertex and two edges;
    face_vertex_normals (F, 3, 3) its vertex normals (used when ``vertex_normals``), face_normals (F, 3)
    unit. Fills, for every ray (outputs (N,) / (N, 3), filled with NaN / -1 by the caller): Möller–Trumbore
    distance along the ray, face, barycentric weights, point ``origin + distance * direction`` (every ray:
    NaN where it missed), and the unit interpolated normal. A face whose determinant vanishes or whose
    distance is not positive is no hit. The arithmetic is NumPy's of the same formulas, term by term (the
    renderer's images stay the same bits).
    """
    for h in range(ray_idx.shape[0]):
        r, f = ray_idx[h], tri_idx[h]
        dx, dy, dz = directions[r, 0], directions[r, 1], directions[r, 2]
        e1x, e1y, e1z = v0_e1_e2[f, 1, 0], v0_e1_e2[f, 1, 1], v0_e1_e2[f, 1, 2]
        e2x, e2y, e2z = v0_e1_e2[f, 2, 0], v0_e1_e2[f, 2, 1], v0_e1_e2[f, 2, 2]
        px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
        det = e1x * px + e1y * py + e1z * pz
        if not abs(det) >= 1e-300:
            continue
        inv = 1.0 / det
        sx, sy, sz = origins[r, 0] - v0_e1_e2[f, 0, 0], origins[r, 1] - v0_e1_e2[f, 0, 1], origins[r, 2] - v0_e1_e2[f, 0, 2]
        b1 = (sx * px + sy * py + sz * pz) * inv
        qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
        b2 = (dx * qx + dy * qy + dz * qz) * inv
        t = (e2x * qx + e2y * qy + e2z * qz) * inv
        if not (np.isfinite(t) and t > 0):
            continue
        distance[r] = t
        triangle[r] = f
        b0 = 1.0 - b1 - b2
        barycentric[r, 0], barycentric[r, 1], barycentric[r, 2] = b0, b1, b2
        if vertex_normals:
            nx = b0 * face_vertex_normals[f, 0, 0] + b1 * face_vertex_normals[f, 1, 0] + b2 * face_vertex_normals[f, 2, 0]
            ny = b0 * face_vertex_normals[f, 0, 1] + b1 * face_vertex_normals[f, 1, 1] + b2 * face_vertex_normals[f, 2, 1]
            nz = b0 * face_vertex_normals[f, 0, 2] + b1 * face_vertex_normals[f, 1, 2] + b2 * face_vertex_normals[f, 2, 2]
        else:
            nx, ny, nz = face_normals[f, 0], face_normals[f, 1], face_normals[f, 2]
        norm = max(np.sqrt(nx * nx + ny * ny + nz * nz), 1e-300)
        normals[r, 0], normals[r, 1], normals[r, 2] = nx / norm, ny / norm, nz / norm
    for r in range(origins.shape[0]):
        for c in range(3):
            points[r, c] = origins[r, c] + distance[r] * directions[r, c]


@njit(cache=True, nogil=True)
def embree_rays(origins, directions, shift, scale, origins32, directions32):
    """The rays (N, 3) float64 as Embree's scene takes them, in one pass: ``origins32 = float32((origins -
    shift) * scale)`` (trimesh's scaled copy of the mesh: the same operations as its wrapper, so the same
    bits) and ``directions32 = float32(directions)``."""
    for r in range(origins.shape[0]):
        for c in range(3):
            origins32[r, c] = np.float32((origins[r, c] - shift[c]) * scale)
            directions32[r, c] = np.float32(directions[r, c])
