"""A per-frame test of each reported pose against the images: is the report wrong beyond its tolerance?

Bound-constrained adjustment trusts every reported box: the true pose is inside. One report that is not
(a tracker glitch, a frame stamped with the wrong pose) ends on the edge of its box and drags the whole
map towards it (dome, 12 frames, 0.5 mm boxes: one frame reported 3 mm off raised the mean surface error
from 0.35 to 2.5 mm). Being on the edge is no proof: a narrow view trades a small tilt for a shift, and
frames of clean data reach their edges along that weakly determined direction too. So each frame is
tested against what the images and the *other* reports say about it:

1. :func:`image_only_adjustment` — a conventional (free) bundle adjustment of every matched observation,
   which the reports do not pull, placed on the reports by the least-squares similarity; and the images'
   information on every pose scalar there (the reduced camera system,
   :func:`scope3d.estimators.bundle.covariance.reduced_camera_system`).
2. :func:`test_reported_poses` — in that linearisation, frame k's pose predicted from the images and every
   other report (each box a uniform error: sigma = half-width / sqrt 3), with its covariance ``S_k``:
   leave one out. The prediction ``x`` (6 scalars in the tolerance's parametrisation: a left rotation
   ``w``, rad, and the centre, mm, both relative to the report) is compared with the box ``B``:
   ``d2 = min over b in B of (x - b)^T S_k^-1 (x - b)``. If the true pose lies in ``B`` (the report is
   right), ``d2 <= (x - truth)^T S_k^-1 (x - truth)``, a chi-square with 6 degrees of freedom, so
   ``P(d2 > q) <= 1 - F_chi2_6(q)`` wherever the truth is in the box. A weakly determined direction has a
   large variance in ``S_k`` and adds little to ``d2``; a report wrong along a well-determined one adds a
   lot. The critical value comes from a stated false-alarm rate for the whole map (Bonferroni over its
   frames); the images' noise is the adjustment's own a-posteriori variance factor, scaled up when the
   frames' leave-one-out residuals show more spread than it (:func:`_variance_factor`). As in geodesy's data snooping, the worst frame beyond it is set aside (its report no longer
   places the others) and the rest are tested again, until none is beyond.
3. :meth:`PoseCheck.released` — a flagged frame's report is replaced by its prediction, in a box that
   holds the prediction's confidence region at the same rate, and the bounded adjustment runs again: the
   images place the frame, and its report no longer places the map.

Units: mm and radians; pixels with their origin at the top-left pixel's centre. Poses are ``cam_from_world``.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from scope3d.estimators.bundle import BundleProblem
from scope3d.estimators.bundle.covariance import reduced_camera_system, reduced_gradient
from scope3d.estimators.bundle.solver import evaluate
from scope3d.estimators.gauge import gauge_from_measurements, moved_by
from scope3d.estimators.triangulation import TrackOptions, reprojection_errors, triangulate_tracks
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.guided_mapping import BundleStageOptions, adjust


#: Fewer triangulated points than this and the images are not asked (as the coarse pass refuses to map
#: with fewer, :func:`scope3d.sfm.guided_mapping.refine_poses_for_matching`).
MIN_POINTS = 50

#: Gauss-Newton steps that confirm a frame found beyond the critical value (the leave-one-out estimate
#: relinearised where the first step put it).
CONFIRMATION_STEPS = 2

#: A loss scale (px) no residual reaches: plain least squares on observations already within the gate.
LEAST_SQUARES = 1e6


@dataclass(frozen=True)
class PoseCheckOptions:
    """The per-frame test of reported poses.

    false_alarm_rate : float, the probability that a map whose reports are all right has any frame flagged
        (default 0.01); each frame is tested at ``false_alarm_rate / n_frames`` (Bonferroni).
    """

    false_alarm_rate: float = 0.01

    def __post_init__(self) -> None:
        if not 0 < self.false_alarm_rate < 1:
            raise ValueError(f"false_alarm_rate must be in (0, 1), got {self.false_alarm_rate}")


@dataclass
class FramePoseTest:
    """The test of one frame's report.

    frame : index. status : ``"ok"`` (tested), ``"exact"`` (a zero tolerance: trusted by definition),
        ``"unseen"`` (no observation) or ``"unplaced"`` (the other reports cannot place the images).
    predicted_pose : ``cam_from_world`` the images and the other reports predict, or None. offset : (6,)
        it relative to the report, ``(w (rad), centre (mm))``; covariance : (6, 6) of it.
    statistic : ``d2`` (at most a chi-square with 6 degrees of freedom under a right report); p_value : its
        upper tail (an upper bound on the probability of a ``d2`` this large under a right report).
    beyond_box : (6,) how far the prediction lies outside the box per scalar (0 inside; rad, mm).
    flagged : the report disagrees with the images (set aside by the data snooping).
    """

    frame: int
    status: str
    predicted_pose: Pose | None = None
    offset: np.ndarray | None = None
    covariance: np.ndarray | None = None
    statistic: float = float("nan")
    p_value: float = float("nan")
    beyond_box: np.ndarray = field(default_factory=lambda: np.zeros(6))
    flagged: bool = False

    @property
    def disagreement_mm(self) -> float:
        """Distance of the predicted centre from the report's centre (mm; NaN without a pose)."""
        return float(np.linalg.norm(self.offset[3:])) if self.offset is not None else float("nan")

    @property
    def disagreement_rad(self) -> float:
        return float(np.linalg.norm(self.offset[:3])) if self.offset is not None else float("nan")


