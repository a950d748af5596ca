"""Panoramic registration of side-view quadrants (reference sec. 8.3, eqs. 8.3-8.7), generalised.

A side-viewing scope scans a hole in ``k`` quadrants, each rotated by the same stage angle about the
hole axis. Each quadrant's sparse cloud is first placed in one frame with the stage's nominal poses (the
"stacked" initial guess); the camera's unknown offset and tilt from the rotation axis, and the stage's
own error, leave each quadrant slightly off. Neighbouring quadrants share features: SIFT descriptors of
their 3-D points matched across the pair give 3-D-3-D correspondences, and a robust rigid fit (RANSAC +
SVD, eqs. 8.1-8.2, :mod:`.rigid`) gives each neighbour pair's relative transform. Chaining the pairs
round the circle should give the identity; what it gives instead is the loop-closure residual.

The joint solve (eqs. 8.5-8.7) then places every quadrant at once from all pairs' correspondences, with
the last-to-first pair closing the loop, so that its error spreads round the circle instead of piling up
in the last quadrant. The reference keeps one known rotation for every neighbour pair and solves the
offsets ``C_ij`` linearly (eq. 8.7); here the unknowns are each quadrant's rigid correction
(``world_from_stacked``, quadrant 0 fixed as the gauge), translations only when the stage's rotation is
trusted (``solve_rotations=False``: linear, as eq. 8.7) or rotations too when the stage is only
approximately known (default), by robust non-linear least squares from the chained pairwise estimate.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import matrix_to_rotvec, rotation_angle_between, rotvec_to_matrix
from scope3d.registration.rigid import RansacOptions, fit_rigid, ransac_rigid
from scope3d.utils.robust import robust_sigma


@dataclass
class QuadrantCloud:
    """One quadrant's sparse reconstruction in the stacked frame.

    index : int, quadrant number (0..k-1, in stage order). angle_deg : float, the stage's rotation.
    points : (N, 3) float64 mm (stacked frame: the stage's nominal poses; its z axis is the stage's
        nominal rotation axis through the origin, which the "stage" model needs).
    descriptors : (N, 128) float32, a SIFT descriptor per point (its first observation's).
    colors : (N, 3) uint8 or None.
    observation_point, observation_frame : (M,) int64 or None, every view of every point: its point and
        its frame's place in the quadrant's order of advance; observation_descriptors : (M, 128) float32
        or None, that view's SIFT descriptor (see :func:`match_quadrants`).
    """

    index: int
    angle_deg: float
    points: np.ndarray
    descriptors: np.ndarray
    colors: np.ndarray | None = None
    observation_point: np.ndarray | None = None
    observation_frame: np.ndarray | None = None
    observation_descriptors: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, float).reshape(-1, 3)
        self.descriptors = np.asarray(self.descriptors, np.float32).reshape(len(self.points), -1)

    @property
    def has_observations(self) -> bool:
        return self.observation_descriptors is not None and len(self.observation_descriptors) > 0


@dataclass(frozen=True)
class PanoramaOptions:
    """Options of :func:`register_quadrants`.

    ratio : float, Lowe's ratio test between the two quadrants' descriptors (default 0.8, the reference's).
    ransac : RansacOptions of the pairwise rigid fits (default inlier threshold 0.15 mm: a sparse side-view
        point triangulated over a 0.1-0.7 mm axial baseline at ~5 mm range is good to ~0.05-0.1 mm along
        its ray, measured on the phantom's M8 quadrants at 400x320 px).
    min_correspondences : int, a neighbour pair with fewer RANSAC inliers does not overlap (default 12).
    model : "stage" (default) or "free". "stage": the rotation stage's model, few unknowns — one rigid
        mount error ``D`` shared by every quadrant (the camera's offset and tilt from the rotation axis;
        its rotation about and shift along the axis are the gauge) seen through each quadrant's nominal
        stage rotation ``S_q`` about the stacked frame's z axis, plus per quadrant a stage-angle error and an
        axial re-positioning error: ``G_q = Tz(dz_q) Rz(e_q) S_q D S_q^-1`` (quadrant 0: e = dz = 0).
        "free": a free rigid correction per quadrant (the pose graph; needs no stage, but is noisier).
    solve_rotations : bool, "free" model only: solve each quadrant's rotation too (default True); False
        trusts the stacked rotations and solves the offsets only (linear, as eq. 8.7).
    angle_tolerance_deg : float, the quadrants' stage angles must step evenly within this (default 1°).
    loss_scale_mm : float, scale of the joint solve's robust loss (default 0.05 mm, a third of the pairwise
        inlier threshold).
    """

    ratio: float = 0.8
    ransac: RansacOptions = RansacOptions(threshold_mm=0.15)
    min_correspondences: int = 12
    model: str = "stage"
    solve_rotations: bool = True
    angle_tolerance_deg: float = 1.0
    loss_scale_mm: float = 0.05

    def __post_init__(self) -> None:
        if not 0 < self.ratio <= 1 or self.min_correspondences < 3:
            raise ValueError("need ratio in (0, 1] and min_correspondences >= 3")
        if self.model not in ("stage", "free"):
            raise ValueError(f"model must be 'stage' or 'free', got {self.model!r}")
        if not (self.angle_tolerance_deg > 0 and self.loss_scale_mm > 0):
            raise ValueError("need angle_tolerance_deg > 0 and loss_scale_mm > 0")


@dataclass
class PairRegistration:
    """i, j : quadrants; i_from_j : Pose taking quadrant j's stacked frame to quadrant i's (maps j's
    points onto i's); points_i, points_j : (M, 3) mm inlier correspondences; n_matches : before RANSAC;
    rms_mm : inliers' residual; time_s : matching + RANSAC."""

    i: int
    j: int
    i_from_j: Pose
    points_i: np.ndarray
    points_j: np.ndarray
    n_matches: int
    rms_mm: float
    time_s: float


@dataclass(frozen=True, eq=False)
class StagePoseModel:
    """The rotation-stage model's parameters -> every quadrant's ``world_from_stacked`` (see
    :class:`PanoramaOptions`), for quadrants at the stage angles ``angles_rad`` (k,). Plain data, so a
    result holding it pickles (cluster workers)."""

    angles_rad: np.ndarray

    def __call__(self, x: np.ndarray) -> list[Pose]:
        return _stage_poses(x, self.angles_rad)


@dataclass(frozen=True, eq=False)
class FreePoseModel:
    """The free model's parameters -> every quadrant's ``world_from_stacked`` (quadrant 0 the identity):
    a rotation vector and an offset per other quadrant, or the offsets alone under fixed ``rotations``
    (k, 3, 3)."""

    n_quadrants: int
    rotations: np.ndarray | None = None

    def __call__(self, x: np.ndarray) -> list[Pose]:
        return _poses_from_params(x, self.n_quadrants, self.rotations)


@dataclass
class PanoramaResult:
    """world_from_stacked : one Pose per quadrant (quadrant 0 the identity: the gauge).
    pairs : the pairwise registrations. loop_closure_deg, loop_closure_mm : rotation angle of the chained
    pairwise transforms round the circle, and how far that chain moves quadrant 0's centroid (None when
    the quadrants do not close a circle). residual_rms_mm : correspondences' RMS after the joint solve,
    per pair. step_deg : the stage's angle step."""

    world_from_stacked: list[Pose]
    pairs: list[PairRegistration]
    loop_closure_deg: float | None
    loop_closure_mm: float | None
    residual_rms_mm: list[float]
    step_deg: float
    closed: bool
    log: list[str] = field(default_factory=list)
    parameters: np.ndarray | None = None
    parameter_covariance: np.ndarray | None = None
    pose_model: StagePoseModel | FreePoseModel | None = field(default=None, repr=False)

    def apply(self, clouds: list[QuadrantCloud]) -> list[np.ndarray]:
        """Each quadrant's points in the registered frame, (N_q, 3) mm each."""
        return [g.transform(c.points) for g, c in zip(self.world_from_stacked, clouds)]

    def sample_world_from_stacked(self, n: int, seed: int = 0) -> list[list[Pose]]:
        """``n`` draws of every quadrant's ``world_from_stacked`` from the joint solve's estimate and its
        covariance (Gaussian, linearised at the solution): the registration's own uncertainty, for
        propagating into what is measured on the registered cloud. Empty without a covariance."""
        if self.parameter_covariance is None or self.pose_model is None or n < 1:
            return []
        rng = np.random.default_rng(seed)
        draws = rng.multivariate_normal(self.parameters, self.parameter_covariance, size=n, method="eigh")
        return [self.pose_model(x) for x in draws]


def registered_frame_poses(world_from_stacked: Pose, poses: list[Pose], anchor: int) -> list[Pose]:
    """The frames of one quadrant in the registered world, from the stage's reported ``cam_from_world``
    ``poses`` (the stacked frame) and the quadrant's ``world_from_stacked``. The registration is exact at
    the ``anchor`` frame; the others keep their orientation relative to it but are displaced from it by the
    stage's reported axial steps *in the world* (the stage advances along its own axis, whatever the
    camera's unknown tilt): moving them rigidly with the quadrant would turn a tilted camera's baseline
    with it, and a 0.5° tilt at a 45° view changes the baseline across the view by ~1 % and every
    triangulated depth with it."""
    c_anchor = poses[anchor].centre
    out = []
    for p in poses:
        world_from_cam = world_from_stacked @ p.inverse()
        centre = world_from_stacked.transform(c_anchor[None])[0] + (p.centre - c_anchor)
        out.append(Pose.from_centre(world_from_cam.rotation.T, centre))
    return out


def check_quadrant_angles(clouds: list[QuadrantCloud], tolerance_deg: float = 1.0) -> tuple[float, bool]:
    """The stage's angle step and whether the quadrants close a full circle. Raises :class:`InputError`
    naming the first quadrant whose angle breaks the even stepping (or an out-of-order index)."""
    if len(clouds) < 2:
        raise InputError(f"panoramic registration needs at least 2 quadrants, got {len(clouds)}")
    for k, c in enumerate(clouds):
        if c.index != k:
            raise InputError(f"quadrant {c.index} is at position {k}: quadrants must be numbered 0..{len(clouds) - 1} in order")
    angles = np.array([c.angle_deg for c in clouds], float)
    steps = (np.diff(angles) + 180.0) % 360.0 - 180.0
    step = float(np.median(steps))
    if abs(step) < tolerance_deg:
        raise InputError(f"quadrants 0 and 1 have the same stage angle ({angles[0]:.2f}°)")
    for k, s in enumerate(steps):
        if abs(s - step) > tolerance_deg:
            raise InputError(f"quadrant {k + 1}: stage angle {angles[k + 1]:.2f}° is {s:.2f}° from quadrant {k}'s, "
                             f"the others step by {step:.2f}° (inconsistent rotation angles)")
    closed = abs(abs(step) * len(clouds) - 360.0) <= tolerance_deg * len(clouds)
    return step, closed


def match_descriptors(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours passing Lowe's ratio test (L2, OpenCV brute force). -> (idx_a, idx_b)."""
    import cv2

    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    ab = matcher.knnMatch(desc_a, desc_b, k=2)
    ba = matcher.match(desc_b, desc_a)
    back = np.full(len(desc_b), -1)
    for m in ba:
        back[m.queryIdx] = m.trainIdx
    a, b = [], []
    for m in ab:
        if len(m) == 2 and m[0].distance < ratio * m[1].distance and back[m[0].trainIdx] == m[0].queryIdx:
            a.append(m[0].queryIdx)
            b.append(m[0].trainIdx)
    return np.asarray(a, np.int64), np.asarray(b, np.int64)


def _frame_pairs(frames_i: np.ndarray, frames_j: np.ndarray, window: int) -> list[tuple[int, int]]:
    """Pairs (f, g) of frames of two quadrants at most ``window`` steps of advance apart."""
    fi, fj = np.unique(frames_i), np.unique(frames_j)
    return [(int(f), int(g)) for f in fi for g in fj if abs(int(f) - int(g)) <= window]


def match_quadrants(cloud_i: QuadrantCloud, cloud_j: QuadrantCloud, ratio: float,
                    advance_window: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """3-D-3-D correspondences of two neighbour quadrants from their points' descriptors -> (idx_i, idx_j),
    unique pairs of point indices.

    Each point's first-view descriptor is matched across the pair; and, when the clouds keep every view
    of their points, so are the views in the frames taken at the same advance (the same place in each
    quadrant's order: the stage repeats its axial steps every quadrant). Two such frames differ by the
    stage's turn about the axis only, so a surface point looks alike in both; its first views, in
    general from different heights, see it from directions up to the view's whole vertical field apart
    (a thread crest seen from above and from below), and match far less often."""
    a, b = match_descriptors(cloud_i.descriptors, cloud_j.descriptors, ratio)
    pairs = [np.stack([a, b], 1)]
    if cloud_i.has_observations and cloud_j.has_observations:
        for f, g in _frame_pairs(cloud_i.observation_frame, cloud_j.observation_frame, advance_window):
            in_i = np.flatnonzero(cloud_i.observation_frame == f)
            in_j = np.flatnonzero(cloud_j.observation_frame == g)
            oa, ob = match_descriptors(cloud_i.observation_descriptors[in_i], cloud_j.observation_descriptors[in_j], ratio)
            pairs.append(np.stack([cloud_i.observation_point[in_i[oa]], cloud_j.observation_point[in_j[ob]]], 1))
    unique = np.unique(np.concatenate(pairs).astype(np.int64).reshape(-1, 2), axis=0)
    return unique[:, 0], unique[:, 1]


def register_pair(cloud_i: QuadrantCloud, cloud_j: QuadrantCloud, *, options: PanoramaOptions = PanoramaOptions(), 
                  seed: int = 0) -> PairRegistration:
    """Feature-based registration of two neighbour quadrants (sec. 8.2.2): descriptor matches give
    3-D-3-D correspondences; RANSAC + SVD the rigid ``i_from_j``. Raises :class:`InputError` naming the
    quadrants when they share too few consistent correspondences (no overlap)."""
    import time

    t0 = time.perf_counter()
    a, b = match_quadrants(cloud_i, cloud_j, options.ratio)
    fit = ransac_rigid(cloud_j.points[b], cloud_i.points[a], options=options.ransac, seed=seed) if len(a) >= 3 else None
    n_inl = 0 if fit is None else fit.n_inliers
    if n_inl < options.min_correspondences:
        raise InputError(f"quadrants {cloud_i.index} and {cloud_j.index} (stage {cloud_i.angle_deg:.1f}° and "
                         f"{cloud_j.angle_deg:.1f}°): {n_inl} consistent feature correspondences of {len(a)} matches, "
                         f"need {options.min_correspondences}: the quadrants do not overlap")
    return PairRegistration(cloud_i.index, cloud_j.index, fit.target_from_source, cloud_i.points[a][fit.inliers],
                            cloud_j.points[b][fit.inliers], len(a), fit.rms_mm, time.perf_counter() - t0)


def _poses_from_params(x: np.ndarray, k: int, rotations: np.ndarray | None) -> list[Pose]:
    out = [Pose.identity()]
    for q in range(1, k):
        if rotations is None:
            out.append(Pose(rotvec_to_matrix(x[6 * (q - 1):6 * (q - 1) + 3]), x[6 * (q - 1) + 3:6 * q]))
        else:
            out.append(Pose(rotations[q], x[3 * (q - 1):3 * q]))
    return out


def solve_panorama(pairs: list[PairRegistration], n_quadrants: int, *, solve_rotations: bool = True,
                   loss_scale_mm: float = 0.03, return_covariance: bool = False):
    """Joint solve (eqs. 8.5-8.7, generalised): each quadrant's ``world_from_stacked`` (quadrant 0 fixed)
    minimising ``|G_i p_i - G_j p_j|`` over every pair's correspondences, robustly (soft L1). Started from
    the pairs chained from quadrant 0 (the last-to-first pair, if any, then only enters the solve).
    Returns (poses, per-pair residual RMS in mm), and with ``return_covariance`` also the parameters,
    their covariance (or None) and the model from parameters to poses."""
    k = n_quadrants
    chained = [Pose.identity()] + [None] * (k - 1)
    for p in pairs:
        if p.j == p.i + 1 and chained[p.i] is not None:
            chained[p.j] = chained[p.i] @ p.i_from_j
    if any(c is None for c in chained):
        missing = next(q for q, c in enumerate(chained) if c is None)
        raise InputError(f"quadrant {missing} is not linked to quadrant {missing - 1} by a registered pair")
    if solve_rotations:
        x0 = np.concatenate([np.concatenate([matrix_to_rotvec(c.rotation), c.translation]) for c in chained[1:]])
        fixed_rot = None
        width = 6
    else:
        # The stage's rotation trusted: only the offsets are unknown, and the problem is linear (eq. 8.7).
        fixed_rot = np.stack([np.eye(3)] * k)
        x0 = np.concatenate([c.translation for c in chained[1:]])
        width = 3
    n_res = sum(3 * len(p.points_i) for p in pairs)
    sparsity = lil_matrix((n_res, len(x0)), dtype=int)
    row = 0
    for p in pairs:
        m = 3 * len(p.points_i)
        for q in (p.i, p.j):
            if q > 0:
                sparsity[row:row + m, width * (q - 1):width * q] = 1
        row += m

    def residual(x):
        poses = _poses_from_params(x, k, fixed_rot)
        return np.concatenate([(poses[p.i].transform(p.points_i) - poses[p.j].transform(p.points_j)).ravel()
                               for p in pairs])

    sol = least_squares(residual, x0, jac_sparsity=sparsity, loss="soft_l1", f_scale=loss_scale_mm, x_scale="jac")
    poses = _poses_from_params(sol.x, k, fixed_rot)
    rms = [float(np.sqrt(np.mean(np.sum((poses[p.i].transform(p.points_i) - poses[p.j].transform(p.points_j)) ** 2, 1))))
           for p in pairs]
    if return_covariance:
        return poses, rms, sol.x, _covariance(sol, loss_scale_mm), FreePoseModel(k, fixed_rot)
    return poses, rms


def _covariance(sol, loss_scale_mm: float) -> np.ndarray | None:
    """Covariance of a robust least-squares solution's parameters, linearised at the solution:
    ``s^2 (J^T J)^-1`` over the core residuals (within 3 loss scales and 3 robust sigmas; the others are
    the robust loss' outliers), ``s^2`` their mean square per degree of freedom. Assumes independent
    residuals; None when the Jacobian is singular."""
    res = sol.fun
    core = np.abs(res) < 3 * loss_scale_mm + 3 * robust_sigma(res, about=0.0)
    jac = sol.jac[core]
    jac = jac.toarray() if hasattr(jac, "toarray") else np.asarray(jac)
    dof = int(core.sum()) - len(sol.x)
    if dof < 1:
        return None
    try:
        return np.linalg.inv(jac.T @ jac) * float(np.sum(res[core] ** 2) / dof)
    except np.linalg.LinAlgError:
        return None


def _stage_poses(x: np.ndarray, angles_rad: np.ndarray) -> list[Pose]:
    """``G_q = Tz(dz_q) Rz(e_q) S_q D S_q^-1`` from x = (D's rotation about x, y; D's shift along x, y;
    e_1..e_k-1; dz_1..dz_k-1)."""
    k = len(angles_rad)
    d = Pose(rotvec_to_matrix([x[0], x[1], 0.0]), [x[2], x[3], 0.0])
    e = np.concatenate([[0.0], x[4:4 + k - 1]])
    dz = np.concatenate([[0.0], x[4 + k - 1:4 + 2 * (k - 1)]])
    out = []
    for q in range(k):
        s_q = Pose(rotvec_to_matrix([0.0, 0.0, angles_rad[q]]), np.zeros(3))
        fix = Pose(rotvec_to_matrix([0.0, 0.0, e[q]]), [0.0, 0.0, dz[q]])
        out.append(fix @ s_q @ d @ s_q.inverse())
    return out


def solve_stage_model(pairs: list[PairRegistration], angles_deg: list[float], *,
                      loss_scale_mm: float = 0.05, return_covariance: bool = False):
    """Joint solve under the rotation-stage model (see :class:`PanoramaOptions`): 4 + 2 (k - 1) unknowns
    from every pair's correspondences, started at the stacked guess. Returns (world_from_stacked per
    quadrant, per-pair residual RMS in mm), and with ``return_covariance`` also the parameters, their
    covariance (or None) and the model from parameters to poses."""
    angles = np.deg2rad(np.asarray(angles_deg, float))
    k = len(angles)

    def residual(x):
        poses = _stage_poses(x, angles)
        return np.concatenate([(poses[p.i].transform(p.points_i) - poses[p.j].transform(p.points_j)).ravel()
                               for p in pairs])

    sol = least_squares(residual, np.zeros(4 + 2 * (k - 1)), loss="soft_l1", f_scale=loss_scale_mm, x_scale="jac")
    poses = _stage_poses(sol.x, angles)
    rms = [float(np.sqrt(np.mean(np.sum((poses[p.i].transform(p.points_i) - poses[p.j].transform(p.points_j)) ** 2, 1))))
           for p in pairs]
    if return_covariance:
        return poses, rms, sol.x, _covariance(sol, loss_scale_mm), StagePoseModel(angles)
    return poses, rms


def loop_closure(pairs: list[PairRegistration], clouds: list[QuadrantCloud]) -> tuple[float, float]:
    """Chain every neighbour pair's ``i_from_j`` round the circle (0 <- 1 <- ... <- k-1 <- 0): its rotation
    angle (degrees) and the displacement of quadrant 0's centroid (mm); both 0 for a perfect loop."""
    loop = Pose.identity()
    for p in pairs:
        loop = loop @ p.i_from_j
    centroid = clouds[0].points.mean(axis=0)
    return (float(np.rad2deg(rotation_angle_between(loop.rotation, np.eye(3)))),
            float(np.linalg.norm(loop.transform(centroid[None])[0] - centroid)))


def joint_solve(pairs: list[PairRegistration], angles_deg: list[float], *,
                options: PanoramaOptions = PanoramaOptions()):
    """The joint solve of ``options.model`` over the pairs -> (world_from_stacked per quadrant, per-pair
    residual RMS mm, parameters, their covariance or None, the model from parameters to poses)."""
    if options.model == "stage":
        return solve_stage_model(pairs, angles_deg, loss_scale_mm=options.loss_scale_mm, return_covariance=True)
    return solve_panorama(pairs, len(angles_deg), solve_rotations=options.solve_rotations,
                          loss_scale_mm=options.loss_scale_mm, return_covariance=True)


def pairs_drawn_apart(pairs: list[PairRegistration], gap_mm: float) -> list[PairRegistration]:
    """The pairs with every correspondence's two points drawn apart along the circle about the stacked z
    axis (the stage's): the first quadrant's point moved by ``gap_mm / 2`` against the direction of
    increasing angle, the second's by as much along it — as if each keypoint lay ``gap_mm / 2`` nearer its
    own frame's centre along a crest than its match does. Neighbours overlap at the edges of their views,
    so the joint solve can close such a gap only by moving every quadrant radially (by ~gap / (2 sin(s / 2))
    for a stage step s): a bias of the diameters that the correspondences' scatter does not show."""
    def along_circle(points):
        radial = points[:, :2] / np.maximum(np.linalg.norm(points[:, :2], axis=1, keepdims=True), 1e-12)
        return np.c_[-radial[:, 1], radial[:, 0], np.zeros(len(points))]

    return [PairRegistration(p.i, p.j, p.i_from_j, p.points_i - gap_mm / 2 * along_circle(p.points_i),
                             p.points_j + gap_mm / 2 * along_circle(p.points_j), p.n_matches, p.rms_mm, p.time_s)
            for p in pairs]


def register_quadrants(clouds: list[QuadrantCloud], *, options: PanoramaOptions = PanoramaOptions(), 
                       seed: int = 0, progress=None) -> PanoramaResult:
    """Pairwise feature-based registration of angular neighbours, then the joint solve with the loop
    closure. clouds : quadrants in stage order (see :class:`QuadrantCloud`). Raises :class:`InputError`
    naming the quadrant for inconsistent stage angles or a pair without overlap."""
    from scope3d.utils.progress import advance, stage

    step, closed = check_quadrant_angles(clouds, options.angle_tolerance_deg)
    k = len(clouds)
    links = [(q, q + 1) for q in range(k - 1)] + ([(k - 1, 0)] if closed and k > 2 else [])
    stage(progress, "registering quadrant pairs", len(links))
    pairs = []
    for i, j in links:
        pairs.append(register_pair(clouds[i], clouds[j], options=options, seed=seed + i))
        advance(progress)
    log = [f"pair {p.i}-{p.j}: {len(p.points_i)} of {p.n_matches} matches consistent, rms {p.rms_mm:.4f} mm"
           for p in pairs]
    loop_deg = loop_mm = None
    if closed and k > 2:
        loop_deg, loop_mm = loop_closure(pairs, clouds)
        log.append(f"loop closure of the chained pairs: {loop_deg:.3f}°, {loop_mm:.4f} mm")
    poses, rms, x, cov, model = joint_solve(pairs, [c.angle_deg for c in clouds], options=options)
    return PanoramaResult(poses, pairs, loop_deg, loop_mm, rms, step, closed and k > 2, log, x, cov, model)


def registration_errors(estimated: list[Pose], truth: list[Pose], clouds: list[QuadrantCloud]) -> tuple[np.ndarray, np.ndarray]:
    """Per-quadrant errors of ``world_from_stacked`` against the truth, the common rigid motion (the
    gauge) removed by a least-squares fit over every point. Returns (rotation error in degrees (k,),
    offset error in mm (k,): RMS displacement of the quadrant's own points)."""
    est = np.concatenate([g.transform(c.points) for g, c in zip(estimated, clouds)])
    tru = np.concatenate([g.transform(c.points) for g, c in zip(truth, clouds)])
    align = fit_rigid(est, tru)
    rot, off = [], []
    for g, t, c in zip(estimated, truth, clouds):
        err = t.inverse() @ align @ g
        rot.append(np.rad2deg(rotation_angle_between(err.rotation, np.eye(3))))
        off.append(np.sqrt(np.mean(np.sum((err.transform(c.points) - c.points) ** 2, axis=1))))
    return np.asarray(rot), np.asarray(off)
