"""The coarse pass for poses too inaccurate to guide matching: overlap and camera poses from the images.

A cable-driven arm's poses are off by millimetres and degrees. Placed on the scene, their frusta no longer
say which frames overlap, and triangulating with them puts points millimetres off. The images do not
depend on the poses, so this pass asks them first and keeps the measurements for what images cannot say:

1. :func:`scope3d.feature.retrieval.image_similarity` ranks every frame's partners by shared visual words;
   partners the measured orientations cannot reconcile (their axes differ by more than the view-angle
   limit plus both tolerances) are never tried.
2. Each frame's best partners, and the pairs of a maximum spanning tree on similarity, are matched
   exhaustively (no prediction: the poses are not trusted yet) and verified by the essential matrix
   (:func:`scope3d.estimators.averaging.relative_pose`). A relative rotation further from the measured one than the
   two orientation tolerances allow cannot be the truth and is dropped, and so is a pair with too little
   parallax to tell its rotation from its baseline (frames a fraction of a millimetre apart: a scope held
   still, a live mapper's keyframes while it tracks badly).
3. While the verified pairs leave the frames in several groups, the best untried pairs between groups
   are tried, a few rounds.
4. Rotation averaging, then position averaging with the measured centres as priors
   (:mod:`scope3d.estimators.averaging`), give every camera's pose; the measurements fix only the similarity.

The caller adjusts these poses by BCBA inside the measured boxes and guides the fine matching with them.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree

from scope3d.estimators.averaging import (
    RelativePose,
    average_positions,
    average_rotations,
    poses_from,
    positions_from_points,
    relative_pose,
)
from scope3d.feature.detection import Features
from scope3d.feature.matching import MatchOptions, PairMatches, match_exhaustive
from scope3d.feature.tracks import build_tracks
from scope3d.feature.retrieval import RetrievalOptions, image_similarity
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotation_angle_between
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose
from scope3d.utils.progress import advance
from scope3d.utils.threads import check_threads, resolve_threads


@dataclass(frozen=True)
class CoarseOptions:
    """The coarse pass.

    partners_per_frame : int, each frame's most similar plausible partners matched exhaustively
        (default 3: with the spanning tree, enough for every frame to be in two or more verified pairs).
    max_view_angle_deg : float, partners whose measured optical axes differ by more than this plus both
        orientation tolerances are never tried (default 60 deg, where SIFT stops matching).
    connect_rounds : int, rounds of trying pairs between groups the verified pairs leave apart (default 4).
    min_pairs_per_frame : int, a frame in fewer verified pairs tries more partners (default 3: one pair
        leaves its distance free, two can leave a hinge). reinforce_rounds : int, rounds of that (default 2).
    noise_px : float, keypoint localisation noise, for the relative poses' uncertainty (default 0.5 px).
    min_parallax_deg : float, a pair whose inliers' median triangulation angle under its relative pose is
        below this is not verified (default 1 deg, the angle below which the map does not triangulate a
        point, ``TrackOptions.min_angle_deg``). With less parallax a small rotation moves the image as the
        baseline does and the essential matrix's rotation and direction trade off, while their sigmas (the
        cost's curvature at the minimum) stay small: on ``bench_live``'s keyframes, pairs 0.15 mm apart at
        15 mm (2 px of motion) came out with the direction 60-95 deg and the rotation 0.4 deg off at a
        stated 0.03 deg; averaged, they pulled ten frames onto one point and the map's points onto the
        cameras. The angle is measured under the pair's own estimate, which puts a rotation that absorbed
        the baseline at a few hundredths of a degree.
    threads : int, pairs matched at once (OpenCV releases the GIL; default 0: every available core,
        :mod:`scope3d.utils.threads`).
    """

    partners_per_frame: int = 3
    max_view_angle_deg: float = 60.0
    connect_rounds: int = 4
    min_pairs_per_frame: int = 3
    reinforce_rounds: int = 2
    noise_px: float = 0.5
    min_parallax_deg: float = 1.0
    threads: int = 0
    retrieval: RetrievalOptions = field(default_factory=RetrievalOptions)

    def __post_init__(self) -> None:
        if (self.partners_per_frame < 1 or self.connect_rounds < 0 or self.min_pairs_per_frame < 0
                or self.reinforce_rounds < 0 or self.noise_px <= 0 or not 0 <= self.min_parallax_deg < 90):
            raise ValueError("need partners_per_frame >= 1, connect_rounds, min_pairs_per_frame, reinforce_rounds >= 0, "
                             "noise_px > 0, 0 <= min_parallax_deg < 90")
        check_threads(self.threads)
        if not 0 < self.max_view_angle_deg <= 180:
            raise ValueError(f"max_view_angle_deg must be in (0, 180], got {self.max_view_angle_deg}")


@dataclass
class CoarseResult:
    """What the coarse pass found.

    matches : verified pairs (essential-matrix inliers only). relative : their relative poses.
    poses : (n) ``cam_from_world`` from the averaging (a frame in no verified pair keeps its measurement).
    similarity : (n, n) image similarity. n_tried : pairs matched. n_groups : connected groups of frames
    left by the verified pairs (1 when every frame is tied to every other).
    """

    matches: list[PairMatches]
    relative: list[RelativePose]
    poses: list[Pose]
    similarity: np.ndarray
    n_tried: int
    n_groups: int
    time_s: float


def plausible_partners(measured: list[MeasuredPose], max_view_angle_deg: float) -> np.ndarray:
    """(n, n) bool: the measured optical axes may differ by at most the limit once both orientation
    tolerances are allowed for (an infinite tolerance allows anything)."""
    axes = np.stack([m.pose.optical_axis for m in measured])
    angle = np.arccos(np.clip(axes @ axes.T, -1.0, 1.0))
    slack = np.array([np.linalg.norm(m.tolerance.orientation_rad) for m in measured])
    ok = angle <= np.deg2rad(max_view_angle_deg) + slack[:, None] + slack[None, :]
    np.fill_diagonal(ok, False)
    return ok


def _first_pairs(score: np.ndarray, per_frame: int) -> set[tuple[int, int]]:
    """Each frame's ``per_frame`` best partners, and the pairs of a maximum spanning forest on ``score``."""
    n = len(score)
    chosen: set[tuple[int, int]] = set()
    for a in range(n):
        for b in np.argsort(-score[a], kind="stable")[:per_frame]:
            if score[a, b] > 0:
                chosen.add((min(a, int(b)), max(a, int(b))))
    # maximum spanning forest = minimum spanning forest of (2 - score) over the plausible pairs
    cost = np.where(score > 0, 2.0 - score, 0.0)
    tree = minimum_spanning_tree(np.triu(cost)).tocoo()
    chosen.update((min(int(a), int(b)), max(int(a), int(b))) for a, b in zip(tree.row, tree.col))
    return chosen


