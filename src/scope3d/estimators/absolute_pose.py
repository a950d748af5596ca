"""The pose of one camera from 2-D/3-D correspondences: robust PnP, then pose-only bound-constrained refinement.

Two stages, as the reference localizes a frame against its map (sec. 5.1: "SIFT and RANSAC ... then a
constrained bundle adjustment to solely recover pose information since the 3D scene and its 2D projection
were known"):

1. :func:`estimate_absolute_pose` runs OpenCV's ``solvePnPRansac`` (EPnP minimal solver, USAC loop with a
   seeded random state) on undistorted pixels;
2. :func:`refine_pose` refines it with every point and the intrinsics held fixed, Huber loss, and — when
   the frame comes with a reported pose — every pose scalar kept inside the reported
   :class:`~scope3d.sensor.pose_tolerance.PoseTolerance` box (BCBA, eq. 6.2, with the points fixed). An
   infinite tolerance leaves the scalar free: the image alone decides.

A frame is never given a pose it cannot support: too few correspondences, too few inliers, inliers
bunched in a small patch of the image (rotation and translation trade off there) or all on one line, and
a RANSAC pose that the reported box cannot hold, each return a status other than ``"ok"`` and no pose.

Units: mm and radians; pixels with their origin at the top-left pixel's centre.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import _SMALL_ANGLE_RAD, matrix_to_rotvec, rotvec_to_matrix
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose

#: Outcomes of one estimate. Only ``"ok"`` carries a pose.
POSE_STATUSES = ("ok", "too_few_matches", "too_few_inliers", "degenerate", "outside_tolerance")

# a Gaussian keypoint error of sigma px has a 2-D norm whose median is 1.1774 sigma (Rayleigh)
_RAYLEIGH_MEDIAN = 1.1774


@dataclass(frozen=True)
class AbsolutePoseOptions:
    """How one camera's pose is estimated from correspondences.

    ransac_threshold_px : float, RANSAC inlier threshold on undistorted pixels (default 4 px: SIFT keypoints
        are good to ~0.5 px, the map's points reproject to ~0.3 px, and the minimal-sample poses of EPnP are
        rougher than the refined one; the refinement re-selects inliers at ``inlier_threshold_px``).
    inlier_threshold_px : float, final inliers: reprojection error under the refined pose (default 2 px,
        about 4 sigma of the ~0.5 px keypoint error).
    ransac_confidence : float, USAC's confidence (default 0.9999).
    max_ransac_iterations : int, cap on RANSAC samples (default 2000: a 20 % inlier ratio with 4-point
        samples needs ~5700 at 0.9999, 30 % ~1100; a lower ratio is not a localizable frame anyway).
    min_inliers : int, fewer final inliers is ``"too_few_inliers"`` (default 15: 6 degrees of freedom and
        a check that a wrong pose with 4-6 chance agreements cannot pass).
    min_inlier_ratio : float, final inliers over correspondences below this is ``"too_few_inliers"``
        (default 0.1: with random correspondences, a wrong pose collects a few percent).
    min_spread_fraction : float, the inliers' spread (square root of the smaller eigenvalue of their pixel
        covariance) over the image's smaller side; below it the frame is ``"degenerate"`` (default 0.03:
        points within a few percent of the view, or all on one line, fix rotation against translation
        poorly).
    loss_scale_px : float, Huber scale of the refinement (default 1 px, two sigmas of SIFT's error).
    refine_iterations : int, cap on the refinement's iterations (default 20: from a RANSAC start the
        pose-only problem converges in 3-6).
    seed : int, USAC's random state.
    """

    ransac_threshold_px: float = 4.0
    inlier_threshold_px: float = 2.0
    ransac_confidence: float = 0.9999
    max_ransac_iterations: int = 2000
    min_inliers: int = 15
    min_inlier_ratio: float = 0.1
    min_spread_fraction: float = 0.03
    loss_scale_px: float = 1.0
    refine_iterations: int = 20
    seed: int = 0

    def __post_init__(self) -> None:
        if not (self.ransac_threshold_px > 0 and self.inlier_threshold_px > 0 and self.loss_scale_px > 0):
            raise ValueError("thresholds and the loss scale must be positive pixels")
        if not 0 < self.ransac_confidence < 1:
            raise ValueError(f"ransac_confidence must be in (0, 1), got {self.ransac_confidence}")
        if self.max_ransac_iterations < 1 or self.refine_iterations < 0:
            raise ValueError("need max_ransac_iterations >= 1 and refine_iterations >= 0")
        if self.min_inliers < 6:
            raise ValueError(f"min_inliers must be >= 6 (a pose has 6 degrees of freedom), got {self.min_inliers}")
        if not 0 <= self.min_inlier_ratio < 1 or not 0 <= self.min_spread_fraction < 0.5:
            raise ValueError("min_inlier_ratio must be in [0, 1) and min_spread_fraction in [0, 0.5)")


@dataclass
class AbsolutePoseResult:
    """One estimate.

    status : one of :data:`POSE_STATUSES`; pose : ``cam_from_world`` when ``"ok"``, else None.
    inliers : (N,) bool over the correspondences given (all False when no pose).
    covariance : (6, 6) of ``(w (rad, left rotation about the world axes), centre (mm))`` from the
        refinement's curvature and the residuals' noise, when ``"ok"``; else None.
    rms_px : RMS reprojection error of the inliers. time_s : wall time.
    """

    status: str
    pose: Pose | None
    inliers: np.ndarray
    covariance: np.ndarray | None = None
    rms_px: float = float("nan")
    time_s: float = 0.0

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    @property
    def position_sigma_mm(self) -> np.ndarray:
        """(3,) standard deviation of the centre per world axis (inf without a pose)."""
        if self.covariance is None:
            return np.full(3, np.inf)
        return np.sqrt(np.diag(self.covariance)[3:])

    @property
    def orientation_sigma_rad(self) -> np.ndarray:
        if self.covariance is None:
            return np.full(3, np.inf)
        return np.sqrt(np.diag(self.covariance)[:3])


def undistorted_pixels(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    """(N, 2) observed pixels -> (N, 2) pixels of the same rays through the distortion-free pinhole ``K``."""
    n = camera.pixel_to_normalised(np.asarray(pixels, float))
    return np.stack([camera.fx * n[:, 0] + camera.cx, camera.fy * n[:, 1] + camera.cy], axis=1)


def _ransac_pnp(camera: Camera, points_world: np.ndarray, pixels_ud: np.ndarray, options: AbsolutePoseOptions
                ) -> tuple[Pose | None, np.ndarray]:
    params = cv2.UsacParams()
    params.threshold = options.ransac_threshold_px
    params.confidence = options.ransac_confidence
    params.maxIterations = options.max_ransac_iterations
    params.randomGeneratorState = options.seed
    params.loIterations = 0
    params.final_polisher = cv2.NONE_POLISHER
    params.isParallel = False
    obj = np.ascontiguousarray(points_world, np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(pixels_ud, np.float64).reshape(-1, 1, 2)
    try:
        found, _, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, camera.K.copy(), None, params=params)
    except cv2.error:
        found = False
    mask = np.zeros(len(points_world), bool)
    if not found or inl is None or rvec is None:
        return None, mask
    mask[np.asarray(inl).ravel()] = True
    rotation = rotvec_to_matrix(np.asarray(rvec, float).ravel())
    return Pose(rotation, np.asarray(tvec, float).ravel()), mask


def _reprojection(camera: Camera, pose: Pose, points_world: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(N,) reprojection error (px, observed image); inf behind the camera."""
    cam = pose.transform(points_world)
    err = np.full(len(points_world), np.inf)
    front = cam[:, 2] > 1e-6
    if np.any(front):
        err[front] = np.linalg.norm(camera.project(cam[front]) - pixels[front], axis=1)
    return err


