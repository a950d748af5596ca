"""Start poses of a scope turning inside a cavity, from its frames' pairs alone (the image-only cavity map's
steps 1-3, :mod:`scope3d.sfm.cavity_mapping`), beside the general averaging of :mod:`scope3d.estimators.averaging`.

A scope inside a bladder turns about a point near the cavity's centre: baselines of 2-5 mm against a wall
20-40 mm away, consecutive views turned by tens of degrees. Essential matrices then often fall into the
rotation-translation (bas-relief) ambiguity; what tells the true motion apart is the shape: it puts the wall
at nearly one distance, the ambiguous one bends it.

* :func:`cavity_relative_pose` — a pair's relative pose chosen by the shape (:func:`depth_spread` of its
  points triangulated with a unit baseline, :func:`pair_depths`).
* :func:`start_rotations` — rotations chained along a minimum spanning tree of the verified pairs (the
  most certain rotations first), then averaged over every pair
  (:func:`scope3d.estimators.averaging.average_rotations`); :func:`consistent_pairs` names the pairs whose
  rotation agrees with the averaged ones.
* :func:`start_centres` — every pair's baseline scaled by the median depth of its points (the wall is at
  about one distance from a scope inside it), solved together by robust least squares.

Units: centres in units of the wall's distance (the map's scale comes later), radians; pixels with their
origin at the top-left pixel's centre. Poses are ``cam_from_world``.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
from scipy.sparse.linalg import spsolve

from scope3d.errors import InputError
from scope3d.estimators.averaging import RelativePose, average_rotations, refine_relative_pose, relative_pose
from scope3d.feature.detection import Features
from scope3d.feature.matching import PairMatches
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotation_angle, rotvec_to_matrix
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.utils.robust import huber_weights, relative_spread, robust_norm_sigma


def pair_depths(camera: Camera, pixels_i: np.ndarray, pixels_j: np.ndarray,
                relative: RelativePose) -> tuple[np.ndarray, np.ndarray]:
    """Distances along frame i's rays (M,) of the pair's points triangulated with a unit baseline (midpoint
    of the closest approach), and whether each lies in front of both cameras (M,) bool."""
    # unit bearings through the lens model (a fisheye's past 90 deg too)
    di = camera.unproject(np.asarray(pixels_i, float))
    dj = camera.unproject(np.asarray(pixels_j, float)) @ relative.rotation
    cj = -relative.rotation.T @ relative.direction  # centre j in frame i (unit baseline)
    b = np.einsum("ij,ij->i", di, dj)
    d, e = di @ cj, dj @ cj
    den = np.maximum(1.0 - b * b, 1e-12)
    zi, zj = (d - b * e) / den, (b * d - e) / den
    return zi, (zi > 0) & (zj > 0)


def depth_spread(camera: Camera, pixels_i: np.ndarray, pixels_j: np.ndarray, relative: RelativePose) -> float:
    """Spread of the triangulated points' distances from camera i: median absolute deviation over the
    median (0 for a sphere seen from its centre), over the pair's inliers in front of both cameras;
    inf when fewer than half lie in front."""
    zi, front = pair_depths(camera, pixels_i, pixels_j, relative)
    if front.mean() < 0.5:
        return float("inf")
    return relative_spread(zi[front])


def _bearing_rotation(camera: Camera, pixels_i: np.ndarray, pixels_j: np.ndarray) -> np.ndarray:
    """The rotation ``R_ji`` that best turns frame i's bearings onto frame j's, as if the scope had turned
    about its centre (Kabsch on unit rays): a start off by the parallax only (5-7 deg on the spiral)."""
    a = camera.unproject(np.asarray(pixels_i, float))
    b = camera.unproject(np.asarray(pixels_j, float))
    U, _, Vt = np.linalg.svd(b.T @ a)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


#: the bearings' rotation is off by the parallax (5-7 deg on the bladder spiral, where refinements started
#: from it alone fell into the ambiguous basin for 2 of 33 consecutive pairs): starts also turned by this
#: much about each camera axis
_START_TURN_DEG = 6.0
#: a candidate spreading the wall's distances by less than this fraction of the limit ends the search
#: (true pairs on the spiral: 0.01-0.04; the ambiguous ones: 0.09-0.5)
_SETTLED_SPREAD = 0.4


def cavity_relative_pose(camera: Camera, pixels_i: np.ndarray, pixels_j: np.ndarray, i: int, j: int, *,
                         threshold_px: float, noise_px: float = 0.5, max_depth_spread: float = 0.15) -> RelativePose | None:
    """The relative pose of two frames looking at a cavity's wall from near its centre, or None.

    Candidates: the essential matrix's (:func:`scope3d.estimators.averaging.relative_pose`) and
    refinements from the bearings' rotation with the baseline along each camera axis (both signs).
    Among those keeping at least 90 % of the most inliers, the one whose points' distances spread least
    (:func:`depth_spread`); None when even that spread exceeds ``max_depth_spread``. On the bladder spiral
    (256 px) this picked a rotation within 2 deg of the truth for 31 of 33 consecutive pairs, where the
    essential matrix alone did for 21.
    """
    pixels_i, pixels_j = np.asarray(pixels_i, float), np.asarray(pixels_j, float)
    candidates: list[RelativePose] = []
    essential = relative_pose(camera, pixels_i, pixels_j, threshold_px=threshold_px, noise_px=noise_px, i=i, j=j)
    if essential is not None:
        candidates.append(essential)
    bearing = _bearing_rotation(camera, pixels_i, pixels_j)
    # cheapest first: the essential matrix, then starts from the bearings' rotation, then those turned;
    # stop as soon as the best candidate puts the wall at nearly one distance
    rounds = [np.zeros((1, 3)), np.r_[np.eye(3), -np.eye(3)] * np.deg2rad(_START_TURN_DEG)]
    best, spread = None, np.inf
    for turns in [None] + rounds:
        for turn in [] if turns is None else turns:
            for axis in np.r_[np.eye(3), -np.eye(3)]:
                r = refine_relative_pose(camera, pixels_i, pixels_j, rotvec_to_matrix(turn) @ bearing, axis,
                                         threshold_px=threshold_px, noise_px=noise_px, i=i, j=j)
                if r is not None:
                    candidates.append(r)
        if not candidates:
            continue
        most = max(c.n_inliers for c in candidates)
        spread, k = min((depth_spread(camera, pixels_i[c.inliers], pixels_j[c.inliers], c), k)
                        for k, c in enumerate(candidates) if c.n_inliers >= 0.9 * most)
        best = candidates[k]
        if spread <= _SETTLED_SPREAD * max_depth_spread:
            break
    return best if spread <= max_depth_spread else None



def _spanning_tree(n: int, relative: list[RelativePose], where: str) -> tuple[np.ndarray, np.ndarray]:
    """Breadth-first order and parents (n,) of a minimum spanning tree (weight: the pairs' rotation sigma)
    from frame 0.
    Raises InputError when the pairs leave some frame unconnected to frame 0 (no overlap)."""
    if not relative:
        raise InputError(f"{where}: no two frames overlap (no pair of frames verified by their matches)")
    ii = np.array([r.i for r in relative])
    jj = np.array([r.j for r in relative])
    # the tree of the most certain rotations: on the spiral, cross-turn pairs of 30-40 matches had 3-6 deg
    # sigmas (and 5-6 deg errors) where consecutive pairs have ~1 deg (the averaging that follows weighs
    # them the same way; the start only has to be in its basin)
    sigma = np.array([r.rotation_sigma_rad for r in relative], float)
    cost = coo_matrix((np.where(np.isfinite(sigma), sigma, 1e3) + 1e-12, (ii, jj)), shape=(n, n)).tocsr()
    tree = minimum_spanning_tree(cost + cost.T)
    order, parent = breadth_first_order(tree + tree.T, 0, directed=False)
    if len(order) < n:
        missing = sorted(set(range(n)) - set(order.tolist()))
        raise InputError(f"{where}: frames {missing[:10]} share no verified matches with frame 0 (no overlap)")
    return order, parent


def start_rotations(n: int, relative: list[RelativePose], *, where: str = "dataset") -> np.ndarray:
    """(n, 3, 3) ``cam_from_world`` rotations, frame 0 the identity: chained along the minimum spanning
    tree, then averaged over every pair (robust, :func:`average_rotations`)."""
    order, parent = _spanning_tree(n, relative, where)
    by_pair = {(r.i, r.j): r.rotation for r in relative}
    R = np.zeros((n, 3, 3))
    R[0] = np.eye(3)
    for k in order[1:]:
        p = parent[k]
        R[k] = by_pair[(p, k)] @ R[p] if (p, k) in by_pair else by_pair[(k, p)].T @ R[p]
    loose = [MeasuredPose(Pose(R[k], np.zeros(3)), PoseTolerance.unknown()) for k in range(n)]
    rotations, _ = average_rotations(loose, relative)
    return rotations @ rotations[0].T  # gauge: frame 0 the identity


#: a pair whose relative rotation disagrees with the averaged rotations by more than this many of its
#: sigmas (its own, times the common factor of all pairs' normalised disagreements) is inconsistent: 3 sigma,
#: the usual outlier gate of a Gaussian error
_CONSISTENT_SIGMAS = 3.0


def consistent_pairs(rotations: np.ndarray, relative: list[RelativePose]) -> np.ndarray:
    """(len(relative),) bool: the pairs whose relative rotation ``R_ji`` agrees with ``rotations`` (n, 3,
    3, ``cam_from_world``) within ``_CONSISTENT_SIGMAS`` of its ``rotation_sigma_rad`` (times the robust
    common factor, at least 1, of every pair's normalised disagreement; the weighting of
    :func:`average_rotations`).

    Why: a pair whose relative pose fell into another solution (the bas-relief ambiguity, or a few matches
    fitting a wrong motion) has a wrong baseline direction too. The robust rotation averaging outvotes it,
    but :func:`start_centres` takes its direction. On the unseen cavity (``--shape-seed 5 --cavity-mm
    40,35,30``, 608 px) 9 of 51 posed pairs were 2-110 deg off; the averaged rotations stayed within 2.1
    deg of the truth, the centres from every pair were up to 5 mm off and the all-pair map ended at 11.4
    mm mean wall error; without the pairs this test drops, 1.3-1.5 mm and 0.19-0.21 mm."""
    if not relative:
        return np.zeros(0, bool)
    R = np.asarray(rotations, float)
    ii = np.array([r.i for r in relative])
    jj = np.array([r.j for r in relative])
    A = R[jj] @ np.swapaxes(R[ii], 1, 2)
    e = np.stack([r.rotation for r in relative]) @ np.swapaxes(A, 1, 2)
    resid = rotation_angle(e)
    sigma = np.array([r.rotation_sigma_rad for r in relative], float)
    sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, np.inf)
    normalised = resid / sigma
    factor = robust_norm_sigma(normalised[np.isfinite(sigma)], 1.0) if len(relative) >= 3 else 1.0
    return normalised <= _CONSISTENT_SIGMAS * factor


def start_centres(camera: Camera, rotations: np.ndarray, relative: list[RelativePose], matches: list[PairMatches],
                  features: list[Features], *, iterations: int = 10, where: str = "dataset") -> np.ndarray:
    """(n, 3) centres, frame 0 at the origin, in units of the wall's distance: each pair's baseline scaled
    so that its points lie at a median distance of 1 from camera i, then every pair's
    ``C_j - C_i = L_ij R_i^T c_ij`` (``c_ij`` the unit direction to centre j in frame i) solved together
    by least squares with Huber weights (IRLS).

    Why the wall's distance: a scope turning inside a cavity sees the wall at about the same distance from
    every pose (the truth on the bladder spiral: 23-28 mm in frame 0), so the median depth of a pair's
    points, triangulated with a unit baseline, gives the baseline's length to ~10 %. Pairwise matches
    give tracks of ~2 views on a spiral, and those fix no ratio between two baselines, so neither unit
    baselines nor the known-rotation ray problem (:func:`positions_from_points`) could place the centres:
    measured on the 36-frame spiral (256 px), centres 6.4 mm off (of a 15 mm spread) and the wall 22 mm
    off, against 2.5 mm and 2.3 mm from the depths.
    rotations : (n, 3, 3) ``cam_from_world``; relative, matches : the verified pairs (inliers only), in
    the same order. Raises InputError when the pairs leave a frame unconnected to frame 0.
    """
    n = len(rotations)
    _spanning_tree(n, relative, where)  # every frame connected, or a clear refusal
    ii, jj, v, sigma = [], [], [], []
    for rel, m in zip(relative, matches):
        z, front = pair_depths(camera, features[rel.i].keypoints[m.idx_i], features[rel.j].keypoints[m.idx_j], rel)
        if front.sum() < 3:
            continue
        length = 1.0 / float(np.median(z[front]))
        ii.append(rel.i)
        jj.append(rel.j)
        v.append(length * rotations[rel.i].T @ (-rel.rotation.T @ rel.direction))
        # the direction's sigma across the baseline, and the ~10 % of the length the wall's shape leaves
        sigma.append(length * max(rel.direction_sigma_rad if np.isfinite(rel.direction_sigma_rad) else 1.0, 0.1))
    ii, jj, v, sigma = np.array(ii), np.array(jj), np.array(v), np.array(sigma)
    k = len(ii)
    # unknowns C (3n); rows C_j - C_i = v_ij per pair, and C_0 = 0 (the gauge)
    rows = np.concatenate([np.tile(np.arange(3 * k), 2), 3 * k + np.arange(3)])
    cols = np.concatenate([(3 * jj[:, None] + np.arange(3)).ravel(), (3 * ii[:, None] + np.arange(3)).ravel(),
                           np.arange(3)])
    vals = np.concatenate([np.ones(3 * k), -np.ones(3 * k), np.ones(3)])
    J = coo_matrix((vals, (rows, cols)), shape=(3 * k + 3, 3 * n)).tocsr()
    rhs = np.r_[v.ravel(), np.zeros(3)]
    weight = np.ones(k)
    C = np.zeros((n, 3))
    for _ in range(iterations):
        w = np.r_[np.repeat(weight / sigma**2, 3), np.full(3, 1e6 / sigma.min() ** 2)]
        JtW = J.T.multiply(w).tocsr()
        C = spsolve((JtW @ J).tocsc(), JtW @ rhs).reshape(n, 3)
        r = np.linalg.norm(C[jj] - C[ii] - v, axis=1) / sigma
        new = huber_weights(r / robust_norm_sigma(r, 1.0), 2.0)
        if np.allclose(new, weight):
            break
        weight = new
    return C - C[0]
