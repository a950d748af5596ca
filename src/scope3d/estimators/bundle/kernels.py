"""Compiled inner loops of the bundle adjuster: a kernel module of :mod:`scope3d.utils.aot` (compiled at
install; numba's JIT, cached on disk, where that could not run).

Everything here works on flat arrays; :mod:`.problem` and :mod:`.solver` own the meaning. The maths of
:func:`residuals_and_jacobians` is that of :func:`scope3d.sensor.camera.project_with_jacobians` (tests check
they agree); it is fused here so that one pass over the observations gives residuals and Jacobians
without (N, 3, 3) temporaries.

Layout shared by all kernels
----------------------------
* Observations are sorted by point; ``point_ptr`` (n+1,) delimits each point's observations.
* The camera side of the parameter vector is a sequence of 6-blocks: the ``m`` pose blocks
  ``(w_x, w_y, w_z, pos_x, pos_y, pos_z)``, then the ``g`` intrinsic blocks ``(fx, fy, cx, cy, k1, k2)``,
  then, when a lens model's later parameters are refined, the ``g`` blocks of those (:mod:`.lens_kernels`).
  ``cam_blocks`` (K, H) gives, per observation, its H blocks: H = 2 (pose, intrinsics) or 3 (and the
  lens's later parameters).
* ``jc`` (K, 2, 6 H): d residual / d (those blocks, in that order); ``jp`` (K, 2, 3): d residual /
  d point parameters.
* The reduced camera matrix S is symmetric and only its upper block triangle (row <= col) is written:
  block-sparse with 6x6 blocks in BSR layout (``indptr``, ``indices``, ``data``) or, for the dense
  solver, a dense matrix (see :func:`assemble_point_range`).
"""
from __future__ import annotations

import numpy as np
from numba import njit

_F2 = "f8[:, ::1]"
_F3 = "f8[:, :, ::1]"
_I1 = "i8[::1]"
_I2 = "i8[:, ::1]"
# Exported at install (scope3d.utils.aot) with the exact argument types the solver passes (all arrays
# C-contiguous): an exported function does not dispatch on types, it converts its arguments to these or
# raises TypeError.
AOT_SIGNATURES = {
    "residuals_and_jacobians": f"void(f8[:, ::1], {_I1}, {_I1}, {_I1}, {_F3}, {_F2}, {_F3}, b1, {_F2}, {_F3}, "
                               f"{_F2}, b1, {_F2}, {_F3}, {_F3})",
    "squared_residuals": f"void({_F2}, {_I1}, {_I1}, {_I1}, {_F3}, {_F2}, {_F2}, {_F2}, b1, f8[::1])",
    "gradient_and_diagonal": f"Tuple((f8[::1], f8[::1], {_F2}, {_F2}))({_F2}, {_F3}, {_F3}, {_I2}, {_I1}, i8, i8)",
    "zero_frozen_columns": f"void({_F3}, {_F3}, {_I2}, {_I1}, b1[::1], b1[:, ::1])",
    "block_structure_keys": f"{_I1}({_I2}, {_I1}, i8)",
    "pair_slots": f"Tuple((i4[::1], {_I1}))({_I2}, {_I1}, {_I1}, {_I1})",
    "term_counts": f"{_I1}({_I2}, {_I1})",
    "add_diagonal": f"void({_I1}, {_I1}, {_F3}, f8[::1])",
    "assemble_point_range": f"b1(i8, i8, i8, {_F2}, {_F3}, {_F3}, {_I2}, {_I1}, {_F2}, f8[::1], b1, i8, f8[::1], "
                            f"{_F3}, {_F2}, i4[::1])",
    "back_substitute": f"{_F2}({_F3}, {_F3}, {_I2}, {_I1}, {_F3}, {_F2}, f8[::1])",
    "jacobian_step_norm2": f"f8({_F3}, {_F3}, {_I2}, {_I1}, f8[::1], {_F2})",
    "scale_rows": f"void({_F2}, {_F3}, {_F3}, f8[::1])",
}

# --- residuals and Jacobians -------------------------------------------------------------------