@dataclass
class PoseCheck:
    """Every frame's test; ``critical_value`` is the chi-square (6 dof) quantile each frame was held to;
    ``variance_factor`` how much the images' pixel noise was scaled up (:func:`_variance_factor`)."""

    tests: list[FramePoseTest]
    false_alarm_rate: float
    critical_value: float
    variance_factor: float = 1.0

    @property
    def flagged(self) -> list[int]:
        return [t.frame for t in self.tests if t.flagged]

    def released(self, measured: list[MeasuredPose]) -> list[MeasuredPose]:
        """``measured`` with every flagged frame's report replaced by what the images and the other
        reports predict for it, with a box holding that prediction's confidence region at the critical
        value (``sqrt(critical value * variance)`` per scalar) and at least the reported box's size.

        Not released altogether: an unknown tolerance lets a frame the images hold weakly float, and on
        the dome (seed 21, two frames 1 mm off) the rerun map then lost its shape (0.82 mm after ICP
        against 0.14 mm). Not the report's box widened around the report either: the wrong report then
        still takes part in placing the map (3 mm glitch: 0.53 mm direct error against 0.20 mm)."""
        out = list(measured)
        for t in self.tests:
            if not t.flagged:
                continue
            m = measured[t.frame]
            reach = np.sqrt(self.critical_value * np.diag(t.covariance))
            half = np.maximum(np.r_[m.tolerance.orientation_rad, m.tolerance.position_mm], reach)
            out[t.frame] = MeasuredPose(t.predicted_pose, PoseTolerance(half[3:], half[:3]))
        return out

    def as_dict(self, names: list[str], measured: list[MeasuredPose]) -> dict:
        """For report.json: the rate, the critical value, and each flagged frame with its figures."""
        flagged = []
        for t in self.tests:
            if not t.flagged:
                continue
            tol = measured[t.frame].tolerance
            flagged.append({
                "frame": names[t.frame], "statistic": t.statistic, "p_value": t.p_value,
                "disagreement_mm": t.disagreement_mm, "disagreement_deg": float(np.rad2deg(t.disagreement_rad)),
                "beyond_tolerance_mm": float(np.linalg.norm(t.beyond_box[3:])),
                "beyond_tolerance_deg": float(np.rad2deg(np.linalg.norm(t.beyond_box[:3]))),
                "tolerance_mm": tol.position_mm.tolist(), "tolerance_deg": tol.orientation_deg.tolist(),
                "action": "released to the images' estimate"})
        tested = [t for t in self.tests if np.isfinite(t.statistic)]
        return {"false_alarm_rate": self.false_alarm_rate, "critical_chi2_6dof": self.critical_value,
                "variance_factor": self.variance_factor,
                "frames_tested": len(tested),
                "untested_frames": [names[t.frame] for t in self.tests if not np.isfinite(t.statistic)],
                "flagged": flagged}


def pose_check_lines(checks: dict) -> list[str]:
    """One line per flagged frame, for people (from :meth:`PoseCheck.as_dict`)."""
    lines = []
    for f in checks["flagged"]:
        tol = max(f["tolerance_mm"])
        p = f["p_value"]
        lines.append(f"frame {f['frame']}: reported pose disagrees with the images by {f['disagreement_mm']:.2f} mm / "
                     f"{f['disagreement_deg']:.2f} deg (tolerance {tol:.3g} mm; chi2 = {f['statistic']:.1f}, "
                     f"p {'< 1e-6' if p < 1e-6 else f'= {p:.1e}'}); {f['action']}")
    return lines


# --- 1. the images' own poses ----------------------------------------------------------------------


