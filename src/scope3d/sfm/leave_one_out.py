"""Each frame's pose from the images and the *other* frames' reports, its own report released: the leave-one-out
estimator behind the per-frame test of reported poses (:mod:`scope3d.sfm.pose_checks`).

Three ways to the same estimate, from exact to cheap:

* :func:`leave_one_out`: a bounded adjustment of every matched observation again, from the bounded map's
  poses, with the frame's own report released (its box unknown) and every other box kept; the frame starts
  from a robust PnP against the points two other frames triangulate
  (:func:`scope3d.estimators.absolute_pose.estimate_absolute_pose`), so that its wrong report does not gate
  its own observations away. At that solution, the images' cost in the poses alone (the reduced camera
  system, points eliminated, per unit of the a-posteriori keypoint noise ``s``, with ``nu`` redundant
  observations) plus each other report's box as a Gaussian error (sigma = half-width / sqrt 3) gives the
  frame's estimate ``x`` (one Gauss-Newton step from the bounded solution, whose frames the boxes' edges
  hold) and its covariance ``C``, in the tolerance's scalars: a left rotation ``w`` (rad) and the centre
  (mm), both relative to the report (:class:`FramePoseTest`).
* :func:`local_leave_one_out`: the same, re-solving only the frame's pose and the points it sees, the other
  frames held, and taking the other frames' images from one bounded adjustment of the whole map
  (:func:`linearise`, a :class:`Linearised` model), so that their uncertainty is propagated into the frame's
  covariance.
* :func:`screen_reported_poses`: every frame's leave-one-out read off the normal equations of that one
  adjustment (its Schur complement without its own box): a screen, linearised at the bounded map.

:func:`box_mahalanobis` measures an estimate's distance from a reported box in its covariance. The variance
factor that scales ``C`` is :mod:`scope3d.sfm.variance_factor`'s, the test itself
:mod:`scope3d.sfm.pose_checks`'s (docs/reliability.md section 5 measures the three estimates' agreement and cost).

Units: mm and radians; pixels with their origin at the top-left pixel's centre. Poses are ``cam_from_world``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scope3d.estimators.absolute_pose import AbsolutePoseOptions, estimate_absolute_pose
from scope3d.estimators.bundle import BundleProblem, SolverOptions, solve
from scope3d.estimators.bundle.covariance import reduced_camera_system, reduced_gradient
from scope3d.estimators.bundle.solver import evaluate
from scope3d.estimators.triangulation import TrackOptions, reprojection_errors, triangulate_tracks
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.guided_mapping import start_noise_px
from scope3d.utils.blas import blas_threads


@dataclass(frozen=True)
class LeaveOneOutOptions:
    """One frame's leave-one-out estimate.

    absolute_pose : the start of each frame's image-only pose (robust PnP against the points two other
        frames triangulate) and the fewest observations a tested frame needs (``min_inliers``, 15).
    loss_scale_px : float, Huber scale of each frame's adjustment (default 1 px, as the map's).
    max_iterations : int, LM iterations of each frame's adjustment, and joint Gauss-Newton steps of
        :func:`local_leave_one_out` (default 30: one pose and its points converge in under 10 from a PnP
        start; the joint steps, measured on the dome with a glitch, in 2-7).
    """

    # only a start, refined by the frame's own adjustment after: as before issue 34 (no refinement on the
    # final inliers, no precision bound, which would swap a loose start for the bounded pose)
    absolute_pose: AbsolutePoseOptions = field(default_factory=lambda: AbsolutePoseOptions(
        final_refinements=0, max_centre_sigma_fraction=float("inf")))
    loss_scale_px: float = 1.0
    max_iterations: int = 30

    def __post_init__(self) -> None:
        if self.loss_scale_px <= 0 or self.max_iterations < 1:
            raise ValueError("need loss_scale_px > 0 and max_iterations >= 1")


@dataclass
class FramePoseTest:
    """The test of one frame's report.

    frame : index. status : ``"ok"`` (tested), ``"exact"`` (a zero tolerance: trusted by definition),
        ``"unseen"`` (fewer observations than ``absolute_pose.min_inliers``) or ``"unplaced"`` (too few kept
        at its start, or the other reports cannot place the images without it).
    predicted_pose : ``cam_from_world`` the images predict from the other frames, or None. offset : (6,)
        it relative to the report, ``(w (rad), centre (mm))``; covariance : (6, 6) of it, scaled by
        ``variance_factor`` (the other frames' :func:`scope3d.sfm.variance_factor.scale_of_images`, with
        ``factor_dof`` degrees of freedom).
    statistic : ``d2`` (at most about ``6 F(6, factor_dof)`` under a right report); p_value : its upper tail
        (an upper bound on the probability of a ``d2`` this large under a right report); critical_value : the
        ``d2`` this frame was held to.
    noise_px : the keypoint noise ``s`` of the frame's leave-one-out adjustment (a-posteriori); inliers :
        the frame's observations it kept; dof : its redundancy ``nu`` (observations x 2 - points x 3 -
        observed frames x 6 + 7).
    beyond_box : (6,) how far the prediction lies outside the box per scalar (0 inside; rad, mm).
    flagged : the report disagrees with the images (set aside by the data snooping).
    observations : the frame's matched observations; why : for a frame not tested, the reason in words.
    exact : tested by its own leave-one-out adjustment (:func:`local_leave_one_out` or :func:`leave_one_out`);
        False: by the linearised screen alone (:func:`screen_reported_poses`), which found it well within its level.
    """

    frame: int
    status: str
    predicted_pose: Pose | None = None
    offset: np.ndarray | None = None
    covariance: np.ndarray | None = None
    statistic: float = float("nan")
    p_value: float = float("nan")
    critical_value: float = float("nan")
    noise_px: float = float("nan")
    inliers: int = 0
    dof: int = 0
    beyond_box: np.ndarray = field(default_factory=lambda: np.zeros(6))
    flagged: bool = False
    variance_factor: float = 1.0
    factor_dof: float = float("inf")
    observations: int = 0
    why: str = ""
    exact: bool = True

    @property
    def disagreement_mm(self) -> float:
        """Distance of the predicted centre from the report's centre (mm; NaN without a pose)."""
        return float(np.linalg.norm(self.offset[3:])) if self.offset is not None else float("nan")

    @property
    def disagreement_sd_mm(self) -> float:
        """The prediction's standard deviation along its centre's disagreement with the report (mm; from
        ``covariance``; NaN without a pose or where they agree exactly)."""
        if self.offset is None or not np.any(self.offset[3:]):
            return float("nan")
        u = self.offset[3:] / np.linalg.norm(self.offset[3:])
        return float(np.sqrt(u @ self.covariance[3:, 3:] @ u))

    @property
    def disagreement_rad(self) -> float:
        return float(np.linalg.norm(self.offset[:3])) if self.offset is not None else float("nan")


