"""Mapping with known-but-inaccurate poses: bundle adjustment set-up, the adjustment rounds, and the poses
that guide matching when the robot's are too coarse (reference chapters 3, 4 and 6).

* :func:`bundle_problem` — the problem of a pose mode: ``fixed`` (poses trusted, points refined — the
  reference's chapter 3-4 method), ``free`` (conventional BA, gauge fixed by the first camera and one
  coordinate of the farthest), ``bounded`` (BCBA, chapter 6: every pose scalar within its measured box).
* :func:`adjust_map` — triangulate, adjust, align the gauge, re-triangulate; a second round when the
  poses moved.
* :func:`refine_poses_for_matching` — the reference's "combination algorithm" (sec. 3.5): BCBA on a
  coarse pass's tracks, and the tolerance the images leave each adjusted pose, for predicting the fine
  matching pass.

Units: mm and radians; pixels with their origin at the top-left pixel's centre. Poses are ``cam_from_world``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from scope3d.errors import InputError
from scope3d.estimators.bundle import BundleProblem, BundleResult, SolverOptions, solve
from scope3d.estimators.bundle.covariance import marginal_sigmas, pairwise_pose_covariances, reduced_camera_system
from scope3d.estimators.bundle.problem import camera_from_block, lens_block
from scope3d.estimators.gauge import align_gauge
from scope3d.estimators.triangulation import TrackOptions, reprojection_errors, triangulate_tracks
from scope3d.feature.depth_prior import DepthPrior, pose_error_px
from scope3d.feature.detection import Features
from scope3d.feature.matching import PairMatches
from scope3d.feature.pairs import fov_samples
from scope3d.feature.tracks import build_tracks
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.scene.surface import OFF_SURFACE_FLOORS_MM, off_surface_points
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import INTRINSIC_NAMES, Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.depth_priors import points_depth_prior
from scope3d.utils.robust import robust_norm_sigma

POSE_MODES = ("fixed", "free", "bounded")


@dataclass(frozen=True)
class BundleStageOptions:
    """Bundle adjustment as the map uses it.

    max_iterations : int, LM iterations per adjustment (default 60: exact poses converge in a few,
        a robot's poses several mm off need ~50 in the first round).
    loss_scale_px : float, Huber loss scale (default 1.0 px: SIFT localisation ~0.3-0.5 px, so a
        residual beyond 1 px is downweighted as a likely wrong match).
    max_points : int, the adjustment uses at most this many tracks, the longest first (default 6000):
        poses are fixed by a few thousand well-spread points; the rest are re-triangulated with the
        adjusted poses, which is exact for them and costs nothing. It does not bound the map's points:
        every track is re-triangulated after the adjustment (500 or 100 000 give the same points).
    refine_intrinsics : bool, let the intrinsics move (default False: the scope is calibrated, and
        with a short-baseline survey focal length and depth trade off).
    intrinsic_bounds : ((P,), (P,)) tuples or None, a box ``(lower, upper)`` on ``(fx, fy, cx, cy, k1, k2)``
        (P = 6) and, beyond them, on the camera model's later parameters in
        :attr:`scope3d.estimators.bundle.BundleProblem.intrinsic_names` order (OPENCV's p1, p2; FULL_OPENCV's
        p1, p2, k3..k6; the fisheye's k3, k4): from ``scope3d calibrate``'s intrinsic_bounds.json, the
        calibration's value +- k sigma, the reference's FOV range of sec. 6.3. NaN in both holds that
        intrinsic fixed (so do the later parameters beyond P); +-inf leaves a side unbounded. Used only with
        ``refine_intrinsics``.
    align_gauge : bool, after free or bounded BA with inexact poses, move the map to the similarity frame
        that best fits all measured poses (:func:`scope3d.estimators.gauge.align_gauge`; default True). After
        bounded BA this finishes what its box prior (:func:`adjust`) asks for along the similarities, where
        the adjustment converges slowly, as far as the boxes allow.
    settled_mm, settled_rad : no second adjustment round when no camera moved more than ``settled_mm``
        in the first and none turned more than ``settled_rad`` (defaults 0.02 mm, twice a micro-stage's
        tolerance, and 2e-4 rad, which moves a point by a tenth of a pixel at a focal length of 600 px).
    """

    max_iterations: int = 60
    loss_scale_px: float = 1.0
    max_points: int = 6000
    refine_intrinsics: bool = False
    intrinsic_bounds: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    align_gauge: bool = True
    settled_mm: float = 0.02
    settled_rad: float = 2e-4

    def __post_init__(self) -> None:
        if self.max_iterations < 0 or self.loss_scale_px <= 0 or self.max_points < 10:
            raise ValueError("need max_iterations >= 0, loss_scale_px > 0, max_points >= 10")
        if not (self.settled_mm >= 0 and self.settled_rad >= 0):
            raise ValueError("need settled_mm >= 0 and settled_rad >= 0")
        if self.intrinsic_bounds is not None:
            lower, upper = (np.asarray(b, dtype=float) for b in self.intrinsic_bounds)
            if lower.ndim != 1 or lower.size < 6 or lower.shape != upper.shape or np.any(lower > upper):
                raise ValueError("intrinsic_bounds must be two (P,) arrays, P >= 6, with lower <= upper")

    def solver(self) -> SolverOptions:
        return SolverOptions(max_iterations=self.max_iterations, loss="huber", loss_scale_px=self.loss_scale_px)


# --- the bundle problem ------------------------------------------------------------------------


def bundle_problem(mode: str, measured: list[MeasuredPose], camera: Camera, tracks: Tracks, *,
                   refine_intrinsics: bool = False, start: list[Pose] | None = None,
                   intrinsic_bounds: tuple | None = None) -> BundleProblem:
    """The bundle problem of ``mode`` on ``tracks`` (observations and points in mm world).

    bounded : the measured boxes, starting from ``start`` (clipped into them) when given;
    free : conventional BA from ``start`` (default: the measured poses), gauge fixed on the start
        (:func:`fix_gauge`);
    fixed : the measured poses held.
    intrinsic_bounds : (lower, upper) (P,) box on the intrinsics when they are refined, in
        ``problem.intrinsic_names`` order (NaN: held fixed; see :class:`BundleStageOptions`).
    """
    if mode not in POSE_MODES:
        raise ValueError(f"mode must be one of {POSE_MODES}, got {mode!r}")
    pts = tracks.points
    if mode == "bounded":
        problem = BundleProblem.from_measured_poses(
            measured, camera, pts, tracks.pixels, tracks.frame, tracks.track, refine_intrinsics=refine_intrinsics)
        if all(not np.isfinite(m.tolerance.position_mm).all() for m in measured):
            fix_gauge(problem, [m.pose for m in measured])  # no box holds the gauge: fix it as free BA does
        if start is not None:
            problem.start_from(start)
        _bound_intrinsics(problem, refine_intrinsics, intrinsic_bounds)
        return problem
    base = [m.pose for m in measured] if mode == "fixed" or start is None else start
    rot = np.stack([p.rotation for p in base])
    trans = np.stack([p.translation for p in base])
    block, model, extra = lens_block(camera)
    problem = BundleProblem(tracks.pixels, tracks.frame, tracks.track, rot, trans, pts, block, model=model,
                            extra=extra)
    if not refine_intrinsics:
        problem.fix("intrinsics")
    if mode == "fixed":
        problem.fix("pose")
    else:
        fix_gauge(problem, base)
    _bound_intrinsics(problem, refine_intrinsics, intrinsic_bounds)
    return problem


def _bound_intrinsics(problem: BundleProblem, refine_intrinsics: bool, intrinsic_bounds: tuple | None) -> None:
    """Box the refined intrinsics. The six start free and are held where a bound is NaN; the model's later
    parameters start held and are freed where one is given (a parameter the model lacks stays held)."""
    if not refine_intrinsics or intrinsic_bounds is None:
        return
    lower, upper = (np.asarray(b, dtype=float) for b in intrinsic_bounds)
    names = problem.intrinsic_names
    if lower.size > len(names):
        raise InputError(f"{lower.size} intrinsic bounds for the {len(names)} parameters of a {problem.model} "
                         f"camera ({', '.join(names)})")
    names = names[:lower.size]
    held = np.isnan(lower) | np.isnan(upper)
    absent = problem.intrinsic_absent[:lower.size]
    if held.any():
        problem.fix("intrinsics", components=[n for n, h in zip(names, held) if h])
    later = [n for i, n in enumerate(names) if i >= len(INTRINSIC_NAMES) and not held[i] and not absent[i]]
    if later:
        problem.free("intrinsics", components=later)
    bounded = ~held & ~absent
    if bounded.any():
        problem.set_bounds("intrinsics", None, [n for n, b in zip(names, bounded) if b], lower[bounded], upper[bounded])


def fix_gauge(problem: BundleProblem, poses: list[Pose]) -> None:
    """Conventional BA's gauge: the first camera's pose, and the scale through one position coordinate
    of the camera farthest from it (along the axis where they differ most)."""
    problem.fix("pose", [0])
    centres = np.stack([p.centre for p in poses])
    d = np.abs(centres - centres[0])
    far = int(np.argmax(d.max(axis=1)))
    if far != 0:
        problem.fix("pose", [far], [("px", "py", "pz")[int(np.argmax(d[far]))]])


def adjust(options: BundleStageOptions, mode: str, measured: list[MeasuredPose], camera: Camera, tracks: Tracks,
           start: list[Pose]) -> tuple[BundleProblem, BundleResult]:
    """One bundle adjustment of the ``options.max_points`` strongest tracks in ``mode`` from ``start``.

    ``bounded`` mode holds every pose weakly at its measurement besides its box
    (:meth:`scope3d.estimators.bundle.BundleProblem.set_box_prior`), at the observations' noise as the
    residuals at the start show it (:func:`start_noise_px`)."""
    strongest = tracks.strongest(options.max_points)
    problem = bundle_problem(mode, measured, camera, strongest, refine_intrinsics=options.refine_intrinsics,
                             start=start, intrinsic_bounds=options.intrinsic_bounds)
    if mode == "bounded":
        problem.set_box_prior(start_noise_px(camera, start, strongest))
    return problem, solve(problem, options.solver())


def start_noise_px(camera: Camera, poses: list[Pose], tracks: Tracks) -> float:
    """The observations' noise (px) as the residuals of ``tracks`` (triangulated with ``poses``) show it: their
    norms' median / 1.1774 (a 2-D Gaussian's), as :func:`scope3d.estimators.bundle.covariance.reduced_camera_system`
    reads it; robust to the wrong matches the Huber loss discounts. The start's pose errors can only add to it:
    an overstated noise holds the poses a little harder at their measurements, never outside their boxes."""
    errors = reprojection_errors(camera, poses, tracks)
    return robust_norm_sigma(errors[np.isfinite(errors)], 1e-3)


# --- the adjustment rounds ---------------------------------------------------------------------


@dataclass
class AdjustedMap:
    """tracks (points in mm world), poses (``cam_from_world``), camera (adjusted when intrinsics were
    refined), one bundle result per round, and the points dropped for standing off their neighbours'
    surface, (K, 3) mm world (empty unless the scene was declared a height field)."""

    tracks: Tracks
    poses: list[Pose]
    camera: Camera
    bundle_results: list[BundleResult]
    off_surface_points: np.ndarray


def adjust_map(mode: str, measured: list[MeasuredPose], camera: Camera, tracks: Tracks, start: list[MeasuredPose],
               depth_prior: DepthPrior | None, *, track_options: TrackOptions, options: BundleStageOptions, 
               height_field: bool = False, where: str = "dataset") -> AdjustedMap:
    """Triangulate ``tracks`` (untriangulated, from :func:`scope3d.feature.tracks.build_tracks`) and adjust.

    Triangulation and the adjustment start from ``start`` (the poses that guided matching); the bounds
    are always the ``measured`` boxes. With inexact poses and a mode that may move them, the first
    triangulation keeps the observations the pose error can explain (:func:`scope3d.feature.depth_prior.pose_error_px`). Each round:
    adjust (bounded: with the boxes' prior, :func:`adjust`), align the gauge to the measurements,
    re-triangulate every track with the strict gate. A second
    round runs unless the poses cannot move or barely moved. Raises InputError (naming ``where``) when no
    point survives.

    height_field : the scene is a surface seen from one side (a surgical field, not an object in a ring):
        after every triangulation, points millimetres off their neighbours' surface (:func:`on_surface`,
        gross errors only) are dropped before they enter an adjustment (a wrong two-view match millimetres
        off pulls a weakly held camera); the final points get the full check once (each check has its
        false alarms, so it is not repeated).
    """
    movable = mode != "fixed"
    # both ends of a ray pair may be off: twice one pose's effect
    slack = max((2.0 * pose_error_px(camera, m.tolerance, depth_prior) for m in start), default=0.0) if movable else 0.0
    if mode == "free" and not np.isfinite(slack):
        slack = 50.0
    first = track_options.widened_by(slack)
    if movable:
        first = replace(first, min_angle_deg=0.5 * track_options.min_angle_deg)
    poses = [m.pose for m in start]
    dropped = [np.zeros((0, 3))]

    def keep_on_surface(tracks: Tracks, *, gross_only: bool) -> Tracks:
        if not height_field or tracks.n_tracks == 0:
            return tracks
        keep = on_surface(tracks, poses, gross_only=gross_only)
        dropped.append(tracks.points[~keep])
        return tracks.subset(keep[tracks.track])

    tracks = keep_on_surface(triangulate_tracks(camera, poses, tracks, first), gross_only=True)
    if tracks.n_tracks == 0:
        raise InputError(f"{where}: no point could be triangulated (poses inconsistent with the images?)")
    exact = all(m.tolerance.is_exact for m in measured)
    results = []
    for _ in range(2):
        before = poses
        _, result = adjust(options, mode, measured, camera, tracks, poses)
        results.append(result)
        poses = result.poses
        if movable and options.align_gauge and not exact:
            poses = align_gauge(poses, measured, bounded=mode == "bounded")
        if options.refine_intrinsics:
            camera = camera_from_block(camera, result.intrinsics[0], result.extra[0] if result.extra.size else None)
        tracks = keep_on_surface(triangulate_tracks(camera, poses, tracks.untriangulated(), track_options),
                                 gross_only=True)
        if tracks.n_tracks == 0:
            raise InputError(f"{where}: bundle adjustment left no consistent point")
        if not movable or (mode == "bounded" and exact):
            break  # poses cannot move: one adjustment of the points is all there is
        moved = max(p.distance_to(q)[0] for p, q in zip(poses, before))
        turned = max(p.distance_to(q)[1] for p, q in zip(poses, before))
        if moved < options.settled_mm and turned < options.settled_rad:
            break  # the poses barely moved (a micro-stage's 0.01 mm box): a second round would change nothing
    tracks = keep_on_surface(tracks, gross_only=False)
    if tracks.n_tracks == 0:
        raise InputError(f"{where}: no point lies on a consistent surface")
    return AdjustedMap(tracks, poses, camera, results, np.concatenate(dropped))


def adjusted_pose_sigmas(mode: str, measured: list[MeasuredPose], camera: Camera, tracks: Tracks, poses: list[Pose],
                         *, options: BundleStageOptions) -> np.ndarray:
    """(m, 6) standard deviations of the adjusted ``poses`` (rotation vector about the world axes, rad; camera
    centre, mm): what the images and the measurements together leave of each pose's uncertainty.

    The measured box of half-width ``a`` is a uniform error of sigma ``a / sqrt(3)``; it is the prior, and the
    images' information at the adjusted poses (the reduced camera system of the ``options.max_points``
    strongest tracks, the noise estimated from their residuals, as the adjustment weighed them) is added to it.
    A scalar measured exactly (``a = 0``) keeps sigma 0; an unknown one (``a = inf``) has only the images'
    information, and when no camera has a finite position box the images fix no gauge and those sigmas are
    inf. ``fixed`` mode keeps the measured poses as they are, so their sigma is the prior's. The Gaussian
    reading of a box is an approximation: a bounded adjustment at its box's edge is not Gaussian there."""
    prior = np.array([np.r_[m.tolerance.orientation_rad, m.tolerance.position_mm] for m in measured]) / np.sqrt(3.0)
    if mode == "fixed" or not np.isfinite(prior[:, 3:]).any() or tracks.n_tracks == 0:
        return prior
    strongest = tracks.strongest(options.max_points)
    # the problem parametrised at the adjusted poses themselves (rotation vector 0 about each), so that the
    # information is the curvature where the adjustment ended, whatever box that is in
    at = [MeasuredPose(p, m.tolerance) for p, m in zip(poses, measured)]
    problem = BundleProblem.from_measured_poses(at, camera, strongest.points, strongest.pixels, strongest.frame,
                                                strongest.track, refine_intrinsics=False)
    S, seen, noise_px = reduced_camera_system(problem, problem.initial, options.loss_scale_px)
    flat = prior.reshape(-1)
    free = flat > 0
    information = S[np.ix_(free, free)] / noise_px**2 + np.diag(1.0 / flat[free] ** 2)  # 1 / inf^2 = 0
    out = np.zeros_like(flat)
    out[free] = marginal_sigmas(information)  # inf for a camera with an unknown pose no image ties to the rest
    return out.reshape(prior.shape)