@njit(cache=True, nogil=True)
def residuals_and_jacobians(
    observed, cam_index, point_index, intr_index, rotations, translations, rot_jac, centre_param,
    points, point_jac, intrinsics, square_pixels, residuals, jc, jp,
):
    """Fill residuals (K, 2) = projected - observed pixels, ``jc`` (K, 2, 12) and ``jp`` (K, 2, 3).

    rotations (m, 3, 3) and translations (m, 3) are the current cam_from_world; rot_jac (m, 3, 3) is
    the SO(3) left Jacobian of each camera's rotation parameter; centre_param selects whether the
    position parameter is the camera centre C (P = R (X - C)) or the translation t (P = R X + t).
    points (n, 3) are world points and point_jac (n, 3, 3) d X / d point parameters.
    """
    k_obs = observed.shape[0]
    for o in range(k_obs):
        c = cam_index[o]
        j = point_index[o]
        q = intr_index[o]
        fx = intrinsics[q, 0]
        fy = fx if square_pixels else intrinsics[q, 1]
        cx = intrinsics[q, 2]
        cy = intrinsics[q, 3]
        k1 = intrinsics[q, 4]
        k2 = intrinsics[q, 5]
        r00 = rotations[c, 0, 0]; r01 = rotations[c, 0, 1]; r02 = rotations[c, 0, 2]
        r10 = rotations[c, 1, 0]; r11 = rotations[c, 1, 1]; r12 = rotations[c, 1, 2]
        r20 = rotations[c, 2, 0]; r21 = rotations[c, 2, 1]; r22 = rotations[c, 2, 2]
        X0 = points[j, 0]; X1 = points[j, 1]; X2 = points[j, 2]
        a0 = r00 * X0 + r01 * X1 + r02 * X2
        a1 = r10 * X0 + r11 * X1 + r12 * X2
        a2 = r20 * X0 + r21 * X1 + r22 * X2
        p0 = a0 + translations[c, 0]
        p1 = a1 + translations[c, 1]
        p2 = a2 + translations[c, 2]
        if centre_param:
            # P = R (X - C): a change of rotation moves R (X - C) = P, not R X.
            a0 = p0; a1 = p1; a2 = p2
        iz = 1.0 / p2
        x = p0 * iz
        y = p1 * iz
        r2 = x * x + y * y
        d = 1.0 + k1 * r2 + k2 * r2 * r2
        residuals[o, 0] = fx * d * x + cx - observed[o, 0]
        residuals[o, 1] = fy * d * y + cy - observed[o, 1]
        dd = k1 + 2.0 * k2 * r2
        jxx = fx * (d + 2.0 * x * x * dd)
        jxy = fx * (2.0 * x * y * dd)
        jyx = fy * (2.0 * x * y * dd)
        jyy = fy * (d + 2.0 * y * y * dd)
        # d pixel / d P (2x3) = j_xy @ [[iz, 0, -x iz], [0, iz, -y iz]]
        e00 = jxx * iz; e01 = jxy * iz; e02 = -(jxx * x + jxy * y) * iz
        e10 = jyx * iz; e11 = jyy * iz; e12 = -(jyx * x + jyy * y) * iz
        # rotation: d P / d w = -[a]x J_l(w)
        # first  m = -[a]x  rows: (0, a2, -a1), (-a2, 0, a0), (a1, -a0, 0)
        # then  (d pixel / d P) @ m
        f00 = -e01 * a2 + e02 * a1; f01 = e00 * a2 - e02 * a0; f02 = -e00 * a1 + e01 * a0
        f10 = -e11 * a2 + e12 * a1; f11 = e10 * a2 - e12 * a0; f12 = -e10 * a1 + e11 * a0
        for k in range(3):
            jc[o, 0, k] = f00 * rot_jac[c, 0, k] + f01 * rot_jac[c, 1, k] + f02 * rot_jac[c, 2, k]
            jc[o, 1, k] = f10 * rot_jac[c, 0, k] + f11 * rot_jac[c, 1, k] + f12 * rot_jac[c, 2, k]
        # d pixel / d X = e @ R
        g00 = e00 * r00 + e01 * r10 + e02 * r20
        g01 = e00 * r01 + e01 * r11 + e02 * r21
        g02 = e00 * r02 + e01 * r12 + e02 * r22
        g10 = e10 * r00 + e11 * r10 + e12 * r20
        g11 = e10 * r01 + e11 * r11 + e12 * r21
        g12 = e10 * r02 + e11 * r12 + e12 * r22
        if centre_param:
            jc[o, 0, 3] = -g00; jc[o, 0, 4] = -g01; jc[o, 0, 5] = -g02
            jc[o, 1, 3] = -g10; jc[o, 1, 4] = -g11; jc[o, 1, 5] = -g12
        else:
            jc[o, 0, 3] = e00; jc[o, 0, 4] = e01; jc[o, 0, 5] = e02
            jc[o, 1, 3] = e10; jc[o, 1, 4] = e11; jc[o, 1, 5] = e12
        # intrinsics (fx, fy, cx, cy, k1, k2); with square pixels fy follows fx.
        if square_pixels:
            jc[o, 0, 6] = d * x; jc[o, 1, 6] = d * y
            jc[o, 0, 7] = 0.0; jc[o, 1, 7] = 0.0
        else:
            jc[o, 0, 6] = d * x; jc[o, 1, 6] = 0.0
            jc[o, 0, 7] = 0.0; jc[o, 1, 7] = d * y
        jc[o, 0, 8] = 1.0; jc[o, 1, 8] = 0.0
        jc[o, 0, 9] = 0.0; jc[o, 1, 9] = 1.0
        jc[o, 0, 10] = fx * x * r2; jc[o, 1, 10] = fy * y * r2
        jc[o, 0, 11] = fx * x * r2 * r2; jc[o, 1, 11] = fy * y * r2 * r2
        for k in range(3):
            jp[o, 0, k] = g00 * point_jac[j, 0, k] + g01 * point_jac[j, 1, k] + g02 * point_jac[j, 2, k]
            jp[o, 1, k] = g10 * point_jac[j, 0, k] + g11 * point_jac[j, 1, k] + g12 * point_jac[j, 2, k]


