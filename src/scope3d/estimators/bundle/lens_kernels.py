"""Compiled residuals and Jacobians of the bundle adjuster for the lens models other than scope3d's radial one
(a kernel module of :mod:`scope3d.utils.aot`, beside :mod:`.kernels`, whose radial kernels stay as they were).

The layout is :mod:`.kernels`' (``jc`` (K, 2, 12): the 6 pose columns, then the intrinsic block
``(fx, fy, cx, cy, k1, k2)``; ``jp`` (K, 2, 3)). The model's parameters after k2 (``extra`` (g, E) per
intrinsic group: a pinhole family's ``(p1, p2, k3, k4, k5, k6)``, zeros for the terms a model lacks, a
fisheye's ``(k3, k4)``) enter the projection. With ``jc`` (K, 2, 18) the kernel also writes their columns, a
third 6-block (the fisheye's padded with zeros): the bundle adjuster refines them; with (K, 2, 12) they are
held. The maths is that of :mod:`scope3d.sensor.camera_models` (tests check they agree to rounding):

* pinhole family: ``x = X/Z``, ``radial = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)``,
  ``x_d = x radial + 2 p1 x y + p2 (r^2 + 2 x^2)``, ``y_d = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y``;
* fisheye: ``theta = atan2(rho, Z)``, ``theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)``,
  ``(x_d, y_d) = theta_d (X, Y) / rho`` (on the axis, ``(X, Y) / Z``).
"""
from __future__ import annotations

import math

from numba import njit

_F2 = "f8[:, ::1]"
_F3 = "f8[:, :, ::1]"
_I1 = "i8[::1]"
_RJ = (f"void(b1, f8[:, ::1], {_I1}, {_I1}, {_I1}, {_F3}, {_F2}, {_F3}, b1, {_F2}, {_F3}, {_F2}, {_F2}, b1, "
       f"{_F2}, {_F3}, {_F3})")
_SQ = f"void(b1, {_F2}, {_I1}, {_I1}, {_I1}, {_F3}, {_F2}, {_F2}, {_F2}, {_F2}, b1, f8[::1])"
AOT_SIGNATURES = {"residuals_and_jacobians": _RJ, "squared_residuals": _SQ}


@njit(cache=True, nogil=True, inline="always")
def _pinhole(p0, p1, p2, k1, k2, e):
    """Distorted normalised coordinates of the pinhole family, d (x_d, y_d) / d P (2 x 3) and the factors
    of k1, k2: returns (xd, yd, e00..e12, dk1x, dk1y, dk2x, dk2y, x, y, r^2, radial). e : (p1, p2, k3, k4, k5,
    k6)."""
    iz = 1.0 / p2
    x = p0 * iz
    y = p1 * iz
    r2 = x * x + y * y
    r4 = r2 * r2
    num = 1.0 + k1 * r2 + k2 * r4 + e[2] * r4 * r2
    den = 1.0 + e[3] * r2 + e[4] * r4 + e[5] * r4 * r2
    radial = num / den
    dnum = k1 + 2.0 * k2 * r2 + 3.0 * e[2] * r4
    dden = e[3] + 2.0 * e[4] * r2 + 3.0 * e[5] * r4
    dr = (dnum * den - num * dden) / (den * den)
    tp1 = e[0]
    tp2 = e[1]
    xd = x * radial + 2.0 * tp1 * x * y + tp2 * (r2 + 2.0 * x * x)
    yd = y * radial + tp1 * (r2 + 2.0 * y * y) + 2.0 * tp2 * x * y
    jxx = radial + 2.0 * x * x * dr + 2.0 * tp1 * y + 6.0 * tp2 * x
    jxy = 2.0 * x * y * dr + 2.0 * tp1 * x + 2.0 * tp2 * y
    jyx = jxy
    jyy = radial + 2.0 * y * y * dr + 6.0 * tp1 * y + 2.0 * tp2 * x
    e00 = jxx * iz
    e01 = jxy * iz
    e02 = -(jxx * x + jxy * y) * iz
    e10 = jyx * iz
    e11 = jyy * iz
    e12 = -(jyx * x + jyy * y) * iz
    return (xd, yd, e00, e01, e02, e10, e11, e12, x * r2 / den, y * r2 / den, x * r4 / den, y * r4 / den,
            x, y, r2, radial)