def box_mahalanobis(offset: np.ndarray, covariance: np.ndarray, half_width: np.ndarray) -> tuple[float, np.ndarray]:
    """``min over |b| <= half_width of (offset - b)^T covariance^-1 (offset - b)`` and the minimiser ``b``.

    offset : (6,), covariance : (6, 6) symmetric positive (semi)definite, half_width : (6,) (inf: unbounded).
    A bounded least-squares problem (scipy's ``lsq_linear``) on the whitened difference.
    """
    from scipy.optimize import lsq_linear

    # whiten by the covariance's eigenvectors; a direction of (numerically) zero variance is held to a
    # standard deviation a millionth of the largest (an exact zero would make round-off an infinite disagreement)
    values, vectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
    values = np.maximum(values, 1e-12 * max(float(values.max()), 1e-300))
    whiten = vectors.T / np.sqrt(values)[:, None]  # covariance^-1 = whiten^T whiten
    lower = -np.asarray(half_width, float)
    upper = np.where(-lower > lower, -lower, lower + 1e-15)  # lsq_linear wants lower < upper
    fit = lsq_linear(whiten, whiten @ offset, bounds=(lower, upper), method="bvls")
    d = whiten @ (offset - fit.x)
    return float(d @ d), fit.x


def _start_pose(camera: Camera, tracks: Tracks, poses: list[Pose], k: int, track_options: TrackOptions,
                options: LeaveOneOutOptions) -> Pose:
    """Frame ``k``'s pose from the images alone where they can give one (robust PnP against the points of
    ``tracks`` that two other frames triangulate at ``poses``), else ``poses[k]`` (pulled by its report: a
    glitched frame's sits on its box's edge, which the adjustment then leaves)."""
    others = tracks.subset(tracks.frame != k)
    points = triangulate_tracks(camera, poses, others, track_options)
    if points.n_tracks < options.absolute_pose.min_inliers:
        return poses[k]
    # the original track of each triangulated one, through any of its observations' (frame, feature)
    stride = int(tracks.feature.max(initial=0)) + 1
    key = tracks.frame * stride + tracks.feature
    order = np.argsort(key)
    first = np.unique(points.track, return_index=True)[1]
    source = tracks.track[order][np.searchsorted(key[order], points.frame[first] * stride + points.feature[first])]
    point_of = np.full(tracks.n_tracks, -1)
    point_of[source] = np.arange(points.n_tracks)
    own = np.flatnonzero((tracks.frame == k) & (point_of[tracks.track] >= 0))
    if len(own) < options.absolute_pose.min_inliers:
        return poses[k]
    estimate = estimate_absolute_pose(camera, points.points[point_of[tracks.track[own]]], tracks.pixels[own],
                                      options=options.absolute_pose)
    return estimate.pose if estimate.ok else poses[k]