def _groups(n: int, pairs: list[tuple[int, int]]) -> np.ndarray:
    """Connected-group label (n,) of the frames under the given pairs."""
    if not pairs:
        return np.arange(n)
    i, j = np.array(pairs).T
    return connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)), directed=False)[1]


def coarse_poses(camera: Camera, features: list[Features], measured: list[MeasuredPose],
                 *,
                 match_options: MatchOptions = MatchOptions(), options: CoarseOptions = CoarseOptions(), 
                 progress=None) -> CoarseResult:
    """Run the coarse pass (module docstring). progress : tqdm-like or None, advanced by one per pair matched."""
    t0 = time.perf_counter()
    n = len(features)
    similarity = image_similarity(features, options.retrieval)
    score = np.where(plausible_partners(measured, options.max_view_angle_deg), similarity, 0.0)
    min_parallax = np.deg2rad(options.min_parallax_deg)

    def verify(pair: tuple[int, int]):
        i, j = pair
        m = match_exhaustive(camera, features[i], features[j], match_options, i=i, j=j)
        if len(m) < max(match_options.min_matches, 8):
            return None
        mi, mj = measured[i].pose, measured[j].pose
        r_meas = mj.rotation @ mi.rotation.T
        rel = relative_pose(camera, features[i].keypoints[m.idx_i], features[j].keypoints[m.idx_j],
                            threshold_px=match_options.ransac_threshold_px, noise_px=options.noise_px,
                            confidence=match_options.ransac_confidence,
                            prior=(r_meas, mj.translation - r_meas @ mi.translation), i=i, j=j)
        if rel is None or rel.n_inliers < match_options.min_matches or rel.parallax_rad < min_parallax:
            return None
        # the true relative rotation lies within both tolerances of the measured one (3 sigma of the
        # estimate's own noise on top)
        limit = (np.linalg.norm(measured[i].tolerance.orientation_rad) + np.linalg.norm(measured[j].tolerance.orientation_rad)
                 + 3.0 * rel.rotation_sigma_rad)
        if rotation_angle_between(rel.rotation, r_meas) > limit:
            return None
        return PairMatches(i, j, m.idx_i[rel.inliers], m.idx_j[rel.inliers], m.n_putative, m.n_candidates,
                           m.time_s, "exhaustive"), rel

    tried: set[tuple[int, int]] = set()
    found: list[tuple[PairMatches, RelativePose]] = []

    def run(batch: list[tuple[int, int]]) -> None:
        tried.update(batch)
        with ThreadPoolExecutor(max_workers=resolve_threads(options.threads)) as pool:
            for out in pool.map(verify, batch):
                if out is not None:
                    found.append(out)
                advance(progress)

    run(sorted(_first_pairs(score, options.partners_per_frame)))
    for _ in range(options.connect_rounds):
        group = _groups(n, [(m.i, m.j) for m, _ in found])
        if len(np.unique(group)) == 1:
            break
        # the best untried plausible pairs between different groups, a few per group
        ii, jj = np.nonzero(np.triu(score > 0, 1) & (group[:, None] != group[None, :]))
        order = np.argsort(-score[ii, jj], kind="stable")
        per_group = np.zeros(n, int)
        batch = []
        for k in order:
            a, b = int(ii[k]), int(jj[k])
            if (a, b) in tried or per_group[group[a]] >= options.partners_per_frame:
                continue
            batch.append((a, b))
            per_group[group[a]] += 1
            per_group[group[b]] += 1
        if not batch:
            break
        run(batch)
    # a frame in fewer than three verified pairs is weakly placed: one pair leaves its distance along the
    # baseline free and two in a row leave a hinge. Retrieval on a repetitive texture can rank a true
    # neighbour low, so its next candidates alternate between image similarity and the measured centres'
    # distance (the robot's poses still say roughly where the frame was)
    centres = np.stack([m.pose.centre for m in measured])
    distance = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    for _ in range(options.reinforce_rounds):
        degree = np.bincount(np.array([(m.i, m.j) for m, _ in found], int).ravel(), minlength=n) if found else np.zeros(n, int)
        batch = set()
        for a in np.flatnonzero(degree < options.min_pairs_per_frame):
            ranked = [np.argsort(-score[a], kind="stable"), np.argsort(np.where(score[a] > 0, distance[a], np.inf), kind="stable")]
            wanted = options.min_pairs_per_frame - degree[a]
            picks = []
            for b in (int(b) for pair in zip(*ranked) for b in pair):
                key = (min(int(a), b), max(int(a), b))
                if score[a, b] <= 0 or key in tried or key in batch or key in picks:
                    continue
                picks.append(key)
                if len(picks) >= wanted:
                    break
            batch.update(picks)
        if not batch:
            break
        run(sorted(batch))
    found.sort(key=lambda mr: (mr[0].i, mr[0].j))
    matches = [m for m, _ in found]
    relative = [r for _, r in found]
    rotations, _ = average_rotations(measured, relative)
    centres, _ = average_positions(measured, rotations, relative)
    centres, _ = positions_from_points(camera, measured, rotations, centres, build_tracks(features, matches),
                                       noise_px=options.noise_px)
    n_groups = len(np.unique(_groups(n, [(m.i, m.j) for m in matches])))
    return CoarseResult(matches, relative, poses_from(rotations, centres), similarity, len(tried), n_groups,
                        time.perf_counter() - t0)