@njit(cache=True, nogil=True)
def squared_residuals(
    observed, cam_index, point_index, intr_index, rotations, translations, points, intrinsics,
    square_pixels, out,
):
    """out (K,) = |projected - observed|^2 per observation (pixels^2); the cost-only pass."""
    for o in range(observed.shape[0]):
        c = cam_index[o]
        j = point_index[o]
        q = intr_index[o]
        fx = intrinsics[q, 0]
        fy = fx if square_pixels else intrinsics[q, 1]
        p0 = translations[c, 0]
        p1 = translations[c, 1]
        p2 = translations[c, 2]
        for k in range(3):
            p0 += rotations[c, 0, k] * points[j, k]
            p1 += rotations[c, 1, k] * points[j, k]
            p2 += rotations[c, 2, k] * points[j, k]
        x = p0 / p2
        y = p1 / p2
        r2 = x * x + y * y
        d = 1.0 + intrinsics[q, 4] * r2 + intrinsics[q, 5] * r2 * r2
        u = fx * d * x + intrinsics[q, 2] - observed[o, 0]
        v = fy * d * y + intrinsics[q, 3] - observed[o, 1]
        out[o] = u * u + v * v


# --- gradient, diagonal, masking ---------------------------------------------------------------


@njit(cache=True, nogil=True)
def gradient_and_diagonal(residuals, jc, jp, cam_blocks, point_index, n_blocks, n_points):
    """g = J^T r and diag(J^T J), camera side (6 n_blocks,) and points (n, 3)."""
    gc = np.zeros(6 * n_blocks)
    dc = np.zeros(6 * n_blocks)
    gp = np.zeros((n_points, 3))
    dp = np.zeros((n_points, 3))
    for o in range(residuals.shape[0]):
        r0 = residuals[o, 0]
        r1 = residuals[o, 1]
        for h in range(cam_blocks.shape[1]):
            base = 6 * cam_blocks[o, h]
            for k in range(6):
                a = jc[o, 0, 6 * h + k]
                b = jc[o, 1, 6 * h + k]
                gc[base + k] += a * r0 + b * r1
                dc[base + k] += a * a + b * b
        j = point_index[o]
        for k in range(3):
            a = jp[o, 0, k]
            b = jp[o, 1, k]
            gp[j, k] += a * r0 + b * r1
            dp[j, k] += a * a + b * b
    return gc, dc, gp, dp