@njit(cache=True, nogil=True, inline="always")
def _fisheye(p0, p1, p2, k1, k2, e):
    """The same for the fisheye, its last four (0, 0, theta^2, 0). e : (k3, k4)."""
    rho2 = p0 * p0 + p1 * p1
    rho = math.sqrt(rho2)
    R2 = rho2 + p2 * p2
    theta = math.atan2(rho, p2)
    t2 = theta * theta
    k3 = e[0]
    k4 = e[1]
    theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    g = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
    if rho > 0.0:
        s = theta_d / rho
        ds_drho = (g * p2 / R2 - s) / rho
        cx_ = p0 / rho
        cy_ = p1 / rho
    else:  # on the axis: s -> 1 / Z, even in rho
        s = 1.0 / p2
        ds_drho = 0.0
        cx_ = 0.0
        cy_ = 0.0
    ds_dz = -g / R2
    ds_dx = ds_drho * cx_
    ds_dy = ds_drho * cy_
    t3 = theta * t2
    t5 = t3 * t2
    return (s * p0, s * p1, s + p0 * ds_dx, p0 * ds_dy, p0 * ds_dz, p1 * ds_dx, s + p1 * ds_dy, p1 * ds_dz,
            t3 * cx_, t3 * cy_, t5 * cx_, t5 * cy_, 0.0, 0.0, t2, 0.0)


@njit(cache=True, nogil=True, inline="always")
def _write_extra(fisheye, fx, fy, xd_k1, yd_k1, x, y, r2, radial, jc, o):
    """jc[o, :, 12:18] = d pixel / d the later parameters, from what :func:`_pinhole` / :func:`_fisheye` return
    (``xd_k1, yd_k1`` = d (x_d, y_d) / d k1).

    * pinhole family, (p1, p2, k3, k4, k5, k6): ``d x_d / d p1 = 2 x y``, ``d y_d / d p1 = r^2 + 2 y^2``,
      ``d x_d / d p2 = r^2 + 2 x^2``, ``d y_d / d p2 = 2 x y``; ``d radial / d k3 = r^6 / den`` = (d / d k1)
      ``r^4`` and ``d radial / d k(3+i) = -num r^(2i) / den^2`` = -(d / d k1) ``radial r^(2i-2)``, times (x, y);
    * fisheye, (k3, k4) then four zero columns: ``d theta_d / d k3 = theta^7`` = (d / d k1) ``theta^4``,
      ``d theta_d / d k4 = theta^9``; ``r2`` carries ``theta^2`` here.
    """
    if fisheye:
        t4 = r2 * r2
        jc[o, 0, 12] = fx * xd_k1 * t4; jc[o, 1, 12] = fy * yd_k1 * t4
        jc[o, 0, 13] = fx * xd_k1 * t4 * r2; jc[o, 1, 13] = fy * yd_k1 * t4 * r2
        for k in range(14, 18):
            jc[o, 0, k] = 0.0
            jc[o, 1, k] = 0.0
        return
    xy2 = 2.0 * x * y
    jc[o, 0, 12] = fx * xy2; jc[o, 1, 12] = fy * (r2 + 2.0 * y * y)
    jc[o, 0, 13] = fx * (r2 + 2.0 * x * x); jc[o, 1, 13] = fy * xy2
    r4 = r2 * r2
    jc[o, 0, 14] = fx * xd_k1 * r4; jc[o, 1, 14] = fy * yd_k1 * r4
    ax = -fx * xd_k1 * radial
    ay = -fy * yd_k1 * radial
    jc[o, 0, 15] = ax; jc[o, 1, 15] = ay
    jc[o, 0, 16] = ax * r2; jc[o, 1, 16] = ay * r2
    jc[o, 0, 17] = ax * r4; jc[o, 1, 17] = ay * r4


