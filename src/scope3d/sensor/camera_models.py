"""Lens models: one interface for the pinhole family (OpenCV's radial-tangential and rational distortion)
and the Kannala-Brandt fisheye (OpenCV's ``cv2.fisheye``), with COLMAP's names and parameter orders.

Every model maps a point ``X_cam = (X, Y, Z)`` (mm, camera frame, +z forward) to a pixel ``(u, v)`` with
the origin at the centre of the top-left pixel (scope3d's convention, OpenCV's and ROS's; COLMAP puts it
at the pixel's corner, 0.5 px away: :mod:`scope3d.io.colmap` converts). Parameter vectors start with
``(fx, fy, cx, cy)`` (pixels) and go on with the model's distortion coefficients (unitless):

==========================  =====================================================  ========================
scope3d name                parameters                                             equals
==========================  =====================================================  ========================
``PINHOLE``                 fx, fy, cx, cy                                         COLMAP PINHOLE
``pinhole_radial_k1k2``     fx, fy, cx, cy, k1, k2                                 COLMAP OPENCV with
                                                                                   p1 = p2 = 0 (RADIAL when
                                                                                   fx = fy); OpenCV with
                                                                                   (k1, k2, 0, 0)
``OPENCV``                  fx, fy, cx, cy, k1, k2, p1, p2                         COLMAP OPENCV, OpenCV's
                                                                                   4-term distortion
``FULL_OPENCV``             fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6         COLMAP FULL_OPENCV,
                                                                                   OpenCV's rational model
``OPENCV_FISHEYE``          fx, fy, cx, cy, k1, k2, k3, k4                         COLMAP OPENCV_FISHEYE,
                                                                                   cv2.fisheye
==========================  =====================================================  ========================

``pinhole_radial_k1k2`` keeps scope3d's own name (the model of the reference's bundle adjustment, sec. 6.2,
and of every camera.json written so far): COLMAP's RADIAL has one focal length, and COLMAP has no model
with fx, fy, k1, k2 alone.

Pinhole family, on normalised coordinates ``x = X/Z, y = Y/Z``, ``r^2 = x^2 + y^2``::

    radial = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
    x_d = x radial + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y
    u = fx x_d + cx,  v = fy y_d + cy

Fisheye, with ``theta`` the angle between the ray and the optical axis (``atan2(sqrt(X^2 + Y^2), Z)``, so
the field continues past 90 deg half-angle where the lens sees that far; OpenCV and COLMAP use ``atan(r)``,
the same for ``Z > 0``)::

    theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
    (x_d, y_d) = theta_d (X, Y) / sqrt(X^2 + Y^2),   u = fx x_d + cx,  v = fy y_d + cy

The *field* of a model is the half-angle up to which the radial map is increasing (beyond it the image
folds back and a pixel has two rays); :meth:`LensModel.max_half_angle` finds it from the parameters.
Arrays of parameters are ``(P,)`` (one camera) or ``(N, P)`` (one row per point).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scope3d.geometry.rotation import hat, rotvec_to_matrix, so3_left_jacobian

_UNDISTORT_ITERATIONS = 20
# Newton inside a bracket: quadratic where theta_d is steep, 60 halvings of 180 deg at worst (to 1e-16 rad).
_FISHEYE_ITERATIONS = 60
# Samples of the radial map when looking for the end of the field: the map is a low-degree polynomial (or a
# ratio of two) in r or theta, whose derivative changes sign at most a few times; 4000 steps over 90 or
# 180 deg place the fold within 0.05 deg, and a bisection then pins it to 1e-12 rad.
_FIELD_SAMPLES = 4000
#: A pinhole model's field ends here at the widest (rad): its fold, when it has none before (89.9 deg).
PINHOLE_HALF_ANGLE_LIMIT = float(np.deg2rad(89.9))
# Largest normalised radius searched for a pinhole model's fold: tan(89.9 deg).
_PINHOLE_R_MAX = float(np.tan(PINHOLE_HALF_ANGLE_LIMIT))


def _col(params: np.ndarray, i: int) -> np.ndarray:
    return params[..., i]


@dataclass(frozen=True)
class LensModel:
    """One camera model: its name, its parameters' names and COLMAP's name for it (None: no COLMAP model)."""

    name: str
    param_names: tuple[str, ...]
    colmap_name: str | None

    @property
    def num_params(self) -> int:
        return len(self.param_names)

    @property
    def is_fisheye(self) -> bool:
        return False

    def check(self, params: np.ndarray) -> np.ndarray:
        """params as a float array with the model's count of parameters (ValueError otherwise)."""
        p = np.asarray(params, dtype=float)
        if p.shape[-1:] != (self.num_params,):
            raise ValueError(f"{self.name} takes {self.num_params} parameters ({', '.join(self.param_names)}), "
                             f"got {p.shape[-1] if p.ndim else 0}")
        return p

    # --- interface (each model implements these) ----------------------------------------------
    def distort(self, params: np.ndarray, normalised: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def undistort(self, params: np.ndarray, distorted: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def project(self, params: np.ndarray, points_cam: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def project_with_jacobians(self, params, points_cam):  # pragma: no cover
        raise NotImplementedError

    def unproject(self, params: np.ndarray, pixels: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def max_half_angle(self, params: np.ndarray) -> float:  # pragma: no cover
        raise NotImplementedError

    # --- shared -------------------------------------------------------------------------------
    def to_distorted(self, params: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) distorted normalised coordinates ``((u - cx) / fx, (v - cy) / fy)``."""
        p = self.check(params)
        uv = np.asarray(pixels, dtype=float)
        return np.stack([(uv[..., 0] - _col(p, 2)) / _col(p, 0), (uv[..., 1] - _col(p, 3)) / _col(p, 1)], axis=-1)

    def half_angle(self, points_cam: np.ndarray) -> np.ndarray:
        """(N,) angle (rad) between each point's ray and the optical axis."""
        p = np.asarray(points_cam, dtype=float)
        return np.arctan2(np.hypot(p[..., 0], p[..., 1]), p[..., 2])

    def in_field(self, params: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
        """(N,) bool: the point lies inside the lens's field (:meth:`max_half_angle`)."""
        return self.half_angle(points_cam) < self.max_half_angle(params)


def _first_fold(grid: np.ndarray, derivative) -> float:
    """The first value of ``grid`` where ``derivative`` (a function of it) is no longer positive, refined by
    bisection; ``grid[-1]`` when it stays positive."""
    d = derivative(grid)
    bad = np.nonzero(~(d > 0))[0]
    if bad.size == 0:
        return float(grid[-1])
    i = int(bad[0])
    if i == 0:
        return float(grid[0])
    lo, hi = float(grid[i - 1]), float(grid[i])
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if derivative(np.array([mid]))[0] > 0:
            lo = mid
        else:
            hi = mid
    return lo


@dataclass(frozen=True)
class PinholeFamily(LensModel):
    """Pinhole with OpenCV's distortion: which coefficients the model has decides its terms (a model
    without k3 computes ``1 + k1 r^2 + k2 r^4`` exactly as scope3d always has, bit for bit)."""

    def _coefficients(self, p: np.ndarray) -> dict[str, np.ndarray]:
        return {n: _col(p, i) for i, n in enumerate(self.param_names) if i >= 4}

    @property
    def _tangential(self) -> bool:
        return "p1" in self.param_names

    def _radial(self, c: dict, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """radial factor, its numerator and denominator at r2 (the denominator is 1 without k4..k6)."""
        num = 1.0
        if "k1" in c:
            num = 1.0 + c["k1"] * r2 + c["k2"] * r2 * r2
        if "k3" in c:
            num = num + c["k3"] * r2 * r2 * r2
        if "k4" in c:
            den = 1.0 + c["k4"] * r2 + c["k5"] * r2 * r2 + c["k6"] * r2 * r2 * r2
            return num / den, num, den
        return num, num, 1.0

    def _radial_dr2(self, c: dict, r2: np.ndarray) -> np.ndarray:
        """d radial / d r^2."""
        _, num, den = self._radial(c, r2)
        dnum = 0.0
        if "k1" in c:
            dnum = c["k1"] + 2.0 * c["k2"] * r2
        if "k3" in c:
            dnum = dnum + 3.0 * c["k3"] * r2 * r2
        if "k4" in c:
            dden = c["k4"] + 2.0 * c["k5"] * r2 + 3.0 * c["k6"] * r2 * r2
            return (dnum * den - num * dden) / (den * den)
        return dnum + 0.0 * r2

    def _radius_derivative(self, c: dict, r2: np.ndarray) -> np.ndarray:
        """d (r radial(r)) / d r at r2; written out term by term without k4..k6, the arithmetic of scope3d's
        original k1, k2 model (its undistortion stays bit for bit the same)."""
        if "k4" in c:
            return self._radial(c, r2)[0] + 2.0 * r2 * self._radial_dr2(c, r2)
        d = 1.0
        if "k1" in c:
            d = 1.0 + 3.0 * c["k1"] * r2 + 5.0 * c["k2"] * r2 * r2
        if "k3" in c:
            d = d + 7.0 * c["k3"] * r2 * r2 * r2
        return d + 0.0 * r2

    def distort(self, params: np.ndarray, normalised: np.ndarray) -> np.ndarray:
        """(N, 2) undistorted normalised coordinates -> (N, 2) distorted ones."""
        c = self._coefficients(self.check(params))
        xy = np.asarray(normalised, dtype=float)
        r2 = np.sum(xy * xy, axis=-1, keepdims=True)
        c1 = {k: np.asarray(v)[..., None] for k, v in c.items()}
        radial = self._radial(c1, r2)[0]
        out = xy * radial
        if self._tangential:
            x, y = xy[..., 0:1], xy[..., 1:2]
            p1, p2 = c1["p1"], c1["p2"]
            out = out + np.concatenate([2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                                        p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y], axis=-1)
        return out

    def _distort_jacobian(self, c: dict, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(N, 2, 2) d (x_d, y_d) / d (x, y)."""
        r2 = x * x + y * y
        radial = self._radial(c, r2)[0]
        dr = self._radial_dr2(c, r2)
        j = np.empty(np.broadcast(x, radial).shape + (2, 2))
        j[..., 0, 0] = radial + 2.0 * x * x * dr
        j[..., 0, 1] = 2.0 * x * y * dr
        j[..., 1, 0] = 2.0 * x * y * dr
        j[..., 1, 1] = radial + 2.0 * y * y * dr
        if self._tangential:
            p1, p2 = c["p1"], c["p2"]
            j[..., 0, 0] += 2.0 * p1 * y + 6.0 * p2 * x
            j[..., 0, 1] += 2.0 * p1 * x + 2.0 * p2 * y
            j[..., 1, 0] += 2.0 * p1 * x + 2.0 * p2 * y
            j[..., 1, 1] += 6.0 * p1 * y + 2.0 * p2 * x
        return j

    def undistort(self, params: np.ndarray, distorted: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`distort`: Newton's method on the radius for radial models (exact to ~1e-12 in
        the image), on (x, y) with the analytic 2x2 Jacobian when there are tangential terms."""
        p = self.check(params)
        c = self._coefficients(p)
        xy_d = np.asarray(distorted, dtype=float)
        if not c or all(np.all(v == 0.0) for v in c.values()):
            return xy_d.copy()
        if not self._tangential:
            rd = np.linalg.norm(xy_d, axis=-1)
            r = rd.copy()
            for _ in range(_UNDISTORT_ITERATIONS):
                r2 = r * r
                f = r * self._radial(c, r2)[0] - rd
                df = self._radius_derivative(c, r2)
                r = r - f / np.where(np.abs(df) < 1e-12, 1e-12, df)
            scale = np.where(rd > 0, r / np.where(rd > 0, rd, 1.0), 1.0)
            return xy_d * scale[..., None]
        xy = xy_d.copy()
        for _ in range(_UNDISTORT_ITERATIONS):
            res = self.distort(p, xy) - xy_d
            j = self._distort_jacobian(c, xy[..., 0], xy[..., 1])
            det = j[..., 0, 0] * j[..., 1, 1] - j[..., 0, 1] * j[..., 1, 0]
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            dx = (j[..., 1, 1] * res[..., 0] - j[..., 0, 1] * res[..., 1]) / det
            dy = (j[..., 0, 0] * res[..., 1] - j[..., 1, 0] * res[..., 0]) / det
            xy = xy - np.stack([dx, dy], axis=-1)
        return xy

    def project(self, params: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
        """(N, 3) mm -> (N, 2) pixels; points at or behind the camera plane give NaN."""
        p = self.check(params)
        pts = np.asarray(points_cam, dtype=float)
        z = pts[..., 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = np.where(z > 0, pts[..., :2] / z, np.nan)
        xy_d = self.distort(p, xy)
        return np.stack([_col(p, 0) * xy_d[..., 0] + _col(p, 2), _col(p, 1) * xy_d[..., 1] + _col(p, 3)], axis=-1)

    def project_with_jacobians(self, params: np.ndarray, points_cam: np.ndarray,
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """pixels (N, 2), d pixel / d point_cam (N, 2, 3), d pixel / d params (N, 2, P)."""
        pts = np.asarray(points_cam, dtype=float)
        n = pts.shape[0]
        p = np.broadcast_to(self.check(params), (n, self.num_params))
        c = self._coefficients(p)
        fx, fy = p[:, 0], p[:, 1]
        inv_z = 1.0 / pts[:, 2]
        x, y = pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2]  # as project divides, to the last bit
        xy_d = self.distort(p, np.stack([x, y], axis=-1))
        pixels = np.stack([fx * xy_d[:, 0] + p[:, 2], fy * xy_d[:, 1] + p[:, 3]], axis=-1)
        j_xy = self._distort_jacobian(c, x, y) * np.stack([fx, fy], axis=-1)[:, :, None]
        j_norm = np.zeros((n, 2, 3))
        j_norm[:, 0, 0] = inv_z
        j_norm[:, 0, 2] = -x * inv_z
        j_norm[:, 1, 1] = inv_z
        j_norm[:, 1, 2] = -y * inv_z
        d_params = np.zeros((n, 2, self.num_params))
        d_params[:, 0, 0] = xy_d[:, 0]
        d_params[:, 1, 1] = xy_d[:, 1]
        d_params[:, 0, 2] = 1.0
        d_params[:, 1, 3] = 1.0
        r2 = x * x + y * y
        _, num, den = self._radial(c, r2)
        powers = {"k1": r2, "k2": r2 * r2, "k3": r2 * r2 * r2}
        for i, name in enumerate(self.param_names):
            if name in powers:  # numerator terms
                g = powers[name] / den
                d_params[:, 0, i], d_params[:, 1, i] = fx * x * g, fy * y * g
            elif name in ("k4", "k5", "k6"):  # denominator terms
                g = -num * {"k4": r2, "k5": r2 * r2, "k6": r2 * r2 * r2}[name] / (den * den)
                d_params[:, 0, i], d_params[:, 1, i] = fx * x * g, fy * y * g
            elif name == "p1":
                d_params[:, 0, i], d_params[:, 1, i] = fx * 2.0 * x * y, fy * (r2 + 2.0 * y * y)
            elif name == "p2":
                d_params[:, 0, i], d_params[:, 1, i] = fx * (r2 + 2.0 * x * x), fy * 2.0 * x * y
        return pixels, j_xy @ j_norm, d_params

    def unproject(self, params: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 3) unit rays in the camera frame."""
        xy = self.undistort(params, self.to_distorted(params, pixels))
        rays = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def max_half_angle(self, params: np.ndarray) -> float:
        """Half-angle (rad) up to which ``r radial(r)`` increases (the tangential terms are ignored: they
        move the fold by their own small size); at most 89.9 deg, a pinhole's limit."""
        c = self._coefficients(self.check(params))
        if not any(k in c for k in ("k1", "k3", "k4")):
            return float(np.arctan(_PINHOLE_R_MAX))

        def derivative(r):
            return self._radius_derivative(c, r * r)

        grid = np.tan(np.linspace(0.0, np.arctan(_PINHOLE_R_MAX), _FIELD_SAMPLES))
        return float(np.arctan(_first_fold(grid, derivative)))


@dataclass(frozen=True)
class Fisheye(LensModel):
    """Kannala-Brandt equidistant fisheye with k1..k4 (cv2.fisheye, COLMAP's OPENCV_FISHEYE)."""

    @property
    def is_fisheye(self) -> bool:
        return True

    @staticmethod
    def _theta_d(k: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """theta_d and d theta_d / d theta. k : (..., 4)."""
        t2 = theta * theta
        k1, k2, k3, k4 = k[..., 0], k[..., 1], k[..., 2], k[..., 3]
        poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
        dpoly = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
        return theta * poly, dpoly

    def distort(self, params: np.ndarray, normalised: np.ndarray) -> np.ndarray:
        """(N, 2) undistorted normalised coordinates (rays in front of the camera) -> (N, 2) distorted ones
        ``theta_d (x, y) / r``."""
        p = self.check(params)
        xy = np.asarray(normalised, dtype=float)
        r = np.linalg.norm(xy, axis=-1)
        theta_d, _ = self._theta_d(p[..., 4:8], np.arctan(r))
        scale = np.where(r > 0, theta_d / np.where(r > 0, r, 1.0), 1.0)
        return xy * scale[..., None]

    def _theta_from_distorted(self, p: np.ndarray, rd: np.ndarray) -> np.ndarray:
        """Solve theta_d(theta) = rd for theta in [0, the fold]: Newton's method kept inside a bracket that
        shrinks every step (bisection where Newton would leave it), as theta_d flattens near the fold and a
        plain Newton step from there lands beyond it. Beyond the fold's radius theta is the fold."""
        k = p[..., 4:8]
        fold = self.max_half_angle(p) if p.ndim == 1 else np.pi
        lo, hi = np.zeros_like(rd), np.full_like(rd, fold)
        theta = np.minimum(rd, fold)
        for _ in range(_FISHEYE_ITERATIONS):
            f, df = self._theta_d(k, theta)
            above = f > rd
            hi = np.where(above, theta, hi)
            lo = np.where(above, lo, theta)
            with np.errstate(divide="ignore", invalid="ignore"):
                step = theta - (f - rd) / df
            theta = np.where((step > lo) & (step < hi), step, 0.5 * (lo + hi))
        return theta

    def undistort(self, params: np.ndarray, distorted: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`distort` for rays in front of the camera (theta < 90 deg; NaN beyond: such a
        ray has no normalised coordinates, use :meth:`unproject`)."""
        p = self.check(params)
        xy_d = np.asarray(distorted, dtype=float)
        rd = np.linalg.norm(xy_d, axis=-1)
        theta = self._theta_from_distorted(p, rd)
        with np.errstate(invalid="ignore"):
            r = np.where(theta < np.pi / 2, np.tan(theta), np.nan)
        scale = np.where(rd > 0, r / np.where(rd > 0, rd, 1.0), 1.0)
        return xy_d * scale[..., None]

    def project(self, params: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
        """(N, 3) mm -> (N, 2) pixels, at any angle from the axis (past 90 deg too); the camera centre
        itself gives NaN. Whether the lens sees that far is :meth:`in_field`."""
        return self._project(self.check(params), np.asarray(points_cam, dtype=float))[0]

    def _project(self, p, pts):
        rho = np.hypot(pts[..., 0], pts[..., 1])
        theta = np.arctan2(rho, pts[..., 2])
        theta_d, dtheta_d = self._theta_d(p[..., 4:8], theta)
        centre = (rho == 0) & (pts[..., 2] <= 0)  # the camera centre, or straight behind: no direction
        with np.errstate(divide="ignore", invalid="ignore"):
            # on the axis the scale's limit is d theta_d / d rho = 1 / Z
            scale = np.where(rho > 0, theta_d / np.where(rho > 0, rho, 1.0), 1.0 / pts[..., 2])
        scale = np.where(centre, np.nan, scale)
        xy_d = pts[..., :2] * scale[..., None]
        pixels = np.stack([_col(p, 0) * xy_d[..., 0] + _col(p, 2), _col(p, 1) * xy_d[..., 1] + _col(p, 3)], axis=-1)
        return pixels, xy_d, rho, theta, theta_d, dtheta_d, scale

    def project_with_jacobians(self, params: np.ndarray, points_cam: np.ndarray,
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """pixels (N, 2), d pixel / d point_cam (N, 2, 3), d pixel / d params (N, 2, 8)."""
        pts = np.asarray(points_cam, dtype=float)
        n = pts.shape[0]
        p = np.broadcast_to(self.check(params), (n, 8))
        pixels, xy_d, rho, theta, theta_d, dtheta_d, scale = self._project(p, pts)
        X, Y, Z = pts[:, 0], pts[:, 1], pts[:, 2]
        R2 = rho * rho + Z * Z
        safe_rho = np.where(rho > 0, rho, 1.0)
        # scale s = theta_d / rho as a function of (rho, Z): ds/drho = (g Z / R^2 - s) / rho, ds/dZ = -g / R^2
        # with g = d theta_d / d theta (d theta / d rho = Z / R^2, d theta / d Z = -rho / R^2). On the axis s
        # is even in rho, so ds/drho = 0 there and ds/dZ = -1 / Z^2.
        ds_drho = np.where(rho > 0, (dtheta_d * Z / R2 - scale) / safe_rho, 0.0)
        ds_dz = -dtheta_d / R2
        ds_dx = ds_drho * X / safe_rho
        ds_dy = ds_drho * Y / safe_rho
        j = np.empty((n, 2, 3))
        j[:, 0, 0] = scale + X * ds_dx
        j[:, 0, 1] = X * ds_dy
        j[:, 0, 2] = X * ds_dz
        j[:, 1, 0] = Y * ds_dx
        j[:, 1, 1] = scale + Y * ds_dy
        j[:, 1, 2] = Y * ds_dz
        j[:, 0, :] *= p[:, 0:1]
        j[:, 1, :] *= p[:, 1:2]
        d_params = np.zeros((n, 2, 8))
        d_params[:, 0, 0] = xy_d[:, 0]
        d_params[:, 1, 1] = xy_d[:, 1]
        d_params[:, 0, 2] = 1.0
        d_params[:, 1, 3] = 1.0
        # d x_d / d k_i = theta^(2i+1) X / rho
        direction = np.where(rho > 0, 1.0 / safe_rho, 0.0)
        power = theta * theta * theta
        for i in range(4):
            d_params[:, 0, 4 + i] = p[:, 0] * power * X * direction
            d_params[:, 1, 4 + i] = p[:, 1] * power * Y * direction
            power = power * theta * theta
        return pixels, j, d_params

    def unproject(self, params: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 3) unit rays, past 90 deg from the axis where the lens sees that far."""
        p = self.check(params)
        xy_d = self.to_distorted(p, pixels)
        rd = np.linalg.norm(xy_d, axis=-1)
        theta = self._theta_from_distorted(p, rd)
        direction = xy_d / np.where(rd > 0, rd, 1.0)[..., None]
        return np.concatenate([direction * np.sin(theta)[..., None], np.cos(theta)[..., None]], axis=-1)

    def max_half_angle(self, params: np.ndarray) -> float:
        """Half-angle (rad) up to which theta_d increases, at most 180 deg."""
        k = self.check(params)[..., 4:8]
        grid = np.linspace(0.0, np.pi, _FIELD_SAMPLES)
        return _first_fold(grid, lambda t: self._theta_d(k, t)[1])


DEFAULT_MODEL = "pinhole_radial_k1k2"

MODELS: dict[str, LensModel] = {m.name: m for m in (
    PinholeFamily("PINHOLE", ("fx", "fy", "cx", "cy"), "PINHOLE"),
    PinholeFamily(DEFAULT_MODEL, ("fx", "fy", "cx", "cy", "k1", "k2"), None),
    PinholeFamily("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"), "OPENCV"),
    PinholeFamily("FULL_OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
                  "FULL_OPENCV"),
    Fisheye("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"), "OPENCV_FISHEYE"),
)}


def lens_model(name: str) -> LensModel:
    """The model of that name (ValueError naming the known ones otherwise)."""
    try:
        return MODELS[name]
    except KeyError:
        raise ValueError(f"unknown camera model {name!r} (known: {', '.join(MODELS)})") from None


def opencv_distortion(model: str, params: np.ndarray) -> np.ndarray:
    """OpenCV's distortion vector for these parameters: (k1, k2, p1, p2[, k3, k4, k5, k6]) for the pinhole
    family (cv2.projectPoints), (k1, k2, k3, k4) for the fisheye (cv2.fisheye.projectPoints)."""
    lens = lens_model(model)
    p = dict(zip(lens.param_names, lens.check(params)))
    if lens.is_fisheye:
        return np.array([p["k1"], p["k2"], p["k3"], p["k4"]])
    base = [p.get("k1", 0.0), p.get("k2", 0.0), p.get("p1", 0.0), p.get("p2", 0.0)]
    if "k4" in p:
        return np.array(base + [p["k3"], p["k4"], p["k5"], p["k6"]])
    return np.array(base)


def project_world_with_jacobians(
    model: str,
    params: np.ndarray,
    points_world: np.ndarray,
    rotvecs: np.ndarray,
    translations: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Any model's projection of N observations with analytic Jacobians; the pose's and the world point's
    follow from d pixel / d point_cam by the chain rule.

    params : (P,) or (N, P) in the model's order. points_world : (N, 3) mm. rotvecs, translations : (N, 3)
    ``cam_from_world`` (rad, mm). Returns pixels (N, 2), d pixel / d point_world (N, 2, 3),
    d pixel / d (w, t) (N, 2, 6) and d pixel / d params (N, 2, P).
    """
    points_world = np.asarray(points_world, dtype=float)
    rotations = rotvec_to_matrix(rotvecs)
    rotated = np.einsum("nij,nj->ni", rotations, points_world)
    pixels, d_pcam, d_params = lens_model(model).project_with_jacobians(params, rotated + translations)
    d_rot = -hat(rotated) @ so3_left_jacobian(rotvecs)
    d_pose = np.concatenate([d_pcam @ d_rot, d_pcam], axis=-1)
    return pixels, d_pcam @ rotations, d_pose, d_params