@njit(cache=True, nogil=True)
def zero_frozen_columns(jc, jp, cam_blocks, point_index, frozen_c, frozen_p):
    """Zero the Jacobian columns of frozen (fixed or active) parameters, in place (eq. 6.12)."""
    for o in range(jc.shape[0]):
        for h in range(cam_blocks.shape[1]):
            base = 6 * cam_blocks[o, h]
            for k in range(6):
                if frozen_c[base + k]:
                    jc[o, 0, 6 * h + k] = 0.0
                    jc[o, 1, 6 * h + k] = 0.0
        j = point_index[o]
        for k in range(3):
            if frozen_p[j, k]:
                jp[o, 0, k] = 0.0
                jp[o, 1, k] = 0.0


# --- reduced camera system (Schur complement, eq. 6.7) ---------------------------------------


@njit(cache=True, nogil=True)
def block_structure_keys(cam_blocks, point_ptr, n_blocks):
    """Keys ``row * n_blocks + col`` (row <= col) of the nonzero 6x6 blocks of the reduced camera
    matrix's upper triangle; it is symmetric, so only the upper triangle is stored."""
    n_points = point_ptr.shape[0] - 1
    total = n_blocks
    max_deg = 0
    for j in range(n_points):
        deg = cam_blocks.shape[1] * (point_ptr[j + 1] - point_ptr[j])
        total += deg * (deg + 1) // 2
        max_deg = max(max_deg, deg)
    keys = np.empty(total, dtype=np.int64)
    for b in range(n_blocks):
        keys[b] = b * n_blocks + b
    pos = n_blocks
    ids = np.empty(max_deg, dtype=np.int64)
    for j in range(n_points):
        count = 0
        for o in range(point_ptr[j], point_ptr[j + 1]):
            for h in range(cam_blocks.shape[1]):
                b = cam_blocks[o, h]
                seen = False
                for t in range(count):
                    if ids[t] == b:
                        seen = True
                        break
                if not seen:
                    ids[count] = b
                    count += 1
        for s in range(count):
            for t in range(count):
                if ids[s] <= ids[t]:
                    keys[pos] = ids[s] * n_blocks + ids[t]
                    pos += 1
    return keys[:pos]


@njit(cache=True, nogil=True)
def _find_block(indptr, indices, row, col):
    lo = indptr[row]
    hi = indptr[row + 1] - 1
    while lo <= hi:
        mid = (lo + hi) >> 1
        v = indices[mid]
        if v == col:
            return mid
        if v < col:
            lo = mid + 1
        else:
            hi = mid - 1
    return -1


@njit(cache=True, nogil=True)
def _inv3(m, out):
    a = m[0, 0]; b = m[0, 1]; c = m[0, 2]
    d = m[1, 0]; e = m[1, 1]; f = m[1, 2]
    g = m[2, 0]; h = m[2, 1]; i = m[2, 2]
    c00 = e * i - f * h
    c01 = c * h - b * i
    c02 = b * f - c * e
    det = a * c00 + d * c01 + g * c02
    if not (abs(det) > 0.0) or not np.isfinite(det):
        return False
    inv = 1.0 / det
    out[0, 0] = c00 * inv; out[0, 1] = c01 * inv; out[0, 2] = c02 * inv
    out[1, 0] = (f * g - d * i) * inv; out[1, 1] = (a * i - c * g) * inv; out[1, 2] = (c * d - a * f) * inv
    out[2, 0] = (d * h - e * g) * inv; out[2, 1] = (b * g - a * h) * inv; out[2, 2] = (a * e - b * d) * inv
    return True


@njit(cache=True, nogil=True, inline="always")
def _shares_last_block(cam_blocks, start, stop):
    """Whether the observations [start, stop) of a point, with three blocks each, share their third (the
    lens's later parameters: one intrinsic group): then :func:`assemble_point_range` adds that block's terms
    per observation, not per pair."""
    if cam_blocks.shape[1] != 3:
        return False
    for o in range(start + 1, stop):
        if cam_blocks[o, 2] != cam_blocks[start, 2]:
            return False
    return True


