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
  ``(w_x, w_y, w_z, pos_x, pos_y, pos_z)`` then the ``g`` intrinsic blocks ``(fx, fy, cx, cy, k1, k2)``.
  ``cam_blocks`` (K, 2) gives, per observation, its pose block and its intrinsic block.
* ``jc`` (K, 2, 12): d residual / d (pose block, intrinsic block); ``jp`` (K, 2, 3): d residual /
  d point parameters.
* The reduced camera matrix is block-sparse with 6x6 blocks in BSR layout (``indptr``, ``indices``,
  ``data``); S is symmetric and only its upper block triangle (row <= col) is stored.
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
    "assemble_reduced_system": f"b1({_F2}, {_F3}, {_F3}, {_I2}, {_I1}, f8[::1], {_F2}, {_I1}, {_I1}, {_F3}, "
                               f"f8[::1], {_F3}, {_F2}, {_I1}, i4[::1])",
    "add_diagonal": f"void({_I1}, {_I1}, {_F3}, f8[::1])",
    "assemble_point_range": f"b1(i8, i8, i8, {_F2}, {_F3}, {_F3}, {_I2}, {_I1}, {_F2}, {_F3}, f8[::1], {_F3}, "
                            f"{_F2}, {_I1}, i4[::1])",
    "back_substitute": f"{_F2}({_F3}, {_F3}, {_I2}, {_I1}, {_F3}, {_F2}, f8[::1])",
    "jacobian_step_norm2": f"f8({_F3}, {_F3}, {_I2}, {_I1}, f8[::1], {_F2})",
    "bsr_to_dense": f"{_F2}({_I1}, {_I1}, {_F3})",
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
        for h in range(2):
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
        for h in range(2):
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
        deg = 2 * (point_ptr[j + 1] - point_ptr[j])
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
            for h in range(2):
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


@njit(cache=True, nogil=True)
def pair_slots(cam_blocks, point_ptr, indptr, indices):
    """Slot in ``data`` of every (observation pair, quadrant) term of S, in the order
    :func:`assemble_reduced_system` visits them (int32, one binary search each, done once per solve),
    and where each point's terms start, (n + 1,) int64."""
    n_points = point_ptr.shape[0] - 1
    slot_ptr = np.zeros(n_points + 1, dtype=np.int64)
    for j in range(n_points):
        deg = point_ptr[j + 1] - point_ptr[j]
        slot_ptr[j + 1] = slot_ptr[j] + 4 * deg * (deg + 1) // 2 - deg
    out = np.empty(slot_ptr[n_points], dtype=np.int32)
    pos = 0
    for j in range(n_points):
        start = point_ptr[j]
        stop = point_ptr[j + 1]
        for oi in range(start, stop):
            for ok_ in range(oi, stop):
                for hi in range(2):
                    bi = cam_blocks[oi, hi]
                    for hk in range(2):
                        if oi == ok_ and hk < hi:
                            continue
                        bk = cam_blocks[ok_, hk]
                        if bi <= bk:
                            out[pos] = _find_block(indptr, indices, bi, bk)
                        else:
                            out[pos] = _find_block(indptr, indices, bk, bi)
                        pos += 1
    return out, slot_ptr


@njit(cache=True, nogil=True)
def assemble_reduced_system(
    residuals, jc, jp, cam_blocks, point_ptr, damp_c, damp_p, indptr, indices, data, rhs, v_inv, gp,
    used_cols, slots,
):
    """Build the damped reduced camera system S dc = rhs of eq. 6.7 applied to eq. 6.13 (one thread).

    damp_c (6 n_blocks,) and damp_p (n, 3) are added to the diagonal of the camera and point blocks
    (lambda * D for free parameters, the kept diagonal for frozen ones). used_cols lists the columns of
    ``jc`` (of 12) that are not zero for every observation (fixed intrinsics are skipped); slots comes
    from :func:`pair_slots`. Outputs, overwritten: data (nnzb, 6, 6) the upper block triangle of S,
    rhs (6 n_blocks,) = -g_c + W V^-1 g_p, v_inv (n, 3, 3) the inverted damped point blocks and
    gp (n, 3) the point gradients, both reused by the back-substitution.
    Returns False if a point block is singular.
    """
    data[:] = 0.0
    rhs[:] = 0.0
    ok = assemble_point_range(0, point_ptr.shape[0] - 1, 0, residuals, jc, jp, cam_blocks, point_ptr, damp_p,
                          data, rhs, v_inv, gp, used_cols, slots)
    add_diagonal(indptr, indices, data, damp_c)
    return ok


@njit(cache=True, nogil=True)
def add_diagonal(indptr, indices, data, damp_c):
    """Add damp_c (6 n_blocks,) to the diagonal of the diagonal blocks of the BSR ``data``, in place."""
    n_blocks = indptr.shape[0] - 1
    for b in range(n_blocks):
        slot = _find_block(indptr, indices, b, b)
        for s in range(6):
            data[slot, s, s] += damp_c[6 * b + s]


