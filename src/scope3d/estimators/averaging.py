"""Camera poses from pairwise relative poses and the robot's measurements (global structure from motion).

When the reported poses are off by millimetres, triangulating with them puts points millimetres off and
bundle adjustment starting there converges slowly or wrongly. The images know better: each overlapping
pair's essential matrix gives its relative rotation to a fraction of a degree and the direction of its
baseline. Combining all pairs at once (not chaining them, which accumulates error) gives every camera's
pose up to a similarity; the measurements, each weighted by its tolerance, fix that similarity:

* :func:`relative_pose` — essential matrix by RANSAC on undistorted matches, decomposed with the
  cheirality test: ``x_j = R_ji x_i + t_ji`` with ``|t_ji| = 1``.
* :func:`average_rotations` — least squares over all pairs of ``R_j R_i^T = R_ji`` plus the measured
  orientations as priors, linearised about the current estimate and iterated, with Huber weights so that
  a wrong pair cannot pull the solution (Govindu 2004; Chatterjee & Govindu 2013 use the same
  linearisation).
* :func:`average_positions` — with the rotations known, each pair says ``C_i - C_j = s_ij d_ij`` along a
  known world direction ``d_ij = R_j^T t_ji`` with an unknown length ``s_ij >= 0``; the measured centres
  fix position and scale. Linear least squares with Huber weights; a pair whose length comes out
  negative (the direction points the wrong way) is dropped.

Units: mm and radians. Poses are ``cam_from_world``.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import spsolve

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import hat, matrix_to_rotvec, rotvec_to_matrix
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose
from scope3d.utils.robust import huber_weights, robust_norm_sigma

# A prior with an infinite tolerance still holds the gauge: its sigma is this many times the scene's size.
_LOOSE_PRIOR_FACTOR = 1e3


@dataclass
class RelativePose:
    """Relative pose of frame j with respect to frame i from their matches.

    rotation : (3, 3) ``R_ji`` with ``x_j = R_ji x_i + t_ji``; direction : (3,) unit ``t_ji``.
    inliers : (M,) bool over the matches given; n_inliers : their count.
    rotation_sigma_rad, direction_sigma_rad : standard deviations (rad, along the worst axis) from the
        refinement's covariance, for a keypoint noise of ``noise_px``: a pair with few matches on a
        small patch, or a baseline along the line of sight, has a large one and weighs little.
    parallax_rad : the inliers' median triangulation angle under this pose (the angle between frame j's
        ray and frame i's ray turned by ``rotation``; COLMAP's two-view ``tri_angle``), NaN when not
        measured. Below about a degree a small rotation mimics the baseline's image motion, so rotation
        and direction trade off along a valley the sigmas (a local curvature) do not see.
    """

    i: int
    j: int
    rotation: np.ndarray
    direction: np.ndarray
    inliers: np.ndarray
    rotation_sigma_rad: float = np.inf
    direction_sigma_rad: float = np.inf
    parallax_rad: float = np.nan

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def relative_pose(camera: Camera, pixels_i: np.ndarray, pixels_j: np.ndarray, *, threshold_px: float,
                  noise_px: float = 0.5, confidence: float = 0.999, prior: tuple[np.ndarray, np.ndarray] | None = None,
                  i: int = 0, j: int = 1) -> RelativePose | None:
    """Relative pose of two frames from their matches (M, 2) each, pixels.

    Candidates: the essential matrix by RANSAC (five-point, OpenCV) on undistorted rays, decomposed with
    the cheirality test, and the ``prior`` (R_ji, t_ji) when given (the measured poses'). Each is refined
    by least squares over all five degrees of freedom on the Sampson distances of its inliers
    (:func:`_refine_relative_pose`), and the one with most inliers wins. The refinement matters: a minimal
    sample's model is good only to its five points, and with a scope's short baselines many models fit
    within a pixel (on the dome phantom RANSAC's model was 5 deg off where the refined one is 0.2 deg); the
    prior start matters where RANSAC's model lies in another basin. ``threshold_px`` is the inlier
    threshold on the Sampson distance; ``noise_px`` the keypoints' localisation noise, for the sigmas.
    None when fewer than eight matches or no model is found.
    """
    if len(pixels_i) < 8:
        return None
    xi = camera.pixel_to_normalised(np.asarray(pixels_i, float))
    xj = camera.pixel_to_normalised(np.asarray(pixels_j, float))
    thr = threshold_px / (0.5 * (camera.fx + camera.fy))
    starts = []
    try:
        E, mask = cv2.findEssentialMat(xi, xj, np.eye(3), method=cv2.RANSAC, prob=confidence, threshold=thr)
    except cv2.error:
        E = None
    if E is not None and E.shape == (3, 3):  # several solutions stacked: the sample was degenerate
        _, R, t, _ = cv2.recoverPose(E, xi, xj, np.eye(3), mask=mask.copy())
        starts.append((R, t.ravel()))
    if prior is not None and np.linalg.norm(prior[1]) > 0:
        starts.append((np.asarray(prior[0], float), np.asarray(prior[1], float)))
    best = None
    for R, t in starts:
        inliers = np.abs(_sampson(xi, xj, R, t / np.linalg.norm(t))) <= thr
        cov = None
        for _ in range(2):  # refine on the inliers, re-select them with the refined model, refine again
            if inliers.sum() < 8:
                break
            R, t, cov = _refine_relative_pose(xi[inliers], xj[inliers], R, t, thr)
            inliers = np.abs(_sampson(xi, xj, R, t)) <= thr
        if cov is not None and inliers.sum() >= 8 and (best is None or inliers.sum() > best[2].sum()):
            best = (R, t, inliers, cov)
    if best is None:
        return None
    R, t, inliers, cov = best
    return _relative_pose_with_sigmas(camera, xi, xj, R, t, inliers, cov, noise_px, i, j)


def refine_relative_pose(camera: Camera, pixels_i: np.ndarray, pixels_j: np.ndarray, rotation: np.ndarray,
                         direction: np.ndarray, *, threshold_px: float, noise_px: float = 0.5, i: int = 0,
                         j: int = 1) -> RelativePose | None:
    """The relative pose refined from one given start ``(R_ji, t_ji)`` (as :func:`relative_pose` refines each
    of its candidates: inliers by Sampson distance, refined, re-selected, refined again; the sign of t by
    cheirality). For callers that judge the candidates by something the inlier count cannot see (e.g. a
    shape prior: with short baselines several starts fit the same inliers). None when fewer than eight
    inliers remain."""
    xi = camera.pixel_to_normalised(np.asarray(pixels_i, float))
    xj = camera.pixel_to_normalised(np.asarray(pixels_j, float))
    thr = threshold_px / (0.5 * (camera.fx + camera.fy))
    R, t = np.asarray(rotation, float), np.asarray(direction, float)
    if len(xi) < 8 or not np.linalg.norm(t) > 0:
        return None
    inliers = np.abs(_sampson(xi, xj, R, t / np.linalg.norm(t))) <= thr
    cov = None
    for _ in range(2):
        if inliers.sum() < 8:
            return None
        R, t, cov = _refine_relative_pose(xi[inliers], xj[inliers], R, t, thr)
        inliers = np.abs(_sampson(xi, xj, R, t)) <= thr
    if inliers.sum() < 8:
        return None
    return _relative_pose_with_sigmas(camera, xi, xj, R, t, inliers, cov, noise_px, i, j)


def _relative_pose_with_sigmas(camera: Camera, xi: np.ndarray, xj: np.ndarray, R: np.ndarray, t: np.ndarray,
                               inliers: np.ndarray, cov: np.ndarray, noise_px: float, i: int, j: int) -> RelativePose:
    """The refined pose with its rotation and direction sigmas (largest eigenvalue of the refinement's
    covariance scaled by the pixel noise) and its parallax (the inliers' median triangulation angle), t's
    sign fixed by cheirality."""
    noise = noise_px / (0.5 * (camera.fx + camera.fy))
    sigma_rot = noise * np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0))
    sigma_dir = noise * np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0))
    # the Sampson distance does not see the sign of t: most inliers must lie in front of both cameras
    if _in_front_fraction(xi[inliers], xj[inliers], R, t) < 0.5:
        t = -t
    ray_i = np.c_[xi[inliers], np.ones(int(inliers.sum()))] @ R.T  # frame i's rays in frame j's axes
    ray_j = np.c_[xj[inliers], np.ones(int(inliers.sum()))]
    cos = np.einsum("ij,ij->i", ray_i, ray_j) / (np.linalg.norm(ray_i, axis=1) * np.linalg.norm(ray_j, axis=1))
    parallax = float(np.median(np.arccos(np.clip(cos, -1.0, 1.0))))
    return RelativePose(i, j, R, t, inliers, float(sigma_rot), float(sigma_dir), parallax)


def _sampson(xi: np.ndarray, xj: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Signed Sampson distance (normalised image units) of rays xi, xj (M, 2) to ``E = [t]x R``."""
    return _sampson_homogeneous(np.c_[xi, np.ones(len(xi))], np.c_[xj, np.ones(len(xj))], hat(t) @ R)


def _sampson_homogeneous(hi: np.ndarray, hj: np.ndarray, E: np.ndarray) -> np.ndarray:
    """:func:`_sampson` of homogeneous rays hi, hj (M, 3) (last coordinate 1) to an essential matrix E (3, 3)."""
    Ex = hi @ E.T
    Etx = hj @ E
    num = np.einsum("ij,ij->i", hj, Ex)
    return num / np.sqrt(Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2 + 1e-300)


def _sampson_jacobian(hi: np.ndarray, hj: np.ndarray, E: np.ndarray, dE: np.ndarray) -> np.ndarray:
    """(M, K) derivatives of :func:`_sampson_homogeneous` along K directions dE (K, 3, 3) of E.

    With ``a = E hi``, ``b = E^T hj``, ``n = hj^T E hi`` and ``d = a_0^2 + a_1^2 + b_0^2 + b_1^2`` the
    distance is ``n / sqrt(d)``, so ``dr = dn / sqrt(d) - n (a_0 da_0 + a_1 da_1 + b_0 db_0 + b_1 db_1) / d^1.5``."""
    m, k = len(hi), len(dE)
    a = hi @ E.T
    b = hj @ E
    n = np.einsum("ij,ij->i", hj, a)
    d = a[:, 0] ** 2 + a[:, 1] ** 2 + b[:, 0] ** 2 + b[:, 1] ** 2 + 1e-300
    da = (hi @ dE.reshape(3 * k, 3).T).reshape(m, k, 3)  # dE_k hi
    db = (hj @ dE.transpose(0, 2, 1).reshape(3 * k, 3).T).reshape(m, k, 3)  # dE_k^T hj
    dn = (da * hj[:, None, :]).sum(axis=2)
    dd = a[:, None, 0] * da[..., 0] + a[:, None, 1] * da[..., 1] + b[:, None, 0] * db[..., 0] + b[:, None, 1] * db[..., 1]
    root = np.sqrt(d)[:, None]
    return dn / root - (n[:, None] / (root * d[:, None])) * dd


def _refine_relative_pose(xi, xj, R0, t0, scale):
    """Least squares (soft-L1 loss at ``scale``) on the Sampson distances over a rotation ``exp(w) R0``
    and a unit translation ``t0 + a u + b v`` normalised (u, v span the tangent plane at t0).

    The Jacobian is analytic (:class:`_RelativePoseModel`): the minimum finite differences reach, without
    their five extra Sampson evaluations per Jacobian (on the dome's coarse pass 2.5x less CPU). Returns R, t and the (5, 5) covariance factor ``(J^T J)^-1`` at the
    solution (times the residuals' variance it is the parameters' covariance; an ill-posed pair gives a
    huge one)."""
    from scipy.optimize import least_squares

    model = _RelativePoseModel(xi, xj, R0, t0)
    fit = least_squares(model.residuals, np.zeros(5), jac=model.jacobian, loss="soft_l1", f_scale=scale,
                        x_scale=1e-2, max_nfev=50)
    # scipy's Jacobian at the solution already carries the loss's weights (J^T J is the Gauss-Newton
    # Hessian of the robust cost); x is small, so its rotation block is close to exp(w) R's
    R, t, _ = model.pose(fit.x)
    return R, t, np.linalg.pinv(fit.jac.T @ fit.jac)


class _RelativePoseModel:
    """Sampson distances of matched rays xi, xj (M, 2) and their analytic Jacobian (M, 5) over the
    parameters x (5,) of :func:`_refine_relative_pose`: ``R = exp(w) R0`` with ``w = x[:3]``, and
    ``t = n / |n|`` with ``n = t0 + x[3] u + x[4] v`` (u, v an orthonormal basis of the plane normal to t0).

    The derivative of the distances along a change dE of ``E = [t]x R`` is :func:`_sampson_jacobian`'s;
    along w_k, ``dE = [t]x (d exp(w) / dw_k) R0`` (OpenCV's Rodrigues gives the exact derivative of exp);
    along x[3 + l], ``dt = (I - t t^T) b_l / |n|`` with ``b = (u, v)``, and ``dE = [dt]x R``."""

    def __init__(self, xi: np.ndarray, xj: np.ndarray, R0: np.ndarray, t0: np.ndarray):
        self.hi = np.c_[xi, np.ones(len(xi))]
        self.hj = np.c_[xj, np.ones(len(xj))]
        self.R0 = R0
        self.t0 = t0 / np.linalg.norm(t0)
        u = np.cross(self.t0, [1.0, 0, 0] if abs(self.t0[0]) < 0.9 else [0, 1.0, 0])
        u /= np.linalg.norm(u)
        self.tangent = np.stack([u, np.cross(self.t0, u)], axis=1)  # (3, 2)
        self._last: tuple | None = None  # x and its pose: scipy asks for the Jacobian where it last evaluated

    def pose(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """R (3, 3), unit t (3,) and d exp(w) / dw (3, 3, 3) at x."""
        if self._last is None or not np.array_equal(self._last[0], x):
            rotation, d_rotation = cv2.Rodrigues(np.asarray(x[:3], float))
            n = self.t0 + self.tangent @ x[3:]
            self._last = (x.copy(), rotation @ self.R0, n / np.linalg.norm(n), d_rotation.reshape(3, 3, 3))
        return self._last[1:]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        R, t, _ = self.pose(x)
        return _sampson_homogeneous(self.hi, self.hj, hat(t) @ R)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        R, t, d_rotation = self.pose(x)
        t_hat = hat(t)
        n_norm = np.linalg.norm(self.t0 + self.tangent @ x[3:])
        dt = (self.tangent - np.outer(t, t @ self.tangent)) / n_norm  # (3, 2)
        dE = np.concatenate([t_hat @ d_rotation @ self.R0, hat(dt.T) @ R])
        return _sampson_jacobian(self.hi, self.hj, t_hat @ R, dE)


def _in_front_fraction(xi, xj, R, t) -> float:
    """Fraction of matched rays whose midpoint triangulation lies in front of both cameras."""
    di = np.c_[xi, np.ones(len(xi))]
    dj = np.c_[xj, np.ones(len(xj))] @ R  # frame j's rays in frame i's axes
    cj = -R.T @ t  # frame j's centre in frame i
    # depths along each ray minimising the gap between the rays (2x2 normal equations per match)
    a, b, c = np.einsum("ij,ij->i", di, di), np.einsum("ij,ij->i", di, dj), np.einsum("ij,ij->i", dj, dj)
    d, e = di @ cj, dj @ cj
    den = a * c - b * b
    zi = (c * d - b * e) / np.where(den == 0, 1e-300, den)
    zj = (b * d - a * e) / np.where(den == 0, 1e-300, den)
    return float(np.mean((zi > 0) & (zj > 0))) if len(xi) else 0.0


def average_rotations(measured: list[MeasuredPose], pairs: list[RelativePose], *,
                      iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (n, 3, 3) ``cam_from_world`` that best agree with the pairs and the measurements.

    measured : n measured poses; their orientation tolerance (rad, box half-width per axis, uniform
        errors: sigma = half-width / sqrt 3) weighs each as a prior; an infinite tolerance gives a loose
        prior that only holds the gauge.
    pairs : relative rotations ``R_ji``, each weighed by its ``rotation_sigma_rad`` times a common factor
        (at least 1) estimated robustly from the normalised residuals at every iteration, with Huber
        weights beyond 2 sigma.
    Returns (rotations, pair_residual_rad (len(pairs),)): each pair's disagreement with the solution.
    """
    n, k = len(measured), len(pairs)
    Q = np.stack([m.pose.rotation for m in measured])
    M = Q.copy()
    tol = np.stack([m.tolerance.orientation_rad for m in measured])
    sigma_prior = np.where(np.isfinite(tol), np.maximum(tol, 1e-9) / np.sqrt(3.0), _LOOSE_PRIOR_FACTOR)
    ii = np.array([p.i for p in pairs], int)
    jj = np.array([p.j for p in pairs], int)
    R_rel = np.stack([p.rotation for p in pairs]) if k else np.zeros((0, 3, 3))
    sigma_own = np.array([p.rotation_sigma_rad for p in pairs], float)
    pair_rows = (3 * np.arange(k)[:, None] + np.arange(3)).ravel()
    resid = np.zeros(k)
    for _ in range(iterations):
        A = Q[jj] @ np.swapaxes(Q[ii], 1, 2)  # current R_j R_i^T
        e = matrix_to_rotvec(R_rel @ np.swapaxes(A, 1, 2)) if k else np.zeros((0, 3))
        resid = np.linalg.norm(e, axis=1)
        sigma = sigma_own * (robust_norm_sigma(resid / sigma_own, 1.0) if k >= 3 else 1.0)
        w_pair = huber_weights(resid / sigma, 2.0) / sigma**2
        # unknowns: delta_i (3n), R_i <- exp(delta_i) R_i. Pair rows: delta_j - A delta_i = e (first order of
        # R_ji = exp(delta_j) A exp(-delta_i)); prior rows: deviation from the measurement + delta_i = 0
        rows = np.concatenate([pair_rows, np.repeat(pair_rows, 3), 3 * k + np.arange(3 * n)])
        cols = np.concatenate([(3 * jj[:, None] + np.arange(3)).ravel(),
                               np.broadcast_to(3 * ii[:, None, None] + np.arange(3), (k, 3, 3)).ravel(),
                               np.arange(3 * n)])
        vals = np.concatenate([np.ones(3 * k), -A.ravel(), np.ones(3 * n)])
        J = coo_matrix((vals, (rows, cols)), shape=(3 * k + 3 * n, 3 * n)).tocsr()
        b = np.concatenate([e.ravel(), -matrix_to_rotvec(Q @ np.swapaxes(M, 1, 2)).ravel()])
        wts = np.concatenate([np.repeat(w_pair, 3), 1.0 / sigma_prior.ravel() ** 2])
        JtW = J.T.multiply(wts).tocsr()
        delta = spsolve((JtW @ J).tocsc(), JtW @ b).reshape(n, 3)
        Q = rotvec_to_matrix(delta) @ Q
        if np.abs(delta).max() < 1e-10:
            break
    if k:
        A = Q[jj] @ np.swapaxes(Q[ii], 1, 2)
        resid = np.linalg.norm(matrix_to_rotvec(R_rel @ np.swapaxes(A, 1, 2)), axis=1)
    return Q, resid


def average_positions(measured: list[MeasuredPose], rotations: np.ndarray, pairs: list[RelativePose], *,
                      iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (n, 3) mm from the pairs' baseline directions, the rotations and the measured centres.

    Each pair gives ``C_i - C_j = s_ij R_j^T t_ji`` with an unknown length ``s_ij``; its residual (mm)
    has sigma ``|C_i - C_j| * direction_sigma_rad`` times a common factor (at least 1) estimated robustly
    from the normalised residuals. The measured centres are priors with sigma tolerance / sqrt 3.
    Returns (centres, used (len(pairs),) bool: the pairs that agreed, i.e. a positive length and a
    residual within 3 sigma; the others are dropped from the solve).
    """
    n, k = len(measured), len(pairs)
    meas = np.stack([m.pose.centre for m in measured])
    tol = np.stack([m.tolerance.position_mm for m in measured])
    size = max(float(np.ptp(meas, axis=0).max()), 1.0)
    sigma_prior = np.where(np.isfinite(tol), np.maximum(tol, 1e-6) / np.sqrt(3.0), _LOOSE_PRIOR_FACTOR * size)
    ii = np.array([p.i for p in pairs], int)
    jj = np.array([p.j for p in pairs], int)
    d = np.einsum("kji,kj->ki", rotations[jj], np.stack([p.direction for p in pairs])) if k else np.zeros((0, 3))
    sigma_own = np.array([p.direction_sigma_rad for p in pairs], float)
    # unknowns: centres (3n) then lengths (k). Pair rows: C_i - C_j - s_ij d_ij = 0; prior rows: C_i = measured
    rows = np.concatenate([np.tile(np.arange(3 * k), 3), 3 * k + np.arange(3 * n)])
    cols = np.concatenate([(3 * ii[:, None] + np.arange(3)).ravel(), (3 * jj[:, None] + np.arange(3)).ravel(),
                           3 * n + np.repeat(np.arange(k), 3), np.arange(3 * n)])
    vals = np.concatenate([np.ones(3 * k), -np.ones(3 * k), -d.ravel(), np.ones(3 * n)])
    J = coo_matrix((vals, (rows, cols)), shape=(3 * k + 3 * n, 3 * n + k)).tocsr()
    b = np.concatenate([np.zeros(3 * k), meas.ravel()])
    C = meas.copy()
    used = np.ones(k, bool)
    normalised = np.zeros(k)
    factor = 1.0
    for _ in range(iterations):
        baseline = np.maximum(np.linalg.norm(C[ii] - C[jj], axis=1), 1e-3 * size)
        sigma = baseline * sigma_own * factor
        w_pair = np.where(used, huber_weights(normalised, 2.0) / sigma**2, 0.0)
        wts = np.concatenate([np.repeat(w_pair, 3), 1.0 / sigma_prior.ravel() ** 2])
        JtW = J.T.multiply(wts).tocsr()
        # a dropped pair's length is unobserved: a unit ridge keeps the system regular
        ridge = coo_matrix((np.r_[np.zeros(3 * n), (~used).astype(float)], (np.arange(3 * n + k),) * 2))
        x = spsolve((JtW @ J + ridge).tocsc(), JtW @ b)
        C_new, s = x[:3 * n].reshape(n, 3), x[3 * n:]
        resid = np.linalg.norm(C_new[ii] - C_new[jj] - s[:, None] * d, axis=1)
        normalised = resid / (baseline * sigma_own)
        factor = robust_norm_sigma(normalised[used], 1.0) if used.sum() >= 3 else factor
        normalised = normalised / factor
        used_new = (s > 0) & (normalised <= 3.0)
        moved = np.abs(C_new - C).max()
        C = C_new
        if moved < 1e-9 * size and np.array_equal(used_new, used):
            break
        used = used_new
    return C, used


def poses_from(rotations: np.ndarray, centres: np.ndarray) -> list[Pose]:
    """``cam_from_world`` poses from rotations (n, 3, 3) and centres (n, 3) mm."""
    return [Pose.from_centre(R, c) for R, c in zip(rotations, centres)]


def positions_from_points(camera: Camera, measured: list[MeasuredPose], rotations: np.ndarray, centres: np.ndarray,
                          tracks: Tracks, *, noise_px: float = 0.5, min_observations: int = 8,
                          iterations: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (n, 3) mm from the tracks' rays once the rotations are known (the points fix the lengths).

    Baseline directions alone leave a frame's distance along its only pair free, and cannot space
    cameras along a line at all (a row of a survey grid): :func:`average_positions` then falls back on
    the measured centres, millimetres off. A point seen from three frames fixes the ratio of their
    baselines. With known rotations each observation says that the point lies on a known world ray from
    the camera centre, ``(I - u u^T)(X - C) = 0`` — linear in centres and points (the known-rotation
    problem, Kahl & Hartley 2008). Each residual (mm) is weighed as an angle, by the current distance
    along the ray and the keypoint noise, with Huber weights beyond 2 sigma of a robustly estimated
    common factor; the points are eliminated (3 x 3 blocks) and the centres solved per rigid group
    (frames tied by shared points) with its centroid and scale held to the start's. Each group is then
    scaled and shifted onto the measured centres (weighted by their tolerances), as the averaging does.

    measured : n measured poses (tolerances weigh the final fit). rotations : (n, 3, 3) ``cam_from_world``.
    centres : (n, 3) mm, the start (e.g. :func:`average_positions`). tracks : observations (pixels) of
    frames 0..n-1. min_observations : a frame with fewer observations on points seen twice keeps its start.
    Returns (centres (n, 3), solved (n,) bool: the frames placed by the points).
    """
    start = np.asarray(centres, float).copy()
    if not np.all(np.isfinite(start)):  # measurements beyond float range: nothing to weigh the rays by
        return start, np.zeros(len(measured), bool)
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            C, solved = _positions_from_points(camera, measured, rotations, start.copy(), tracks, noise_px,
                                               min_observations, iterations)
    except np.linalg.LinAlgError:  # e.g. centres so far out that their squares overflow
        return start, np.zeros(len(measured), bool)
    if not np.all(np.isfinite(C)):
        return start, np.zeros(len(measured), bool)
    return C, solved


def _positions_from_points(camera, measured, rotations, C, tracks, noise_px, min_observations, iterations):
    n = len(measured)
    solved = np.zeros(n, bool)
    obs_frame, obs_track = tracks.frame.astype(int), tracks.track.astype(int)
    rays = np.c_[camera.pixel_to_normalised(tracks.pixels), np.ones(len(obs_frame))]
    u = np.einsum("kji,kj->ki", rotations[obs_frame], rays)  # R^T x: world direction of each observation
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    keep = np.ones(len(obs_frame), bool)
    for _ in range(3):  # frames with too few observations out, then tracks left with one view out
        counts = np.bincount(obs_frame[keep], minlength=n)
        keep &= counts[obs_frame] >= min_observations
        keep &= np.bincount(obs_track[keep], minlength=tracks.n_tracks)[obs_track] >= 2
    if not keep.any():
        return C, solved
    obs_frame, obs_track, u = obs_frame[keep], np.unique(obs_track[keep], return_inverse=True)[1], u[keep]
    n_points = int(obs_track.max()) + 1
    graph = coo_matrix((np.ones(len(obs_frame)), (obs_frame, n + obs_track)), shape=(n + n_points,) * 2)
    _, group = connected_components(graph, directed=False)
    P = np.eye(3) - u[:, :, None] * u[:, None, :]  # projector orthogonal to each ray
    sigma_angle = noise_px / (0.5 * (camera.fx + camera.fy))
    weight = np.ones(len(obs_frame))
    factor = 1.0
    X = np.zeros((n_points, 3))
    for _ in range(iterations):
        X = _points_on_rays(P, weight, obs_frame, obs_track, C, n_points)
        depth = np.maximum(np.linalg.norm(X[obs_track] - C[obs_frame], axis=1), 1e-9)
        resid = np.linalg.norm(np.einsum("kij,kj->ki", P, X[obs_track] - C[obs_frame]), axis=1) / depth
        factor = robust_norm_sigma(resid / sigma_angle, 1.0)
        weight = huber_weights(resid / (factor * sigma_angle), 2.0) / depth**2
        C_new = C.copy()
        for g in np.unique(group[:n][np.bincount(obs_frame, minlength=n) > 0]):
            frames = np.flatnonzero(group[:n] == g)
            if len(frames) >= 2:
                C_new[frames] = _solve_group(P, weight, obs_frame, obs_track, frames, C[frames], n_points)
        C = C_new
    for g in np.unique(group[:n][np.bincount(obs_frame, minlength=n) > 0]):
        frames = np.flatnonzero(group[:n] == g)
        if len(frames) >= 2:
            C[frames] = _onto_measured(C[frames], [measured[k] for k in frames])
            solved[frames] = True
    return C, solved


def _points_on_rays(P, weight, obs_frame, obs_track, C, n_points) -> np.ndarray:
    """Each point closest (weighted) to its rays: ``(sum w P) X = sum w P C``, 3 x 3 per point."""
    wP = weight[:, None, None] * P
    H = np.zeros((n_points, 3, 3))
    np.add.at(H, obs_track, wP)
    g = np.zeros((n_points, 3))
    np.add.at(g, obs_track, np.einsum("kij,kj->ki", wP, C[obs_frame]))
    H += 1e-12 * np.trace(H, axis1=1, axis2=2)[:, None, None] * np.eye(3)  # a point on parallel rays: any depth
    return np.linalg.solve(H, g[:, :, None])[:, :, 0]


def _solve_group(P, weight, obs_frame, obs_track, frames, start, n_points) -> np.ndarray:
    """Centres (len(frames), 3) of one rigid group minimising the weighted ray residuals with the points
    eliminated (Schur complement), its centroid and its spread along the start held to the start's."""
    m = len(frames)
    local = np.full(obs_frame.max() + 1, -1)
    local[frames] = np.arange(m)
    sel = local[obs_frame] >= 0
    f, t, wP = local[obs_frame[sel]], obs_track[sel], weight[sel, None, None] * P[sel]
    H = np.zeros((n_points, 3, 3))
    np.add.at(H, t, wP)
    H += 1e-12 * np.trace(H, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    H[np.bincount(t, minlength=n_points) == 0] = np.eye(3)  # another group's points: not in this solve
    Hinv = np.linalg.inv(H)
    S = np.zeros((m, 3, m, 3))
    np.add.at(S, (f, slice(None), f), wP)  # the cameras' own blocks
    # the points' elimination: -sum over pairs of observations (a, b) of one point of wP_a H^-1 wP_b
    order = np.argsort(t, kind="stable")
    t_sorted = t[order]
    starts = np.searchsorted(t_sorted, np.arange(n_points))
    lengths = np.bincount(t_sorted, minlength=n_points)
    a = np.repeat(order, lengths[t_sorted])
    offs = np.arange(len(a)) - np.repeat(np.cumsum(lengths[t_sorted]) - lengths[t_sorted], lengths[t_sorted])
    b = order[np.repeat(starts[t_sorted], lengths[t_sorted]) + offs]
    blocks = np.matmul(np.matmul(wP[a], Hinv[t[a]]), wP[b])  # a 3-operand einsum of 3 x 3 blocks: 2x slower
    np.add.at(S, (f[a], slice(None), f[b]), -blocks)
    S = S.reshape(3 * m, 3 * m)
    S = 0.5 * (S + S.T)
    # gauge: the group's centroid and its spread along the start's (translation and scale are free)
    c0 = start.mean(axis=0)
    A = np.zeros((4, 3 * m))
    A[:3] = np.tile(np.eye(3), m)
    A[3] = (start - c0).ravel()
    rhs = np.r_[m * c0, (start - c0).ravel() @ start.ravel()]
    ridge = 1e-9 * max(float(np.trace(S)) / (3 * m), 1e-300)  # a frame free along a direction stays put
    K = np.block([[S + ridge * np.eye(3 * m), A.T], [A, np.zeros((4, 4))]])
    x = np.linalg.lstsq(K, np.r_[ridge * start.ravel(), rhs], rcond=None)[0]
    return x[:3 * m].reshape(m, 3)


def _onto_measured(C: np.ndarray, measured: list[MeasuredPose]) -> np.ndarray:
    """``s C + t`` with the scale and shift that best fit the measured centres, each weighed by its
    position tolerance (a frame with an infinite tolerance does not pull); unchanged when nothing pulls."""
    meas = np.stack([m.pose.centre for m in measured])
    tol = np.stack([m.tolerance.position_mm for m in measured])
    w = np.where(np.isfinite(tol), 1.0 / np.maximum(tol, 1e-6) ** 2, 0.0)  # (m, 3) per axis
    if np.count_nonzero(w.sum(axis=1)) < 2:
        return C
    # unknowns s, t (4): rows w^1/2 (s C + t - meas) per axis
    J = np.zeros((len(C), 3, 4))
    J[:, :, 0] = C
    J[:, :, 1:] = np.eye(3)
    sw = np.sqrt(w)
    x = np.linalg.lstsq((J * sw[:, :, None]).reshape(-1, 4), (meas * sw).ravel(), rcond=None)[0]
    return x[0] * C + x[1:]