@njit(cache=True, nogil=True)
def term_counts(cam_blocks, point_ptr):
    """Where each point's 6x6 terms start in the order :func:`assemble_point_range` adds them, (n + 1,) int64.
    A point of ``deg`` observations with H blocks each adds every observation pair's (i <= k) quadrants, less
    the lower quadrants of the diagonal pairs (the upper's transposes): ``H^2 deg (deg + 1) / 2 - deg H (H - 1)
    / 2``; with a shared third block (:func:`_shares_last_block`), the pairs' terms of the first two blocks and
    three terms per observation."""
    n_points = point_ptr.shape[0] - 1
    h_blocks = cam_blocks.shape[1]
    slot_ptr = np.zeros(n_points + 1, dtype=np.int64)
    for j in range(n_points):
        deg = point_ptr[j + 1] - point_ptr[j]
        h = h_blocks
        per_observation = 0
        if _shares_last_block(cam_blocks, point_ptr[j], point_ptr[j + 1]):
            h = 2
            per_observation = 3
        slot_ptr[j + 1] = slot_ptr[j] + h * h * deg * (deg + 1) // 2 - deg * h * (h - 1) // 2 + per_observation * deg
    return slot_ptr


@njit(cache=True, nogil=True)
def pair_slots(cam_blocks, point_ptr, indptr, indices):
    """Slot in ``data`` of every (observation pair, quadrant) term of S, in the order
    :func:`assemble_point_range` visits them (int32, one binary search each, done once per solve),
    and where each point's terms start, (n + 1,) int64 (:func:`term_counts`)."""
    n_points = point_ptr.shape[0] - 1
    h_blocks = cam_blocks.shape[1]
    slot_ptr = term_counts(cam_blocks, point_ptr)
    out = np.empty(slot_ptr[n_points], dtype=np.int32)
    pos = 0
    for j in range(n_points):
        start = point_ptr[j]
        stop = point_ptr[j + 1]
        shared = _shares_last_block(cam_blocks, start, stop)
        h_pair = 2 if shared else h_blocks
        for oi in range(start, stop):
            for ok_ in range(oi, stop):
                for hi in range(h_pair):
                    bi = cam_blocks[oi, hi]
                    for hk in range(h_pair):
                        if oi == ok_ and hk < hi:
                            continue
                        bk = cam_blocks[ok_, hk]
                        if bi <= bk:
                            out[pos] = _find_block(indptr, indices, bi, bk)
                        else:
                            out[pos] = _find_block(indptr, indices, bk, bi)
                        pos += 1
        if shared:
            last = cam_blocks[start, 2]
            for o in range(start, stop):
                for h in range(3):
                    out[pos] = _find_block(indptr, indices, cam_blocks[o, h], last)  # the last block is the largest
                    pos += 1
    return out, slot_ptr


@njit(cache=True, nogil=True)
def add_diagonal(indptr, indices, data, damp_c):
    """Add damp_c (6 n_blocks,) to the diagonal of the diagonal blocks of the BSR ``data``, in place."""
    n_blocks = indptr.shape[0] - 1
    for b in range(n_blocks):
        slot = _find_block(indptr, indices, b, b)
        for s in range(6):
            data[slot, s, s] += damp_c[6 * b + s]


