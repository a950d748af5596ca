"""The pose of one camera from 2-D/3-D correspondences: robust PnP, then pose-only bound-constrained refinement.

Two stages, as the reference localizes a frame against its map (sec. 5.1: "SIFT and RANSAC ... then a
constrained bundle adjustment to solely recover pose information since the 3D scene and its 2D projection
were known"):

1. :func:`estimate_absolute_pose` runs OpenCV's ``solvePnPRansac`` (EPnP minimal solver, USAC loop with a
   seeded random state) on undistorted pixels, i.e. on the correspondences whose rays lie in front of the
   camera plane (a fisheye's rays past 90 deg from the axis have no undistorted pixel; the minimal solver
   needs only some of the rays);
2. :func:`refine_pose` refines it with every point and the intrinsics held fixed, Huber loss, and — when
   the frame comes with a reported pose — every pose scalar kept inside the reported
   :class:`~scope3d.sensor.pose_tolerance.PoseTolerance` box (BCBA, eq. 6.2, with the points fixed). An
   infinite tolerance leaves the scalar free: the image alone decides. The final inliers (2 px) are those
   of the refined pose, and the pose is refined again on exactly them until they stop changing.

A frame is never given a pose it cannot support: too few correspondences, too few inliers, inliers
bunched in a small patch of the image (rotation and translation trade off there) or all on one line, a
RANSAC pose that the reported box cannot hold, and a pose its own covariance fixes no better than a stated
fraction of its depth (``"imprecise"``), each return a status other than ``"ok"`` and no pose.

Every test after the minimal solver is made through the lens model itself (its projection and analytic
Jacobians), so a point a fisheye sees past 90 deg from its axis counts as an inlier and holds the pose like
any other.

Units: mm and radians; pixels with their origin at the top-left pixel's centre.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import SMALL_ANGLE_RAD, hat, matrix_to_rotvec, rotvec_to_matrix, so3_left_jacobian
from scope3d.sensor.camera import Camera
from scope3d.sensor.camera_models import DEFAULT_MODEL
from scope3d.sensor.pose_tolerance import MeasuredPose
from scope3d.utils.aot import load_kernels

# compiled at install (scope3d.utils.aot) or, failing that, by numba on first use
_kernels = load_kernels("scope3d.estimators.pose_kernels")

#: Outcomes of one estimate. Only ``"ok"`` carries a pose.
POSE_STATUSES = ("ok", "too_few_matches", "too_few_inliers", "degenerate", "outside_tolerance", "imprecise")

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
    max_centre_sigma_fraction : float, the pose's own covariance must hold its centre to 3 sigma (along the
        worst direction) within this fraction of the inliers' median depth, else ``"imprecise"`` (default
        0.02: at the reference's 15 mm stand-off 0.3 mm, more than the robot's own +-0.25 mm, so such a pose
        tells the robot nothing; measured: the real scenes' poses of docs/localization.md within 1.8 % of
        their depth, the dome approaches' SIFT frames within 1.5 %, median 0.15 %). inf switches it off.
    final_refinements : int, at most this many times the pose is refined again on the final inliers of the
        last refinement, until they stop changing (default 3; 0: the pose refined on RANSAC's inliers only).
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
    final_refinements: int = 3
    max_centre_sigma_fraction: float = 0.02
    seed: int = 0

    def __post_init__(self) -> None:
        if not (self.ransac_threshold_px > 0 and self.inlier_threshold_px > 0 and self.loss_scale_px > 0):
            raise ValueError("thresholds and the loss scale must be positive pixels")
        if not 0 < self.ransac_confidence < 1:
            raise ValueError(f"ransac_confidence must be in (0, 1), got {self.ransac_confidence}")
        if self.max_ransac_iterations < 1 or self.refine_iterations < 0 or self.final_refinements < 0:
            raise ValueError("need max_ransac_iterations >= 1, refine_iterations >= 0 and final_refinements >= 0")
        if self.min_inliers < 6:
            raise ValueError(f"min_inliers must be >= 6 (a pose has 6 degrees of freedom), got {self.min_inliers}")
        if not self.max_centre_sigma_fraction > 0:
            raise ValueError(f"max_centre_sigma_fraction must be > 0, got {self.max_centre_sigma_fraction}")
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
    """(N,) reprojection error (px, observed image); inf where the lens cannot see the point (behind the
    camera plane for the pinhole family, beyond the field's half-angle for a fisheye, past 90 deg too)."""
    cam = pose.transform(points_world)
    err = np.full(len(points_world), np.inf)
    seen = camera.lens.in_field(camera.params, cam) if camera.lens.is_fisheye else cam[:, 2] > 1e-6
    if np.any(seen):
        err[seen] = np.linalg.norm(camera.project(cam[seen]) - pixels[seen], axis=1)
    return np.where(np.isfinite(err), err, np.inf)


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
    compiled pass (:func:`scope3d.estimators.pose_kernels.huber_normal_equations`).

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
    radial = camera.model == DEFAULT_MODEL
    intrinsics = np.ascontiguousarray(camera.intrinsics, float) if radial else None

    def normal_equations(x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """Huber cost, Gauss-Newton matrix (6, 6), gradient (6,) of ``(w, C)`` and residual norms (N,) px."""
        if not radial:  # another lens: its analytic Jacobians in NumPy (the compiled loop is the radial model's)
            return _lens_normal_equations(camera, points_world, pixels, x, ref_rotation, float(options.loss_scale_px))
        return _kernels.huber_normal_equations(points_world, pixels, x, ref_rotation, intrinsics,
                                               float(options.loss_scale_px), SMALL_ANGLE_RAD)

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


def _lens_normal_equations(camera: Camera, points_world: np.ndarray, pixels: np.ndarray, x: np.ndarray,
                           ref_rotation: np.ndarray, loss_scale: float) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`scope3d.estimators.pose_kernels.huber_normal_equations` through any lens model, in NumPy: the
    pixel's Jacobian with respect to the camera-frame point is the model's analytic one
    (:meth:`Camera.project_with_jacobians`), then ``d p / d w = -[p]x J_l(w)`` and ``d p / d C = -R`` as in
    the kernel. Same cost, weights and returns."""
    rotation = rotvec_to_matrix(x[:3]) @ ref_rotation
    p = (points_world - x[3:]) @ rotation.T
    projected, d_cam, _ = camera.project_with_jacobians(p)
    residual = projected - pixels
    jac = np.concatenate([-d_cam @ hat(p) @ so3_left_jacobian(x[:3]), -d_cam @ rotation], axis=2)  # (N, 2, 6)
    norms = np.linalg.norm(residual, axis=1)
    inside = norms <= loss_scale
    cost = float(np.sum(np.where(inside, 0.5 * norms**2, loss_scale * norms - 0.5 * loss_scale**2)))
    weight = np.where(inside, 1.0, loss_scale / np.maximum(norms, 1e-300))
    hessian = np.einsum("n,nri,nrj->ij", weight, jac, jac)
    gradient = np.einsum("n,nri,nr->i", weight, jac, residual)
    return cost, hessian, gradient, norms


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
    ahead = camera.unproject(pixels)[:, 2] > 0  # rays with an undistorted pixel (all of a pinhole's)
    start, inliers_ahead = _ransac_pnp(camera, points_world[ahead], undistorted_pixels(camera, pixels[ahead]), options)
    ransac_inliers = np.zeros(n, bool)
    ransac_inliers[ahead] = inliers_ahead
    if start is None or ransac_inliers.sum() < options.min_inliers:
        return fail("too_few_inliers")
    if _spread_px(pixels[ransac_inliers]) < options.min_spread_fraction * min(camera.width, camera.height):
        return fail("degenerate", ransac_inliers)
    pose, cov = refine_pose(camera, points_world[ransac_inliers], pixels[ransac_inliers], start, reported, options)
    err = _reprojection(camera, pose, points_world, pixels)
    inliers = err <= options.inlier_threshold_px
    refined_on = ransac_inliers
    for _ in range(options.final_refinements):
        # the pose refined on exactly its final inliers: RANSAC's looser gate let points in that the final
        # gate drops (and the refined pose may bring back some that RANSAC's rough one missed)
        if np.array_equal(inliers, refined_on) or inliers.sum() < options.min_inliers:
            break
        pose, cov = refine_pose(camera, points_world[inliers], pixels[inliers], pose, reported, options)
        refined_on = inliers
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
    seen = pose.transform(points_world[inliers])
    # the scale of the scene: the z-depth, or the range where the lens sees past 90 deg (z changes sign there)
    depth = float(np.median(np.linalg.norm(seen, axis=1) if camera.max_half_angle_rad > np.pi / 2 else seen[:, 2]))
    worst_sigma = float(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:])[-1], 0.0)))
    if 3.0 * worst_sigma > options.max_centre_sigma_fraction * depth:
        # the inliers agree with the pose but fix it too loosely to be used (few, or bunched in depth)
        return fail("imprecise", inliers)
    rms = float(np.sqrt(np.mean(err[inliers] ** 2)))
    return AbsolutePoseResult("ok", pose, inliers, cov, rms, time.perf_counter() - t0)