@dataclass
class ImageOnlyPoses:
    """A free adjustment placed on the reports.

    poses : (n) placed ``cam_from_world``. tracks : the observations it kept (untriangulated).
    noise_px : the keypoints' noise its residuals show (:func:`_noise_px`).
    """

    poses: list[Pose]
    tracks: Tracks
    noise_px: float


def image_only_adjustment(camera: Camera, measured: list[MeasuredPose], tracks: Tracks, start: list[Pose],
                          track_options: TrackOptions, bundle_options: BundleStageOptions) -> ImageOnlyPoses | None:
    """Conventional bundle adjustment of ``tracks`` from ``start``, placed on the reports by the
    least-squares similarity (:func:`scope3d.estimators.gauge.gauge_from_measurements`).

    tracks : every matched observation, untriangulated (:func:`scope3d.feature.tracks.build_tracks` of the
        map's matches), not only those the bounded map kept: a frame whose report was wrong lost its
        observations to the bounded map's reprojection gate, and the test must see them.
    start : poses to triangulate from; the first triangulation keeps observations within 3 robust sigma of
        their own errors there, as :func:`scope3d.sfm.guided_mapping.refine_poses_for_matching` does.
    Returns None when fewer than :data:`MIN_POINTS` points survive (the images then say too little).
    """
    loose = replace(track_options, max_reprojection_error_px=1e6, min_angle_deg=0.5 * track_options.min_angle_deg)
    current = triangulate_tracks(camera, start, tracks, loose)
    if current.n_tracks >= MIN_POINTS:
        err = reprojection_errors(camera, start, current)
        # 1.1774 = median of a 2-D Gaussian error's norm in sigmas (Rayleigh)
        gate = max(track_options.max_reprojection_error_px, 3.0 * float(np.median(err)) / 1.1774)
        current = triangulate_tracks(camera, start, tracks, replace(loose, max_reprojection_error_px=gate))
    if current.n_tracks < MIN_POINTS:
        return None
    unknown = [MeasuredPose(m.pose, PoseTolerance.unknown()) for m in measured]
    held = replace(bundle_options, refine_intrinsics=False)
    strict = replace(track_options, min_angle_deg=loose.min_angle_deg)
    poses = list(start)
    for round_ in range(2):
        if round_:
            current = triangulate_tracks(camera, poses, current.untriangulated(), strict)
            if current.n_tracks < MIN_POINTS:
                return None
        _, result = adjust(held, "bounded", unknown, camera, current, poses)  # no box: fix_gauge's free gauge
        poses = result.poses
    current = triangulate_tracks(camera, poses, current.untriangulated(), strict)
    if current.n_tracks < MIN_POINTS:
        return None
    problem = BundleProblem.from_measured_poses(unknown, camera, current.points, current.pixels, current.frame,
                                                current.track, refine_intrinsics=False)
    problem.start_from(poses)
    noise = _noise_px(problem, problem.initial, LEAST_SQUARES)
    return ImageOnlyPoses(moved_by(poses, gauge_from_measurements(poses, measured)), current.untriangulated(), noise)


def _noise_px(problem: BundleProblem, parameters, loss_scale_px: float) -> float:
    """The keypoints' noise (px) from an adjustment's own residuals: the a-posteriori variance factor, the
    Huber-weighted squared residuals over the redundancy (2 per observation, less 3 per point and 6 per
    observed camera, plus the 7 gauge directions). A two-view point keeps 1 of its 4 residual dimensions,
    so the residuals' plain spread understates the noise by up to 2x there; an understated noise would
    make frames of clean data look wrong (on the dome the median-based estimate was 3x too small)."""
    r, _, _ = evaluate(problem, parameters)
    norm = np.linalg.norm(r, axis=1)
    weighted = np.where(norm <= loss_scale_px, norm**2, loss_scale_px * (2.0 * norm - loss_scale_px))
    cameras = int(np.count_nonzero(np.bincount(problem.camera_index, minlength=problem.num_cameras)))
    redundancy = 2 * problem.num_observations - 3 * problem.num_points - 6 * cameras + 7
    return float(np.sqrt(weighted.sum() / max(redundancy, 1)))


@dataclass
class _QuadraticModel:
    """The images' cost in the pose scalars alone about ``parameters`` (n, 6): ``g^T d + d^T S d / 2``
    (information ``S`` (6n, 6n) and gradient ``g`` (6n,), in units of the keypoint noise); ``seen`` (n,)."""

    parameters: np.ndarray
    information: np.ndarray
    gradient: np.ndarray
    seen: np.ndarray