@njit(cache=True, nogil=True)
def assemble_point_range(j_start, j_stop, pos, residuals, jc, jp, cam_blocks, point_ptr, damp_p, out, dense,
                         stride, rhs, v_inv, gp, slots):
    """Add the Schur terms (eq. 6.7 applied to eq. 6.13) of points [j_start, j_stop) to the reduced camera
    matrix ``out`` and right-hand side ``rhs`` (6 n_blocks,); returns False if a point block is singular.

    Per observation i of a point, with ``P_i = Jp_i V^-1`` (2x3), the term of S for observations (i, k)
    is ``Jc_i^T (delta_ik I - P_i Jp_k^T) Jc_k``: a 2x2 middle matrix between the two camera Jacobian
    rows, so each 6x6 quadrant costs a rank-2 update instead of the 3-column product ``W_i V^-1 W_k^T``,
    and the point's own U term rides along on the diagonal pairs. rhs gets ``Jc_i^T (P_i g_p - r_i)``
    (= -g_c + W V^-1 g_p). Columns of fixed parameters are zero in ``jc`` (:func:`zero_frozen_columns`).

    ``out`` (flat float64) holds the upper block triangle (row block <= column block) of S: with
    ``dense`` a row-major matrix of 6 n_blocks columns (``stride = 6 n_blocks``); else 6x6 blocks in BSR
    layout (``stride = 6``), the block of each term at ``slots[pos]`` (:func:`pair_slots`; ``pos`` is
    where the range's terms start, ``slot_ptr[j_start]``). damp_p (n, 3) is added to the point blocks'
    diagonal. Outputs v_inv (n, 3, 3), the inverted damped point blocks, and gp (n, 3), the point
    gradients, both reused by the back-substitution.

    Each 6-entry row of a quadrant is updated through a view with constant indices: numba then drops its
    negative-index checks and the update runs ~1.5x faster than an indexed inner loop.

    A third block shared by all of a point's observations (the lens's later parameters of its one intrinsic
    group, ``e``) is added per observation instead of per pair: summed over k, the terms of observation i's
    block a with it are ``Jc_ia^T (Jc_ie - P_i W_e)``, ``W_e = sum_k Jp_k^T Jc_ke`` (3x6), the same rank-2 form
    (its own diagonal block included, a = e), so that the block costs O(deg) per point, not O(deg^2).

    Threads run it on disjoint point ranges with their own ``out`` and ``rhs`` (the GIL is released), and
    add the results up: the parallel Schur assembly without numba's parfors, which cost three quarters of
    the kernels' compile time.
    """
    max_deg = 1
    for j in range(j_start, j_stop):
        max_deg = max(max_deg, point_ptr[j + 1] - point_ptr[j])
    pv = np.empty((max_deg, 2, 3))
    h_blocks = cam_blocks.shape[1]
    tk = np.empty((2, jc.shape[2]))
    we = np.empty((3, 6))
    mi = np.empty((2, 6))
    v = np.empty((3, 3))
    vi = np.empty((3, 3))
    ok = True
    for j in range(j_start, j_stop):
        start = point_ptr[j]
        deg = point_ptr[j + 1] - start
        shared = _shares_last_block(cam_blocks, start, start + deg)
        h_pair = 2 if shared else h_blocks
        width = 6 * h_pair
        v[:] = 0.0
        g0 = 0.0; g1 = 0.0; g2 = 0.0
        for i in range(deg):
            o = start + i
            r0 = residuals[o, 0]
            r1 = residuals[o, 1]
            for s in range(3):
                for t in range(3):
                    v[s, t] += jp[o, 0, s] * jp[o, 0, t] + jp[o, 1, s] * jp[o, 1, t]
            g0 += jp[o, 0, 0] * r0 + jp[o, 1, 0] * r1
            g1 += jp[o, 0, 1] * r0 + jp[o, 1, 1] * r1
            g2 += jp[o, 0, 2] * r0 + jp[o, 1, 2] * r1
        for s in range(3):
            v[s, s] += damp_p[j, s]
        gp[j, 0] = g0; gp[j, 1] = g1; gp[j, 2] = g2
        if not _inv3(v, vi):
            ok = False
            vi[:] = 0.0
        v_inv[j] = vi
        for i in range(deg):
            o = start + i
            for a in range(2):
                for t in range(3):
                    pv[i, a, t] = jp[o, a, 0] * vi[0, t] + jp[o, a, 1] * vi[1, t] + jp[o, a, 2] * vi[2, t]
            e0 = pv[i, 0, 0] * g0 + pv[i, 0, 1] * g1 + pv[i, 0, 2] * g2 - residuals[o, 0]
            e1 = pv[i, 1, 0] * g0 + pv[i, 1, 1] * g1 + pv[i, 1, 2] * g2 - residuals[o, 1]
            for h in range(h_blocks):
                row0 = 6 * cam_blocks[o, h]
                for s in range(6):
                    rhs[row0 + s] += jc[o, 0, 6 * h + s] * e0 + jc[o, 1, 6 * h + s] * e1
        for i in range(deg):
            oi = start + i
            for k in range(i, deg):
                ok_ = start + k
                # the middle matrix, negated: P_i Jp_k^T - delta_ik I
                m00 = pv[i, 0, 0] * jp[ok_, 0, 0] + pv[i, 0, 1] * jp[ok_, 0, 1] + pv[i, 0, 2] * jp[ok_, 0, 2]
                m01 = pv[i, 0, 0] * jp[ok_, 1, 0] + pv[i, 0, 1] * jp[ok_, 1, 1] + pv[i, 0, 2] * jp[ok_, 1, 2]
                m10 = pv[i, 1, 0] * jp[ok_, 0, 0] + pv[i, 1, 1] * jp[ok_, 0, 1] + pv[i, 1, 2] * jp[ok_, 0, 2]
                m11 = pv[i, 1, 0] * jp[ok_, 1, 0] + pv[i, 1, 1] * jp[ok_, 1, 1] + pv[i, 1, 2] * jp[ok_, 1, 2]
                if i == k:
                    m00 -= 1.0
                    m11 -= 1.0
                # tk = -(middle) Jc_k: the term of S is Jc_i^T tk
                for t in range(width):
                    tk[0, t] = -(m00 * jc[ok_, 0, t] + m01 * jc[ok_, 1, t])
                    tk[1, t] = -(m10 * jc[ok_, 0, t] + m11 * jc[ok_, 1, t])
                for hi in range(h_pair):
                    bi = cam_blocks[oi, hi]
                    ci = 6 * hi
                    for hk in range(h_pair):
                        if i == k and hk < hi:
                            continue  # the lower quadrant of a diagonal term is the upper's transpose
                        bk = cam_blocks[ok_, hk]
                        if dense:
                            lo = min(bi, bk)
                            base = 6 * (lo * stride + bi + bk - lo)
                        else:
                            base = 36 * np.int64(slots[pos])
                            pos += 1
                        ck = 6 * hk
                        t0 = tk[0, ck]; t1 = tk[0, ck + 1]; t2 = tk[0, ck + 2]
                        t3 = tk[0, ck + 3]; t4 = tk[0, ck + 4]; t5 = tk[0, ck + 5]
                        u0 = tk[1, ck]; u1 = tk[1, ck + 1]; u2 = tk[1, ck + 2]
                        u3 = tk[1, ck + 3]; u4 = tk[1, ck + 4]; u5 = tk[1, ck + 5]
                        if bi < bk or (bi == bk and i == k):
                            for s in range(6):
                                a0 = jc[oi, 0, ci + s]; a1 = jc[oi, 1, ci + s]
                                if a0 == 0.0 and a1 == 0.0:
                                    continue  # a fixed or active column: its row of the term is zero
                                row = out[base + s * stride:]
                                row[0] += a0 * t0 + a1 * u0
                                row[1] += a0 * t1 + a1 * u1
                                row[2] += a0 * t2 + a1 * u2
                                row[3] += a0 * t3 + a1 * u3
                                row[4] += a0 * t4 + a1 * u4
                                row[5] += a0 * t5 + a1 * u5
                        elif bi > bk:
                            # stored transposed: the term's row s is column s of the upper block
                            for s in range(6):
                                a0 = jc[oi, 0, ci + s]; a1 = jc[oi, 1, ci + s]
                                if a0 == 0.0 and a1 == 0.0:
                                    continue
                                col = out[base + s:]
                                col[0] += a0 * t0 + a1 * u0
                                col[stride] += a0 * t1 + a1 * u1
                                col[2 * stride] += a0 * t2 + a1 * u2
                                col[3 * stride] += a0 * t3 + a1 * u3
                                col[4 * stride] += a0 * t4 + a1 * u4
                                col[5 * stride] += a0 * t5 + a1 * u5
                        else:
                            # two observations in one block: add the (k, i) term too
                            for s in range(6):
                                a0 = jc[oi, 0, ci + s]; a1 = jc[oi, 1, ci + s]
                                for t in range(6):
                                    val = a0 * tk[0, ck + t] + a1 * tk[1, ck + t]
                                    out[base + s * stride + t] += val
                                    out[base + t * stride + s] += val
        if shared:
            last = cam_blocks[start, 2]
            we[:] = 0.0
            for i in range(deg):
                o = start + i
                for t in range(3):
                    for c in range(6):
                        we[t, c] += jp[o, 0, t] * jc[o, 0, 12 + c] + jp[o, 1, t] * jc[o, 1, 12 + c]
            for i in range(deg):
                o = start + i
                for a in range(2):
                    for c in range(6):
                        mi[a, c] = jc[o, a, 12 + c] - (pv[i, a, 0] * we[0, c] + pv[i, a, 1] * we[1, c]
                                                       + pv[i, a, 2] * we[2, c])
                t0 = mi[0, 0]; t1 = mi[0, 1]; t2 = mi[0, 2]; t3 = mi[0, 3]; t4 = mi[0, 4]; t5 = mi[0, 5]
                u0 = mi[1, 0]; u1 = mi[1, 1]; u2 = mi[1, 2]; u3 = mi[1, 3]; u4 = mi[1, 4]; u5 = mi[1, 5]
                for h in range(3):
                    # the block (b, last), b <= last: stored as it is, rows of block b
                    if dense:
                        base = 6 * (cam_blocks[o, h] * stride + last)
                    else:
                        base = 36 * np.int64(slots[pos])
                        pos += 1
                    for s in range(6):
                        a0 = jc[o, 0, 6 * h + s]; a1 = jc[o, 1, 6 * h + s]
                        if a0 == 0.0 and a1 == 0.0:
                            continue
                        row = out[base + s * stride:]
                        row[0] += a0 * t0 + a1 * u0
                        row[1] += a0 * t1 + a1 * u1
                        row[2] += a0 * t2 + a1 * u2
                        row[3] += a0 * t3 + a1 * u3
                        row[4] += a0 * t4 + a1 * u4
                        row[5] += a0 * t5 + a1 * u5
    return ok