def _spread_px(pixels: np.ndarray) -> float:
    """Square root of the smaller eigenvalue of the pixels' covariance: 0 for points on a line or at a point."""
    if len(pixels) < 3:
        return 0.0
    return float(np.sqrt(max(np.linalg.eigvalsh(np.cov(pixels.T))[0], 0.0)))


def refine_pose(camera: Camera, points_world: np.ndarray, pixels: np.ndarray, start: Pose,
                reported: MeasuredPose | None, options: AbsolutePoseOptions) -> tuple[Pose, np.ndarray]:
    """Pose-only bound-constrained adjustment: points and intrinsics fixed, the pose kept inside
    ``reported``'s box (free where its tolerance is infinite, or everywhere without a report), Huber loss.

    The parameters are those of the tolerance (and of the bundle engine's BCBA, eq. 6.2): a left rotation
    ``w`` with ``R = exp([w]x) R_ref`` (rad) and the centre ``C`` (mm), ``R_ref`` and the box centred on
    the reported pose (on ``start`` without a report). A zero half-width fixes its scalar. Solved by
    Levenberg-Marquardt on the six scalars with Huber weights (IRLS), each step projected into the box —
    the bundle engine's method (:mod:`scope3d.estimators.bundle`, eq. 6.9-6.13) reduced to one camera. The
    engine itself solves this problem too, with every point fixed, but its set-up is built for thousands
    of cameras and took 12-19 ms per frame, over half a video frame's 33 ms. Each iteration's sums run in one
    compiled pass (:func:`_huber_normal_equations`).

    points_world : (N, 3) mm; pixels : (N, 2) observed. Returns the refined pose and the (6, 6) covariance of
    ``(w, C)`` (rad, mm): ``sigma^2 (J^T J)^-1`` with the Huber-weighted Jacobian and sigma from the
    residuals' median norm; zero rows and columns for fixed scalars.
    """
    ref = reported.pose if reported is not None else start
    half = (np.concatenate([reported.tolerance.orientation_rad, reported.tolerance.position_mm])
            if reported is not None else np.full(6, np.inf))
    ref_rotation = np.ascontiguousarray(ref.rotation, float)
    value = np.concatenate([np.zeros(3), ref.centre])
    lower, upper = value - half, value + half
    x = np.clip(np.concatenate([matrix_to_rotvec(start.rotation @ ref_rotation.T), start.centre]), lower, upper)
    free = half > 0
    x[~free] = value[~free]
    points_world = np.ascontiguousarray(points_world, float)
    pixels = np.ascontiguousarray(pixels, float)
    intrinsics = np.ascontiguousarray(camera.intrinsics, float)

    def normal_equations(x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """Huber cost, Gauss-Newton matrix (6, 6), gradient (6,) of ``(w, C)`` and residual norms (N,) px."""
        return _huber_normal_equations(points_world, pixels, x, ref_rotation, intrinsics, options.loss_scale_px)

    cost, hessian, gradient, norm = normal_equations(x)
    damping = 1e-4
    for _ in range(options.refine_iterations if np.any(free) else 0):
        h, g = hessian[np.ix_(free, free)], gradient[free]
        diag = np.maximum(np.diag(h), 1e-12)
        improved = False
        while damping < 1e16:
            step = np.linalg.solve(h + damping * np.diag(diag), -g)
            candidate = x.copy()
            candidate[free] = np.clip(x[free] + step, lower[free], upper[free])
            cost_new, hessian_new, gradient_new, norm_new = normal_equations(candidate)
            if cost_new < cost:
                improved = True
                done = cost - cost_new < 1e-10 * cost or np.abs(candidate - x).max() < 1e-12
                x, cost, hessian, gradient, norm = candidate, cost_new, hessian_new, gradient_new, norm_new
                damping = max(damping / 10.0, 1e-12)
                break
            damping *= 10.0
        if not improved or done:
            break
    sigma = max(float(np.median(norm)) / _RAYLEIGH_MEDIAN, 1e-3)
    cov = np.zeros((6, 6))
    if np.any(free):
        cov[np.ix_(free, free)] = sigma**2 * np.linalg.pinv(hessian[np.ix_(free, free)])
    rotation = rotvec_to_matrix(x[:3]) @ ref_rotation
    return Pose.from_centre(rotation, x[3:]), cov


def estimate_absolute_pose(
    camera: Camera, points_world: np.ndarray, pixels: np.ndarray, *, reported: MeasuredPose | None = None,
    options: AbsolutePoseOptions = AbsolutePoseOptions(),
) -> AbsolutePoseResult:
    """The camera's ``cam_from_world`` from correspondences, or an honest failure.

    Parameters
    ----------
    camera : intrinsics (held fixed).
    points_world : (N, 3) float, mm, map points.
    pixels : (N, 2) float, their observations in this frame (distorted image, origin at the top-left pixel's
        centre).
    reported : the robot's pose for this frame with its tolerance, or None. With a finite tolerance the
        refinement stays inside the box, and when the box's best pose keeps fewer than half the inliers the
        free RANSAC pose had, image and report disagree: ``"outside_tolerance"``. An infinite tolerance is
        the image alone.
    options : :class:`AbsolutePoseOptions`.
    """
    t0 = time.perf_counter()
    points_world = np.asarray(points_world, float).reshape(-1, 3)
    pixels = np.asarray(pixels, float).reshape(-1, 2)
    if len(points_world) != len(pixels):
        raise ValueError(f"{len(points_world)} points but {len(pixels)} pixels")
    n = len(points_world)
    none = np.zeros(n, bool)

    def fail(status: str, inliers=none) -> AbsolutePoseResult:
        return AbsolutePoseResult(status, None, inliers, time_s=time.perf_counter() - t0)

    if n < options.min_inliers:
        return fail("too_few_matches")
    start, ransac_inliers = _ransac_pnp(camera, points_world, undistorted_pixels(camera, pixels), options)
    if start is None or ransac_inliers.sum() < options.min_inliers:
        return fail("too_few_inliers")
    if _spread_px(pixels[ransac_inliers]) < options.min_spread_fraction * min(camera.width, camera.height):
        return fail("degenerate", ransac_inliers)
    pose, cov = refine_pose(camera, points_world[ransac_inliers], pixels[ransac_inliers], start, reported, options)
    err = _reprojection(camera, pose, points_world, pixels)
    inliers = err <= options.inlier_threshold_px
    if reported is not None and np.any(np.isfinite(reported.tolerance.position_mm)):
        # inside the box the refinement could not bring the image's inliers together: the image and the
        # report disagree, and neither pose is to be trusted
        free_err = _reprojection(camera, start, points_world, pixels)
        if inliers.sum() < 0.5 * np.count_nonzero(free_err <= options.ransac_threshold_px):
            return fail("outside_tolerance", inliers)
    if inliers.sum() < max(options.min_inliers, options.min_inlier_ratio * n):
        return fail("too_few_inliers", inliers)
    if _spread_px(pixels[inliers]) < options.min_spread_fraction * min(camera.width, camera.height):
        return fail("degenerate", inliers)
    rms = float(np.sqrt(np.mean(err[inliers] ** 2)))
    return AbsolutePoseResult("ok", pose, inliers, cov, rms, time.perf_counter() - t0)


@njit(cache=True, nogil=True)
def _huber_normal_equations(points_world, pixels, x, ref_rotation, intrinsics, loss_scale):
    """One pass over the correspondences of the pose-only problem (:func:`refine_pose`).

    points_world (N, 3) mm, pixels (N, 2) observed, the parameters ``x = (w, C)`` (rad, mm) of the pose
    ``x_cam = exp([w]x) ref_rotation (X - C)``, intrinsics ``(fx, fy, cx, cy, k1, k2)``, the Huber scale
    (px). Returns the Huber cost, ``H = sum w_i J_i^T J_i`` (6, 6) and ``g = sum w_i J_i^T r_i`` (6,)
    with the IRLS weights ``w_i`` and ``J_i = d r_i / d (w, C)``, and the residual norms (N,) px. Fused
    into one compiled loop: the same sums in NumPy took ~0.7 ms an iteration for 200 points (temporaries
    of shape (N, 2, 6)) and the rotation's helpers as much again: ~10 ms a frame, a third of a video
    frame's budget.
    """
    exp_w, left_jacobian = _exp_and_left_jacobian(x[:3])
    rotation = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            rotation[a, b] = exp_w[a, 0] * ref_rotation[0, b] + exp_w[a, 1] * ref_rotation[1, b] + exp_w[a, 2] * ref_rotation[2, b]
    centre = x[3:]
    fx, fy, cx, cy, k1, k2 = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3], intrinsics[4], intrinsics[5]
    n = points_world.shape[0]
    hessian = np.zeros((6, 6))
    gradient = np.zeros(6)
    norms = np.empty(n)
    cost = 0.0
    p = np.empty(3)
    d_cam = np.empty((2, 3))
    jac = np.empty((2, 6))
    for i in range(n):
        for a in range(3):
            p[a] = (rotation[a, 0] * (points_world[i, 0] - centre[0]) + rotation[a, 1] * (points_world[i, 1] - centre[1])
                    + rotation[a, 2] * (points_world[i, 2] - centre[2]))
        inv_z = 1.0 / p[2]
        x = p[0] * inv_z
        y = p[1] * inv_z
        r2 = x * x + y * y
        d = 1.0 + k1 * r2 + k2 * r2 * r2
        ru = fx * d * x + cx - pixels[i, 0]
        rv = fy * d * y + cy - pixels[i, 1]
        dd = k1 + 2.0 * k2 * r2
        # d (u, v) / d (x, y), then d (x, y) / d p = [[1/z, 0, -x/z], [0, 1/z, -y/z]]
        a00 = fx * (d + 2.0 * x * x * dd)
        a01 = fx * 2.0 * x * y * dd
        a10 = fy * 2.0 * x * y * dd
        a11 = fy * (d + 2.0 * y * y * dd)
        d_cam[0, 0] = a00 * inv_z
        d_cam[0, 1] = a01 * inv_z
        d_cam[0, 2] = -(a00 * x + a01 * y) * inv_z
        d_cam[1, 0] = a10 * inv_z
        d_cam[1, 1] = a11 * inv_z
        d_cam[1, 2] = -(a10 * x + a11 * y) * inv_z
        for r in range(2):
            # d p / d w = -[p]x J_l ; d p / d C = -R
            m0 = d_cam[r, 2] * p[1] - d_cam[r, 1] * p[2]  # row r of -D [p]x
            m1 = d_cam[r, 0] * p[2] - d_cam[r, 2] * p[0]
            m2 = d_cam[r, 1] * p[0] - d_cam[r, 0] * p[1]
            for b in range(3):
                jac[r, b] = m0 * left_jacobian[0, b] + m1 * left_jacobian[1, b] + m2 * left_jacobian[2, b]
                jac[r, 3 + b] = -(d_cam[r, 0] * rotation[0, b] + d_cam[r, 1] * rotation[1, b] + d_cam[r, 2] * rotation[2, b])
        norm = np.sqrt(ru * ru + rv * rv)
        norms[i] = norm
        if norm <= loss_scale:
            cost += 0.5 * norm * norm
            weight = 1.0
        else:
            cost += loss_scale * norm - 0.5 * loss_scale * loss_scale
            weight = loss_scale / max(norm, 1e-300)
        for a in range(6):
            gradient[a] += weight * (jac[0, a] * ru + jac[1, a] * rv)
            for b in range(a, 6):
                hessian[a, b] += weight * (jac[0, a] * jac[0, b] + jac[1, a] * jac[1, b])
    for a in range(6):
        for b in range(a):
            hessian[a, b] = hessian[b, a]
    return cost, hessian, gradient, norms