def _noise_px(residuals: np.ndarray, loss_scale_px: float, redundancy: int) -> float:
    """The keypoints' noise (px): the Huber-weighted squared residuals (N, 2) over the redundancy (the
    a-posteriori variance factor). A two-view point keeps 1 of its 4 residual dimensions, so the residuals'
    plain spread would understate the noise by up to 2x."""
    norm = np.linalg.norm(residuals, axis=1)
    weighted = np.where(norm <= loss_scale_px, norm**2, loss_scale_px * (2.0 * norm - loss_scale_px))
    return float(np.sqrt(weighted.sum() / redundancy))


def _unseen(k: int, observations: int, options: LeaveOneOutOptions) -> FramePoseTest:
    """Frame ``k``'s test when it has fewer matched observations than a test needs: not tested, with why."""
    return FramePoseTest(k, "unseen", observations=observations, why=f"{observations} matched observations, fewer "
                         f"than the {options.absolute_pose.min_inliers} a test needs")


def _best_start(camera: Camera, tracks: Tracks, start: list[Pose], k: int, fallback: Pose, track_options: TrackOptions,
                options: LeaveOneOutOptions) -> tuple[list[Pose], Tracks]:
    """Frame ``k``'s start for its leave-one-out, the others at ``start``: its image-only pose
    (:func:`_start_pose`) or ``fallback`` (its bounded pose), whichever keeps more of its observations within
    the map's gate (a PnP on few points can land millimetres off: 7 mm on the dome, seed 11, frame 3); ->
    ``start`` with frame k's, and ``tracks`` triangulated there."""
    best = None
    start = list(start)
    for candidate in (_start_pose(camera, tracks, start, k, track_options, options), fallback):
        start[k] = candidate
        kept = triangulate_tracks(camera, start, tracks, track_options)
        if best is None or np.count_nonzero(kept.frame == k) > np.count_nonzero(best[1].frame == k):
            best = (candidate, kept)
    start[k] = best[0]
    return start, best[1]


def _adjust(camera: Camera, released: list[MeasuredPose], current: Tracks, start: list[Pose], k: int, observations: int,
            held: list[int] | None, track_options: TrackOptions,
            options: LeaveOneOutOptions) -> tuple[BundleProblem, object, Tracks] | FramePoseTest:
    """Frame ``k``'s leave-one-out adjustment from ``start`` with the observations ``current`` kept there, in two
    rounds (adjust, triangulate the kept tracks again at the adjusted poses, adjust), the poses of ``held``
    fixed where ``start`` puts them (None: every other frame in its box of ``released``); -> the problem, its
    solution and the tracks, or the frame's test "unplaced" where too few of its observations fit a pose."""
    least = options.absolute_pose.min_inliers
    solver = SolverOptions(max_iterations=options.max_iterations, loss="huber", loss_scale_px=options.loss_scale_px,
                           num_threads=1)
    for round_ in range(2):
        fitted = int(np.count_nonzero(current.frame == k))
        if fitted < least:
            return FramePoseTest(k, "unplaced", inliers=fitted, observations=observations,
                                 why=f"{fitted} of its {observations} matched observations fit a pose "
                                     f"({'its image-only start or its bounded pose' if round_ == 0 else 'after adjustment'}"
                                     f") at the other frames' adjusted poses, fewer than the {least} a test needs")
        problem = BundleProblem.from_measured_poses(released, camera, current.points, current.pixels, current.frame,
                                                    current.track, refine_intrinsics=False)
        problem.start_from(start)
        problem.set_box_prior(start_noise_px(camera, start, current))  # as the map's adjustment holds them
        if held:
            problem.fix("pose", held)
        result = solve(problem, solver)
        start = result.poses
        if round_ == 0:
            current = triangulate_tracks(camera, start, current.untriangulated(), track_options)
    return problem, result, current