@njit(cache=True, nogil=True)
def back_substitute(jc, jp, cam_blocks, point_ptr, v_inv, gp, delta_c):
    """Point steps dp_j = V_j^-1 (-g_p - W_j^T dc) of eq. 6.7; returns (n, 3)."""
    n_points = point_ptr.shape[0] - 1
    out = np.empty((n_points, 3))
    for j in range(n_points):
        b0 = -gp[j, 0]; b1 = -gp[j, 1]; b2 = -gp[j, 2]
        for o in range(point_ptr[j], point_ptr[j + 1]):
            # (J_c dc) for this observation, then J_p^T of it
            u0 = 0.0
            u1 = 0.0
            for h in range(cam_blocks.shape[1]):
                base = 6 * cam_blocks[o, h]
                for k in range(6):
                    dv = delta_c[base + k]
                    u0 += jc[o, 0, 6 * h + k] * dv
                    u1 += jc[o, 1, 6 * h + k] * dv
            b0 -= jp[o, 0, 0] * u0 + jp[o, 1, 0] * u1
            b1 -= jp[o, 0, 1] * u0 + jp[o, 1, 1] * u1
            b2 -= jp[o, 0, 2] * u0 + jp[o, 1, 2] * u1
        for s in range(3):
            out[j, s] = v_inv[j, s, 0] * b0 + v_inv[j, s, 1] * b1 + v_inv[j, s, 2] * b2
    return out