def _quadratic_model(camera: Camera, measured: list[MeasuredPose], tracks: Tracks, poses: list[Pose],
                     track_options: TrackOptions, loss_scale_px: float, noise_px: float) -> _QuadraticModel | None:
    """Points triangulated at ``poses``, then the reduced camera system and gradient there, in the
    tolerance boxes' coordinates (a left rotation from each report's orientation, rad; the centre, mm)."""
    current = triangulate_tracks(camera, poses, tracks, track_options)
    if current.n_tracks < MIN_POINTS:
        return None
    unknown = [MeasuredPose(m.pose, PoseTolerance.unknown()) for m in measured]
    problem = BundleProblem.from_measured_poses(unknown, camera, current.points, current.pixels, current.frame,
                                                current.track, refine_intrinsics=False)
    problem.start_from(poses)
    system, seen, _ = reduced_camera_system(problem, problem.initial, loss_scale_px, noise_px=noise_px)
    # positive semidefinite in exact arithmetic; a point whose rays are nearly parallel makes its 3x3 block
    # nearly singular and the Schur complement's round-off then has negative eigenvalues larger than the
    # reports' weights (on the 56-frame survey every leave-one-out system failed to factor)
    values, vectors = np.linalg.eigh(0.5 * (system + system.T))
    system = (vectors * np.maximum(values, 0.0)) @ vectors.T
    gradient = reduced_gradient(problem, problem.initial, loss_scale_px)
    return _QuadraticModel(problem.initial.pose.copy(), system / noise_px**2, gradient / noise_px**2, seen)


# --- 2. the test ---------------------------------------------------------------------------------


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


def _posterior(model: _QuadraticModel, prior: np.ndarray, report: np.ndarray, columns: np.ndarray | None = None):
    """Minimiser of the images' quadratic cost plus the reports' Gaussian priors (weights ``prior`` (n, 6),
    values ``report`` (n, 6)), as (n, 6), and, with ``columns`` (6n, c), the posterior covariance's columns;
    None when the priors leave the gauge free."""
    from scipy.linalg import cho_factor, cho_solve

    system = model.information + np.diag(prior.ravel())
    try:
        factor = cho_factor(system)
    except np.linalg.LinAlgError:
        return None
    rhs = model.information @ model.parameters.ravel() - model.gradient + (prior * report).ravel()
    solved = cho_solve(factor, rhs if columns is None else np.c_[rhs, columns])
    if columns is None:
        return solved.reshape(-1, 6), None
    return solved[:, 0].reshape(-1, 6), solved[:, 1:]


def _variance_factor(model: _QuadraticModel, weight: np.ndarray, report: np.ndarray, testable: list[int]) -> float:
    """How much larger the images' errors are than their pixel noise says (at least 1): the a-posteriori
    variance factor of the leave-one-out predictions, robustly. Each frame's prediction from the images
    and the other reports differs from its report by the two errors together, covariance ``S_k`` plus its
    box's ``half^2 / 3``: ``e^T (S_k + B_k)^-1 e`` is about chi-square with 6 degrees of freedom, whose
    median is 5.35. The median over the frames (a few wrong reports do not move it) over 5.35 estimates
    the factor. Keypoint errors that are not independent (the same texture seen from nearby views) make
    the pixel noise alone too optimistic: on the dome, clean frames then failed at a 1 % rate."""
    from scipy.stats import chi2

    values = []
    for k in testable:
        prior = weight.copy()
        prior[k] = 0.0
        columns = np.zeros((6 * len(weight), 6))
        columns[6 * k:6 * k + 6] = np.eye(6)
        solved = _posterior(model, prior, report, columns)
        usable = np.isfinite(weight[k]) & (weight[k] > 0)
        if solved is None or not usable.any():
            continue
        e = (solved[0][k] - report[k])[usable]
        cov = solved[1][6 * k:6 * k + 6][np.ix_(usable, usable)] + np.diag(1.0 / weight[k][usable])
        values.append(float(e @ np.linalg.solve(cov, e)) / chi2.median(int(usable.sum())))
    return max(1.0, float(np.median(values))) if len(values) >= 3 else 1.0


