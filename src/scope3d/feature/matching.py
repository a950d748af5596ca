"""Which features correspond between two frames (reference sec. 3.3, 4.3.1, 4.4.4): sparse feature matching.

* :func:`match_guided` — *feature position prediction* (reference sec. 4.3.1): each feature of frame a
  is predicted in frame b from the two measured poses and the depth prior
  (:mod:`scope3d.feature.depth_prior`), and its match is searched only in a window around the
  prediction. The reference used a plane-induced homography and a fixed 100-px window; here the
  prediction is the **epipolar segment** swept by the feature's ray between the prior's near and far
  depths, which degenerates to the homography's single point when the depth range is thin (a
  near-planar scene). The window's radius follows the physics: a pose error of ``dp`` mm moves a point
  at depth ``z`` by ``f dp / z`` px and an orientation error of ``dw`` rad by about ``f dw`` px. The
  ratio test (0.8) is applied among the candidates inside the window only, which is why prediction
  finds *more* matches than exhaustive search: look-alike features elsewhere in the image no longer
  spoil the ratio. A long segment (a deep prior across a wide baseline, or a high resolution: on the
  Strecha photographs at 3072 x 2048, every one) is still a thin strip of the image and is searched by
  brute force along it; only a strip wider than a sixteenth of the image falls back, for that feature, to
  descriptor matching against the whole frame with the prediction as a gate (:func:`_long_segment_matches`).
* :func:`match_exhaustive` — the conventional baseline: every feature against every feature, ratio
  test 0.8.

Both matchers end with the same RANSAC (fundamental matrix on undistorted pixels, or a homography) so
their outputs are comparable. Per-pair loops are fine; nothing loops over features in Python. Which
frames to pair is :mod:`scope3d.feature.pairs`; dense stereo matching is :mod:`scope3d.mvs.dense_matching`.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from scope3d.feature.depth_prior import DepthPrior, _project_ray_ranges, _ray_depth_ranges, window_radius_px
from scope3d.feature.detection import Features
from scope3d.sensor.camera import Camera
from scope3d.sensor.camera_models import DEFAULT_MODEL
from scope3d.sensor.pose_tolerance import MeasuredPose
from scope3d.utils.aot import load_kernels

# compiled at install (scope3d.utils.aot) or, failing that, by numba on first use
_kernels = load_kernels("scope3d.feature.descriptor_kernels")
from scope3d.utils.progress import advance
from scope3d.utils.threads import check_threads, resolve_threads

_GEOMETRIC_MODELS = ("fundamental", "homography", "none")


# segments are sampled every _SAMPLE_SPACING window radii; a point within a radius of the segment is then
# within sqrt(1 + spacing^2 / 4) radii of its nearest sample
_SAMPLE_SPACING = 4.0


@dataclass(frozen=True)
class MatchOptions:
    """Options shared by both matchers.

    ratio : float, Lowe's ratio test, best/second-best descriptor distance (reference: 0.8).
    geometric_model : "fundamental" (general scenes), "homography" (planar scenes) or "none".
    ransac_threshold_px : float, RANSAC inlier threshold on undistorted pixels (default 1.5 px: SIFT
        keypoints are good to ~0.5 px; the margin covers residual distortion-model error).
    ransac_confidence : float, RANSAC confidence (default 0.999).
    min_matches : int, pairs with fewer verified matches are dropped (default 15; 8 would fit F but
        a pair that weak contributes little and is often wrong).
    base_radius_px : float, guided matcher: the window radius with exact poses — the keypoint
        localisation error (~1 px), the shift of a keypoint between views under perspective (~1-2 px)
        and the unmodelled distortion of the camera model (default 4 px).
    max_radius_px : float, guided matcher: cap on the window radius (default 250 px). With tolerances
        so large that the window would exceed it, the prediction carries no information and the
        pair is matched exhaustively instead. The cap is also never more than the radius of a disc of a
        sixteenth of the image: beyond it every feature has a sixteenth of the other frame's features or
        more as candidates, so the windowed search holds ~N^2/16 candidates per pair in memory (on a
        30-frame survey with 1 mm-wide windows, 271 million) for what brute force does in place.
        Segments longer than ``2 max_radius_px`` are not sampled but searched by brute force along
        their strip, and the same sixteenth of the image bounds the strip (:func:`_long_segment_matches`).
    mutual : bool, keep a match only if it is also the best for the feature in the other frame.
    threads : int, threads for the per-pair RANSAC of the guided matcher (default 0: every available core,
        :mod:`scope3d.utils.threads`).
    """

    ratio: float = 0.8
    geometric_model: str = "fundamental"
    ransac_threshold_px: float = 1.5
    ransac_confidence: float = 0.999
    min_matches: int = 15
    base_radius_px: float = 4.0
    max_radius_px: float = 250.0
    mutual: bool = True
    threads: int = 0

    def __post_init__(self) -> None:
        if not 0 < self.ratio <= 1:
            raise ValueError(f"ratio must be in (0, 1], got {self.ratio}")
        if self.geometric_model not in _GEOMETRIC_MODELS:
            raise ValueError(f"geometric_model must be one of {_GEOMETRIC_MODELS}, got {self.geometric_model!r}")
        if self.ransac_threshold_px <= 0 or not 0 < self.ransac_confidence < 1:
            raise ValueError("ransac_threshold_px must be > 0 and ransac_confidence in (0, 1)")
        if self.min_matches < 0:
            raise ValueError("min_matches must be >= 0")
        if self.base_radius_px <= 0 or self.max_radius_px < self.base_radius_px:
            raise ValueError("need 0 < base_radius_px <= max_radius_px")
        check_threads(self.threads)


@dataclass
class PairMatches:
    """Verified matches between frames ``i`` and ``j``.

    idx_i, idx_j : (M,) int64, indices into the frames' :class:`~scope3d.feature.detection.Features`.
    n_putative : int, matches after the ratio test, before RANSAC.
    n_candidates : int, descriptor comparisons made (the cost the prediction saves).
    time_s : float, wall time of this pair (descriptor search + RANSAC).
    method : "guided", "exhaustive" or "guided->exhaustive" when the window was uninformative.
    """

    i: int
    j: int
    idx_i: np.ndarray
    idx_j: np.ndarray
    n_putative: int = 0
    n_candidates: int = 0
    time_s: float = 0.0
    method: str = "guided"

    def __len__(self) -> int:
        return len(self.idx_i)


def _ratio_select_grouped(a: np.ndarray, b: np.ndarray, d2: np.ndarray, ratio: float):
    """Ratio test among candidates already grouped by ``a`` (equal values contiguous), in O(C).

    Returns matched (a, b, d2) where best < ratio * second-best; a lone candidate passes.
    """
    if len(a) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32)
    start = np.flatnonzero(np.r_[True, a[1:] != a[:-1]])
    best = np.minimum.reduceat(d2, start)
    group = np.repeat(np.arange(len(start)), np.diff(np.r_[start, len(a)]))
    is_best = d2 == best[group]
    # position of the (first) best in each group
    pos = np.full(len(start), len(a))
    np.minimum.at(pos, group[is_best], np.flatnonzero(is_best))
    masked = d2.copy()
    masked[pos] = np.inf
    second = np.minimum.reduceat(masked, start)
    passed = best < (ratio * ratio) * second
    chosen = pos[passed]
    return a[chosen], b[chosen], d2[chosen]


def _keep_mutual(a: np.ndarray, b: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """Boolean mask over (a, b) pairs keeping, for each b, only its closest a."""
    if len(a) == 0:
        return np.zeros(0, dtype=bool)
    order = np.lexsort((d2, b))
    first = np.ones(len(order), dtype=bool)
    first[1:] = b[order][1:] != b[order][:-1]
    keep = np.zeros(len(a), dtype=bool)
    keep[order[first]] = True
    return keep


def pair_squared_distances(desc_a: np.ndarray, desc_b: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared L2 descriptor distances ``|desc_a[a[k]] - desc_b[b[k]]|^2`` of candidate pairs, (C,) float32.

    desc_a (Na, D), desc_b (Nb, D) descriptors (any real dtype, computed in float32); a, b (C,) row indices.
    One compiled pass reading the rows in place (:mod:`scope3d.feature.descriptor_kernels`).
    """
    out = np.empty(len(a), dtype=np.float32)
    _kernels.candidate_squared_distances(
        np.ascontiguousarray(desc_a, np.float32), np.ascontiguousarray(desc_b, np.float32),
        np.ascontiguousarray(a, np.int64), np.ascontiguousarray(b, np.int64), out)
    return out


