"""Image-only mapping of a closed cavity seen from inside (reference sec. 2.3.4, 2.4.3): camera poses and
points from the images, a spherical shape prior, then released.

A scope inside a bladder turns about a point near the cavity's centre: baselines of 2-5 mm against a wall
20-40 mm away, consecutive views turned by tens of degrees. Essential matrices then often fall into the
rotation-translation (bas-relief) ambiguity: on the bladder spiral a third of the consecutive pairs
decomposed into a rotation 5-7 deg off with the baseline turned by ~90 deg, and chained rotations drifted by
40 deg over 36 frames. What tells the true motion apart is the shape: it puts the wall at nearly one
distance, the ambiguous one bends it (:func:`cavity_relative_pose`). The steps, run by :func:`map_cavity`:

1. :func:`pair_poses` — each frame's successors in capture order and its most similar frames
   (:func:`scope3d.feature.retrieval.image_similarity`) matched exhaustively and their relative pose chosen
   by the shape (:func:`cavity_relative_pose`); with planned poses also the pairs the plan says overlap,
   verified with the planned relative pose as a start.
2. :func:`start_rotations` — rotations chained along a minimum spanning tree of the verified pairs (the
   most certain rotations first), then averaged over every pair (:func:`scope3d.estimators.averaging.average_rotations`).
3. :func:`start_centres` — every pair's baseline scaled by the median depth of its points (the wall is at
   about one distance from a scope inside it), all pairs whose rotation agrees with the averaged ones
   (:func:`consistent_pairs`) solved together by robust least squares. The
   gauge: the first camera, rescaled so that the sphere fitted to the points has the nominal radius (the
   provisional scale until the stars set it).
4. Tracks from every geometrically verified pair: the pairs the start says overlap are matched too
   (:func:`overlapping_pairs`) and every pair whose relative pose the shape test refused is kept if its
   essential matrix has enough inliers (:func:`verified_matches`); geometric verification (which matches
   are right) is apart from the relative pose (which the start needs). The centres are solved again from
   the tracks' rays with the rotations held (:func:`scope3d.estimators.averaging.positions_from_points`).
5. :func:`adjust_cavity` — points triangulated with the start; optionally an adjustment with every point
   bounded to the spherical shell between an anatomical minimum and maximum radius
   (:meth:`BundleProblem.bound_points_to_shell`); bundle adjustment, observations farther than the
   reprojection gate dropped and the adjustment repeated; points outside the shell dropped. The chain of
   posed pairs alone, adjusted from the depth-scaled start, is the fallback (:func:`choose_map`): a map
   whose cameras are not inside near its wall's centre (:func:`cameras_off_centre`) loses to one whose
   are; otherwise the all-pair map is kept unless the chain's explains more of the verified observations
   within the gate, or the all-pair wall spreads significantly more on the points both hold
   (:func:`spread_difference`) while it explains not significantly more (:func:`explained_difference`). How far the two maps disagree (:func:`map_disagreement`) is reported with
   the choice (``CavityMap.choice``). Planned poses (finite tolerance) start the poses and bound them
   (BCBA) instead of steps 2-4, and the pairs the plan says overlap are matched.

What limited the image-only map (36-frame spiral): the frames overlap only their neighbours (35-65 %),
so the pairs that passed the shape test formed a chain with a few cross-turn links and tracks of 2.1
views, which fix no ratio between baselines (wall 2.06 mm mean at 608 px). With every geometrically
verified pair in the tracks and the centres from their rays, 0.175 mm at 608 px. At 256 px the start was
2.6 deg off and the all-pair map fell into another minimum (a block of frames 9 deg off) and the chain's
map (2.44 mm) was kept; with today's pairs the all-pair map there is 0.48 mm and kept. On an unseen
cavity at 608 px six posed pairs 10-110 deg off pulled the start's centres 5 mm off through their
baselines and the all-pair map ended at 11.4 mm; without them (:func:`consistent_pairs`) 0.194 mm. On an unseen wet cavity (608 px) a start 6-12 deg off let the tracks' centres build a cap of a
sphere 3.4 times too large with the cameras against it (26.5 mm), which explained more and fitted a sphere
better than the chain's map: the cameras' place now rules it out (1.6 mm, the chain's).
The wall's spread alone, compared as it was, kept the chain's map whenever the all-pair wall spread 1-5 %
more (an unseen cavity: 1.14 mm kept against 0.213 mm; the 30 mm spirals: 0.227 against 0.137 mm); the
choice now asks the spread for a significant difference only (docs/panorama.md, "Which image-only map").

Units: mm (provisional until :mod:`scope3d.metrology.star_scale` rescales), radians; pixels with their
origin at the top-left pixel's centre. Poses are ``cam_from_world``.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import spsolve
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

from scope3d.errors import InputError
from scope3d.estimators.averaging import (RelativePose, _huber_weights, _robust_sigma, average_rotations,
                                          poses_from, positions_from_points, refine_relative_pose,
                                          relative_pose)
from scope3d.estimators.bundle import BundleResult, SolverOptions, solve
from scope3d.estimators.triangulation import TrackOptions, ray_angles_deg, reprojection_errors, triangulate_tracks
from scope3d.feature.detection import Features
from scope3d.feature.depth_prior import DepthPrior, pose_error_px
from scope3d.feature.matching import MatchOptions, PairMatches, match_exhaustive
from scope3d.feature.pairs import frame_overlap
from scope3d.feature.retrieval import RetrievalOptions, image_similarity
from scope3d.feature.tracks import build_tracks
from scope3d.geometry.pose import Pose
from scope3d.geometry.similarity import fit_similarity
from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.guided_mapping import bundle_problem
from scope3d.utils.progress import advance


@dataclass(frozen=True)
class CavityOptions:
    """Image-only cavity mapping.

    sequence_neighbours : int, each frame is also matched with the next this many frames in capture order
        (default 2: key frames of a video overlap their successors; on the 36-frame spiral retrieval
        alone missed pair 16-17, 35 % overlap, the only consecutive link between the spiral's turns,
        and the map fell apart there). 0 for unordered images.
    min_overlap : float, pairs whose fields overlap by at least this fraction, placed by the planned poses
        (with the wall between the shell's radii) or by the image-only start (the wall at its points'
        median depth), are matched too (:func:`scope3d.feature.pairs.frame_overlap`; default 0.05). On the
        36-frame spiral at 608 px, 0.05 finds with the start 102 pairs holding 86 of the 88 pairs that pass
        geometric verification when all 630 are matched (0.1: 77, 0.25: 39); with the planned poses the
        wall went from 1.78 (0.25) to 0.19 mm mean at 608 px, 1.93 to 0.91 mm at 256 px, and 3.26 to 3.16
        mm on the unseen cavity at 224 px.
    partners_per_frame : int, each frame's most similar frames matched (default 4: on a spiral the two
        neighbours along the path and one or two across the turns).
    max_depth_spread : float, a pair whose best relative pose still spreads its points' distances by more
        than this (median absolute deviation over the median) is rejected (default 0.15: a sphere seen
        from 0.3 radii off its centre, the farthest a scope on a spiral of a third of the cavity's radius
        gets, spreads its distances by less than that).
    nominal_radius_mm : float, without a plan the provisional scale: the sphere fitted to the start's
        points gets this radius (default 40 mm: a sphere of 270 ml, a bladder half filled for cystoscopy).
    min_radius_mm, max_radius_mm : float, the anatomical shell about the centre of the sphere fitted robustly
        to the points (:func:`anatomical_shell`; defaults 20 and 70 mm: spheres of 34 ml and 1.4 l, an
        almost empty and an over-filled adult bladder): final points outside it are dropped, the shell
        stage bounds the points to it, and with planned poses the wall is placed between these distances
        to find the overlapping pairs.
    shell_stage : bool, a first adjustment with every point bounded to the shell, then released (the
        reference's proposal; default False: from the depth-scaled start it was measured to hurt, on the
        36-frame spiral at 256 px the wall went from 2.45 to 5.71 mm mean, the bounded points sticking
        to the shell's radii).
    loss_scale_px : float, Huber scale of the adjustments (default 1 px: SIFT localisation is 0.3-0.5 px).
    max_iterations : int, LM iterations per adjustment (default 100).
    max_points : int, at most this many tracks enter the adjustments: the longest, and among tracks of one
        length each frame's ``min_observations`` widest first, then those whose rays meet at the widest angle
        (default 8000).
    tracks : triangulation gates (reprojection error, smallest ray angle).
    noise_px : float, keypoint localisation noise for the pair and ray weights (default 0.5 px).
    min_observations : int, a frame with fewer observations in the final map is not registered (default 8).
    threads : int, pairs matched at once (default 2, the machine's cores).
    plan_overlap_at_wall : bool, with planned poses the overlapping pairs are found with the wall at the
        distance the first pairs (capture order, retrieval) measure, the median over their points with the
        plan's baselines, instead of anywhere in the shell (its geometric mean, 37 mm). Default True. On the
        unseen cavity's 15 mm spiral (wall 14.4 mm away) the shell's depth chooses 1770 overlapping pairs of
        which 583 pass verification, the wall's 638 holding 578 of them (2050 -> 1139 pairs tried, the same
        map to the bit); the sweeps' other planned maps in docs/panorama.md.
    """

    sequence_neighbours: int = 2
    min_overlap: float = 0.05
    partners_per_frame: int = 4
    max_depth_spread: float = 0.15
    nominal_radius_mm: float = 40.0
    min_radius_mm: float = 20.0
    max_radius_mm: float = 70.0
    shell_stage: bool = False
    loss_scale_px: float = 1.0
    max_iterations: int = 100
    max_points: int = 8000
    tracks: TrackOptions = field(default_factory=TrackOptions)
    noise_px: float = 0.5
    min_observations: int = 8
    threads: int = 2
    retrieval: RetrievalOptions = field(default_factory=RetrievalOptions)
    plan_overlap_at_wall: bool = True

    def __post_init__(self) -> None:
        if not 0 < self.min_radius_mm <= self.nominal_radius_mm <= self.max_radius_mm:
            raise ValueError("need 0 < min_radius_mm <= nominal_radius_mm <= max_radius_mm")
        if self.sequence_neighbours < 0 or not 0 < self.min_overlap <= 1:
            raise ValueError("need sequence_neighbours >= 0 and 0 < min_overlap <= 1")
        if self.partners_per_frame < 1 or self.max_depth_spread <= 0 or self.loss_scale_px <= 0:
            raise ValueError("need partners_per_frame >= 1, max_depth_spread > 0, loss_scale_px > 0")
        if self.max_iterations < 1 or self.max_points < 10 or self.noise_px <= 0 or self.min_observations < 1:
            raise ValueError("need max_iterations >= 1, max_points >= 10, noise_px > 0, min_observations >= 1")
        if self.threads < 1:
            raise ValueError("threads must be >= 1")


def knows_poses(measured: list[MeasuredPose] | None) -> bool:
    """True when every measured pose has a finite tolerance (a plan or a robot), False for image-only."""
    return measured is not None and all(
        np.all(np.isfinite(m.tolerance.position_mm)) and np.all(np.isfinite(m.tolerance.orientation_rad))
        for m in measured)


# --- 1. pairs --------------------------------------------------------------------------------------


def pair_depths(camera: Camera, pixels_i: np.ndarray, pixels_j: np.ndarray,
                relative: RelativePose) -> tuple[np.ndarray, np.ndarray]:
    """Distances along frame i's rays (M,) of the pair's points triangulated with a unit baseline (midpoint
    of the closest approach), and whether each lies in front of both cameras (M,) bool."""
    di = np.c_[camera.pixel_to_normalised(np.asarray(pixels_i, float)), np.ones(len(pixels_i))]
    dj = np.c_[camera.pixel_to_normalised(np.asarray(pixels_j, float)), np.ones(len(pixels_j))] @ relative.rotation
    di /= np.linalg.norm(di, axis=1, keepdims=True)
    dj /= np.linalg.norm(dj, axis=1, keepdims=True)
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
    med = float(np.median(zi[front]))
    return float(np.median(np.abs(zi[front] - med)) / med)


def _bearing_rotation(camera: Camera, pixels_i: np.ndarray, pixels_j: np.ndarray) -> np.ndarray:
    """The rotation ``R_ji`` that best turns frame i's bearings onto frame j's, as if the scope had turned
    about its centre (Kabsch on unit rays): a start off by the parallax only (5-7 deg on the spiral)."""
    a = np.c_[camera.pixel_to_normalised(np.asarray(pixels_i, float)), np.ones(len(pixels_i))]
    b = np.c_[camera.pixel_to_normalised(np.asarray(pixels_j, float)), np.ones(len(pixels_j))]
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
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


def pair_poses(camera: Camera, features: list[Features], options: CavityOptions = CavityOptions(),
               match_options: MatchOptions = MatchOptions(), measured: list[MeasuredPose] | None = None, *,
               progress=None) -> tuple[list[PairMatches], list[RelativePose], list[PairMatches], set]:
    """Each frame's ``sequence_neighbours`` successors and ``partners_per_frame`` most similar frames
    matched exhaustively and verified by :func:`cavity_relative_pose`. With planned poses (finite
    tolerances, :func:`knows_poses`) also every pair whose fields overlap by at least
    ``min_overlap`` with the wall between the shell's radii
    (:func:`scope3d.feature.pairs.frame_overlap`), each verified by the relative pose that keeps most
    inliers with the planned one among the starts (:func:`relative_pose`'s prior): the plan already
    says where the frames are, so the wall's shape need not (on an unseen cavity the depth-spread test
    refused the consecutive pairs that joined frames 7-16 to the rest).
    Returns (matches (inliers only), relative poses, the matches (fundamental-matrix inliers) of the pairs
    whose relative pose was refused, for :func:`verified_matches`; the pairs tried, a set of (i, j) with
    i < j). progress : tqdm-like or None, advanced once per pair."""
    n = len(features)
    similarity = image_similarity(features, options.retrieval)
    np.fill_diagonal(similarity, 0.0)
    chosen = {(a, b) for a in range(n) for b in range(a + 1, min(a + 1 + options.sequence_neighbours, n))}
    for a in range(n):
        for b in np.argsort(-similarity[a], kind="stable")[:options.partners_per_frame]:
            if similarity[a, b] > 0:
                chosen.add((min(a, int(b)), max(a, int(b))))
    planned = knows_poses(measured)
    if planned:
        poses = [m.pose for m in measured]
        if not options.plan_overlap_at_wall:
            chosen.update(_plan_overlaps(camera, poses, DepthPrior(options.min_radius_mm, options.max_radius_mm),
                                         options.min_overlap))

    def verify(pair):
        i, j = pair
        m = match_exhaustive(camera, features[i], features[j], match_options, i=i, j=j)
        advance(progress)
        if len(m) < max(match_options.min_matches, 8):
            return None
        pixels_i, pixels_j = features[i].keypoints[m.idx_i], features[j].keypoints[m.idx_j]
        if planned:
            R_ji = poses[j].rotation @ poses[i].rotation.T
            rel = relative_pose(camera, pixels_i, pixels_j, threshold_px=match_options.ransac_threshold_px,
                                noise_px=options.noise_px, prior=(R_ji, poses[j].translation - R_ji @ poses[i].translation),
                                i=i, j=j)
        else:
            rel = cavity_relative_pose(camera, pixels_i, pixels_j, i, j, threshold_px=match_options.ransac_threshold_px,
                                       noise_px=options.noise_px, max_depth_spread=options.max_depth_spread)
        if rel is None or rel.n_inliers < match_options.min_matches:
            return m, None
        return PairMatches(i, j, m.idx_i[rel.inliers], m.idx_j[rel.inliers], m.n_putative, m.n_candidates,
                           m.time_s, "exhaustive"), rel

    with ThreadPoolExecutor(max_workers=options.threads) as pool:
        found = [r for r in pool.map(verify, sorted(chosen)) if r is not None]
        if planned and options.plan_overlap_at_wall:
            depth = _wall_distance(camera, features, poses, found)
            prior = DepthPrior(depth, depth) if depth else DepthPrior(options.min_radius_mm, options.max_radius_mm)
            more = _plan_overlaps(camera, poses, prior, options.min_overlap) - chosen
            chosen |= more
            found += [r for r in pool.map(verify, sorted(more)) if r is not None]
    posed = [(m, r) for m, r in found if r is not None]
    refused = [m for m, r in found if r is None]
    return [m for m, _ in posed], [r for _, r in posed], refused, chosen


def _plan_overlaps(camera: Camera, poses: list[Pose], wall: DepthPrior, min_overlap: float) -> set:
    """The pairs (i, j), i < j, whose fields overlap by ``min_overlap`` with the wall at ``wall``'s depth."""
    ii, jj = np.nonzero(np.triu(frame_overlap(camera, poses, wall) >= min_overlap, 1))
    return set(zip(ii.tolist(), jj.tolist()))


def _wall_distance(camera: Camera, features: list[Features], poses: list[Pose], found: list) -> float | None:
    """Distance (mm) from the cameras to the wall: the median over the posed pairs of their inliers' median
    distance from the first camera, triangulated with the plan's relative pose (pairs with fewer than half
    their points in front of both cameras left out, as in :func:`depth_spread`); None without such a pair.
    The plan's pose, not the pair's own: on the 200 px turn the pairs' own baseline directions put 9 of 15
    pairs' points 4-16 x too far. Per pair first, then the median over pairs: a few bad pairs do not move it."""
    distances = []
    for m, rel in found:
        if rel is None:
            continue
        R_ji = poses[m.j].rotation @ poses[m.i].rotation.T
        t_ji = poses[m.j].translation - R_ji @ poses[m.i].translation
        baseline = float(np.linalg.norm(t_ji))
        plan = RelativePose(m.i, m.j, R_ji, t_ji / baseline, np.ones(len(m.idx_i), bool))
        zi, front = pair_depths(camera, features[m.i].keypoints[m.idx_i], features[m.j].keypoints[m.idx_j], plan)
        if front.mean() >= 0.5:
            distances.append(baseline * float(np.median(zi[front])))
    return float(np.median(distances)) if distances else None


def verified_matches(camera: Camera, features: list[Features], matches: list[PairMatches], poses: list[Pose],
                     match_options: MatchOptions = MatchOptions(), noise_px: float = 0.5,
                     threads: int = 2) -> tuple[list[PairMatches], list[RelativePose]]:
    """Geometric verification for the tracks, apart from the shape test the start needs: each pair's
    matches reduced to the inliers of its relative pose (:func:`scope3d.estimators.averaging.relative_pose`:
    the essential matrix by five-point RANSAC on the calibrated rays and the relative pose of ``poses``
    (a map already adjusted), each refined, the one with most inliers kept); pairs left with fewer than
    ``match_options.min_matches`` are dropped. Returns (matches, their relative poses).

    Why the essential matrix and not the fundamental one the matcher fits: on the 36-frame spiral (608 px,
    all 630 pairs matched) 117 pairs passed the fundamental-matrix RANSAC at 1.5 px, with 10.5 % wrong
    matches in the pairs more than two frames apart (three pairs of 15 matches were wholly wrong: seven
    degrees of freedom fit 15 random matches); the essential matrix (five) kept 88 pairs, and the tracks
    built from them had 1.0 % wrong observations (5.0 % from the fundamental matrix's)."""
    def verify(m: PairMatches):
        R_ji = poses[m.j].rotation @ poses[m.i].rotation.T
        rel = relative_pose(camera, features[m.i].keypoints[m.idx_i], features[m.j].keypoints[m.idx_j],
                            threshold_px=match_options.ransac_threshold_px, noise_px=noise_px,
                            prior=(R_ji, poses[m.j].translation - R_ji @ poses[m.i].translation), i=m.i, j=m.j)
        if rel is None or rel.n_inliers < max(match_options.min_matches, 8):
            return None
        return PairMatches(m.i, m.j, m.idx_i[rel.inliers], m.idx_j[rel.inliers], m.n_putative, m.n_candidates,
                           m.time_s, m.method), rel

    with ThreadPoolExecutor(max_workers=threads) as pool:
        found = [v for v in pool.map(verify, matches) if v is not None]
    return [m for m, _ in found], [r for _, r in found]


def overlapping_pairs(camera: Camera, features: list[Features], poses: list[Pose], tracks: Tracks,
                      tried: set, options: CavityOptions = CavityOptions(),
                      match_options: MatchOptions = MatchOptions(), *, progress=None) -> list[PairMatches]:
    """The pairs the start says overlap and that were not matched yet, matched exhaustively (fundamental
    matrix inliers; :func:`verified_matches` verifies them). The fields are placed on the wall at the
    median depth of the start's points (tracks triangulated with ``poses``, provisional units);
    pairs overlapping by at least ``options.min_overlap`` are kept (:func:`frame_overlap`).

    Retrieval and capture order find the neighbours along the spiral; this finds the two-apart and
    cross-turn pairs that tie the chain (tracks of three or more views fix the ratios between baselines)."""
    points = triangulate_tracks(camera, poses, tracks, options.tracks)
    if points.n_tracks == 0:
        return []
    z = np.concatenate([(points.points[points.track[points.frame == k]] @ p.rotation.T + p.translation)[:, 2]
                        for k, p in enumerate(poses)])
    depth = float(np.median(z[z > 0])) if np.any(z > 0) else 1.0
    overlap = frame_overlap(camera, poses, DepthPrior(depth, depth))
    ii, jj = np.nonzero(np.triu(overlap >= options.min_overlap, 1))
    todo = sorted(set(zip(ii.tolist(), jj.tolist())) - tried)

    def match(pair):
        m = match_exhaustive(camera, features[pair[0]], features[pair[1]], match_options, i=pair[0], j=pair[1])
        advance(progress)
        return m

    with ThreadPoolExecutor(max_workers=options.threads) as pool:
        return [m for m in pool.map(match, todo) if len(m) >= max(match_options.min_matches, 8)]


# --- 2., 3. start poses ---------------------------------------------------------------------------


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
    resid = np.arccos(np.clip((np.trace(e, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
    sigma = np.array([r.rotation_sigma_rad for r in relative], float)
    sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, np.inf)
    normalised = resid / sigma
    factor = _robust_sigma(normalised[np.isfinite(sigma)], 1.0) if len(relative) >= 3 else 1.0
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
        new = _huber_weights(r / _robust_sigma(r, 1.0), 2.0)
        if np.allclose(new, weight):
            break
        weight = new
    return C - C[0]


def fit_sphere(points: np.ndarray, *, robust: bool = False) -> tuple[np.ndarray, float]:
    """Least-squares sphere (centre (3,), radius) through points (N, 3), N >= 4.

    The algebraic fit (``|X|^2 = 2 c.X + (r^2 - |c|^2)``, linear in c and the constant) measures each
    point's misfit in squared radii, so a point triangulated far off weighs with its distance squared.
    robust : refine it geometrically, the misfit being each point's distance to the sphere
    ``|X - c| - r``, under a soft-L1 loss whose scale is the residuals' robust spread (1.4826 x their
    median absolute deviation), re-estimated over three rounds. Why: the start's triangulation of the 30
    mm default spiral (planned poses) has 1 % of its points 100-240 mm from the cavity's centre; the
    algebraic sphere sat 28.7 mm off the true centre (radius 52 mm) and the shell about it cut the near
    end's real wall, the robust one is 0.5 mm off (radius 38 mm)."""
    X = np.asarray(points, float)
    A = np.c_[2.0 * X, np.ones(len(X))]
    sol = np.linalg.lstsq(A, np.einsum("ij,ij->i", X, X), rcond=None)[0]
    centre = sol[:3]
    radius = float(np.sqrt(max(sol[3] + centre @ centre, 0.0)))
    if not robust:
        return centre, radius

    def misfit(p):
        return np.linalg.norm(X - p[:3], axis=1) - p[3]

    def jacobian(p):
        d = X - p[:3]
        return np.c_[-d / np.maximum(np.linalg.norm(d, axis=1), 1e-300)[:, None], -np.ones(len(X))]

    p = np.r_[centre, radius]
    for _ in range(3):
        r = misfit(p)
        scale = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 1e-9 * max(abs(p[3]), 1.0))
        p = least_squares(misfit, p, jac=jacobian, loss="soft_l1", f_scale=scale).x
    return p[:3], float(abs(p[3]))


def wall_spread(points: np.ndarray) -> float:
    """Spread of the points' (N, 3) distances from the centre of their fitted sphere (:func:`fit_sphere`):
    median absolute deviation over the median; inf with fewer than four points. A wall seen from inside a
    cavity is at nearly one distance from its centre (the maps kept on the bladder phantoms, 608 and 256
    px: 0.04-0.06); an all-pair map fallen into another minimum scatters them (0.08-0.22 measured). No
    threshold: :func:`map_cavity` only compares two maps of the same frames."""
    if len(points) < 4:
        return float("inf")
    r = np.linalg.norm(np.asarray(points, float) - fit_sphere(points)[0], axis=1)
    med = float(np.median(r))
    return float(np.median(np.abs(r - med)) / med)


#: the cameras' centroid of a scope scanning a cavity from inside lies within this fraction of the wall's
#: radius from the wall's centre: the scope turns about the cavity's centre (the bladder spiral: its centres
#: within 0.3 radii of it), and a plan of views at a fixed stand-off around the whole wall is centred on it
#: too. Half the radius leaves room for an uneven scan and rejects the measured failure, a map whose cameras
#: sit at the wall of a sphere 3.4 times the cavity's size (0.97; the maps kept on the phantoms,
#: dry, wet, unseen shapes: 0.02-0.07, docs/panorama.md)
MAX_OFF_CENTRE = 0.5


def cameras_off_centre(points: np.ndarray, poses: list[Pose]) -> float:
    """Distance of the cameras' centroid from the centre of the points' (N, 3) fitted sphere
    (:func:`fit_sphere`), over its radius; inf with fewer than four points. Scale-free: a map whose cameras
    look at their wall from inside near its centre is near 0; above :data:`MAX_OFF_CENTRE` the map is not a
    cavity seen from inside.

    Why: with the rotations degrees off, the known-rotation problem can place the centres so that the
    adjusted map is a cap of a large sphere with the cameras against it (the unseen wet cavity,
    ``--shape-seed 11``: cameras 0.97 radii off, points at 0.04 radii from the cameras, every point ~26 mm
    off the truth). That cap fits a sphere better than a real wall does, so :func:`wall_spread` preferred
    it; where the cameras are is what gives it away."""
    if len(points) < 4:
        return float("inf")
    centre, radius = fit_sphere(points)
    if radius <= 0:
        return float("inf")
    return float(np.linalg.norm(np.mean([p.centre for p in poses], axis=0) - centre) / radius)


def map_figures(camera: Camera, every: Tracks, tracks: Tracks, poses: list[Pose], options: CavityOptions) -> dict:
    """What tells one image-only candidate map from another without the truth: the observations of every
    verified track (``every``, untriangulated) explained within the reprojection gate by ``poses``, the
    wall's spread (:func:`wall_spread`) and the cameras' place (:func:`cameras_off_centre`) of the adjusted
    ``tracks``, and the frames registered; the explained observations per frame too (``explained_per_frame``,
    for the significance of a difference: :func:`explained_difference`)."""
    n = len(poses)
    explained = triangulate_tracks(camera, poses, every, options.tracks)
    return {"explained_observations": int(explained.n_observations),
            "explained_per_frame": np.bincount(explained.frame, minlength=n).tolist(),
            "wall_spread": wall_spread(tracks.points), "cameras_off_centre": cameras_off_centre(tracks.points, poses),
            "n_registered": int((np.bincount(tracks.frame, minlength=n) >= options.min_observations).sum())}


#: a difference between the two maps (the observations they explain, their walls' spreads) decides only
#: beyond this many of its standard errors (a 3-sigma test: 0.13 % by chance on each side)
SIGNIFICANT_SIGMAS = 3.0


def explained_difference(all_pairs: dict, chain: dict) -> tuple[float, float]:
    """How many more verified observations the all-pair map explains than the chain's (from their
    :func:`map_figures`), and the standard error of that total over frames: sqrt(n) times the spread of the
    per-frame differences, what a bootstrap over frames gives. Why over frames: a map's errors are shared by
    the wall a frame sees (a block of frames turned off loses every track across it), so observations are
    no independent samples."""
    d = np.asarray(all_pairs["explained_per_frame"], float) - np.asarray(chain["explained_per_frame"], float)
    sigma = float(np.sqrt(len(d)) * np.std(d, ddof=1)) if len(d) > 1 else float("inf")
    return float(d.sum()), sigma


def choose_map(all_pairs: dict, chain: dict, spread_excess: tuple[float, float]) -> tuple[bool, str]:
    """Whether to keep the chain's map rather than the all-pair map, and why, from their
    :func:`map_figures` and how much more the all-pair map's wall spreads than the chain's on the points
    both hold, with its standard error (:func:`spread_difference`).

    A map that is no cavity seen from inside (:func:`cameras_off_centre`) loses to one that is. Otherwise
    the all-pair map, adjusted from tracks that tie more frames, is kept unless the chain's explains more
    of the verified observations within the gate, or unless its wall spreads significantly more than the
    chain's on the same points (beyond :data:`SIGNIFICANT_SIGMAS` standard errors, :func:`spread_difference`:
    a bent map that still explains a little more, as the 256 px spiral's once did, 0.22 against 0.04) while
    it does not explain significantly more (:func:`explained_difference`): the data outrank the shape.

    Measured (docs/panorama.md, "Which image-only map"): with the spread deciding whatever the counts, a
    chain's map 2.42 mm off was kept over an all-pair map 0.29 mm off that explained 18 % more (wet
    mucosa, its wall spreading 3.2 standard errors more). A chain explaining more still wins by any amount:
    a block of frames turned off loses the tracks across it, but by less than its frames' scatter (a
    synthetic 9 deg block: 644 fewer, 1.9 standard errors). Not per frame: a test that the all-pair map
    explains no frame significantly less kept a chain's map of 4.0 mm over an all-pair map of 0.42 mm that
    had lost one frame (an unseen cavity)."""
    inside = [f["cameras_off_centre"] <= MAX_OFF_CENTRE for f in (all_pairs, chain)]
    if inside[0] != inside[1]:
        return inside[1], "only the " + ("chain's" if inside[1] else "all-pair") + " map has its cameras inside the cavity"
    more, sigma = explained_difference(all_pairs, chain)
    if more < 0:
        return True, f"the chain's map explains more of the verified observations ({-more:.0f})"
    if more > SIGNIFICANT_SIGMAS * sigma:
        z = f"{more / sigma:.1f} standard errors" if sigma > 0 else "the same in every frame"
        return False, f"the all-pair map explains significantly more of the verified observations ({more:.0f}, {z})"
    excess, sigma = spread_excess
    if excess > SIGNIFICANT_SIGMAS * sigma:
        return True, (f"the all-pair map's wall spreads more than the chain's on the same points "
                      f"({excess:.3f}, {excess / sigma:.1f} standard errors)")
    return False, ("the all-pair map explains at least as many of the verified observations, and its wall "
                   "spreads not significantly more")


def common_points(a: Tracks, b: Tracks) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points (K, 3) of two maps of the same features that share an observation (frame, feature), one
    row per pair of tracks, and the first frame (K,) observing each in map a."""
    key_a = a.frame.astype(np.int64) * (1 << 32) + a.feature
    key_b = b.frame.astype(np.int64) * (1 << 32) + b.feature
    _, ia, ib = np.intersect1d(key_a, key_b, return_indices=True)
    pairs = np.unique(np.c_[a.track[ia], b.track[ib]], axis=0)
    first = np.full(a.n_tracks, np.iinfo(np.int64).max)
    np.minimum.at(first, a.track, a.frame.astype(np.int64))
    return a.points[pairs[:, 0]], b.points[pairs[:, 1]], first[pairs[:, 0]]


def spread_difference(a: Tracks, b: Tracks, *, draws: int = 200, seed: int = 0) -> tuple[float, float]:
    """``wall_spread`` of map a minus map b on the points both hold (:func:`common_points`), and its
    standard error by a bootstrap over frames (each point drawn with the first frame that sees it).

    Why over frames and on the same points: a map's errors are shared by the wall a frame sees (a block of
    frames off moves all of its points), so points are no independent samples (a bootstrap over points gave
    standard errors 2-46 times smaller on 11 maps, docs/panorama.md); and two maps holding different parts
    of a wall that is no sphere differ in spread by the parts alone. (0, inf) with fewer than four common
    points."""
    pa, pb, frame = common_points(a, b)
    if len(pa) < 4:
        return 0.0, float("inf")
    frames, index = np.unique(frame, return_inverse=True)
    rng = np.random.default_rng(seed)
    diffs = []
    for _ in range(draws):
        weight = np.bincount(rng.integers(0, len(frames), len(frames)), minlength=len(frames))[index]
        keep = np.repeat(np.arange(len(pa)), weight)
        if len(keep) >= 4:
            diffs.append(wall_spread(pa[keep]) - wall_spread(pb[keep]))
    return wall_spread(pa) - wall_spread(pb), float(np.std(diffs)) if len(diffs) > 1 else float("inf")


def map_disagreement(a: Tracks, b: Tracks) -> dict:
    """How far two maps of the same frames disagree: the points they share (:func:`common_points`) after the
    similarity that best takes one's onto the other's, their distances over the wall radius of the map
    taken onto (median, p95), the larger of both ways (a map fallen into a cap of a sphere 3.4 times too
    large shrinks the other's distances over its radius: 0.07 against 0.90 on an unseen cavity), and how many
    points. Scale-free; 0 for maps equal up to a similarity. NaN with fewer than four common points."""
    pa, pb, _ = common_points(a, b)
    if len(pa) < 4:
        return {"median": float("nan"), "p95": float("nan"), "n_common_points": int(len(pa))}
    d = [np.linalg.norm(fit_similarity(q, p).apply(q) - p, axis=1) / fit_sphere(p)[1]
         for p, q in ((pa, pb), (pb, pa))]
    return {"median": float(max(np.median(x) for x in d)), "p95": float(max(np.percentile(x, 95) for x in d)),
            "n_common_points": int(len(pa))}


# --- 4. adjustment --------------------------------------------------------------------------------


@dataclass
class CavityMap:
    """The adjusted map.

    tracks : observations and points (mm, provisional scale unless the poses were planned);
    poses : per frame ``cam_from_world``; centre_mm, radius_mm : the sphere fitted to the final points;
    registered : (n,) bool, frames with at least ``min_observations`` observations in the final map;
    matches, relative : the verified pairs; n_pairs_tried : pairs matched; stages : per adjustment
    (name, cost before and after, iterations); scale_known : the poses were planned (mm are mm);
    time_s : per step (pairs, start, adjustment); alternative : images only, the candidate map not kept
    (tracks, poses); choice : images only, why the map was kept (:func:`choose_map`: both candidates'
    :func:`map_figures`, the spread excess, the reason) and their :func:`map_disagreement`.
    """

    tracks: Tracks
    poses: list[Pose]
    centre_mm: np.ndarray
    radius_mm: float
    registered: np.ndarray
    matches: list[PairMatches]
    relative: list[RelativePose]
    n_pairs_tried: int
    stages: list[dict]
    scale_known: bool
    time_s: dict = field(default_factory=dict)
    alternative: tuple[Tracks, list[Pose]] | None = None
    choice: dict = field(default_factory=dict)

    def scaled(self, factor: float) -> "CavityMap":
        """The map with every length multiplied by ``factor`` (e.g. the stars' scale)."""
        t = self.tracks
        poses = [Pose(p.rotation, factor * p.translation) for p in self.poses]
        tracks = Tracks(t.track, t.frame, t.feature, t.pixels, t.colors, factor * t.points)
        alternative = None
        if self.alternative is not None:
            a, a_poses = self.alternative
            alternative = (Tracks(a.track, a.frame, a.feature, a.pixels, a.colors, factor * a.points),
                           [Pose(p.rotation, factor * p.translation) for p in a_poses])
        return CavityMap(tracks, poses, factor * self.centre_mm, factor * self.radius_mm, self.registered,
                         self.matches, self.relative, self.n_pairs_tried, self.stages, self.scale_known, self.time_s,
                         alternative, self.choice)


def _cap_priority(camera: Camera, poses: list[Pose], tracks: Tracks, min_observations: int) -> np.ndarray:
    """(n_tracks,) the order in which tracks of one length enter under ``max_points``: each frame's
    ``min_observations`` widest first (every frame keeps enough to be registered), then the rest by their
    rays' widest angle. Why the angle: a point's depth error is its distance times the keypoint noise over
    that angle; the lowest ids (the order before) were the first frames' tracks: on the 30 mm default spiral
    (planned) the two-view tracks kept were frames 0-26's, 1-2 deg ones included, and the wall was 0.137 mm
    mean; by the angle alone 0.108 mm, but on the unseen cavity's 15 mm spiral (165 views) a frame whose rays
    are all narrow then lost every track (164/165). All tracks ranked within each frame instead: 0.119 mm,
    and 0.144 against 0.117 mm on the unseen cavity's 30 mm spiral (images only; docs/panorama.md)."""
    angle = ray_angles_deg(camera, poses, tracks)
    order = np.lexsort((-angle[tracks.track], tracks.frame))  # per frame, the widest first
    frame = tracks.frame[order]
    first = np.zeros(tracks.n_tracks, bool)
    first[tracks.track[order[np.arange(len(order)) - np.searchsorted(frame, frame) < min_observations]]] = True
    return angle + 180.0 * first  # angles < 180 deg: a frame's first above every other


def _adjust(camera: Camera, tracks: Tracks, poses: list[Pose], measured: list[MeasuredPose] | None,
            options: CavityOptions, shell: tuple[np.ndarray, float, float] | None, name: str,
            stages: list[dict]) -> tuple[Tracks, list[Pose]]:
    work = tracks.strongest(options.max_points, _cap_priority(camera, poses, tracks, options.min_observations))
    if knows_poses(measured):
        problem = bundle_problem("bounded", measured, camera, work, start=poses)
    else:
        loose = [MeasuredPose(p, PoseTolerance.unknown()) for p in poses]
        problem = bundle_problem("free", loose, camera, work, start=poses)
    if shell is not None:
        problem.bound_points_to_shell(*shell)
    result: BundleResult = solve(problem, SolverOptions(max_iterations=options.max_iterations, loss="huber",
                                                        loss_scale_px=options.loss_scale_px))
    stages.append({"stage": name, "initial_cost": float(result.initial_cost), "final_cost": float(result.final_cost),
                   "iterations": int(result.iterations), "n_points": int(work.n_tracks)})
    out = Tracks(work.track, work.frame, work.feature, work.pixels, work.colors, result.points_world)
    return out, list(result.poses)


def adjust_cavity(camera: Camera, tracks: Tracks, poses: list[Pose], options: CavityOptions = CavityOptions(),
                  measured: list[MeasuredPose] | None = None) -> tuple[Tracks, list[Pose], list[dict]]:
    """Triangulate with the start, (optionally) adjust inside the anatomical shell, adjust freely (or in
    the planned poses' boxes), drop observations beyond the reprojection gate, adjust again, then drop the
    points without depth of their own or outside the shell (module docstring, step 4).

    tracks : untriangulated observations; poses : the start (provisional scale: the fitted sphere's radius
    is the nominal one). Returns (tracks with points, poses, stages)."""
    stages: list[dict] = []
    gate = options.tracks
    if measured is not None:  # the plan's error moves every observation: both rays' ends may be off
        wall = DepthPrior(options.min_radius_mm, options.max_radius_mm)
        gate = gate.widened_by(max(2.0 * pose_error_px(camera, m.tolerance, wall) for m in measured))
    work = triangulate_tracks(camera, poses, tracks, gate)
    if options.shell_stage:
        shell = anatomical_shell(work.points, poses, options)
        work = work.subset(inside_shell(work.points, shell)[work.track])
        work, poses = _adjust(camera, work, poses, measured, options, shell, "shell", stages)
    work, poses = _adjust(camera, work, poses, measured, options, None, "free", stages)
    # every track again with the adjusted poses: the start's error kept some out (a planned start placed
    # half the tracks of the unseen-shape spiral)
    work = triangulate_tracks(camera, poses, tracks, options.tracks)
    work, poses = _adjust(camera, work, poses, measured, options, None, "retriangulated", stages)
    err = reprojection_errors(camera, poses, work)
    keep = err <= options.tracks.max_reprojection_error_px
    keep &= np.bincount(work.track[keep], minlength=work.n_tracks)[work.track] >= 2
    if not keep.all():
        work, poses = _adjust(camera, work.subset(keep), poses, measured, options, None, "gated", stages)
    # a point whose rays meet at a small angle has no depth of its own (a 0.5 px error moves it by its
    # distance times 0.5 px / f / angle), and one outside the anatomical shell is no wall: both dropped.
    # The shell is fitted to the points it filters: a free adjustment moves the map's frame off the
    # start's (on the unseen cavity at 608 px, images only, a sphere fitted to the start's points was
    # 9.7 mm off the true centre in the adjusted map, one fitted to the adjusted points 0.6 mm)
    shell = anatomical_shell(work.points, poses, options)
    keep = (ray_angles_deg(camera, poses, work) >= options.tracks.min_angle_deg) & inside_shell(work.points, shell)
    return work.subset(keep[work.track]), poses, stages


def anatomical_shell(points: np.ndarray, poses: list[Pose], options: CavityOptions) -> tuple[np.ndarray, float, float]:
    """The anatomical shell (centre (3,), minimum and maximum radius) for points (N, 3) of a map whose
    cameras are ``poses``: about the robust sphere fitted to the points (:func:`fit_sphere` with
    ``robust=True``: a few points triangulated far off do not move it), the radii ``min_radius_mm`` and
    ``max_radius_mm`` times the fitted radius over ``nominal_radius_mm`` (the map's units). With fewer than four
    points, the cameras' centroid (the scope turns about the cavity's centre) and the nominal radius.
    The shell is for gross outliers: a cavity of 90 x 76 x 64 mm has its wall 32-45 mm from its centre,
    well inside 20-70 mm, as long as the centre is within ~12 mm."""
    if len(points) >= 4:
        centre, radius = fit_sphere(points, robust=True)
    else:
        centre, radius = np.mean([p.centre for p in poses], axis=0), options.nominal_radius_mm
    s = radius / options.nominal_radius_mm  # map units per mm of the prior
    return centre, s * options.min_radius_mm, s * options.max_radius_mm


def inside_shell(points: np.ndarray, shell: tuple[np.ndarray, float, float]) -> np.ndarray:
    """(N,) bool: the points between the shell's radii about its centre (:func:`anatomical_shell`)."""
    r = np.linalg.norm(points - shell[0], axis=1)
    return (r >= shell[1]) & (r <= shell[2])


def map_cavity(camera: Camera, features: list[Features], measured: list[MeasuredPose] | None = None,
               options: CavityOptions = CavityOptions(), match_options: MatchOptions = MatchOptions(), *,
               where: str = "dataset", progress=None) -> CavityMap:
    """Poses and points of a cavity from its frames' features (module docstring). measured : planned
    poses with finite tolerances start and bound the poses; otherwise (None or infinite tolerances) they
    come from the images alone. Raises InputError when the frames do not overlap."""
    n = len(features)
    if n < 2:
        raise InputError(f"{where}: need at least 2 frames, found {n}")
    times = {}
    t0 = time.perf_counter()
    matches, relative, refused, tried = pair_poses(camera, features, options, match_options, measured, progress=progress)
    times["pairs_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    planned = knows_poses(measured)
    n_tried = len(tried)
    alternative, choice = None, {}
    if planned:  # the plan places every frame: one that shares no matches is left unregistered, not refused
        if not matches:
            raise InputError(f"{where}: no two frames overlap (no pair of frames verified by their matches)")
        tracks, poses, stages = adjust_cavity(camera, build_tracks(features, matches), [m.pose for m in measured],
                                              options, measured)
        times["adjust_s"] = time.perf_counter() - t0
    else:
        rotations = start_rotations(n, relative, where=where)
        # the centres from the pairs whose rotation agrees with the averaged ones (their baselines too)
        keep = consistent_pairs(rotations, relative)
        try:
            centres = start_centres(camera, rotations, [r for r, k in zip(relative, keep) if k],
                                    [m for m, k in zip(matches, keep) if k], features, where=where)
        except InputError:  # a frame tied by inconsistent pairs only: every pair, rather than no map
            centres = start_centres(camera, rotations, relative, matches, features, where=where)
        chain = build_tracks(features, matches)
        start = _provisional_scale(camera, poses_from(rotations, centres), chain, options)
        # the tracks of every geometrically verified pair: those the start says overlap (two-apart,
        # cross-turn) matched too (module docstring, step 4)
        more = overlapping_pairs(camera, features, start, chain, tried, options, match_options, progress=progress)
        n_tried += len(more)
        more, _ = verified_matches(camera, features, refused + more, start, match_options, options.noise_px,
                                   options.threads)
        every = build_tracks(features, matches + more)
        # the centres from the tracks' rays with the rotations held (the known-rotation problem): tracks of
        # three or more views fix the ratios between baselines that the pairs' depths only guess
        loose = [MeasuredPose(p, PoseTolerance.unknown()) for p in start]
        centres, _ = positions_from_points(camera, loose, rotations, np.stack([p.centre for p in start]), every,
                                           noise_px=options.noise_px)
        times["start_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        tracks, poses, stages = adjust_cavity(camera, every, poses_from(rotations, centres), options)
        # the chain of posed pairs alone, adjusted from the depth-scaled start, is the fallback: a start
        # degrees off can let the cross-turn tracks pull a block of frames into another minimum (choose_map)
        chain_tracks, chain_poses, chain_stages = adjust_cavity(camera, chain, start, options)
        figures = [map_figures(camera, every, t, p, options) for t, p in ((tracks, poses), (chain_tracks, chain_poses))]
        excess = spread_difference(tracks, chain_tracks)
        use_chain, reason = choose_map(*figures, excess)
        kept, other = (chain_tracks, chain_poses), (tracks, poses)
        if not use_chain:
            kept, other = other, kept
        choice = {"kept": "chain" if use_chain else "all pairs", "reason": reason,
                  "all_pairs": figures[0], "chain": figures[1],
                  "spread_excess": {"value": excess[0], "standard_error": excess[1]},
                  "disagreement": map_disagreement(kept[0], other[0])}
        alternative = other
        if use_chain:
            stages = chain_stages
        else:
            matches = matches + more
        tracks, poses = kept
        times["adjust_s"] = time.perf_counter() - t0
    centre, radius = fit_sphere(tracks.points)
    registered = np.bincount(tracks.frame, minlength=n) >= options.min_observations
    return CavityMap(tracks, poses, centre, radius, registered, matches, relative, n_tried, stages, planned, times,
                     alternative, choice)


def _provisional_scale(camera: Camera, poses: list[Pose], tracks: Tracks, options: CavityOptions) -> list[Pose]:
    """The poses rescaled so that the sphere fitted to the tracks' points has the nominal radius (the
    provisional scale until the stars set it); unchanged with fewer than four points."""
    points = triangulate_tracks(camera, poses, tracks, options.tracks).points
    if len(points) < 4:
        return poses
    factor = options.nominal_radius_mm / fit_sphere(points)[1]
    return [Pose.from_centre(p.rotation, factor * p.centre) for p in poses]