def test_reported_poses(camera: Camera, measured: list[MeasuredPose], tracks: Tracks, start: list[Pose],
                        track_options: TrackOptions, bundle_options: BundleStageOptions,
                        options: PoseCheckOptions = PoseCheckOptions()) -> PoseCheck:
    """Test every frame's report against the images and the other reports (see the module docstring).

    measured : the reports with their boxes; tracks : every matched observation, untriangulated; start :
    the poses the free adjustment starts from (:func:`image_only_adjustment`), best the images' own (the
    coarse pass's averaging): from the bounded map's poses, where a wrong report has pulled its frame,
    the first triangulation's gate drops that frame's evidence (dome, a report 5 mm off: not flagged from
    the bounded map, flagged from the coarse pass). The images' cost is linearised about the free
    solution; a frame found beyond the critical value is confirmed by Gauss-Newton steps of its own
    leave-one-out estimate. (Linearising everything at the estimate of images and reports together fails:
    where a wrong report pulls its frame the images' information on that frame drops, 3.5x on the glitched
    axis on the dome, and the report passes.) A frame with an exact report (trusted by definition) or
    without observations is not tested (statistic NaN).
    """
    from scipy.stats import chi2

    n = len(measured)
    critical = float(chi2.isf(options.false_alarm_rate / max(n, 1), 6))
    untested = PoseCheck([FramePoseTest(k, "unseen") for k in range(n)], options.false_alarm_rate, critical)
    images = image_only_adjustment(camera, measured, tracks, start, track_options, bundle_options)
    if images is None:
        return untested
    # the free adjustment's observations (each within the strict gate there: the images' outliers are
    # gone), all kept and weighed alike: a gate, or a robust loss, at poses where a wrong report pulls its
    # frame would discount exactly that frame's evidence
    ungated = replace(track_options, max_reprojection_error_px=1e6, min_angle_deg=0.5 * track_options.min_angle_deg)
    half = np.stack([np.r_[m.tolerance.orientation_rad, m.tolerance.position_mm] for m in measured])
    report = np.stack([np.r_[np.zeros(3), m.pose.centre] for m in measured])
    # a box as a uniform error (sigma^2 = half^2 / 3); an exact scalar as a very narrow one
    weight = np.where(np.isfinite(half), 3.0 / np.maximum(half, 1e-6) ** 2, 0.0)

    def as_poses(x: np.ndarray) -> list[Pose]:
        return [Pose.from_centre(rotvec_to_matrix(v[:3]) @ m.pose.rotation, v[3:]) for v, m in zip(x, measured)]

    model = _quadratic_model(camera, measured, images.tracks, images.poses, ungated, LEAST_SQUARES, images.noise_px)
    if model is None:
        return untested
    testable = [k for k in range(n) if model.seen[k] and not measured[k].tolerance.is_exact]
    factor = _variance_factor(model, weight, report, testable)
    model = replace(model, information=model.information / factor, gradient=model.gradient / factor)
    noise_px = images.noise_px * np.sqrt(factor)
    def leave_one_out(k: int, kept: np.ndarray, model: _QuadraticModel) -> FramePoseTest:
        prior = kept.copy()
        prior[k] = 0.0
        columns = np.zeros((6 * n, 6))
        columns[6 * k:6 * k + 6] = np.eye(6)
        solved = _posterior(model, prior, report, columns)
        if solved is None:  # the other reports cannot place the images without this one
            return FramePoseTest(k, "unplaced")
        predicted, covariance = solved[0][k], solved[1][6 * k:6 * k + 6]
        offset = predicted - report[k]
        statistic, nearest = box_mahalanobis(offset, covariance, half[k])
        return FramePoseTest(k, "ok", as_poses(solved[0])[k], offset, covariance, statistic,
                             float(chi2.sf(statistic, 6)), np.abs(offset - nearest), k in set_aside)

    def confirmed(test: FramePoseTest, kept: np.ndarray) -> FramePoseTest:
        """The leave-one-out estimate carried to convergence: Gauss-Newton steps, each linearised at the
        previous step's poses (the free solution can sit far along a weakly fixed direction, where one
        linearisation misjudges the curvature)."""
        prior = kept.copy()
        prior[test.frame] = 0.0
        for _ in range(CONFIRMATION_STEPS):
            solved = _posterior(model, prior, report)
            at = None if solved is None else _quadratic_model(camera, measured, images.tracks, as_poses(solved[0]),
                                                              ungated, LEAST_SQUARES, noise_px)
            if at is None:
                return test
            test = leave_one_out(test.frame, kept, at)
        return test

    set_aside: list[int] = []
    while True:
        kept = weight.copy()
        kept[set_aside] = 0.0
        tests = [leave_one_out(k, kept, model) if k in testable
                 else FramePoseTest(k, "exact" if measured[k].tolerance.is_exact else "unseen") for k in range(n)]
        # only frames beyond the critical value need the nonlinear estimate (a few at most)
        tests = [confirmed(t, kept) if t.statistic > critical and not t.flagged else t for t in tests]
        candidates = [t for t in tests if np.isfinite(t.statistic) and not t.flagged and t.statistic > critical]
        if not candidates:
            return PoseCheck(tests, options.false_alarm_rate, critical, factor)
        set_aside.append(max(candidates, key=lambda t: t.statistic).frame)