def best_two_per_query(query: np.ndarray, candidate: np.ndarray, d2: np.ndarray, n_queries: int
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ratio test's inputs from candidate pairs in any order, in one compiled pass.

    query, candidate (C,) int indices (query < n_queries), d2 (C,) their squared descriptor distances.
    Returns per query (n_queries,): its best candidate (least ``(d2, candidate)``; -1 for a query without
    pairs), that least d2 and the second least d2 of its pairs (inf with fewer than two), float32.
    """
    return _kernels.best_two_per_query(np.ascontiguousarray(query, np.int64), np.ascontiguousarray(candidate, np.int64),
                                       np.ascontiguousarray(d2, np.float32), int(n_queries))


# pairs matched at once by match_pairs' guided matcher: enough to amortise match_guided_many's per-call
# array set-up (a pair holds ~10^4 candidates), few enough that the batch's candidates, segment samples and
# descriptor copy take tens of MB, not GB (the 1,000-frame survey's 3,800 pairs in one batch peaked at GB)
_GUIDED_PAIRS_PER_BATCH = 128

# tree hits (keypoint near a segment sample) examined at once by match_guided_many: each hit holds ~200 bytes
# of temporaries until the exact distance test, so a chunk takes ~100 MB however wide the windows are
_CANDIDATE_HITS_PER_CHUNK = 1 << 19

# squared distances held at once by two_nearest: a (rows x N) float32 block of 16 MB (1,024 rows at N = 4,000,
# 600 against a 6,800-point map), whatever the size of desc_b
_NEAREST_BLOCK_ENTRIES = 1 << 22


def two_nearest(desc_a: np.ndarray, desc_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each row of ``desc_a``'s nearest and second-nearest row of ``desc_b`` (L2), brute force.

    Returns (nearest index (Na,) int64, its distance, the second distance), float32, as OpenCV's
    ``BFMatcher.knnMatch(k=2)`` gives them (ties to the lowest index); needs len(desc_b) >= 2.
    The squared distances come from one matrix product, ``|a|^2 + |b|^2 - 2 a.b`` (BLAS; ~2.5x faster than
    OpenCV's brute force on 1,200 x 1,200 SIFT descriptors). SIFT's are integers of norm ~512 stored as
    float32, so every product, sum and partial sum is an integer below 2^24 and the distances are exact,
    bitwise those of the direct difference; for non-integer descriptors the squares differ by float32
    rounding of ``|a|^2 + |b|^2`` (the nearest index only where two candidates are that close).
    """
    a = np.ascontiguousarray(desc_a, np.float32)
    b = np.ascontiguousarray(desc_b, np.float32)
    norm_b = np.einsum("ij,ij->i", b, b)
    nearest = np.empty(len(a), np.int64)
    best = np.empty(len(a), np.float32)
    second = np.empty(len(a), np.float32)
    rows_per_block = max(1, _NEAREST_BLOCK_ENTRIES // max(len(b), 1))
    for lo in range(0, len(a), rows_per_block):
        block = a[lo:lo + rows_per_block]
        d2 = block @ b.T
        d2 *= -2.0
        d2 += norm_b[None, :]
        d2 += np.einsum("ij,ij->i", block, block)[:, None]
        rows = np.arange(len(block))
        k = np.argmin(d2, axis=1)
        nearest[lo:lo + len(block)] = k
        best[lo:lo + len(block)] = d2[rows, k]
        d2[rows, k] = np.inf
        second[lo:lo + len(block)] = d2.min(axis=1)
    # rounding of non-integer descriptors can leave a tiny negative square
    return nearest, np.sqrt(np.maximum(best, 0.0)), np.sqrt(np.maximum(second, 0.0))


def _on_segment(q: np.ndarray, p0: np.ndarray, p1: np.ndarray, rad: np.ndarray, owner: np.ndarray, last: np.ndarray,
                sample_k: np.ndarray, si: np.ndarray) -> np.ndarray:
    """Which tree hits are candidates: keypoint ``q`` (H, 2) within its segment's radius of the segment
    (p0, p1 (S, 2), rad (S,), per segment), and found from the sample nearest to its foot on the segment
    (a keypoint near several samples of one segment is kept once). si (H,) sample of each hit; owner,
    last, sample_k (per sample) its segment, that segment's last sample index and its own index."""
    sg = owner[si]
    s0 = p0[sg]
    d = p1[sg] - s0
    off = q - s0
    tpar = np.clip(np.einsum("ij,ij->i", off, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
    off -= tpar[:, None] * d
    keep = np.einsum("ij,ij->i", off, off) <= rad[sg] ** 2
    keep &= np.rint(tpar * last[si]).astype(np.int64) == sample_k[si]
    return keep


# (features x keypoints) point-to-segment distances computed at once by _long_segment_matches: ~32 MB a temporary
_STRIP_BLOCK_ENTRIES = 1 << 22


def _segment_d2(q: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Squared distances of points q (..., 2) to segments (p0, p1) (..., 2), broadcast."""
    d = p1 - p0
    off = q - p0
    t = np.clip((off * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-12), 0.0, 1.0)
    off = off - t[..., None] * d
    return (off * off).sum(-1)


def _long_segment_matches(camera: Camera, features: list[Features], i_frames: np.ndarray, offsets: np.ndarray,
                          a_loc: np.ndarray, p0: np.ndarray, p1: np.ndarray, rad: np.ndarray, pair_of: np.ndarray,
                          frame_j: np.ndarray, long: np.ndarray, ratio: float):
    """Guided matching of the segments too long to sample (``long``, indices into the segment arrays).

    A long segment's search region is the strip within its radius of the segment, ``2 r L + pi r^2`` px^2.
    * While that strip covers at most a sixteenth of the image (the bound that caps a window's radius,
      :class:`MatchOptions`), its candidates are frame j's keypoints inside it, found by brute-force distance
      to the segment; they are returned as (segment, global keypoint) pairs for the ratio test among each
      segment's candidates, as the sampled segments' are.
    * A wider strip would hold ~N/16 candidates or more per feature and carries little information about
      where the match is: the feature is matched by descriptor against every keypoint of j (ratio test
      among all of them, as :func:`match_exhaustive`), and the known poses then gate the match — kept only
      if the matched keypoint lies inside the strip. Returned as matches (segment, global keypoint, d2).
    The strip's length is the unclipped segment's (a segment reaching outside the image counts as longer
    than what it covers: the rule errs towards descriptor matching, never towards a strip too wide).
    """
    empty = np.zeros(0, np.int64)
    strip_s, strip_b, wide_s, wide_b, wide_d2 = [empty], [empty], [empty], [empty], [np.zeros(0, np.float32)]
    if len(long) == 0:
        return empty, empty, empty, empty, np.zeros(0, np.float32)
    length = np.linalg.norm(p1[long] - p0[long], axis=1)
    strip = 2.0 * rad[long] * length + np.pi * rad[long] ** 2
    narrow = strip <= camera.width * camera.height / 16.0
    key = pair_of[long]
    for k in np.unique(key):  # per pair: one frame i, one frame j
        sel = long[key == k]
        nar = narrow[key == k]
        fi, fj = int(i_frames[k]), int(frame_j[sel[0]])
        kp_j = features[fj].keypoints
        if len(kp_j) < 2:
            continue
        s_n = sel[nar]
        rows = max(1, _STRIP_BLOCK_ENTRIES // len(kp_j))
        for lo in range(0, len(s_n), rows):
            s = s_n[lo:lo + rows]
            # distance to the segment's line first (one matrix product: a keypoint within r of the segment is
            # within r of its line), then the exact distance to the segment for those few
            d = p1[s] - p0[s]
            normal = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.maximum(np.linalg.norm(d, axis=1), 1e-12)[:, None]
            to_line = kp_j @ normal.T - np.einsum("sk,sk->s", normal, p0[s])
            b, r = np.nonzero(np.abs(to_line) <= rad[s])
            keep = _segment_d2(kp_j[b], p0[s[r]], p1[s[r]]) <= rad[s[r]] ** 2
            strip_s.append(s[r[keep]])
            strip_b.append(offsets[fj] + b[keep])
        s_w = sel[~nar]
        if len(s_w):
            nearest, best, second = two_nearest(features[fi].descriptors[a_loc[s_w]], features[fj].descriptors)
            d_seg = _segment_d2(kp_j[nearest], p0[s_w], p1[s_w])
            keep = (best < ratio * second) & (d_seg <= rad[s_w] ** 2)
            wide_s.append(s_w[keep])
            wide_b.append(offsets[fj] + nearest[keep])
            wide_d2.append((best[keep].astype(np.float32)) ** 2)
    return (np.concatenate(strip_s), np.concatenate(strip_b), np.concatenate(wide_s), np.concatenate(wide_b),
            np.concatenate(wide_d2))


def _verify(
    camera: Camera, kp_i: np.ndarray, kp_j: np.ndarray, a: np.ndarray, b: np.ndarray, options: MatchOptions
) -> np.ndarray:
    """RANSAC on undistorted pixels; returns an inlier mask over the putative matches."""
    if options.geometric_model == "none" or len(a) < 8:
        return np.ones(len(a), dtype=bool) if options.geometric_model == "none" else np.zeros(len(a), bool)
    # Undistort so that the epipolar / homography model holds exactly for the pinhole part.
    K = camera.K[:2]
    ui = camera.pixel_to_normalised(kp_i[a]) @ K[:, :2].T + K[:, 2]
    uj = camera.pixel_to_normalised(kp_j[b]) @ K[:, :2].T + K[:, 2]
    mask = None
    # OpenCV 5's MAGSAC asserts instead of returning no model on some degenerate sets (e.g. matches on a
    # line); classic RANSAC then decides, and a set neither can fit has no inliers
    for method in (cv2.USAC_MAGSAC, cv2.RANSAC):
        try:
            if options.geometric_model == "homography":
                _, mask = cv2.findHomography(ui, uj, method, options.ransac_threshold_px, confidence=options.ransac_confidence)
            else:
                _, mask = cv2.findFundamentalMat(ui, uj, method, options.ransac_threshold_px, options.ransac_confidence)
            break
        except cv2.error:
            mask = None
    if mask is None:
        return np.zeros(len(a), dtype=bool)
    return mask.ravel().astype(bool)


def match_exhaustive(
    camera: Camera, features_i: Features, features_j: Features, options: MatchOptions = MatchOptions(), *, i: int = 0, j: int = 1
) -> PairMatches:
    """Conventional matching: every feature of i against every feature of j (OpenCV brute force, L2),
    ratio test, optional mutual check, RANSAC. The reference's "previous algorithm"."""
    t0 = time.perf_counter()
    ni, nj = len(features_i), len(features_j)
    if ni < 2 or nj < 2:
        return PairMatches(i, j, np.zeros(0, np.int64), np.zeros(0, np.int64), time_s=time.perf_counter() - t0, method="exhaustive")
    nearest, d_best, d_second = two_nearest(features_i.descriptors, features_j.descriptors)
    passed = d_best < options.ratio * d_second
    a = np.flatnonzero(passed)
    b = nearest[passed]
    d2 = d_best[passed].astype(np.float64) ** 2
    if options.mutual:
        keep = _keep_mutual(a, b, d2)
        a, b = a[keep], b[keep]
    inl = _verify(camera, features_i.keypoints, features_j.keypoints, a, b, options)
    a, b = a[inl], b[inl]
    if len(a) < options.min_matches:
        a, b = a[:0], b[:0]
    return PairMatches(i, j, a, b, int(passed.sum()), ni * nj, time.perf_counter() - t0, "exhaustive")


def match_guided(
    camera: Camera,
    features_i: Features,
    features_j: Features,
    measured_i: MeasuredPose,
    measured_j: MeasuredPose,
    depth_prior: DepthPrior,
    *,
    options: MatchOptions = MatchOptions(),
    i: int = 0,
    j: int = 1,
) -> PairMatches:
    """Pose-guided matching of one pair with feature position prediction (reference sec. 4.3.1, 4.4.4).

    Each feature of frame i is predicted in frame j as the epipolar segment of its ray over the depth
    prior (:func:`predict_segments`); candidates are the features of j within :func:`window_radius_px`
    of that segment. The ratio test runs among those candidates only; then RANSAC. Falls back to
    :func:`match_exhaustive` when the window is larger than ``options.max_radius_px``.
    See :func:`match_guided_many`, which does the same for many pairs at once (faster).
    """
    return match_guided_many(camera, [features_i, features_j], [measured_i, measured_j], [(0, 1, 1.0)], depth_prior,
                             options=options, frame_ids=[i, j])[0]


def _epipolar_sag_px(camera: Camera, pose_i, pose_j, ray_range, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """(N,) how far (px) each feature's epipolar curve bows away from the chord between its ends ``p0``,
    ``p1``: the distance of its middle (the ray at the harmonic mean of the depth range, the middle in
    inverse depth, where a curve's image is most even) from the chord. Through a distorting lens the
    epipolar line is a curve; the search window around the chord is widened by this much (the bow's
    largest distance is at its middle for a curve bending one way, as a lens's smooth field makes it)."""
    rays, near, far = ray_range
    z_mid = 2.0 / (1.0 / near + 1.0 / far)
    middle = _project_ray_ranges(camera, pose_i, pose_j, rays, z_mid, z_mid)[0]
    chord = p1 - p0
    length2 = np.sum(chord * chord, axis=1)
    t = np.clip(np.sum((middle - p0) * chord, axis=1) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
    return np.linalg.norm(middle - (p0 + t[:, None] * chord), axis=1)


def match_guided_many(
    camera: Camera,
    features: list[Features],
    poses: list[MeasuredPose],
    pairs: list[tuple[int, int, float]],
    depth_prior: DepthPrior,
    *,
    options: MatchOptions = MatchOptions(),
    frame_ids: list[int] | None = None,
    progress=None,
) -> list[PairMatches]:
    """Guided matching of all ``pairs`` in one vectorised pass.

    Every pair's segments are sampled every ``_SAMPLE_SPACING`` radii; for each frame j, the samples of all pairs
    into j go into one KD-tree and a single fixed-radius tree-against-tree search against j's keypoints
    (sqrt(1 + spacing^2 / 4) radii cover every point within ``radius`` of a segment) finds their candidates. Descriptor distances, the ratio test among each feature's
    candidates and the mutual check are then single array operations; only RANSAC loops over pairs.
    Batching matters because a pair has only ~10^4 candidates: per-pair array overheads would cost more
    than the descriptor arithmetic itself.

    frame_ids : optional frame numbers to put in the results (default: indices into ``features``).
    Returns one :class:`PairMatches` per pair, in order; ``time_s`` is the pair's share of the batch.
    """
    t0 = time.perf_counter()
    ids = list(range(len(features))) if frame_ids is None else list(frame_ids)
    empty = np.zeros(0, np.int64)
    results: list[PairMatches | None] = [None] * len(pairs)
    offsets = np.concatenate([[0], np.cumsum([len(f) for f in features])]).astype(np.int64)
    seg = {"a": [], "p0": [], "p1": [], "pair": [], "frame_j": [], "radius": []}
    radii = np.zeros(len(pairs))
    ray_ranges: dict[int, tuple] = {}
    radius_limit = min(options.max_radius_px, np.sqrt(camera.width * camera.height / (16.0 * np.pi)))
    for k, (i, j, _) in enumerate(pairs):  # per-pair loop: prediction only
        radius = window_radius_px(camera, poses[i].tolerance, poses[j].tolerance, depth_prior, options.base_radius_px)
        radii[k] = radius
        if radius > radius_limit:
            results[k] = match_exhaustive(camera, features[i], features[j], options, i=ids[i], j=ids[j])
            results[k].method = "guided->exhaustive"
            continue
        if len(features[i]) < 2 or len(features[j]) < 2:
            results[k] = PairMatches(ids[i], ids[j], empty, empty)
            continue
        if i not in ray_ranges:
            ray_ranges[i] = _ray_depth_ranges(camera, poses[i].pose, features[i].keypoints, depth_prior)
        p0, p1 = _project_ray_ranges(camera, poses[i].pose, poses[j].pose, *ray_ranges[i])
        half = 0.5 * np.linalg.norm(p1 - p0, axis=1)
        mid = 0.5 * (p0 + p1)
        seg_radius = np.full(len(p0), radius)
        if camera.model != DEFAULT_MODEL:
            seg_radius = seg_radius + _epipolar_sag_px(camera, poses[i].pose, poses[j].pose, ray_ranges[i], p0, p1)
        m = seg_radius + half
        # the feature must be predicted near frame j's image at all
        valid = np.isfinite(half)
        valid &= (mid[:, 0] > -m) & (mid[:, 0] < camera.width + m) & (mid[:, 1] > -m) & (mid[:, 1] < camera.height + m)
        a = np.flatnonzero(valid)
        seg["a"].append(a)
        seg["p0"].append(p0[a])
        seg["p1"].append(p1[a])
        seg["pair"].append(np.full(len(a), k))
        seg["frame_j"].append(np.full(len(a), j))
        seg["radius"].append(seg_radius[a])
    todo = [k for k in range(len(pairs)) if results[k] is None]
    if todo and sum(len(a) for a in seg["a"]):
        a_loc = np.concatenate(seg["a"]).astype(np.int64)
        p0 = np.concatenate(seg["p0"])
        p1 = np.concatenate(seg["p1"])
        pair_of = np.concatenate(seg["pair"]).astype(np.int64)
        frame_j = np.concatenate(seg["frame_j"]).astype(np.int64)
        rad = np.concatenate(seg["radius"])
        length = np.linalg.norm(p1 - p0, axis=1)
        # a segment longer than 2 max_radius_px (a deep prior seen across a wide baseline, or a high
        # resolution) is searched by brute force (_long_segment_matches), not sampled: it would take
        # length / (4 radii) samples, thousands per feature at full resolution
        sampled = length < 2.0 * options.max_radius_px
        # samples along every segment (fewer samples, larger query: 4 radii measured fastest)
        n_samples = np.where(sampled, np.ceil(length / (_SAMPLE_SPACING * rad)).astype(np.int64) + 1, 0)
        owner = np.repeat(np.arange(len(a_loc)), n_samples)
        first = np.repeat(np.cumsum(n_samples) - n_samples, n_samples)
        sample_k = np.arange(len(owner)) - first
        last = np.repeat(n_samples - 1, n_samples)
        frac = (sample_k / np.maximum(last, 1))[:, None]
        samples = p0[owner] + frac * (p1[owner] - p0[owner])
        kp_all = np.concatenate([f.keypoints for f in features])
        # one tree search per frame j and window size (radii within a factor of 2): a query radius set by
        # one wide window would make every narrow segment's many samples hit most of the image
        group = frame_j * 64 + np.ceil(np.log2(np.maximum(rad, 1.0))).astype(np.int64)
        sample_group = group[owner]
        order_s = np.argsort(sample_group, kind="stable")
        starts = np.flatnonzero(np.r_[True, np.diff(sample_group[order_s]) != 0]) if len(order_s) else order_s
        # the tree search returns every keypoint within the query radius of a sample, several times the
        # candidates that survive the exact distance test (neighbouring samples' discs overlap, and the
        # group's widest window sets the radius); those hits, each with a dozen temporaries, were what
        # held memory (15 million at +-3 mm: 2.5 GB). So samples are searched in chunks whose expected
        # hits (the keypoints a query disc covers, as a share of the image) stay bounded, and each chunk
        # keeps only its exact candidates; the candidates per sample are the same whatever the chunking
        si_parts, b_parts = [], []
        for lo, hi in zip(starts, np.r_[starts[1:], len(order_s)]):  # per (frame, window size) loop
            sel = order_s[lo:hi]
            fj = int(frame_j[owner[sel[0]]])
            if len(features[fj]) == 0:
                continue
            r_query = np.sqrt(1.0 + 0.25 * _SAMPLE_SPACING**2) * float(rad[owner[sel]].max()) * 1.0001
            share = min(1.0, np.pi * r_query**2 / (camera.width * camera.height))
            per_chunk = max(1, int(_CANDIDATE_HITS_PER_CHUNK / max(share * len(features[fj]), 1.0)))
            kp_tree = cKDTree(features[fj].keypoints)
            for c0 in range(0, len(sel), per_chunk):
                chunk = sel[c0:c0 + per_chunk]
                hits = cKDTree(samples[chunk]).sparse_distance_matrix(kp_tree, r_query, output_type="ndarray")
                si, b_loc = chunk[hits["i"]], hits["j"].astype(np.int64)
                del hits
                keep = _on_segment(features[fj].keypoints[b_loc], p0, p1, rad, owner, last, sample_k, si)
                si_parts.append(si[keep])
                b_parts.append(offsets[fj] + b_loc[keep])
        si = np.concatenate(si_parts) if si_parts else np.zeros(0, np.int64)
        b_glob = np.concatenate(b_parts) if b_parts else np.zeros(0, np.int64)
        order_h = np.argsort(si, kind="stable")  # grouped by sample, hence by segment
        sg, b_glob = owner[si[order_h]], b_glob[order_h]
        i_frames = np.array([pairs[k][0] for k in range(len(pairs))], np.int64)
        desc_all = np.concatenate([f.descriptors for f in features])
        long_strip, long_b, wide_seg, wide_b, wide_d2 = _long_segment_matches(
            camera, features, i_frames, offsets, a_loc, p0, p1, rad, pair_of, frame_j, np.flatnonzero(~sampled),
            options.ratio)
        if len(long_strip):  # the brute-force strips' candidates join the sampled ones, grouped by segment
            sg, b_glob = np.r_[sg, long_strip], np.r_[b_glob, long_b]
            order_h = np.argsort(sg, kind="stable")
            sg, b_glob = sg[order_h], b_glob[order_h]
        pair_c = pair_of[sg]
        a_glob = offsets[i_frames[pair_c]] + a_loc[sg]
        d2 = pair_squared_distances(desc_all, desc_all, a_glob, b_glob)
        n_cand = np.bincount(pair_c, minlength=len(pairs))
        n_cand += np.bincount(pair_of[wide_seg], weights=[len(features[f]) for f in frame_j[wide_seg]],
                              minlength=len(pairs)).astype(np.int64)
        # ratio test among each segment's candidates (sg is sorted: candidates grouped by segment)
        g_seg, g_b, g_d2 = _ratio_select_grouped(sg, b_glob, d2, options.ratio)
        g_seg, g_b, g_d2 = np.r_[g_seg, wide_seg], np.r_[g_b, wide_b], np.r_[g_d2, wide_d2]
        n_put = np.bincount(pair_of[g_seg], minlength=len(pairs))
        g_pair = pair_of[g_seg]
        if options.mutual and len(g_seg):
            keep = _keep_mutual(g_seg, g_pair * len(kp_all) + g_b, g_d2)
            g_seg, g_b, g_pair = g_seg[keep], g_b[keep], g_pair[keep]
        order = np.argsort(g_pair, kind="stable")
        g_seg, g_b, g_pair = g_seg[order], g_b[order], g_pair[order]
        bounds = np.searchsorted(g_pair, np.arange(len(pairs) + 1))
        t_share = (time.perf_counter() - t0) / max(len(todo), 1)
        def verify(k):  # per-pair RANSAC; OpenCV releases the GIL, so pairs run on both cores
            t1 = time.perf_counter()
            i, j, _ = pairs[k]
            sl = slice(bounds[k], bounds[k + 1])
            a = a_loc[g_seg[sl]]
            b = g_b[sl] - offsets[j]
            inl = _verify(camera, features[i].keypoints, features[j].keypoints, a, b, options)
            a, b = a[inl], b[inl]
            if len(a) < options.min_matches:
                a, b = a[:0], b[:0]
            return PairMatches(ids[i], ids[j], a, b, int(n_put[k]), int(n_cand[k]),
                               t_share + time.perf_counter() - t1, "guided")

        with ThreadPoolExecutor(max_workers=resolve_threads(options.threads)) as pool:
            for k, m in zip(todo, pool.map(verify, todo)):
                results[k] = m
                advance(progress)
    for k in range(len(pairs)):
        if results[k] is None:
            results[k] = PairMatches(ids[pairs[k][0]], ids[pairs[k][1]], empty, empty, time_s=0.0)
    return results


def match_pairs(
    camera: Camera,
    features: list[Features],
    poses: list[MeasuredPose],
    pairs: list[tuple[int, int, float]],
    depth_prior: DepthPrior | None,
    *,
    options: MatchOptions = MatchOptions(),
    method: str = "guided",
    progress=None,
) -> list[PairMatches]:
    """Match every listed pair with the guided (:func:`match_guided_many`) or exhaustive matcher.

    progress : tqdm-like or None, advanced by one per pair (:mod:`scope3d.utils.progress`).
    """
    if method not in ("guided", "exhaustive"):
        raise ValueError(f"method must be 'guided' or 'exhaustive', got {method!r}")
    if method == "guided":
        if depth_prior is None:
            raise ValueError("the guided matcher needs a depth prior")
        # in batches of pairs, each with only the frames it involves: every pair's matches are the same
        # whatever else is in its batch, while the candidates held at once (and a copy of the batch's
        # descriptors) stay bounded however many frames the map has
        out = []
        for lo in range(0, len(pairs), _GUIDED_PAIRS_PER_BATCH):
            batch = pairs[lo:lo + _GUIDED_PAIRS_PER_BATCH]
            frames = sorted({f for i, j, _ in batch for f in (i, j)})
            local = {f: n for n, f in enumerate(frames)}
            out += match_guided_many(camera, [features[f] for f in frames], [poses[f] for f in frames],
                                     [(local[i], local[j], w) for i, j, w in batch], depth_prior, options=options,
                                     frame_ids=frames, progress=progress)
        return out
    out = []
    for i, j, _ in pairs:
        out.append(match_exhaustive(camera, features[i], features[j], options, i=i, j=j))
        advance(progress)
    return out
