"""Which of two image-only candidate maps of a cavity to keep (the all-pair map or the chain's, both from
:func:`scope3d.sfm.cavity_mapping.map_cavity`), without the truth: the observations each explains
(:func:`map_figures`, :func:`explained_difference`), whether its cameras are inside the cavity
(:func:`cameras_off_centre`), how much more one wall spreads than the other on the points both hold
(:func:`spread_difference`), and the choice (:func:`choose_map`); how far the two disagree is reported
beside it (:func:`map_disagreement`). Measured on the phantoms: docs/panorama.md, "Which image-only map".

Units: the maps' (mm, provisional until the stars set the scale); every figure here is scale-free or a count.
"""
from __future__ import annotations

import numpy as np

from scope3d.estimators.triangulation import TrackOptions, triangulate_tracks
from scope3d.geometry.pose import Pose
from scope3d.geometry.similarity import fit_similarity
from scope3d.geometry.sphere import fit_sphere, wall_spread
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera


#: the cameras' centroid of a scope scanning a cavity from inside lies within this fraction of the wall's
#: radius from the wall's centre: the scope turns about the cavity's centre (the bladder spiral: its centres
#: within 0.3 radii of it), and a plan of views at a fixed stand-off around the whole wall is centred on it
#: too. Half the radius leaves room for an uneven scan and rejects the measured failure, a map whose cameras
#: sit at the wall of a sphere 3.4 times the cavity's size (0.97; the maps kept on the phantoms,
#: dry, wet, unseen shapes: 0.02-0.07, docs/panorama.md)
MAX_OFF_CENTRE = 0.5


def cameras_off_centre(points: np.ndarray, poses: list[Pose]) -> float:
    """Distance of the cameras' centroid from the centre of the points' (N, 3) fitted sphere
    (:func:`scope3d.geometry.sphere.fit_sphere`), over its radius; inf with fewer than four points.
    Scale-free: a map whose cameras look at their wall from inside near its centre is near 0; above
    :data:`MAX_OFF_CENTRE` the map is not a cavity seen from inside.

    Why: with the rotations degrees off, the known-rotation problem can place the centres so that the
    adjusted map is a cap of a large sphere with the cameras against it (the unseen wet cavity,
    ``--shape-seed 11``: cameras 0.97 radii off, points at 0.04 radii from the cameras, every point ~26 mm
    off the truth). That cap fits a sphere better than a real wall does, so the wall's spread preferred
    it; where the cameras are is what gives it away."""
    if len(points) < 4:
        return float("inf")
    centre, radius = fit_sphere(points)
    if radius <= 0:
        return float("inf")
    return float(np.linalg.norm(np.mean([p.centre for p in poses], axis=0) - centre) / radius)


def map_figures(camera: Camera, every: Tracks, tracks: Tracks, poses: list[Pose], track_options: TrackOptions,
                min_observations: int) -> dict:
    """What tells one image-only candidate map from another without the truth: the observations of every
    verified track (``every``, untriangulated) explained within the reprojection gate (``track_options``) by
    ``poses``, the wall's spread (:func:`scope3d.geometry.sphere.wall_spread`) and the cameras' place
    (:func:`cameras_off_centre`) of the adjusted ``tracks``, and the frames registered (at least
    ``min_observations``); the explained observations per frame too (``explained_per_frame``, for the
    significance of a difference: :func:`explained_difference`)."""
    n = len(poses)
    explained = triangulate_tracks(camera, poses, every, track_options)
    return {"explained_observations": int(explained.n_observations),
            "explained_per_frame": np.bincount(explained.frame, minlength=n).tolist(),
            "wall_spread": wall_spread(tracks.points), "cameras_off_centre": cameras_off_centre(tracks.points, poses),
            "n_registered": int((np.bincount(tracks.frame, minlength=n) >= min_observations).sum())}


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