def on_surface(tracks: Tracks, poses: list[Pose], *, gross_only: bool = False) -> np.ndarray:
    """Mask (n_tracks,) of points consistent with their neighbours' local surface.

    A wrong match that happens to lie on the epipolar line passes RANSAC and the reprojection gate
    and triangulates millimetres off the surface (on the dome: 2-4 % of the points, mostly two-view
    tracks, 1-13 mm off); :func:`scope3d.scene.surface.off_surface_points` finds them. Assumes a height field
    seen from one side (the cameras' mean viewing direction). gross_only : only the first pass (points
    more than 2 mm off).
    """
    towards = -np.mean([p.optical_axis for p in poses], axis=0)
    floors = OFF_SURFACE_FLOORS_MM[:1] if gross_only else OFF_SURFACE_FLOORS_MM
    return ~off_surface_points(tracks.points, towards=towards, floors_mm=floors)


# --- poses that guide matching ----------------------------------------------------------------


def refine_poses_for_matching(camera: Camera, measured: list[MeasuredPose], features: list[Features],
                              matches: list[PairMatches], start: list[Pose], *, track_options: TrackOptions,
                              options: BundleStageOptions, where: str = "dataset",
                              ) -> tuple[list[MeasuredPose], DepthPrior]:
    """Poses for predicting the fine matching pass: BCBA on the coarse pass's tracks.

    The reference's "combination algorithm" (sec. 3.5): treat the robot's poses as constrained unknowns
    rather than truth. The coarse tracks are triangulated with the ``start`` poses (the coarse pass's
    averaging), with a reprojection gate of 3 robust sigma of their own errors (the start is good to a
    fraction of a millimetre, not to a pixel); BCBA inside the measured boxes, starting there, adjusts
    poses and points (intrinsics held); the tracks are triangulated again with the strict gate and
    adjusted once more.

    Each adjusted pose carries the tolerance the images leave it relative to the frames it overlaps: the
    covariance of its pose relative to each coarse partner's
    (:func:`scope3d.estimators.bundle.covariance.pairwise_pose_covariances`; a frame tied to the rest by one
    small patch reprojects well and is still poorly fixed, and a group of frames tied loosely to another
    is still well fixed within itself) carried into the image (:func:`projection_sigma_px`). A pair's
    search window is the sum of its two frames' tolerances, so each frame takes half of the largest pair
    sigma among its partners; 3 sigma, expressed as the camera shift that moves a point at the nearest
    depth that far; at most the measured tolerance. Frames the coarse pass did not reach keep their
    measurement.
    Returns the guide poses and the depth prior of the adjusted points
    (:func:`scope3d.sfm.depth_priors.points_depth_prior`). Raises InputError when the coarse pass left
    too few points.
    """
    tracks = build_tracks(features, matches, min_track_length=track_options.min_track_length)
    loose = replace(track_options, max_reprojection_error_px=1e6, min_angle_deg=0.5 * track_options.min_angle_deg)
    tracks = triangulate_tracks(camera, start, tracks, loose)
    if tracks.n_tracks >= 50:
        err = reprojection_errors(camera, start, tracks)
        # 1.1774 = median of a 2-D Gaussian error's norm in sigmas (Rayleigh)
        gate = max(track_options.max_reprojection_error_px, 3.0 * float(np.median(err)) / 1.1774)
        tracks = triangulate_tracks(camera, start, tracks, replace(loose, max_reprojection_error_px=gate))
    if tracks.n_tracks < 50:
        raise InputError(f"{where}: the frames share too few features to map "
                         f"({tracks.n_tracks} points from {len(matches)} verified pairs)")
    held = replace(options, refine_intrinsics=False)
    strict = replace(track_options, min_angle_deg=loose.min_angle_deg)
    poses = start
    for round_ in range(2):
        if round_:
            tracks = triangulate_tracks(camera, poses, tracks, strict)
        problem, result = adjust(held, "bounded", measured, camera, tracks, poses)
        poses = result.poses
    tracks = triangulate_tracks(camera, poses, tracks, strict)
    depth_prior = points_depth_prior(poses, tracks)
    # what the images leave each pose free to do relative to its partners, as pixels of reprojection
    pairs = sorted({(min(m.i, m.j), max(m.i, m.j)) for m in matches})
    # the measured boxes as priors (uniform: sigma = half-width / sqrt(3)) where every one is finite
    boxes = np.array([np.r_[m.tolerance.orientation_rad, m.tolerance.position_mm] for m in measured])
    prior = boxes / np.sqrt(3.0) if np.all(np.isfinite(boxes) & (boxes > 0)) else None
    covariances = pairwise_pose_covariances(problem, result.parameters, pairs, loss_scale_px=options.loss_scale_px,
                                            prior_sigmas=prior)
    sigma_px = np.full(len(poses), np.nan)
    jacobians: dict[int, np.ndarray] = {}  # a frame's image motion per pose scalar, shared by its pairs
    for (i, j), cov in zip(pairs, covariances):
        if not np.all(np.isfinite(cov)):
            continue
        for k in (i, j):
            if k not in jacobians:
                jacobians[k] = projection_jacobian(camera, poses[k], depth_prior)
        pair_sigma = max(projection_sigma_px(jacobians[k], cov) for k in (i, j))
        sigma_px[[i, j]] = np.fmax(sigma_px[[i, j]], 0.5 * pair_sigma)
    f = max(camera.fx, camera.fy)
    guide = []
    for m, pose, sigma in zip(measured, poses, sigma_px):
        if m.tolerance.is_exact or not np.isfinite(sigma):
            guide.append(m)
            continue
        # the camera shift that moves a point at the nearest depth by 3 sigma (per axis, so that the box's
        # half-diagonal is the shift: f * |dp| / z_near = 3 sigma); the orientation is then part of it
        shift = 3.0 * sigma * depth_prior.near_mm / f / np.sqrt(3.0)
        guide.append(MeasuredPose(pose, PoseTolerance(np.minimum(shift, m.tolerance.position_mm), np.zeros(3))))
    return guide, depth_prior