@njit(cache=True, nogil=True)
def assemble_point_range(j_start, j_stop, pos, residuals, jc, jp, cam_blocks, point_ptr, damp_p, data, rhs, v_inv, gp,
                     used_cols, slots):
    """Add the Schur terms of points [j_start, j_stop) to data and rhs (see assemble_reduced_system);
    ``pos`` is where their terms start in ``slots`` (``slot_ptr[j_start]`` of :func:`pair_slots`).

    Threads run it on disjoint point ranges with their own data and rhs (the GIL is released), and
    add the results up: the parallel Schur assembly without numba's parfors, which cost three
    quarters of the kernels' compile time.
    """
    nu = used_cols.shape[0]
    # used columns split by quadrant (pose block: h = 0, intrinsic block: h = 1)
    q_count = np.zeros(2, dtype=np.int64)
    q_pos = np.empty((2, 6), dtype=np.int64)  # index into used_cols
    q_row = np.empty((2, 6), dtype=np.int64)  # row inside the 6x6 block
    for s in range(nu):
        h = used_cols[s] // 6
        q_pos[h, q_count[h]] = s
        q_row[h, q_count[h]] = used_cols[s] % 6
        q_count[h] += 1
    max_deg = 1
    for j in range(j_start, j_stop):
        max_deg = max(max_deg, point_ptr[j + 1] - point_ptr[j])
    w = np.empty((max_deg, nu, 3))
    a = np.empty((max_deg, nu, 3))
    wt = np.empty((max_deg, 3, nu))
    m = np.empty((nu, nu))
    jcu = np.empty((max_deg, 2, nu))
    v = np.empty((3, 3))
    vi = np.empty((3, 3))
    ok = True
    for j in range(j_start, j_stop):
        start = point_ptr[j]
        stop = point_ptr[j + 1]
        deg = stop - start
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
            for s in range(nu):
                c = used_cols[s]
                jcu[i, 0, s] = jc[o, 0, c]
                jcu[i, 1, s] = jc[o, 1, c]
                # the -g_c part of the right-hand side
                rhs[6 * cam_blocks[o, c // 6] + c % 6] -= jc[o, 0, c] * r0 + jc[o, 1, c] * r1
        for s in range(3):
            v[s, s] += damp_p[j, s]
        gp[j, 0] = g0; gp[j, 1] = g1; gp[j, 2] = g2
        if not _inv3(v, vi):
            ok = False
            vi[:] = 0.0
        v_inv[j] = vi
        for i in range(deg):
            o = start + i
            for s in range(nu):
                for t in range(3):
                    w[i, s, t] = jcu[i, 0, s] * jp[o, 0, t] + jcu[i, 1, s] * jp[o, 1, t]
            for s in range(nu):
                for t in range(3):
                    a[i, s, t] = w[i, s, 0] * vi[0, t] + w[i, s, 1] * vi[1, t] + w[i, s, 2] * vi[2, t]
                c = used_cols[s]
                rhs[6 * cam_blocks[o, c // 6] + c % 6] += a[i, s, 0] * g0 + a[i, s, 1] * g1 + a[i, s, 2] * g2
        for i in range(deg):
            for t in range(nu):
                for c in range(3):
                    wt[i, c, t] = w[i, t, c]
        for i in range(deg):
            oi = start + i
            for k in range(i, deg):
                ok_ = start + k
                # the (i, k) term of S: U_ii - A_i W_k^T (only i <= k: S is symmetric)
                for s in range(nu):
                    a0 = a[i, s, 0]; a1 = a[i, s, 1]; a2 = a[i, s, 2]
                    for t in range(nu):
                        m[s, t] = -(a0 * wt[k, 0, t] + a1 * wt[k, 1, t] + a2 * wt[k, 2, t])
                if i == k:
                    for s in range(nu):
                        u0 = jcu[i, 0, s]; u1 = jcu[i, 1, s]
                        for t in range(nu):
                            m[s, t] += u0 * jcu[i, 0, t] + u1 * jcu[i, 1, t]
                for hi in range(2):
                    bi = cam_blocks[oi, hi]
                    for hk in range(2):
                        if i == k and hk < hi:
                            continue  # the lower quadrant of a diagonal term is the upper's transpose
                        bk = cam_blocks[ok_, hk]
                        slot = slots[pos]
                        pos += 1
                        nq_i = q_count[hi]
                        nq_k = q_count[hk]
                        if bi < bk or (bi == bk and i == k):
                            for s_ in range(nq_i):
                                s = q_pos[hi, s_]
                                ri = q_row[hi, s_]
                                for t_ in range(nq_k):
                                    data[slot, ri, q_row[hk, t_]] += m[s, q_pos[hk, t_]]
                        elif bi > bk:
                            for s_ in range(nq_i):
                                s = q_pos[hi, s_]
                                ri = q_row[hi, s_]
                                for t_ in range(nq_k):
                                    data[slot, q_row[hk, t_], ri] += m[s, q_pos[hk, t_]]
                        else:
                            # two observations in one block: add the (k, i) term too
                            for s_ in range(nq_i):
                                s = q_pos[hi, s_]
                                ri = q_row[hi, s_]
                                for t_ in range(nq_k):
                                    val = m[s, q_pos[hk, t_]]
                                    data[slot, ri, q_row[hk, t_]] += val
                                    data[slot, q_row[hk, t_], ri] += val
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
            for h in range(2):
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
        for h in range(2):
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
def bsr_to_dense(indptr, indices, data):
    n_blocks = indptr.shape[0] - 1
    out = np.zeros((6 * n_blocks, 6 * n_blocks))
    # the upper block triangle is enough for an upper Cholesky factorisation
    for b in range(n_blocks):
        for p in range(indptr[b], indptr[b + 1]):
            c = indices[p]
            for s in range(6):
                for t in range(6):
                    out[6 * b + s, 6 * c + t] = data[p, s, t]
    return out


@njit(cache=True, nogil=True)
def scale_rows(residuals, jc, jp, weights):
    """Multiply each observation's residual and Jacobian rows by its weight (robust loss, IRLS)."""
    for o in range(residuals.shape[0]):
        wo = weights[o]
        if wo == 1.0:
            continue
        for r in range(2):
            residuals[o, r] *= wo
            for k in range(12):
                jc[o, r, k] *= wo
            for k in range(3):
                jp[o, r, k] *= wo