@njit(cache=True, nogil=True)
def residuals_and_jacobians(
    fisheye, observed, cam_index, point_index, intr_index, rotations, translations, rot_jac, centre_param,
    points, point_jac, intrinsics, extra, square_pixels, residuals, jc, jp,
):
    """:func:`scope3d.estimators.bundle.kernels.residuals_and_jacobians` through the fisheye (``fisheye``) or
    the pinhole family; ``jc`` (K, 2, 12) holds ``extra`` fixed, (K, 2, 18) adds its columns."""
    with_extra = jc.shape[2] > 12
    for o in range(observed.shape[0]):
        c = cam_index[o]
        j = point_index[o]
        q = intr_index[o]
        fx = intrinsics[q, 0]
        fy = fx if square_pixels else intrinsics[q, 1]
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
            a0 = p0; a1 = p1; a2 = p2
        if fisheye:
            xd, yd, d00, d01, d02, d10, d11, d12, k1x, k1y, k2x, k2y, x, y, r2, radial = _fisheye(
                p0, p1, p2, intrinsics[q, 4], intrinsics[q, 5], extra[q])
        else:
            xd, yd, d00, d01, d02, d10, d11, d12, k1x, k1y, k2x, k2y, x, y, r2, radial = _pinhole(
                p0, p1, p2, intrinsics[q, 4], intrinsics[q, 5], extra[q])
        residuals[o, 0] = fx * xd + intrinsics[q, 2] - observed[o, 0]
        residuals[o, 1] = fy * yd + intrinsics[q, 3] - observed[o, 1]
        # From here on the pose's and the point's columns are the radial kernel's, line for line: a kernel
        # module cannot import another (setup.py compiles each alone, without scope3d), and the radial
        # kernel stays as it was (its compiled build and timings).
        e00 = fx * d00; e01 = fx * d01; e02 = fx * d02
        e10 = fy * d10; e11 = fy * d11; e12 = fy * d12
        f00 = -e01 * a2 + e02 * a1; f01 = e00 * a2 - e02 * a0; f02 = -e00 * a1 + e01 * a0
        f10 = -e11 * a2 + e12 * a1; f11 = e10 * a2 - e12 * a0; f12 = -e10 * a1 + e11 * a0
        for k in range(3):
            jc[o, 0, k] = f00 * rot_jac[c, 0, k] + f01 * rot_jac[c, 1, k] + f02 * rot_jac[c, 2, k]
            jc[o, 1, k] = f10 * rot_jac[c, 0, k] + f11 * rot_jac[c, 1, k] + f12 * rot_jac[c, 2, k]
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
        if square_pixels:
            jc[o, 0, 6] = xd; jc[o, 1, 6] = yd
            jc[o, 0, 7] = 0.0; jc[o, 1, 7] = 0.0
        else:
            jc[o, 0, 6] = xd; jc[o, 1, 6] = 0.0
            jc[o, 0, 7] = 0.0; jc[o, 1, 7] = yd
        jc[o, 0, 8] = 1.0; jc[o, 1, 8] = 0.0
        jc[o, 0, 9] = 0.0; jc[o, 1, 9] = 1.0
        jc[o, 0, 10] = fx * k1x; jc[o, 1, 10] = fy * k1y
        jc[o, 0, 11] = fx * k2x; jc[o, 1, 11] = fy * k2y
        for k in range(3):
            jp[o, 0, k] = g00 * point_jac[j, 0, k] + g01 * point_jac[j, 1, k] + g02 * point_jac[j, 2, k]
            jp[o, 1, k] = g10 * point_jac[j, 0, k] + g11 * point_jac[j, 1, k] + g12 * point_jac[j, 2, k]
        if with_extra:
            _write_extra(fisheye, fx, fy, k1x, k1y, x, y, r2, radial, jc, o)


@njit(cache=True, nogil=True)
def squared_residuals(
    fisheye, observed, cam_index, point_index, intr_index, rotations, translations, points, intrinsics, extra,
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
        if fisheye:
            xd, yd = _fisheye(p0, p1, p2, intrinsics[q, 4], intrinsics[q, 5], extra[q])[:2]
        else:
            xd, yd = _pinhole(p0, p1, p2, intrinsics[q, 4], intrinsics[q, 5], extra[q])[:2]
        u = fx * xd + intrinsics[q, 2] - observed[o, 0]
        v = fy * yd + intrinsics[q, 3] - observed[o, 1]
        out[o] = u * u + v * v