def leave_one_out(camera: Camera, measured: list[MeasuredPose], k: int, tracks: Tracks, poses: list[Pose],
                  set_aside: dict[int, MeasuredPose], track_options: TrackOptions,
                  options: LeaveOneOutOptions) -> FramePoseTest:
    """Frame ``k``'s pose from the images and the other reports, its own report released (its box unknown)
    and those of ``set_aside`` replaced: the bounded adjustment of every point and pose again, from ``poses``
    (the bounded map's), and the test of its report (see the module docstring).

    tracks : every matched observation (untriangulated); poses : (n) the bounded map's ``cam_from_world``;
    set_aside : frames already flagged, each with the report :meth:`PoseCheck.released` would give it (its
    own test's estimate, in a box of that estimate's confidence region). Not released as unknown: a frame
    without any box lets a weakly tied neighbour float with it, and the neighbour was then flagged (dome12,
    seed 21, frame 6 3 mm off: frame 2 too, its estimate 3.2 mm from its truth; docs/reliability.md).
    """

    observations = int(np.count_nonzero(tracks.frame == k))
    if observations < options.absolute_pose.min_inliers:
        return _unseen(k, observations, options)
    released = list(measured)
    released[k] = MeasuredPose(measured[k].pose, PoseTolerance.unknown())
    start = list(poses)
    for j, report in set_aside.items():  # a flagged frame starts where its own test put it, not on its wrong report's edge
        released[j] = report
        start[j] = report.pose
    # the map's gate at the start: the robust loss alone let wrong matches (kept by an open gate) pull
    # the frame 0.85 mm / 2.2 deg off on the dome, with the others at their true poses. The start is the
    # PnP's or the bounded pose, whichever keeps more of the frame's observations within that gate (a PnP
    # on few points can land millimetres off: 7 mm on the dome, seed 11, frame 3); a frame whose
    # observations neither explains is left with too few: "unplaced", not tested
    # the PnP's points triangulated with the flagged frames where their own tests put them: at the bounded map's
    # poses a glitch drags its neighbours, and a neighbour's PnP then lands on the glitch's side (dome12, seed 21,
    # frame 6 3 mm off: frame 2's PnP kept 27 of its 55 observations 3.1 mm from its truth, and was flagged)
    start, current = _best_start(camera, tracks, start, k, poses[k], track_options, options)
    adjusted = _adjust(camera, released, current, start, k, observations, None, track_options, options)
    if isinstance(adjusted, FramePoseTest):
        return adjusted
    problem, result, current = adjusted
    seen = np.bincount(problem.camera_index, minlength=problem.num_cameras) > 0
    r, _, _ = evaluate(problem, result.parameters)
    redundancy = 2 * problem.num_observations - 3 * problem.num_points - 6 * int(np.count_nonzero(seen)) + 7
    if redundancy < 1:
        return FramePoseTest(k, "unplaced", observations=observations, why="no redundant observation")
    noise_px = _noise_px(r, options.loss_scale_px, redundancy)
    system, _, _ = reduced_camera_system(problem, result.parameters, options.loss_scale_px, noise_px=noise_px)
    gradient = reduced_gradient(problem, result.parameters, options.loss_scale_px)
    # the images' cost about that solution (points eliminated), per unit noise, and each other report's
    # box as a uniform error (sigma^2 = half^2 / 3; an exact scalar as a very narrow box): frame k's
    # posterior mean and covariance (a Gauss-Newton step from the bounded solution, whose frames the
    # boxes' edges hold where the Gaussian errors of the reports would not)
    report, _, prior = _gaussian_boxes(released)
    prior[~seen] = 1.0  # a frame without observations: any weight keeps the system regular, and is independent
    at = result.parameters.pose  # (n, 6): w (rad, from each report's orientation), centre (mm)
    rhs = -gradient / noise_px**2 + (prior * (report - at)).ravel()
    return _frame_estimate(k, system / noise_px**2 + np.diag(prior.ravel()), rhs, at, report, measured[k], noise_px,
                           int(np.count_nonzero(current.frame == k)), redundancy, observations)


def _frame_estimate(k: int, matrix: np.ndarray, rhs: np.ndarray, at: np.ndarray, report: np.ndarray,
                    reported: MeasuredPose, noise_px: float, inliers: int, redundancy: int,
                    observations: int) -> FramePoseTest:
    """Frame ``k``'s test from the Gauss-Newton system of every pose with its report released: ``matrix`` (6n,
    6n) and ``rhs`` (6n,) of the step from ``at`` (n, 6); its estimate (``at[k]`` + its step), covariance (its
    block of ``matrix^-1``), offset from ``report[k]`` and distance from the reported box."""
    from scipy.linalg import cho_factor, cho_solve
    from scipy.stats import f as f_dist

    columns = np.zeros((len(rhs), 6))
    columns[6 * k:6 * k + 6] = np.eye(6)
    with blas_threads(1):  # OpenBLAS's default threads spin: 80 ms of CPU for a 180 x 180 factor, 0.5 ms with one
        try:
            factor = cho_factor(matrix)
        except np.linalg.LinAlgError:  # the other reports cannot place the images without this one
            return FramePoseTest(k, "unplaced", observations=observations,
                                 why="the other reports cannot place the images without its own")
        solved = cho_solve(factor, np.c_[rhs, columns])
    covariance = solved[6 * k:6 * k + 6, 1:]
    covariance = 0.5 * (covariance + covariance.T)
    posterior = at[k] + solved[6 * k:6 * k + 6, 0]
    offset = posterior - report[k]
    estimate = Pose.from_centre(rotvec_to_matrix(posterior[:3]) @ reported.pose.rotation, posterior[3:])
    half = np.r_[reported.tolerance.orientation_rad, reported.tolerance.position_mm]
    statistic, nearest = box_mahalanobis(offset, covariance, half)
    return FramePoseTest(k, "ok", estimate, offset, covariance, statistic,
                         float(f_dist.sf(statistic / 6.0, 6, redundancy)), float("nan"), noise_px, inliers, redundancy,
                         np.abs(offset - nearest), observations=observations)