@njit(cache=True, nogil=True)
def _exp_and_left_jacobian(w):
    """``exp([w]x)`` (3, 3) and the SO(3) left Jacobian (3, 3) of the rotation vector ``w`` (rad): the maths
    of :func:`~scope3d.geometry.rotation.rotvec_to_matrix` and :func:`~scope3d.geometry.rotation.so3_left_jacobian`
    (Taylor series near zero), compiled for the refinement's inner loop."""
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    theta = np.sqrt(theta2)
    # the series thresholds of rotvec_to_matrix and so3_left_jacobian
    if theta < _SMALL_ANGLE_RAD:
        a, b = 1.0 - theta2 / 6.0, 0.5 - theta2 / 24.0
    else:
        a, b = np.sin(theta) / theta, (1.0 - np.cos(theta)) / theta2
    if theta < 1e-5:
        b_jac, c = 0.5 - theta2 / 24.0, 1.0 / 6.0 - theta2 / 120.0
    else:
        b_jac, c = (1.0 - np.cos(theta)) / theta2, (theta - np.sin(theta)) / (theta2 * theta)
    # [w]x and [w]x^2 = w w^T - theta^2 I, entry by entry (small arrays cost more than the arithmetic)
    rotation = np.empty((3, 3))
    jacobian = np.empty((3, 3))
    for r in range(3):
        for q in range(3):
            k2 = w[r] * w[q] - (theta2 if r == q else 0.0)
            if r == q:
                k = 0.0
            else:
                k = -w[3 - r - q] if (q - r) % 3 == 1 else w[3 - r - q]
            one = 1.0 if r == q else 0.0
            rotation[r, q] = one + a * k + b * k2
            jacobian[r, q] = one + b_jac * k + c * k2
    return rotation, jacobian