def projection_jacobian(camera: Camera, pose: Pose, depth_prior: DepthPrior, *,
                        samples_per_side: int = 5) -> np.ndarray:
    """How the image of a grid of pixels at the depth prior's near and far ends moves with the pose's
    scalars ``(w, centre)`` (w: a left rotation ``exp(w) R``, rad; centre, mm): (P, 2, 6) px per unit, by
    central differences; rows NaN where the point does not project."""
    pix = fov_samples(camera, samples_per_side)
    world = np.concatenate([(camera.unproject(pix, np.full(len(pix), z)) - pose.translation) @ pose.rotation
                            for z in (depth_prior.near_mm, depth_prior.far_mm)])
    base = camera.project_world(pose, world)
    step = 1e-6
    jac = np.empty((len(world), 2, 6))
    for a in range(6):  # central differences along each pose scalar
        ends = []
        for sign in (1.0, -1.0):
            d = np.zeros(6)
            d[a] = sign * step
            moved = Pose.from_centre(rotvec_to_matrix(d[:3]) @ pose.rotation, pose.centre + d[3:])
            ends.append(camera.project_world(moved, world))
        jac[:, :, a] = (ends[0] - ends[1]) / (2 * step)
    jac[~np.all(np.isfinite(base), axis=1)] = np.nan
    return jac


def projection_sigma_px(jacobian: np.ndarray, covariance: np.ndarray) -> float:
    """The largest standard deviation (px) with which a pose of covariance (6, 6) over ``(w, centre)`` moves
    the image of a point, over the points of its :func:`projection_jacobian` (P, 2, 6). Correlated rotation
    and translation errors partly cancel in the image, which is what matters to a matcher; their separate
    sigmas would not say so."""
    ok = np.all(np.isfinite(jacobian), axis=(1, 2))
    jac = jacobian[ok]
    cov_px = jac @ covariance @ np.swapaxes(jac, 1, 2)
    return float(np.sqrt(np.linalg.eigvalsh(cov_px)[:, -1].max())) if ok.any() else np.inf