@dataclass
class Linearised:
    """The images' cost in the poses about one bounded adjustment of every matched observation the map's gate
    keeps at the bounded poses (points eliminated), per unit of its a-posteriori keypoint noise ``noise_px``:
    ``system`` (6n, 6n) and ``gradient`` (6n,) at ``parameters`` (poses ``at``, (n, 6)), what
    :func:`local_leave_one_out` holds the frames it does not re-solve with."""

    camera: Camera
    measured: list[MeasuredPose]
    problem: BundleProblem
    parameters: object
    system: np.ndarray
    gradient: np.ndarray
    noise_px: float
    redundancy: int
    poses: list[Pose]
    loss_scale_px: float
    shares: dict = field(default_factory=dict)

    def share(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The part of ``system`` and ``gradient`` due to the points frame ``k`` observes (every observation of
        them, whichever frame): what its local leave-one-out replaces by the same points solved again with
        all of frame k's matched observations. Computed once per frame."""
        if k not in self.shares:
            problem = self.problem
            points = np.unique(problem.point_index[problem.camera_index == k])
            if not points.size:
                return np.zeros_like(self.system), np.zeros_like(self.gradient)
            mask = np.isin(problem.point_index, points)
            part = BundleProblem.from_measured_poses(
                self.measured, self.camera, problem.points_world(self.parameters.points)[points],
                problem.observations_px[mask], problem.camera_index[mask],
                np.searchsorted(points, problem.point_index[mask]), refine_intrinsics=False)
            at = part.initial.copy()
            at.pose[:] = self.parameters.pose
            system = reduced_camera_system(part, at, self.loss_scale_px, noise_px=self.noise_px)[0]
            self.shares[k] = (system / self.noise_px**2,
                              reduced_gradient(part, at, self.loss_scale_px) / self.noise_px**2)
        return self.shares[k]


def linearise(camera: Camera, measured: list[MeasuredPose], tracks: Tracks, poses: list[Pose],
              track_options: TrackOptions, options: LeaveOneOutOptions) -> Linearised | str:
    """The quadratic model of every frame's images (:class:`Linearised`) about the bounded map: ``tracks``
    triangulated at ``poses`` (the map's gate), adjusted once with every report in its box; or why not."""
    kept = triangulate_tracks(camera, poses, tracks, track_options)
    if kept.n_observations == 0:
        return "the reports cannot place the images"
    problem = BundleProblem.from_measured_poses(measured, camera, kept.points, kept.pixels, kept.frame, kept.track,
                                                refine_intrinsics=False)
    problem.start_from(poses)
    # no box prior here, unlike the map's adjustment: the test adds every box as a Gaussian error itself and
    # steps from this point, and a prior weighted at the start's noise (a glitch inflates it) held a released
    # frame near its release's centre, which a neighbour's test then followed (dome12, frame 6 3 mm off,
    # seeds 11 and 21-28: with the prior, frame 2 flagged beside frame 6 on seed 21; without it, frame 6 alone
    # on 8 of the 9 seeds, none on seed 25, where its screen's 6.3 mm disagreement has a 4.8 mm deviation)
    result = solve(problem, SolverOptions(max_iterations=options.max_iterations, loss="huber",
                                          loss_scale_px=options.loss_scale_px, num_threads=1))
    seen = np.bincount(problem.camera_index, minlength=problem.num_cameras) > 0
    r, _, _ = evaluate(problem, result.parameters)
    redundancy = 2 * problem.num_observations - 3 * problem.num_points - 6 * int(np.count_nonzero(seen)) + 7
    if redundancy < 1:
        return "no redundant observation"
    noise_px = _noise_px(r, options.loss_scale_px, redundancy)
    system = reduced_camera_system(problem, result.parameters, options.loss_scale_px, noise_px=noise_px)[0]
    gradient = reduced_gradient(problem, result.parameters, options.loss_scale_px)
    return Linearised(camera, measured, problem, result.parameters, system / noise_px**2, gradient / noise_px**2,
                       noise_px, redundancy, result.poses, options.loss_scale_px)


def _gaussian_boxes(measured: list[MeasuredPose]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each report in the adjustment's scalars (its orientation's own chart: w = 0; its centre, mm), its box's
    half-widths and the box as a Gaussian error's information (sigma^2 = half^2 / 3; an exact scalar as a very
    narrow box, an unknown one as none), each (n, 6)."""
    report = np.stack([np.r_[np.zeros(3), m.pose.centre] for m in measured])
    half = np.stack([np.r_[m.tolerance.orientation_rad, m.tolerance.position_mm] for m in measured])
    return report, half, np.where(np.isfinite(half), 3.0 / np.maximum(half, 1e-6) ** 2, 0.0)


def local_leave_one_out(camera: Camera, measured: list[MeasuredPose], k: int, tracks: Tracks, model: Linearised,
                        track_options: TrackOptions, options: LeaveOneOutOptions) -> FramePoseTest:
    """Frame ``k``'s leave-one-out, solved again only where its report acts: its pose (released) and the points
    it sees, with all its matched observations, the other frames held; then one Gauss-Newton step of every
    pose jointly, the other frames' images taken from ``model`` (the one bounded adjustment, linearised), so
    that the others' uncertainty and their relaxation once frame k's report is released are in frame k's
    estimate and covariance. O(frame k's observations) plus one dense 6n x 6n factorisation, instead of
    :func:`leave_one_out`'s bounded adjustment of every observation.

    1. Start from each of two poses, the PnP against the points the other frames triangulate and the frame's
       adjusted pose, the others at ``model``'s poses (a frame of ``set_aside`` at its released estimate);
       adjust frame k's pose and the points of the tracks through it, the others fixed (two rounds, as
       :func:`leave_one_out`). Frame k's observations are those that fit its own re-solved pose, not the
       wrong report's (at the bounded map the gate keeps only those: dome12, seed 21, 3 mm on frame 6, 84 of
       154).
    2. The images' cost in the poses is split by points: those frame k sees (all their observations) and the
       rest. The rest is ``model``'s, less the share of frame k's points there (:meth:`Linearised.share`);
       frame k's points are this adjustment's (per unit of ``model``'s noise: every frame judged at one
       noise). With every other report's box as a Gaussian error and none on frame k, the sum is the whole
       map's model with frame k released; its minimum over every pose (:func:`_joint_minimum`, Gauss-Newton
       iterated to a tenth of a standard deviation, frame k's points solved again at each step) is frame
       k's estimate, its inverse's block there frame k's covariance.
    3. Of the two starts' minima, the one of lower cost, every observation of frame k's tracks counted (those
       the gate drops at the minimum's poses at the gate's cost), so that both are judged on the same data.

    Why both starts, and why iterated: a narrow view trades a tilt for a shift, and with the others held
    where the bounded map put them (a wrong report's neighbours where it dragged them) frame k's observations
    fit poses millimetres and degrees apart along that direction. On dome12, seed 21, frame 6 reported 3 mm
    off, frame 2 (55 observations) re-solved from its PnP 3.4 mm / 8.8 deg off its truth, from its bounded
    pose 0.4 mm / 0.7 deg, each start keeping 42 observations within the gate under one BLAS kernel, and the
    tie went to the PnP; one Gauss-Newton step from there, the others' images at their linearisation, stayed
    there (3.4 mm, its covariance 0.13 mm: d2 = 930 against its truth, scaled), and frame 2 was flagged beside the
    glitch. The glitched frame 6 itself re-solved 1.9 mm / 6.9 deg off its truth (stopped by the iteration
    cap), and one step took it to 0.7 or 1.2 mm / 0.8 or 3.2 deg depending on where the re-solve stopped: a
    step from outside the model's linear range, with the covariance of its start, not of its end. Iterated
    and chosen by cost, frame 6 comes out 0.24-0.26 mm from its truth under five BLAS kernel and thread
    settings (disagreement 3.22-3.24 mm), and frame 2 is not set aside first.

    Why the covariance is right, not only frame k's own: with the others fixed it would be ``S_kk^-1`` (frame
    k's information from its points), too small by the others' own uncertainty. In the joint system the
    others' part is eliminated exactly: ``[H^-1]_kk = S_kk^-1 + G Sigma_o G^T`` (Woodbury), ``G = S_kk^-1
    S_ko`` how frame k's estimate follows the others' poses and ``Sigma_o`` their covariance from every
    other observation and box with frame k released: the others' uncertainty propagated, counted once
    (``tests/test_pose_checks.py`` checks it against a Monte Carlo). Linearised about ``model`` for the
    others only; frame k's own nonlinearity (its wrong report's pose) is solved, not linearised.
    """

    observations = int(np.count_nonzero(tracks.frame == k))
    if observations < options.absolute_pose.min_inliers:
        return _unseen(k, observations, options)
    n = len(measured)
    own = tracks.subset(np.isin(tracks.track, tracks.track[tracks.frame == k]))
    # the frames that share a track with k: the local adjustment's cameras (its cost then follows frame k's
    # observations, not the map's size)
    involved = np.unique(own.frame)
    index = np.full(n, -1)
    index[involved] = np.arange(len(involved))
    own = Tracks(own.track, index[own.frame], own.feature, own.pixels, own.colors)
    local = int(index[k])
    noise = model.noise_px
    share_system, share_gradient = model.share(k)
    rest_system, rest_gradient = model.system - share_system, model.gradient - share_gradient
    report, _, prior = _gaussian_boxes(measured)  # every other report's box as a Gaussian error; none on frame k
    prior[k] = 0.0
    seen = np.bincount(model.problem.camera_index, minlength=n) > 0
    seen[involved] = True
    prior[~seen] = 1.0  # a frame without observations: any weight keeps the system regular, and is independent
    at = model.parameters.pose  # the rest's quadratic is centred at model's poses (n, 6)
    free = [MeasuredPose(measured[j].pose, PoseTolerance.unknown()) for j in involved]  # the reports' charts, as model's
    held = [i for i in range(len(involved)) if i != local]
    gate, scale = track_options.max_reprojection_error_px, options.loss_scale_px
    start = [model.poses[j] for j in involved]
    pnp = _start_pose(camera, own, start, local, track_options, options)
    best, unplaced = None, None
    for candidate in (pnp, model.poses[k]) if pnp is not model.poses[k] else (pnp,):
        start[local] = candidate
        adjusted = _adjust(camera, free, triangulate_tracks(camera, start, own, track_options), list(start), local,
                           observations, held, track_options, options)
        if isinstance(adjusted, FramePoseTest):
            unplaced = unplaced or adjusted
            continue
        problem, result, current = adjusted
        here = at.copy()
        here[involved] = result.parameters.pose
        matrix, rhs = _joint_minimum(problem, result.parameters, involved, here, rest_system, rest_gradient, at, prior,
                                     report, noise, options)
        # the joint cost there, every observation of frame k's tracks counted (the gate's triangulation at
        # those poses; one it drops costs what one on the gate does), so that two starts' minima are compared
        # on the same data
        poses = problem.poses(here[involved])
        kept = triangulate_tracks(camera, poses, own, track_options)
        error = np.r_[reprojection_errors(camera, poses, kept), np.full(own.n_observations - kept.n_observations, gate)]
        cost = (np.sum(np.where(error <= scale, 0.5 * error**2, scale * (error - 0.5 * scale))) / noise**2
                + _rest_cost(here, at, rest_system, rest_gradient, prior, report))
        if best is None or cost < best[0]:
            best = (cost, matrix, rhs, here, int(np.count_nonzero(current.frame == local)))
    if best is None:
        return unplaced
    _, matrix, rhs, here, inliers = best
    return _frame_estimate(k, matrix, rhs, here, report, measured[k], noise, inliers, model.redundancy, observations)


def _rest_cost(poses: np.ndarray, at: np.ndarray, rest_system: np.ndarray, rest_gradient: np.ndarray,
               prior: np.ndarray, report: np.ndarray) -> float:
    """The joint model's cost at ``poses`` (n, 6) less the images of frame k's points: the rest of the map's
    images (a quadratic centred at ``at``) and each report's box as a Gaussian error (see :func:`_joint_minimum`)."""
    offset = (poses - at).ravel()
    return float(offset @ (0.5 * rest_system @ offset + rest_gradient) + 0.5 * np.sum(prior * (poses - report) ** 2))


