"""Image-only mapping of a closed cavity seen from inside (reference sec. 2.3.4, 2.4.3): camera poses and
points from the images, a spherical shape prior, then released.

A scope inside a bladder turns about a point near the cavity's centre: baselines of 2-5 mm against a wall
20-40 mm away, consecutive views turned by tens of degrees. Essential matrices then often fall into the
rotation-translation (bas-relief) ambiguity: on the bladder spiral a third of the consecutive pairs
decomposed into a rotation 5-7 deg off with the baseline turned by ~90 deg, and chained rotations drifted by
40 deg over 36 frames. What tells the true motion apart is the shape: it puts the wall at nearly one
distance, the ambiguous one bends it (:func:`cavity_relative_pose`). The steps, run by :func:`map_cavity`:

1. :func:`pair_poses` — each frame's most similar frames (:func:`scope3d.feature.retrieval.image_similarity`)
   matched exhaustively and their relative pose chosen by the shape (:func:`cavity_relative_pose`).
2. :func:`start_rotations` — rotations chained along a minimum spanning tree of the verified pairs (the
   most certain rotations first), then averaged over every pair (:func:`scope3d.estimators.averaging.average_rotations`).
3. :func:`start_centres` — centres chained along the same tree with unit baselines, then solved jointly
   with the points from the tracks' rays (:func:`scope3d.estimators.averaging.positions_from_points`, a
   linear known-rotation problem). The gauge: the first camera and a unit spread, rescaled so that the
   sphere fitted to the points has the nominal radius (the provisional scale until the stars set it).
4. :func:`adjust_cavity` — triangulated points, those the short baselines cannot place put on that sphere;
   bundle adjustment with every point bounded to the spherical shell between an anatomical minimum and
   maximum radius (:meth:`BundleProblem.bound_points_to_shell`), then released (no shell), observations
   farther than the reprojection gate dropped and the adjustment repeated once. Planned poses (finite
   tolerance) start the poses and bound them (BCBA) instead of steps 2-3.

Units: mm (provisional until :mod:`scope3d.metrology.star_scale` rescales), radians; pixels with their
origin at the top-left pixel's centre. Poses are ``cam_from_world``.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

from scope3d.errors import InputError
from scope3d.estimators.averaging import RelativePose, average_rotations, positions_from_points, refine_relative_pose, relative_pose
from scope3d.estimators.bundle import BundleResult, SolverOptions, solve
from scope3d.estimators.triangulation import TrackOptions, ray_angles_deg, reprojection_errors, triangulate_tracks
from scope3d.feature.detection import Features
from scope3d.feature.matching import MatchOptions, PairMatches, match_exhaustive
from scope3d.feature.retrieval import RetrievalOptions, image_similarity
from scope3d.feature.tracks import build_tracks
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.guided_mapping import bundle_problem
from scope3d.utils.progress import advance


@dataclass(frozen=True)
class CavityOptions:
    """Image-only cavity mapping.

    partners_per_frame : int, each frame's most similar frames matched (default 4: on a spiral the two
        neighbours along the path and one or two across the turns).
    max_depth_spread : float, a pair whose best relative pose still spreads its points' distances by more
        than this (median absolute deviation over the median) is rejected (default 0.15: a sphere seen
        from 0.3 radii off its centre, the farthest a scope on a spiral of a third of the cavity's radius
        gets, spreads its distances by less than that).
    nominal_radius_mm : float, radius of the starting sphere (default 40 mm: a sphere of 270 ml, a bladder
        half filled for cystoscopy). Without a plan this is also the provisional scale.
    min_radius_mm, max_radius_mm : float, the anatomical shell every point is held in during the first
        adjustment (defaults 20 and 70 mm: spheres of 34 ml and 1.4 l, an almost empty and an over-filled
        adult bladder), about the centre of the sphere fitted to the points.
    release_shell : bool, the last adjustments without the shell (default True, the reference's "then
        released"; the shell only keeps the start out of folded minima).
    loss_scale_px : float, Huber scale of the adjustments (default 1 px: SIFT localisation is 0.3-0.5 px).
    max_iterations : int, LM iterations per adjustment (default 100).
    max_points : int, at most this many tracks (the longest) enter the adjustments (default 8000).
    tracks : triangulation gates (reprojection error, smallest ray angle).
    noise_px : float, keypoint localisation noise for the pair and ray weights (default 0.5 px).
    min_observations : int, a frame with fewer observations in the final map is not registered (default 8).
    threads : int, pairs matched at once (default 2, the machine's cores).
    """

    partners_per_frame: int = 4
    max_depth_spread: float = 0.15
    nominal_radius_mm: float = 40.0
    min_radius_mm: float = 20.0
    max_radius_mm: float = 70.0
    release_shell: bool = True
    loss_scale_px: float = 1.0
    max_iterations: int = 100
    max_points: int = 8000
    tracks: TrackOptions = field(default_factory=TrackOptions)
    noise_px: float = 0.5
    min_observations: int = 8
    threads: int = 2
    retrieval: RetrievalOptions = field(default_factory=RetrievalOptions)

    def __post_init__(self) -> None:
        if not 0 < self.min_radius_mm <= self.nominal_radius_mm <= self.max_radius_mm:
            raise ValueError("need 0 < min_radius_mm <= nominal_radius_mm <= max_radius_mm")
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
               match_options: MatchOptions = MatchOptions(), *, progress=None) -> tuple[list[PairMatches], list[RelativePose], int]:
    """Each frame's ``partners_per_frame`` most similar frames matched exhaustively and verified by
    :func:`cavity_relative_pose`. Returns (matches (inliers only), relative poses, pairs tried).
    progress : tqdm-like or None, advanced once per pair."""
    n = len(features)
    similarity = image_similarity(features, options.retrieval)
    np.fill_diagonal(similarity, 0.0)
    chosen: set[tuple[int, int]] = set()
    for a in range(n):
        for b in np.argsort(-similarity[a], kind="stable")[:options.partners_per_frame]:
            if similarity[a, b] > 0:
                chosen.add((min(a, int(b)), max(a, int(b))))

    def verify(pair):
        i, j = pair
        m = match_exhaustive(camera, features[i], features[j], match_options, i=i, j=j)
        advance(progress)
        if len(m) < max(match_options.min_matches, 8):
            return None
        rel = cavity_relative_pose(camera, features[i].keypoints[m.idx_i], features[j].keypoints[m.idx_j], i, j,
                                   threshold_px=match_options.ransac_threshold_px, noise_px=options.noise_px,
                                   max_depth_spread=options.max_depth_spread)
        if rel is None or rel.n_inliers < match_options.min_matches:
            return None
        return PairMatches(i, j, m.idx_i[rel.inliers], m.idx_j[rel.inliers], m.n_putative, m.n_candidates,
                           m.time_s, "exhaustive"), rel

    with ThreadPoolExecutor(max_workers=options.threads) as pool:
        found = [r for r in pool.map(verify, sorted(chosen)) if r is not None]
    return [m for m, _ in found], [r for _, r in found], len(chosen)


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


def start_centres(camera: Camera, rotations: np.ndarray, relative: list[RelativePose], tracks: Tracks, *,
                  noise_px: float = 0.5, where: str = "dataset") -> np.ndarray:
    """(n, 3) centres, frame 0 at the origin, unit mean distance from it: unit baselines chained along the
    spanning tree, then solved with the points from the rays (:func:`positions_from_points`)."""
    n = len(rotations)
    order, parent = _spanning_tree(n, relative, where)
    by_pair = {(r.i, r.j): r for r in relative}
    C = np.zeros((n, 3))
    for k in order[1:]:
        p = parent[k]
        if (p, k) in by_pair:  # C_p - C_k = R_k^T t_kp (unit length)
            C[k] = C[p] - rotations[k].T @ by_pair[(p, k)].direction
        else:  # pair (k, p): C_k - C_p = R_p^T t_pk
            C[k] = C[p] + rotations[p].T @ by_pair[(k, p)].direction
    loose = [MeasuredPose(Pose(rotations[k], np.zeros(3)), PoseTolerance.unknown()) for k in range(n)]
    C, _ = positions_from_points(camera, loose, rotations, C, tracks, noise_px=noise_px)
    C = C - C[0]
    spread = float(np.mean(np.linalg.norm(C, axis=1)))
    return C / spread if spread > 0 else C


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere (centre (3,), radius) through points (N, 3), N >= 4 (algebraic fit:
    ``|X|^2 = 2 c.X + (r^2 - |c|^2)`` is linear in c and the constant)."""
    X = np.asarray(points, float)
    A = np.c_[2.0 * X, np.ones(len(X))]
    sol = np.linalg.lstsq(A, np.einsum("ij,ij->i", X, X), rcond=None)[0]
    centre = sol[:3]
    return centre, float(np.sqrt(max(sol[3] + centre @ centre, 0.0)))


def points_on_sphere(camera: Camera, poses: list[Pose], tracks: Tracks, centre: np.ndarray, radius: float) -> np.ndarray:
    """(n_tracks, 3): each track's point at the mean of its rays' exits through the sphere
    ``|X - centre| = radius`` (cameras inside it)."""
    R = np.stack([p.rotation for p in poses])[tracks.frame]
    C = np.stack([p.centre for p in poses])[tracks.frame]
    xy = camera.pixel_to_normalised(tracks.pixels)
    d = np.einsum("kji,kj->ki", R, np.c_[xy, np.ones(len(xy))])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = C - np.asarray(centre, float)
    b = np.einsum("ki,ki->k", o, d)
    disc = np.maximum(b * b - (np.einsum("ki,ki->k", o, o) - radius**2), 0.0)
    hit = C + (-b + np.sqrt(disc))[:, None] * d
    X = np.zeros((tracks.n_tracks, 3))
    np.add.at(X, tracks.track, hit)
    return X / tracks.lengths()[:, None]


# --- 4. adjustment --------------------------------------------------------------------------------


@dataclass
class CavityMap:
    """The adjusted map.

    tracks : observations and points (mm, provisional scale unless the poses were planned);
    poses : per frame ``cam_from_world``; centre_mm, radius_mm : the sphere fitted to the final points;
    registered : (n,) bool, frames with at least ``min_observations`` observations in the final map;
    matches, relative : the verified pairs; n_pairs_tried : pairs matched; stages : per adjustment
    (name, cost before and after, iterations); scale_known : the poses were planned (mm are mm);
    time_s : per step (pairs, start, adjustment).
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

    def scaled(self, factor: float) -> "CavityMap":
        """The map with every length multiplied by ``factor`` (e.g. the stars' scale)."""
        t = self.tracks
        poses = [Pose(p.rotation, factor * p.translation) for p in self.poses]
        tracks = Tracks(t.track, t.frame, t.feature, t.pixels, t.colors, factor * t.points)
        return CavityMap(tracks, poses, factor * self.centre_mm, factor * self.radius_mm, self.registered,
                         self.matches, self.relative, self.n_pairs_tried, self.stages, self.scale_known, self.time_s)


def _adjust(camera: Camera, tracks: Tracks, poses: list[Pose], measured: list[MeasuredPose] | None,
            options: CavityOptions, shell: tuple[np.ndarray, float, float] | None, name: str,
            stages: list[dict]) -> tuple[Tracks, list[Pose]]:
    work = tracks.strongest(options.max_points)
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
    """Triangulate, put the points the baselines cannot place on the fitted sphere, adjust inside the
    shell, release, drop bad observations, adjust again (module docstring, step 4).

    tracks : untriangulated observations; poses : the start (provisional scale: the fitted sphere's radius
    is the nominal one). Returns (tracks with points, poses, stages)."""
    stages: list[dict] = []
    # every track starts on the sphere (a start off by degrees reprojects tens of pixels away, so no
    # reprojection gate can sort the tracks yet); those the start poses triangulate well at their point
    good = triangulate_tracks(camera, poses, tracks, options.tracks)
    if good.n_tracks >= _MIN_SPHERE_POINTS:
        centre, radius = fit_sphere(good.points)
    else:  # the scope turns about the cavity's centre: the cameras' centroid, the nominal radius
        centre = np.mean([p.centre for p in poses], axis=0)
        radius = options.nominal_radius_mm
    s = radius / options.nominal_radius_mm  # provisional units per mm of the prior
    X = points_on_sphere(camera, poses, tracks, centre, radius)
    ids = _track_ids_like(tracks, good)
    r = np.linalg.norm(good.points - centre, axis=1)
    inside = (r >= s * options.min_radius_mm) & (r <= s * options.max_radius_mm)
    X[ids[inside]] = good.points[inside]
    work = Tracks(tracks.track, tracks.frame, tracks.feature, tracks.pixels, tracks.colors, X)
    shell = (centre, s * options.min_radius_mm, s * options.max_radius_mm)
    work, poses = _adjust(camera, work, poses, measured, options, shell, "shell", stages)
    released = None if options.release_shell else shell
    work, poses = _adjust(camera, work, poses, measured, options, released, "released", stages)
    err = reprojection_errors(camera, poses, work)
    keep = err <= options.tracks.max_reprojection_error_px
    keep &= np.bincount(work.track[keep], minlength=work.n_tracks)[work.track] >= 2
    if not keep.all():
        work = work.subset(keep)
        work, poses = _adjust(camera, work, poses, measured, options, released, "released, gated", stages)
    # a point whose rays meet at a small angle has no depth of its own (a 0.5 px error moves it by its
    # distance times 0.5 px / f / angle), and one outside the anatomical shell is no wall: both dropped
    r = np.linalg.norm(work.points - centre, axis=1)
    keep = (ray_angles_deg(camera, poses, work) >= options.tracks.min_angle_deg) & (r >= shell[1]) & (r <= shell[2])
    return work.subset(keep[work.track]), poses, stages


#: a sphere is fitted to the start's triangulations when at least this many pass the gates
_MIN_SPHERE_POINTS = 20


def _track_ids_like(tracks: Tracks, subset: Tracks) -> np.ndarray:
    """(subset.n_tracks,) ids in ``tracks`` of each track of ``subset`` (a triangulation of some of the
    same observations), found by its first observation's (frame, feature)."""
    key = tracks.frame * (1 << 32) + tracks.feature
    order = np.argsort(key)
    first = np.r_[0, np.flatnonzero(np.diff(subset.track)) + 1][:subset.n_tracks]
    want = subset.frame[first] * (1 << 32) + subset.feature[first]
    return tracks.track[order[np.searchsorted(key[order], want)]]


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
    matches, relative, n_tried = pair_poses(camera, features, options, match_options, progress=progress)
    times["pairs_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    tracks = build_tracks(features, matches)
    planned = knows_poses(measured)
    if planned:
        _spanning_tree(n, relative, where)  # the overlap check
        poses = [m.pose for m in measured]
    else:
        rotations = start_rotations(n, relative, where=where)
        centres = start_centres(camera, rotations, relative, tracks, noise_px=options.noise_px, where=where)
        poses = [Pose.from_centre(R, c) for R, c in zip(rotations, centres)]
        # provisional scale: the points' sphere gets the nominal radius
        points = triangulate_tracks(camera, poses, tracks, options.tracks).points
        if len(points) >= 4:
            factor = options.nominal_radius_mm / fit_sphere(points)[1]
            poses = [Pose.from_centre(p.rotation, factor * p.centre) for p in poses]
    times["start_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    tracks, poses, stages = adjust_cavity(camera, tracks, poses, options, measured if planned else None)
    times["adjust_s"] = time.perf_counter() - t0
    centre, radius = fit_sphere(tracks.points)
    registered = np.bincount(tracks.frame, minlength=n) >= options.min_observations
    return CavityMap(tracks, poses, centre, radius, registered, matches, relative, n_tried, stages, planned, times)
