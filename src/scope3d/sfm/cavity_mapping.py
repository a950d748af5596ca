"""Image-only mapping of a closed cavity seen from inside (reference sec. 2.3.4, 2.4.3): key frames, poses
and points from the images, with a spherical shape prior that is then released.

A scope inside a bladder turns about a point near the cavity's centre: baselines are a few millimetres
against a wall 30-50 mm away, so essential matrices fix the relative rotations well and the positions
poorly, and free bundle adjustment started anywhere can fold the wall. The reference constrained the
points to a sphere first and then released the constraint. Here:

1. :func:`select_key_frames` — a frame becomes a key frame when its features have moved far enough from
   the last key frame's (a rendered spiral: every frame).
2. :func:`scope3d.sfm.coarse_poses.coarse_poses` finds the overlapping pairs and their relative poses by
   retrieval and essential matrices (with an infinite tolerance it tries any pair retrieval proposes).
3. :func:`start_poses` — rotations chained along a maximum spanning tree of the verified pairs (most
   inliers first), then averaged over every pair (:func:`scope3d.estimators.averaging.average_rotations`).
   Measured poses with a finite tolerance (a plan) are used instead where given.
4. :func:`points_on_sphere` — every camera starts at the cavity centre (or its planned centre) and every
   track at the mean of its rays' intersections with a sphere of the nominal radius about that centre.
5. :func:`adjust_cavity` — bundle adjustment with every point bounded to the spherical shell between an
   anatomical minimum and maximum radius (:meth:`BundleProblem.bound_points_to_shell`), then the bound is
   released and the adjustment repeated (robust Huber loss both times), poses bounded by their tolerance.
   The gauge: the first camera's pose and the radius of the longest track's point (the scale the sphere
   chose; the stars fix it afterwards, :mod:`scope3d.metrology.star_scale`).

Units: mm (the provisional scale of the nominal radius until the stars rescale), radians; pixels with their
origin at the top-left pixel's centre. Poses are ``cam_from_world``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

from scope3d.errors import InputError
from scope3d.estimators.averaging import RelativePose, average_rotations, refine_relative_pose
from scope3d.estimators.bundle import BundleProblem, BundleResult, SolverOptions, solve
from scope3d.estimators.triangulation import reprojection_errors
from scope3d.feature.detection import Features
from scope3d.feature.matching import MatchOptions, match_exhaustive
from scope3d.geometry.pose import Pose
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose


@dataclass(frozen=True)
class KeyFrameOptions:
    """min_motion_fraction : float, a frame becomes a key frame when the median motion of its features
        matched to the last key frame reaches this fraction of the image width, or when fewer than
        ``min_matches`` match (default 0.15: consecutive key frames then share about 85 % of the field,
        enough for tracks of three or more views).
    min_matches : int, below this many verified matches with the last key frame the frame is a key frame
        regardless of motion (default 30).
    """

    min_motion_fraction: float = 0.15
    min_matches: int = 30

    def __post_init__(self) -> None:
        if not 0 <= self.min_motion_fraction < 1 or self.min_matches < 8:
            raise ValueError("need 0 <= min_motion_fraction < 1 and min_matches >= 8")


def select_key_frames(camera: Camera, features: list[Features], options: KeyFrameOptions = KeyFrameOptions(),
                      match_options: MatchOptions = MatchOptions()) -> np.ndarray:
    """Indices (K,) int of the key frames, in order; frame 0 is always one. Each frame is matched to the last
    key frame only (one exhaustive match per frame)."""
    keys = [0]
    for k in range(1, len(features)):
        m = match_exhaustive(camera, features[keys[-1]], features[k], match_options, i=keys[-1], j=k)
        if len(m) < options.min_matches:
            keys.append(k)
            continue
        motion = np.median(np.linalg.norm(features[k].keypoints[m.idx_j] - features[keys[-1]].keypoints[m.idx_i], axis=1))
        if motion >= options.min_motion_fraction * camera.width:
            keys.append(k)
    return np.asarray(keys, dtype=int)


@dataclass(frozen=True)
class CavityOptions:
    """The shape prior and the adjustments.

    nominal_radius_mm : float, radius of the starting sphere (default 40 mm: a sphere of 270 ml, a bladder
        half filled for cystoscopy; adult capacity is 400-600 ml). Without a plan or the stars this is also
        the provisional scale.
    min_radius_mm, max_radius_mm : float, the anatomical shell every point is held in during the first
        adjustment (defaults 20 and 70 mm: spheres of 34 ml and 1.4 l, an almost empty and an over-filled
        adult bladder). Scaled with the provisional scale when the scale is not known.
    loss_scale_px : float, Huber scale of both adjustments (default 1 px: SIFT localisation is 0.3-0.5 px).
    max_iterations : int, LM iterations per adjustment (default 100).
    max_reprojection_error_px : float, observations still farther than this from their point after the
        released adjustment are dropped and the adjustment repeated once (default 2 px, 4 sigma of SIFT).
    max_points : int, at most this many tracks (the longest) enter the adjustments (default 6000).
    release_shell : bool, drop the shell in the last adjustment too (default False: the sphere is released
        into the shell, and the shell stays; a two-view track of a few millimetres' baseline has no depth
        of its own, and without the shell such points ran off towards infinity, dragging the poses with
        them: 12-30 deg of rotation error even when started from the true poses on the bladder spiral).
    """

    nominal_radius_mm: float = 40.0
    min_radius_mm: float = 20.0
    max_radius_mm: float = 70.0
    loss_scale_px: float = 1.0
    max_iterations: int = 100
    max_reprojection_error_px: float = 2.0
    max_points: int = 6000
    release_shell: bool = False

    def __post_init__(self) -> None:
        if not 0 < self.min_radius_mm <= self.nominal_radius_mm <= self.max_radius_mm:
            raise ValueError("need 0 < min_radius_mm <= nominal_radius_mm <= max_radius_mm")
        if self.loss_scale_px <= 0 or self.max_iterations < 1 or self.max_reprojection_error_px <= 0 or self.max_points < 10:
            raise ValueError("need loss_scale_px > 0, max_iterations >= 1, max_reprojection_error_px > 0, max_points >= 10")


def knows_poses(measured: list[MeasuredPose]) -> bool:
    """True when every measured pose has a finite tolerance (a plan or a robot), False for image-only."""
    return all(np.all(np.isfinite(m.tolerance.position_mm)) and np.all(np.isfinite(m.tolerance.orientation_rad))
               for m in measured)


def rotation_from_bearings(camera: Camera, pixels_i: np.ndarray, pixels_j: np.ndarray, i: int = 0, j: int = 1, *,
                           noise_px: float = 0.5) -> RelativePose:
    """The rotation ``R_ji`` that best turns frame i's bearings onto frame j's (M, 2) pixels each, as if the
    scope had turned about its centre (Kabsch on unit rays; Wahba's problem).

    Why not the essential matrix: with baselines of 2-6 mm against a wall 40 mm away, a third of the
    bladder spiral's pairs decomposed into a rotation 5-11 deg (or 180 deg) off, the translation along
    the wrong axis (the rotation-translation ambiguity of short baselines), while the rotation of the
    bearings is wrong only by the parallax (a few degrees, smooth along the path), which the shell-bounded
    adjustment then removes. ``rotation_sigma_rad`` is the residual angle's RMS over sqrt(M): the parallax
    left unexplained, not the keypoint noise (``noise_px`` is its floor). ``direction`` is left zero.
    """
    a = np.c_[camera.pixel_to_normalised(np.asarray(pixels_i, float)), np.ones(len(pixels_i))]
    b = np.c_[camera.pixel_to_normalised(np.asarray(pixels_j, float)), np.ones(len(pixels_j))]
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    U, _, Vt = np.linalg.svd(b.T @ a)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    resid = np.linalg.norm(b - a @ R.T, axis=1)
    floor = noise_px / (0.5 * (camera.fx + camera.fy))
    sigma = max(float(np.sqrt(np.mean(resid**2))), floor) / np.sqrt(len(a))
    return RelativePose(i, j, R, np.zeros(3), np.ones(len(a), bool), sigma, np.inf)


def depth_spread(camera: Camera, pixels_i: np.ndarray, pixels_j: np.ndarray, relative: RelativePose) -> float:
    """Spread of the triangulated points' distances from camera i: median absolute deviation over the
    median (0 for a sphere seen from its centre), over the pair's inliers in front of both cameras;
    inf when fewer than half lie in front."""
    di = np.c_[camera.pixel_to_normalised(np.asarray(pixels_i, float)), np.ones(len(pixels_i))]
    dj = np.c_[camera.pixel_to_normalised(np.asarray(pixels_j, float)), np.ones(len(pixels_j))] @ relative.rotation
    di /= np.linalg.norm(di, axis=1, keepdims=True)
    dj /= np.linalg.norm(dj, axis=1, keepdims=True)
    cj = -relative.rotation.T @ relative.direction  # centre j in frame i (unit baseline)
    b = np.einsum("ij,ij->i", di, dj)
    d, e = di @ cj, dj @ cj
    den = np.maximum(1.0 - b * b, 1e-12)
    zi, zj = (d - b * e) / den, (b * d - e) / den
    front = (zi > 0) & (zj > 0)
    if front.mean() < 0.5:
        return float("inf")
    med = float(np.median(zi[front]))
    return float(np.median(np.abs(zi[front] - med)) / med)


def cavity_relative_pose(camera: Camera, pixels_i: np.ndarray, pixels_j: np.ndarray, i: int, j: int, *,
                         threshold_px: float, noise_px: float = 0.5, start: RelativePose | None = None,
                         max_depth_spread: float = 0.15) -> RelativePose | None:
    """The relative pose of two frames looking at a cavity's wall from near its centre, or None.

    With baselines of 2-6 mm against a wall 40 mm away the Sampson distances cannot tell the true motion
    from a rotation 5-10 deg off with the baseline turned by ~90 deg (the bas-relief ambiguity): on the
    bladder spiral a third of the essential-matrix decompositions were such. What tells them apart is the
    shape: the true motion puts the wall at nearly one distance, the ambiguous one bends it. Candidates:
    refinements from ``start`` (the essential matrix's, if given; over these matches) and from the bearings' rotation
    (:func:`rotation_from_bearings`) with the baseline along each camera axis; among those keeping at
    least 90 % of the most inliers, the one whose points' distances spread least (:func:`depth_spread`).
    None when even that spread exceeds ``max_depth_spread`` (default 0.15: a sphere seen from 0.3 radii
    off its centre, the farthest a scope on a spiral of a third of the cavity's radius gets, spreads its
    distances by less than that).
    """
    rotation = rotation_from_bearings(camera, pixels_i, pixels_j).rotation
    starts = [(start.rotation, start.direction)] if start is not None else []
    starts += [(rotation, axis) for axis in np.r_[np.eye(3), -np.eye(3)]]
    candidates = []
    for r0, t0 in starts:
        r = refine_relative_pose(camera, pixels_i, pixels_j, r0, t0, threshold_px=threshold_px,
                                 noise_px=noise_px, i=i, j=j)
        if r is not None:
            candidates.append(r)
    if not candidates:
        return None
    most = max(int(c.inliers.sum()) for c in candidates)
    scored = [(depth_spread(camera, np.asarray(pixels_i)[c.inliers], np.asarray(pixels_j)[c.inliers], c), k)
              for k, c in enumerate(candidates) if c.inliers.sum() >= 0.9 * most]
    spread, best = min(scored)
    return candidates[best] if spread <= max_depth_spread else None


def start_poses(n: int, relative: list[RelativePose], measured: list[MeasuredPose] | None = None, *,
                centre_mm: np.ndarray | None = None, where: str = "dataset") -> list[Pose]:
    """Starting ``cam_from_world`` poses of ``n`` frames.

    With measured poses of finite tolerance: those. Otherwise rotations chained from frame 0 along a
    maximum spanning tree of the pairs (weight: inliers), then averaged over all pairs (``relative``: from
    :func:`rotation_from_bearings`); every centre at
    ``centre_mm`` (default the origin): the scope turns about a point near the cavity's centre.
    Raises InputError when the pairs leave some frame unconnected to frame 0.
    """
    if measured is not None and knows_poses(measured):
        return [m.pose for m in measured]
    centre = np.zeros(3) if centre_mm is None else np.asarray(centre_mm, float)
    if not relative:
        raise InputError(f"{where}: no two frames overlap (no pair verified by an essential matrix)")
    ii = np.array([r.i for r in relative])
    jj = np.array([r.j for r in relative])
    weight = np.array([r.inliers.sum() for r in relative], float)
    # maximum spanning tree = minimum spanning tree of (max + 1 - weight)
    cost = coo_matrix((weight.max() + 1.0 - weight, (ii, jj)), shape=(n, n)).tocsr()
    tree = minimum_spanning_tree(cost + cost.T)
    order, parent = breadth_first_order(tree + tree.T, 0, directed=False)
    if len(order) < n:
        missing = sorted(set(range(n)) - set(order.tolist()))
        raise InputError(f"{where}: frames {missing[:10]} share no verified matches with the others (no overlap)")
    by_pair = {(r.i, r.j): r.rotation for r in relative}
    R = np.zeros((n, 3, 3))
    R[0] = np.eye(3)
    for k in order[1:]:
        p = parent[k]
        if (p, k) in by_pair:  # R_k = R_kp R_p
            R[k] = by_pair[(p, k)] @ R[p]
        else:
            R[k] = by_pair[(k, p)].T @ R[p]
    loose = [MeasuredPose(Pose.from_centre(R[k], centre), _unknown()) for k in range(n)]
    rotations, _ = average_rotations(loose, relative)
    return [Pose.from_centre(r, centre) for r in rotations]


def _unknown():
    from scope3d.sensor.pose_tolerance import PoseTolerance

    return PoseTolerance.unknown()


def points_on_sphere(camera: Camera, poses: list[Pose], tracks: Tracks, centre_mm: np.ndarray,
                     radius_mm: float) -> np.ndarray:
    """(n_tracks, 3) mm: each track's point at the mean of its rays' exits through the sphere
    ``|X - centre| = radius`` (a camera outside the sphere uses the far intersection too)."""
    R = np.stack([p.rotation for p in poses])[tracks.frame]
    C = np.stack([p.centre for p in poses])[tracks.frame]
    xy = camera.pixel_to_normalised(tracks.pixels)
    d = np.einsum("kji,kj->ki", R, np.c_[xy, np.ones(len(xy))])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = C - np.asarray(centre_mm, float)
    b = np.einsum("ki,ki->k", o, d)
    disc = np.maximum(b * b - (np.einsum("ki,ki->k", o, o) - radius_mm**2), 0.0)
    t = -b + np.sqrt(disc)
    hit = C + t[:, None] * d
    X = np.zeros((tracks.n_tracks, 3))
    np.add.at(X, tracks.track, hit)
    return X / tracks.lengths()[:, None]


@dataclass
class CavityMap:
    """The adjusted map. tracks : observations and points (mm, provisional scale unless known);
    poses : per frame ``cam_from_world``; centre_mm : the shell's centre; bundle : the two (or three)
    adjustments' results; registered : (n,) bool, frames with at least ``min_observations`` observations
    in the final map."""

    tracks: Tracks
    poses: list[Pose]
    centre_mm: np.ndarray
    bundle: list[BundleResult] = field(default_factory=list)
    registered: np.ndarray | None = None
    time_s: float = 0.0


def _problem(camera: Camera, poses: list[Pose], tracks: Tracks, measured: list[MeasuredPose] | None) -> BundleProblem:
    rot = np.stack([p.rotation for p in poses])
    trans = np.stack([p.translation for p in poses])
    if measured is not None and knows_poses(measured):
        problem = BundleProblem.from_measured_poses(measured, camera, tracks.points, tracks.pixels, tracks.frame,
                                                    tracks.track, refine_intrinsics=False)
        problem.start_from(poses)
        return problem
    problem = BundleProblem(tracks.pixels, tracks.frame, tracks.track, rot, trans, tracks.points, camera.intrinsics)
    problem.fix("intrinsics")
    return problem


def adjust_cavity(camera: Camera, tracks: Tracks, poses: list[Pose], centre_mm: np.ndarray,
                  options: CavityOptions = CavityOptions(), measured: list[MeasuredPose] | None = None, *,
                  scale: float = 1.0, min_observations: int = 8) -> CavityMap:
    """The sphere, the shell, then released (module docstring, step 5).

    tracks : with points (the sphere start, :func:`points_on_sphere`). poses : the start. scale :
    provisional mm per true mm applied to the shell radii (1 when the scale is known). measured : bounds
    the poses when every tolerance is finite (a plan); otherwise

    0. *sphere*: every camera held at the centre, every point held on the nominal sphere; the rotations
       and the points' directions adjust (a rotating camera looking at a sphere: the panorama);
    1. *shell*: the camera centres free (the first camera's pose held), the points free inside the
       anatomical shell, the radius of the longest track's point held (the scale);
    2. *released*: no shell; the scale held by one coordinate of that point; observations beyond
       ``max_reprojection_error_px`` dropped and the adjustment repeated once.
    """
    t0 = time.perf_counter()
    centre = np.asarray(centre_mm, float)
    solver = SolverOptions(max_iterations=options.max_iterations, loss="huber", loss_scale_px=options.loss_scale_px)
    bounded_poses = measured is not None and knows_poses(measured)
    work = tracks.strongest(options.max_points)
    results: list[BundleResult] = []

    def run(start: list[Pose], stage: str) -> list[Pose]:
        nonlocal work
        problem = _problem(camera, start, work, measured)
        anchor = int(np.argmax(work.lengths()))
        if stage in ("sphere", "shell") or not options.release_shell:
            problem.bound_points_to_shell(centre, scale * options.min_radius_mm, scale * options.max_radius_mm)
        if stage == "sphere":
            problem.fix("point", None, ["y0"])
            if not bounded_poses:
                problem.fix("pose", None, ["px", "py", "pz"])
                problem.fix("pose", [0])
        elif not bounded_poses:
            problem.fix("pose", [0])
            if stage == "shell":
                problem.fix("point", [anchor], ["y0"])
            else:
                rel = work.points[anchor] - start[0].centre
                problem.fix("point", [anchor], [("y0", "y1", "y2")[int(np.argmax(np.abs(rel)))]])
        result = solve(problem, solver)
        results.append(result)
        work = Tracks(work.track, work.frame, work.feature, work.pixels, work.colors, result.points_world)
        return list(result.poses)

    pose_now = list(poses)
    if not bounded_poses:
        pose_now = run(pose_now, "sphere")
    pose_now = run(pose_now, "shell")
    pose_now = run(pose_now, "released")
    err = reprojection_errors(camera, pose_now, work)
    bad = ~(err <= options.max_reprojection_error_px)
    if bad.any():
        keep = ~bad
        keep &= np.bincount(work.track[keep], minlength=work.n_tracks)[work.track] >= 2
        work = work.subset(keep)
        pose_now = run(pose_now, "released")
    n_obs = np.bincount(work.frame, minlength=len(poses))
    return CavityMap(work, pose_now, centre, results, n_obs >= min_observations, time.perf_counter() - t0)