def _joint_minimum(problem: BundleProblem, parameters, involved: np.ndarray, here: np.ndarray, rest_system: np.ndarray,
                   rest_gradient: np.ndarray, at: np.ndarray, prior: np.ndarray, report: np.ndarray, noise: float,
                   options: LeaveOneOutOptions) -> tuple[np.ndarray, np.ndarray]:
    """The minimum of :func:`local_leave_one_out`'s joint model over every pose: the images of frame k's points
    (``problem``, its pose and the poses of ``involved`` at ``here``, nonlinear, per unit ``noise``), the rest
    of the map's images (``rest_system``, ``rest_gradient``: a quadratic centred at ``at``) and each report's
    box as a Gaussian error (``prior`` about ``report``); Gauss-Newton steps of every pose jointly, frame k's
    points solved again at each (all poses held), halved while the cost does not fall, until a step is a
    tenth of a standard deviation (``step^T H step < 0.01``). -> the Gauss-Newton system (matrix, rhs) at
    ``here`` (updated in place), whose step from there is then that small.

    Iterated, not one step from frame k's re-solve with the others held, which can lie outside the model's
    linear range (see :func:`local_leave_one_out`): the step then depended on where that re-solve stopped.
    After ``options.max_iterations`` steps, the system where the last one ended.
    The covariance is the inverse at the solution, not at a point a step away."""
    from scipy.linalg import cho_factor, cho_solve

    rows = (6 * involved[:, None] + np.arange(6)).ravel()
    solver = SolverOptions(max_iterations=options.max_iterations, loss="huber", loss_scale_px=options.loss_scale_px,
                           num_threads=1)
    problem.fix("pose")  # between steps only frame k's points move: the poses are the joint step's

    def system_at(parameters):
        system, gradient = np.zeros_like(rest_system), np.zeros_like(rest_gradient)
        system[np.ix_(rows, rows)] = reduced_camera_system(problem, parameters, options.loss_scale_px,
                                                           noise_px=noise)[0] / noise**2
        gradient[rows] = reduced_gradient(problem, parameters, options.loss_scale_px) / noise**2
        offset = (here - at).ravel()
        matrix = rest_system + system + np.diag(prior.ravel())
        rhs = -rest_system @ offset - rest_gradient - gradient + (prior * (report - here)).ravel()
        return matrix, rhs

    def cost(parameters, poses):
        r, _, _ = evaluate(problem, parameters)
        norm = np.linalg.norm(r, axis=1)
        s = options.loss_scale_px
        images = np.sum(np.where(norm <= s, 0.5 * norm**2, s * (norm - 0.5 * s))) / noise**2
        return images + _rest_cost(poses, at, rest_system, rest_gradient, prior, report)

    current = cost(parameters, here)
    for _ in range(options.max_iterations):
        matrix, rhs = system_at(parameters)
        with blas_threads(1):
            try:
                step = cho_solve(cho_factor(matrix), rhs)
            except np.linalg.LinAlgError:  # _frame_estimate says why
                return matrix, rhs
        if step @ matrix @ step < 0.01:
            return matrix, rhs
        for _halving in range(20):
            poses = here + step.reshape(here.shape)
            problem.initial.pose[:] = poses[involved]
            problem.initial.points[:] = parameters.points
            trial = solve(problem, solver).parameters
            value = cost(trial, poses)
            if value <= current:
                break
            step = 0.5 * step
        else:  # no step lowers the cost: at its minimum to round-off
            return matrix, rhs
        here[:], parameters, current = poses, trial, value
    return system_at(parameters)


