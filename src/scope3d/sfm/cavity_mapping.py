"""Image-only mapping of a closed cavity seen from inside (reference sec. 2.3.4, 2.4.3): camera poses and
points from the images, a spherical shape prior, then released.

A scope inside a bladder turns about a point near the cavity's centre: baselines of 2-5 mm against a wall
20-40 mm away, consecutive views turned by tens of degrees. Essential matrices then often fall into the
rotation-translation (bas-relief) ambiguity: on the bladder spiral a third of the consecutive pairs
decomposed into a rotation 5-7 deg off with the baseline turned by ~90 deg, and chained rotations drifted by
40 deg over 36 frames. What tells the true motion apart is the shape: it puts the wall at nearly one
distance, the ambiguous one bends it (:func:`scope3d.estimators.cavity_start.cavity_relative_pose`). The
steps, run by :func:`map_cavity` (the start poses of steps 2-3 are :mod:`scope3d.estimators.cavity_start`'s,
the choice between candidate maps :mod:`scope3d.sfm.cavity_map_choice`'s):

1. :func:`pair_poses` — each frame's successors in capture order and its most similar frames
   (:func:`scope3d.feature.retrieval.image_similarity`) matched exhaustively and their relative pose chosen
   by the shape (``cavity_relative_pose``); with planned poses also the pairs the plan says overlap,
   verified with the planned relative pose as a start.
2. ``start_rotations`` — rotations chained along a minimum spanning tree of the verified pairs (the
   most certain rotations first), then averaged over every pair
   (:func:`scope3d.estimators.averaging.average_rotations`).
3. ``start_centres`` — every pair's baseline scaled by the median depth of its points (the wall is at
   about one distance from a scope inside it), all pairs whose rotation agrees with the averaged ones
   (``consistent_pairs``) solved together by robust least squares. The gauge: the first camera, rescaled
   so that the sphere fitted to the points has the nominal radius (the provisional scale until the stars
   set it).
4. Tracks from every geometrically verified pair: the pairs the start says overlap are matched too
   (:func:`overlapping_pairs`) and every pair whose relative pose the shape test refused is kept if its
   essential matrix has enough inliers (:func:`verified_matches`); geometric verification (which matches
   are right) is apart from the relative pose (which the start needs). The centres are solved again from
   the tracks' rays with the rotations held (:func:`scope3d.estimators.averaging.positions_from_points`).
5. :func:`adjust_cavity` — points triangulated with the start; optionally an adjustment with every point
   bounded to the spherical shell between an anatomical minimum and maximum radius
   (:meth:`BundleProblem.bound_points_to_shell`); bundle adjustment, observations farther than the
   reprojection gate dropped and the adjustment repeated; points outside the shell dropped. The chain of
   posed pairs alone, adjusted from the depth-scaled start, is the fallback (``choose_map``): a map
   whose cameras are not inside near its wall's centre (``cameras_off_centre``) loses to one whose
   are; otherwise the all-pair map is kept unless the chain's explains more of the verified observations
   within the gate, or the all-pair wall spreads significantly more on the points both hold
   (``spread_difference``) while it explains not significantly more (``explained_difference``). How far
   the two maps disagree (``map_disagreement``) is reported with the choice (``CavityMap.choice``).
   Planned poses (finite tolerance) start the poses and bound them (BCBA) instead of steps 2-4, and the
   pairs the plan says overlap are matched.

What limited the image-only map (36-frame spiral): the frames overlap only their neighbours (35-65 %),
so the pairs that passed the shape test formed a chain with a few cross-turn links and tracks of 2.1
views, which fix no ratio between baselines (wall 2.06 mm mean at 608 px). With every geometrically
verified pair in the tracks and the centres from their rays, 0.175 mm at 608 px. At 256 px the start was
2.6 deg off and the all-pair map fell into another minimum (a block of frames 9 deg off) and the chain's
map (2.44 mm) was kept; with today's pairs the all-pair map there is 0.48 mm and kept. On an unseen
cavity at 608 px six posed pairs 10-110 deg off pulled the start's centres 5 mm off through their
baselines and the all-pair map ended at 11.4 mm; without them (``consistent_pairs``) 0.194 mm. On an
unseen wet cavity (608 px) a start 6-12 deg off let the tracks' centres build a cap of a
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

from scope3d.errors import InputError
from scope3d.estimators.averaging import RelativePose, poses_from, positions_from_points, relative_pose
from scope3d.estimators.bundle import BundleResult, SolverOptions, solve
from scope3d.estimators.cavity_start import (cavity_relative_pose, consistent_pairs, pair_depths, start_centres,
                                             start_rotations)
from scope3d.estimators.triangulation import TrackOptions, ray_angles_deg, reprojection_errors, triangulate_tracks
from scope3d.feature.detection import Features
from scope3d.feature.depth_prior import DepthPrior, pose_error_px
from scope3d.feature.matching import MatchOptions, PairMatches, match_exhaustive
from scope3d.feature.pairs import frame_overlap
from scope3d.feature.retrieval import RetrievalOptions, image_similarity
from scope3d.feature.tracks import build_tracks
from scope3d.geometry.pose import Pose
from scope3d.geometry.sphere import fit_sphere
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.cavity_map_choice import choose_map, map_disagreement, map_figures, spread_difference
from scope3d.sfm.guided_mapping import bundle_problem
from scope3d.utils.progress import advance
from scope3d.utils.threads import check_threads, resolve_threads


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
    threads : int, pairs matched at once: 0 (default) every core, n >= 1 at most n (:mod:`scope3d.utils.threads`;
        the map does not depend on it).
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
    threads: int = 0
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
        check_threads(self.threads)


def knows_poses(measured: list[MeasuredPose] | None) -> bool:
    """True when every measured pose has a finite tolerance (a plan or a robot), False for image-only."""
    return measured is not None and all(
        np.all(np.isfinite(m.tolerance.position_mm)) and np.all(np.isfinite(m.tolerance.orientation_rad))
        for m in measured)


# --- 1. pairs --------------------------------------------------------------------------------------


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

    with ThreadPoolExecutor(max_workers=resolve_threads(options.threads)) as pool:
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
    their points in front of both cameras left out, as in
    :func:`scope3d.estimators.cavity_start.depth_spread`); None without such a pair.
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
                     threads: int = 0) -> tuple[list[PairMatches], list[RelativePose]]:
    """Geometric verification for the tracks, apart from the shape test the start needs: each pair's
    matches reduced to the inliers of its relative pose (:func:`scope3d.estimators.averaging.relative_pose`:
    the essential matrix by five-point RANSAC on the calibrated rays and the relative pose of ``poses``
    (a map already adjusted), each refined, the one with most inliers kept); pairs left with fewer than
    ``match_options.min_matches`` are dropped; ``threads`` pairs at once (0, the default: every core).
    Returns (matches, their relative poses).

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

    check_threads(threads)
    with ThreadPoolExecutor(max_workers=resolve_threads(threads, len(matches))) as pool:
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

    with ThreadPoolExecutor(max_workers=resolve_threads(options.threads, len(todo))) as pool:
        return [m for m in pool.map(match, todo) if len(m) >= max(match_options.min_matches, 8)]


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
        figures = [map_figures(camera, every, t, p, options.tracks, options.min_observations)
                   for t, p in ((tracks, poses), (chain_tracks, chain_poses))]
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