@njit(cache=True, nogil=True)
def jacobian_step_norm2(jc, jp, cam_blocks, point_index, delta_c, delta_p):
    """|J delta|^2, the quadratic term of the model decrease (eq. 6.3 with H = J^T J)."""
    total = 0.0
    for o in range(jc.shape[0]):
        j = point_index[o]
        u0 = 0.0
        u1 = 0.0
        for h in range(cam_blocks.shape[1]):
            base = 6 * cam_blocks[o, h]
            for k in range(6):
                dv = delta_c[base + k]
                u0 += jc[o, 0, 6 * h + k] * dv
                u1 += jc[o, 1, 6 * h + k] * dv
        for k in range(3):
            u0 += jp[o, 0, k] * delta_p[j, k]
            u1 += jp[o, 1, k] * delta_p[j, k]
        total += u0 * u0 + u1 * u1
    return total


@njit(cache=True, nogil=True)
def scale_rows(residuals, jc, jp, weights):
    """Multiply each observation's residual and Jacobian rows by its weight (robust loss, IRLS)."""
    for o in range(residuals.shape[0]):
        wo = weights[o]
        if wo == 1.0:
            continue
        for r in range(2):
            residuals[o, r] *= wo
            for k in range(jc.shape[2]):
                jc[o, r, k] *= wo
            for k in range(3):
                jp[o, r, k] *= wo