def screen_reported_poses(model: Linearised, measured: list[MeasuredPose], testable: list[int], tracks: Tracks,
                          options: LeaveOneOutOptions) -> dict[int, FramePoseTest]:
    """Every frame's leave-one-out, linearised: one bounded adjustment of every matched observation with
    every report in its box, then each frame's estimate from the others alone by removing its own box from
    the normal equations (O(n) instead of :func:`leave_one_out`'s bounded adjustment per frame).

    At the solution the images' cost in the poses (the reduced camera system ``S``, points eliminated, per
    unit of the a-posteriori noise) plus every report's box as a Gaussian error (``P``) give ``H = S + P``
    and the Gauss-Newton step's right-hand side ``r``; ``H^-1`` is formed once. Frame k's block of it is
    ``(H_kk - H_ko H_oo^-1 H_ok)^-1``, the inverse of the frame's Schur complement with its own box in;
    taking its box ``P_k`` out of that complement, and ``P_k (report_k - at_k)`` out of its reduced
    right-hand side, gives exactly what :func:`leave_one_out`'s last step computes for the frame with its
    report released, *linearised at the bounded map* instead of re-adjusted: the frame's observations are
    those the map's gate kept at its bounded pose, and the others' poses are not moved by its release. So
    it is a screen: a frame it finds beyond (or cannot place) gets the exact test.

    model : that adjustment (:func:`linearise`). testable : frames to screen (those with a tolerance).
    Returns {frame: test}, unscaled (variance factor 1) like :func:`leave_one_out`'s; status ``"unplaced"`` where its kept observations are too few or its
    complement without its box is not positive definite (the images alone do not fix it).
    """
    from scipy.linalg import cho_factor, cho_solve

    least = options.absolute_pose.min_inliers
    out = {}
    fitted = np.bincount(model.problem.camera_index, minlength=len(measured))
    observations = np.bincount(tracks.frame, minlength=len(measured))
    report, half, prior = _gaussian_boxes(measured)
    prior[fitted == 0] = 1.0
    at = model.parameters.pose
    rhs = -model.gradient + (prior * (report - at)).ravel()
    noise_px, redundancy = model.noise_px, model.redundancy
    with blas_threads(1):
        try:
            factor = cho_factor(model.system + np.diag(prior.ravel()))
        except np.linalg.LinAlgError:
            return {k: FramePoseTest(k, "unplaced", observations=int(observations[k]),
                                     why="the reports cannot place the images") for k in testable}
        inverse = cho_solve(factor, np.eye(len(rhs)))
    step = inverse @ rhs
    for k in testable:
        if observations[k] < least:
            out[k] = _unseen(k, int(observations[k]), options)
            continue
        if fitted[k] < least:
            out[k] = FramePoseTest(k, "unplaced", inliers=int(fitted[k]), observations=int(observations[k]),
                                   why=f"{fitted[k]} of its {observations[k]} matched observations fit its bounded pose")
            continue
        block = slice(6 * k, 6 * k + 6)
        complement = np.linalg.inv(inverse[block, block])  # the frame's Schur complement, its own box in
        reduced_rhs = complement @ step[block]
        complement = complement - np.diag(prior[k])
        reduced_rhs = reduced_rhs - prior[k] * (report[k] - at[k])
        try:
            covariance = cho_solve(cho_factor(0.5 * (complement + complement.T)), np.eye(6))
        except np.linalg.LinAlgError:
            out[k] = FramePoseTest(k, "unplaced", inliers=int(fitted[k]), observations=int(observations[k]),
                                   why="the images alone do not fix its pose (linearised)")
            continue
        covariance = 0.5 * (covariance + covariance.T)
        posterior = at[k] + covariance @ reduced_rhs
        offset = posterior - report[k]
        estimate = Pose.from_centre(rotvec_to_matrix(posterior[:3]) @ measured[k].pose.rotation, posterior[3:])
        statistic, nearest = box_mahalanobis(offset, covariance, half[k])
        out[k] = FramePoseTest(k, "ok", estimate, offset, covariance, statistic, float("nan"), float("nan"), noise_px,
                               int(fitted[k]), redundancy, np.abs(offset - nearest), observations=int(observations[k]),
                               exact=False)
    return out
