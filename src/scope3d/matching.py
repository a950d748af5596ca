"""Which frames overlap, and which features correspond between them (reference sec. 3.3, 4.3.1, 4.4.4).

Three pieces, lowest first:

* :func:`frame_overlap` / :func:`select_pairs` — the reference's first use of known poses: "by knowing
  each position of cameras, the frame pairs with overlap can be easily discovered". A frame's field of
  view is placed on the scene at a depth prior; the fraction of it that lands inside the other frame's
  field of view is the pair's overlap.
* :func:`match_guided` — *feature position prediction* (reference sec. 4.3.1): each feature of frame a
  is predicted in frame b from the two measured poses and the depth prior, and its match is searched
  only in a window around the prediction. The reference used a plane-induced homography and a fixed
  100-px window; here the prediction is the **epipolar segment** swept by the feature's ray between the
  prior's near and far depths, which degenerates to the homography's single point when the depth range
  is thin (a near-planar scene). The window's radius follows the physics: a pose error of ``dp`` mm
  moves a point at depth ``z`` by ``f dp / z`` px and an orientation error of ``dw`` rad by about
  ``f dw`` px. The ratio test (0.8) is applied among the candidates inside the window only, which is
  why prediction finds *more* matches than exhaustive search: look-alike features elsewhere in the
  image no longer spoil the ratio.
* :func:`match_exhaustive` — the conventional baseline: every feature against every feature, ratio
  test 0.8.

Both matchers end with the same RANSAC (fundamental matrix on undistorted pixels, or a homography) so
their outputs are comparable. Per-pair loops are fine; nothing loops over features in Python.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from .camera import Camera
from .features import Features
from .pose import MeasuredPose, Pose, PoseTolerance

_GEOMETRIC_MODELS = ("fundamental", "homography", "none")
# segments are sampled every _SAMPLE_SPACING window radii; a point within a radius of the segment is then
# within sqrt(1 + spacing^2 / 4) radii of its nearest sample
_SAMPLE_SPACING = 4.0


@dataclass(frozen=True)
class DepthPrior:
    """Range of z-depths (mm, camera frame, along the optical axis) at which the scene may lie.

    near_mm, far_mm : float, 0 < near <= far. The overlap and the matcher's prediction use the
    geometric mean as the "expected" depth (the depth of the plane in the homography case).
    per_ray : optional callable ``per_ray(pose, rays_cam) -> (near (N,), far (N,))`` giving a tighter
        z-depth range (mm) for each ray ``rays_cam`` (N, 3) (camera frame, z = 1) of a frame at
        ``pose`` — e.g. the band around a coarse surface already reconstructed; NaN where it knows
        nothing (the global range is used there). Ranges are clipped to [near_mm, far_mm].
    """

    near_mm: float
    far_mm: float
    per_ray: object = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.near_mm) and np.isfinite(self.far_mm)) or not 0 < self.near_mm <= self.far_mm:
            raise ValueError(f"depth prior must satisfy 0 < near <= far, got [{self.near_mm}, {self.far_mm}] mm")

    @property
    def mid_mm(self) -> float:
        return float(np.sqrt(self.near_mm * self.far_mm))


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
    mutual : bool, keep a match only if it is also the best for the feature in the other frame.
    threads : int, threads for the per-pair RANSAC of the guided matcher (default 2, the machine's cores).
    """

    ratio: float = 0.8
    geometric_model: str = "fundamental"
    ransac_threshold_px: float = 1.5
    ransac_confidence: float = 0.999
    min_matches: int = 15
    base_radius_px: float = 4.0
    max_radius_px: float = 250.0
    mutual: bool = True
    threads: int = 2

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
        if self.threads < 1:
            raise ValueError("threads must be >= 1")


@dataclass(frozen=True)
class PairOptions:
    """Which frame pairs to match.

    min_overlap : float, minimum fraction of one frame's field of view (placed at the depth prior)
        seen by the other (default 0.25; the reference planned >= 50 % between grid neighbours, so
        0.25 keeps diagonal and second neighbours, which tie the tracks together).
    max_pairs_per_frame : int, keep at most this many best-overlapping partners per frame
        (default 10; bounds the cost on dense trajectories). 0 = no limit.
    max_pairs_per_direction : int, keep at most this many best-scored partners in each direction of
        camera motion (default 0 = no such limit). The baseline to a partner, in the frame's camera
        coordinates, is classed by its dominant axis (+-x, +-y, +-z); partners whose baseline subtends
        less than 1 deg at the prior depth (the same place, no triangulation) form a seventh class.
        With 1, a ring links each view to its nearest neighbour on either side, a raster to its four
        neighbours, whatever the spacing. Why not more partners: tracks are joined by union-find, and
        every extra pair adds a few wrong matches that glue two tracks into one holding two features
        of a frame, which is dropped whole (:func:`~scope3d.tracks.build_tracks`). A point's views are
        already connected by the chain of nearest neighbours, and the glue grows with pairs per frame
        x track length, i.e. with the density of views: on a 48-view ring rendered around the dome
        phantom, 24 % of the matched features were lost so with the 4 best partners and 64 % with all
        partners within 35 deg, none with 1 per direction (benchmarks/bench_map_views.py).
    samples_per_side : int, the field of view is sampled on this many pixels per side (default 16).
    max_view_angle_deg : float, pairs whose optical axes differ by more are skipped (default 60 deg:
        SIFT descriptors stop matching beyond ~50-60 deg of viewpoint change). Partners are ranked by
        overlap x cos(axis angle), so around an object (where every frustum "overlaps" at the depth
        prior) the nearest viewpoints come first.
    """

    min_overlap: float = 0.25
    max_pairs_per_frame: int = 10
    samples_per_side: int = 16
    max_view_angle_deg: float = 60.0
    max_pairs_per_direction: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.min_overlap <= 1:
            raise ValueError(f"min_overlap must be in [0, 1], got {self.min_overlap}")
        if self.max_pairs_per_frame < 0 or self.max_pairs_per_direction < 0 or self.samples_per_side < 2:
            raise ValueError("max_pairs_per_frame and max_pairs_per_direction must be >= 0 and samples_per_side >= 2")
        if not 0 < self.max_view_angle_deg <= 180:
            raise ValueError(f"max_view_angle_deg must be in (0, 180], got {self.max_view_angle_deg}")


@dataclass
class PairMatches:
    """Verified matches between frames ``i`` and ``j``.

    idx_i, idx_j : (M,) int64, indices into the frames' :class:`~scope3d.features.Features`.
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


def box_depth_prior(box_min_mm: np.ndarray, box_max_mm: np.ndarray, poses: list[Pose], *, margin_mm: float = 0.0) -> DepthPrior:
    """Depth prior from a bounding box of the scene (world, mm), e.g. a calibrated object's.

    Each ray's range is where it crosses the box (slab test), so the prediction's segments end at the
    object; the global range spans the box's distance from every camera. ``margin_mm`` enlarges the box.
    """
    lo = np.asarray(box_min_mm, float) - margin_mm
    hi = np.asarray(box_max_mm, float) + margin_mm
    if lo.shape != (3,) or hi.shape != (3,) or np.any(hi <= lo):
        raise ValueError(f"bounding box must be two (3,) corners with min < max, got {lo} and {hi}")
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    z = np.concatenate([p.transform(corners)[:, 2] for p in poses])
    near = max(float(z.min()), 1e-3)
    far = float(z.max())
    if far <= near:
        raise ValueError("the bounding box is behind every camera")

    def per_ray(pose: Pose, rays_cam: np.ndarray):
        d = np.asarray(rays_cam, float) @ pose.rotation  # world direction per unit z-depth
        c = pose.centre
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo - c) / d
            t2 = (hi - c) / d
        t_near = np.nanmax(np.minimum(t1, t2), axis=1)
        t_far = np.nanmin(np.maximum(t1, t2), axis=1)
        miss = ~(t_far >= np.maximum(t_near, 0.0))
        t_near[miss] = np.nan
        t_far[miss] = np.nan
        return np.maximum(t_near, 1e-3), t_far

    return DepthPrior(near, far, per_ray=per_ray)


# --- which frames overlap --------------------------------------------------------------------


def fov_samples(camera: Camera, n: int) -> np.ndarray:
    """(K, 2) pixels on an n x n grid inside the valid image (circular mask respected)."""
    u = np.linspace(0, camera.width - 1, n)
    v = np.linspace(0, camera.height - 1, n)
    grid = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    return grid[camera.in_image(grid)]


def frame_overlap(camera: Camera, poses: list[Pose], depth: DepthPrior, *, samples_per_side: int = 16) -> np.ndarray:
    """Pairwise overlap of the frames' fields of view placed at the depth prior.

    poses : n ``cam_from_world`` poses (mm). Returns (n, n) float in [0, 1]: entry [a, b] is the fraction
    of frame a's field of view, back-projected to depth ``depth.mid_mm`` in frame a, that projects
    inside frame b. The matrix is symmetrised with the minimum (both must see each other).
    """
    if not poses:
        raise ValueError("no poses given")
    pix = fov_samples(camera, samples_per_side)
    pts_cam = camera.unproject(pix, np.full(len(pix), depth.mid_mm))
    n = len(poses)
    rot = np.stack([p.rotation for p in poses])
    trans = np.stack([p.translation for p in poses])
    # world points of every frame's footprint: (n, K, 3)
    world = np.einsum("nji,nkj->nki", rot, pts_cam[None] - trans[:, None, :])
    overlap = np.zeros((n, n))
    for b in range(n):  # per-frame loop; all samples of all frames at once
        uv = camera.project(world.reshape(-1, 3) @ rot[b].T + trans[b]).reshape(n, -1, 2)
        overlap[:, b] = camera.in_image(uv.reshape(-1, 2)).reshape(n, -1).mean(axis=1)
    np.fill_diagonal(overlap, 1.0)
    return np.minimum(overlap, overlap.T)


def select_pairs(
    camera: Camera, poses: list[Pose], depth: DepthPrior, options: PairOptions = PairOptions()
) -> list[tuple[int, int, float]]:
    """Frame pairs worth matching, as (i, j, overlap) with i < j, best overlap first.

    Each frame keeps its best-scored partners (overlap x cos(axis angle)) within the limits of
    ``options``: per direction of camera motion first (``max_pairs_per_direction``), then per frame
    (``max_pairs_per_frame``); a pair is matched when either frame keeps it.
    """
    ov = frame_overlap(camera, poses, depth, samples_per_side=options.samples_per_side)
    n = len(poses)
    axes = np.stack([p.optical_axis for p in poses])
    cos_axes = np.clip(axes @ axes.T, -1.0, 1.0)
    score = ov * np.maximum(cos_axes, 0.0)
    keep = np.zeros((n, n), dtype=bool)
    cand = (ov >= options.min_overlap) & (cos_axes >= np.cos(np.deg2rad(options.max_view_angle_deg)))
    np.fill_diagonal(cand, False)
    centres = np.stack([p.centre for p in poses])
    for a in range(n):
        partners = np.flatnonzero(cand[a])
        partners = partners[np.argsort(-score[a, partners], kind="stable")]
        if options.max_pairs_per_direction:
            cls = _motion_direction(poses[a], centres[partners], depth.mid_mm)
            rank = np.zeros(len(partners), int)  # rank within its class, best first
            for c in np.unique(cls):
                rank[cls == c] = np.arange(np.count_nonzero(cls == c))
            partners = partners[rank < options.max_pairs_per_direction]
        if options.max_pairs_per_frame:
            partners = partners[: options.max_pairs_per_frame]
        keep[a, partners] = True
    keep = keep | keep.T
    ii, jj = np.nonzero(np.triu(keep, 1))
    order = np.argsort(-score[ii, jj], kind="stable")
    return [(int(ii[k]), int(jj[k]), float(ov[ii[k], jj[k]])) for k in order]


def _motion_direction(pose: Pose, centres: np.ndarray, depth_mm: float) -> np.ndarray:
    """Direction class (M,) int of the baselines from ``pose``'s centre to ``centres`` (M, 3) mm:
    0..5 for the dominant axis of the baseline in camera coordinates (+x, -x, +y, -y, +z, -z), 6 when
    the baseline subtends less than 1 deg at ``depth_mm`` (the same place: no triangulation angle)."""
    b = (np.asarray(centres, float).reshape(-1, 3) - pose.centre) @ pose.rotation.T
    axis = np.argmax(np.abs(b), axis=1)
    cls = 2 * axis + (b[np.arange(len(b)), axis] < 0)
    cls[np.linalg.norm(b, axis=1) < np.tan(np.deg2rad(1.0)) * depth_mm] = 6
    return cls


# --- prediction --------------------------------------------------------------------------------


def predict_segments(
    camera: Camera, pose_i: Pose, pose_j: Pose, keypoints_i: np.ndarray, depth: DepthPrior
) -> tuple[np.ndarray, np.ndarray]:
    """Where features of frame i may appear in frame j.

    keypoints_i : (N, 2) pixels in frame i. Returns the two ends of each feature's epipolar segment in
    frame j, ``near_px`` and ``far_px``, (N, 2) each: the projections of the feature's ray at z-depths
    ``depth.near_mm`` and ``depth.far_mm`` (camera i), or the per-ray range of ``depth.per_ray``. Ends
    behind camera j are NaN. With
    ``near == far`` both ends are the plane-induced homography's prediction ``H = K (R - t n^T / d) K^-1``
    (distortion included).
    """
    return _project_ray_ranges(camera, pose_i, pose_j, *_ray_depth_ranges(camera, pose_i, keypoints_i, depth))


def _ray_depth_ranges(camera: Camera, pose_i: Pose, keypoints_i: np.ndarray, depth: DepthPrior):
    """Rays (N, 3) (camera i, z = 1) of the keypoints and their z-depth ranges near, far (N,) mm.
    Depends on frame i only, so it is computed once per frame, not once per pair."""
    kp = np.asarray(keypoints_i, dtype=float).reshape(-1, 2)
    rays = camera.unproject(kp, np.ones(len(kp)))
    near = np.full(len(kp), depth.near_mm)
    far = np.full(len(kp), depth.far_mm)
    if depth.per_ray is not None:
        lo, hi = depth.per_ray(pose_i, rays)
        known = np.isfinite(lo) & np.isfinite(hi)
        near[known] = np.clip(lo[known], depth.near_mm, depth.far_mm)
        far[known] = np.clip(hi[known], depth.near_mm, depth.far_mm)
    return rays, near, far


def _project_ray_ranges(camera: Camera, pose_i: Pose, pose_j: Pose, rays, near, far):
    """Both ends of each ray's depth range (camera i) projected into frame j, (N, 2) each."""
    ends = []
    for z in (near, far):
        x_world = (rays * z[:, None] - pose_i.translation) @ pose_i.rotation
        ends.append(camera.project_world(pose_j, x_world))
    return ends[0], ends[1]


def window_radius_px(
    camera: Camera, tolerance_i: PoseTolerance, tolerance_j: PoseTolerance, depth: DepthPrior, base_radius_px: float
) -> float:
    """Search-window radius (px) that contains the true match given both poses' tolerance boxes.

    A centre error ``dp`` (mm, the box's half-diagonal, both frames) shifts a point at the nearest depth
    by ``f dp / z_near``; an orientation error ``dw`` (rad) by about ``f dw`` (small angles, near the
    image centre; the distortion-free worst case grows towards the edge, covered by ``base_radius_px``).
    """
    f = max(camera.fx, camera.fy)
    dp = np.linalg.norm(tolerance_i.position_mm) + np.linalg.norm(tolerance_j.position_mm)
    dw = np.linalg.norm(tolerance_i.orientation_rad) + np.linalg.norm(tolerance_j.orientation_rad)
    if not np.isfinite(dp + dw):
        return float("inf")
    return float(base_radius_px + f * dp / depth.near_mm + f * dw)


# --- descriptor search -------------------------------------------------------------------------


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


def _pair_d2(desc_a: np.ndarray, desc_b: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared L2 descriptor distances ``|desc_a[a[k]] - desc_b[b[k]]|^2`` of candidate pairs, (C,) float32."""
    out = np.empty(len(a), dtype=np.float32)
    _candidate_d2(np.ascontiguousarray(desc_a, np.float32), np.ascontiguousarray(desc_b, np.float32),
                  np.ascontiguousarray(a, np.int64), np.ascontiguousarray(b, np.int64), out)
    return out


@njit(cache=True)
def _candidate_d2(desc_a, desc_b, a, b, out):
    # Reads the two descriptor rows in place: gathering them first (desc[a], desc[b]) moved
    # 2 x 512 bytes per candidate through memory and cost 10x the arithmetic.
    for k in range(a.shape[0]):
        ra, rb = a[k], b[k]
        acc = np.float32(0.0)
        for c in range(desc_a.shape[1]):
            d = desc_a[ra, c] - desc_b[rb, c]
            acc += d * d
        out[k] = acc


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
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(features_i.descriptors, features_j.descriptors, k=2)
    pairs = np.array([(m[0].queryIdx, m[0].trainIdx, m[0].distance, m[1].distance) for m in knn if len(m) == 2])
    passed = pairs[:, 2] < options.ratio * pairs[:, 3]
    a = pairs[passed, 0].astype(np.int64)
    b = pairs[passed, 1].astype(np.int64)
    d2 = pairs[passed, 2] ** 2
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
    depth: DepthPrior,
    options: MatchOptions = MatchOptions(),
    *,
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
    return match_guided_many(camera, [features_i, features_j], [measured_i, measured_j], [(0, 1, 1.0)], depth,
                             options, frame_ids=[i, j])[0]


def match_guided_many(
    camera: Camera,
    features: list[Features],
    poses: list[MeasuredPose],
    pairs: list[tuple[int, int, float]],
    depth: DepthPrior,
    options: MatchOptions = MatchOptions(),
    *,
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
        radius = window_radius_px(camera, poses[i].tolerance, poses[j].tolerance, depth, options.base_radius_px)
        radii[k] = radius
        if radius > radius_limit:
            results[k] = match_exhaustive(camera, features[i], features[j], options, i=ids[i], j=ids[j])
            results[k].method = "guided->exhaustive"
            continue
        if len(features[i]) < 2 or len(features[j]) < 2:
            results[k] = PairMatches(ids[i], ids[j], empty, empty)
            continue
        if i not in ray_ranges:
            ray_ranges[i] = _ray_depth_ranges(camera, poses[i].pose, features[i].keypoints, depth)
        p0, p1 = _project_ray_ranges(camera, poses[i].pose, poses[j].pose, *ray_ranges[i])
        half = 0.5 * np.linalg.norm(p1 - p0, axis=1)
        mid = 0.5 * (p0 + p1)
        m = radius + half
        # a segment spanning most of the image carries no information (it would only add look-alike
        # candidates); and the feature must be predicted near frame j's image at all
        valid = np.isfinite(half) & (half < options.max_radius_px)
        valid &= (mid[:, 0] > -m) & (mid[:, 0] < camera.width + m) & (mid[:, 1] > -m) & (mid[:, 1] < camera.height + m)
        a = np.flatnonzero(valid)
        seg["a"].append(a)
        seg["p0"].append(p0[a])
        seg["p1"].append(p1[a])
        seg["pair"].append(np.full(len(a), k))
        seg["frame_j"].append(np.full(len(a), j))
        seg["radius"].append(np.full(len(a), radius))
    todo = [k for k in range(len(pairs)) if results[k] is None]
    if todo and sum(len(a) for a in seg["a"]):
        a_loc = np.concatenate(seg["a"]).astype(np.int64)
        p0 = np.concatenate(seg["p0"])
        p1 = np.concatenate(seg["p1"])
        pair_of = np.concatenate(seg["pair"]).astype(np.int64)
        frame_j = np.concatenate(seg["frame_j"]).astype(np.int64)
        rad = np.concatenate(seg["radius"])
        # samples along every segment (fewer samples, larger query: 4 radii measured fastest)
        n_samples = np.ceil(np.linalg.norm(p1 - p0, axis=1) / (_SAMPLE_SPACING * rad)).astype(np.int64) + 1
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
        starts = np.flatnonzero(np.r_[True, np.diff(sample_group[order_s]) != 0])
        si_parts, b_parts = [], []
        for lo, hi in zip(starts, np.r_[starts[1:], len(order_s)]):  # per (frame, window size) loop
            sel = order_s[lo:hi]
            fj = int(frame_j[owner[sel[0]]])
            if len(features[fj]) == 0:
                continue
            r_max = float(rad[owner[sel]].max())
            hits = cKDTree(samples[sel]).sparse_distance_matrix(
                cKDTree(features[fj].keypoints), np.sqrt(1.0 + 0.25 * _SAMPLE_SPACING**2) * r_max * 1.0001, output_type="ndarray")
            si_parts.append(sel[hits["i"]])
            b_parts.append(offsets[fj] + hits["j"].astype(np.int64))
        si = np.concatenate(si_parts) if si_parts else np.zeros(0, np.int64)
        b_glob = np.concatenate(b_parts) if b_parts else np.zeros(0, np.int64)
        order_h = np.argsort(si, kind="stable")  # grouped by sample, hence by segment
        si, b_glob = si[order_h], b_glob[order_h]
        sg = owner[si]
        # exact distance to the segment, within the pair's own radius; de-duplication: a keypoint near
        # several samples of one segment is kept from the sample nearest to its foot on the segment
        q = kp_all[b_glob]
        s0, d = p0[sg], p1[sg] - p0[sg]
        tpar = np.clip(np.einsum("ij,ij->i", q - s0, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
        off = q - s0 - tpar[:, None] * d
        keep = np.einsum("ij,ij->i", off, off) <= rad[sg] ** 2
        keep &= np.rint(tpar * last[si]).astype(np.int64) == sample_k[si]
        sg, b_glob = sg[keep], b_glob[keep]
        pair_c = pair_of[sg]
        i_frames = np.array([pairs[k][0] for k in range(len(pairs))], np.int64)
        a_glob = offsets[i_frames[pair_c]] + a_loc[sg]
        desc_all = np.concatenate([f.descriptors for f in features])
        d2 = _pair_d2(desc_all, desc_all, a_glob, b_glob)
        n_cand = np.bincount(pair_c, minlength=len(pairs))
        # ratio test among each segment's candidates (sg is sorted: candidates grouped by segment)
        g_seg, g_b, g_d2 = _ratio_select_grouped(sg, b_glob, d2, options.ratio)
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

        with ThreadPoolExecutor(max_workers=options.threads) as pool:
            for k, m in zip(todo, pool.map(verify, todo)):
                results[k] = m
                if progress is not None:
                    progress(1)
    for k in range(len(pairs)):
        if results[k] is None:
            results[k] = PairMatches(ids[pairs[k][0]], ids[pairs[k][1]], empty, empty, time_s=0.0)
    return results


def match_pairs(
    camera: Camera,
    features: list[Features],
    poses: list[MeasuredPose],
    pairs: list[tuple[int, int, float]],
    depth: DepthPrior | None,
    options: MatchOptions = MatchOptions(),
    *,
    method: str = "guided",
    progress=None,
) -> list[PairMatches]:
    """Match every listed pair with the guided (:func:`match_guided_many`) or exhaustive matcher.

    progress : optional callable ``progress(n_done)`` called after each pair (e.g. ``tqdm.update``).
    """
    if method not in ("guided", "exhaustive"):
        raise ValueError(f"method must be 'guided' or 'exhaustive', got {method!r}")
    if method == "guided":
        if depth is None:
            raise ValueError("the guided matcher needs a depth prior")
        return match_guided_many(camera, features, poses, pairs, depth, options, progress=progress)
    out = []
    for i, j, _ in pairs:
        out.append(match_exhaustive(camera, features[i], features[j], options, i=i, j=j))
        if progress is not None:
            progress(1)
    return out


def estimate_depth_prior(
    camera: Camera,
    features: list[Features],
    poses: list[MeasuredPose],
    options: MatchOptions = MatchOptions(),
    *,
    percentiles: tuple[float, float] = (2.0, 98.0),
    margin: float = 0.1,
    n_pairs: int = 5,
) -> DepthPrior:
    """Depth prior from the data: match the ``n_pairs`` closest frame pairs exhaustively, triangulate
    with the measured poses, take robust depth percentiles and widen them by ``margin`` (fraction).

    This bootstraps the guided matcher without asking the user for a working distance; it costs a
    few exhaustive pair matches. Raises ``ValueError`` if no pair yields enough matches.
    """
    from .tracks import TrackOptions, Tracks, triangulate_tracks  # imported late: tracks sits above matching

    centres = np.stack([m.pose.centre for m in poses])
    axes = np.stack([m.pose.optical_axis for m in poses])
    n = len(poses)
    if n < 2:
        raise ValueError("need at least two frames to estimate a depth prior")
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    # prefer close pairs looking the same way (they overlap most), but not coincident ones (no parallax)
    same_way = axes @ axes.T
    score = dist + 1e9 * (same_way < 0.5) + 1e9 * (dist < 1e-6 * max(float(dist.max()), 1e-9))
    iu, ju = np.triu_indices(n, 1)
    order = np.argsort(score[iu, ju], kind="stable")
    # among the closest pairs (within 1.5 x the closest distance), take ones spread along the sequence,
    # so that the prior sees the whole field, not one corner of it
    close = order[score[iu[order], ju[order]] <= 1.5 * score[iu[order[0]], ju[order[0]]]]
    close = close[np.argsort(iu[close], kind="stable")]
    spread = close[np.unique(np.linspace(0, len(close) - 1, min(len(close), n_pairs)).round().astype(int))]
    order = np.concatenate([spread, order[~np.isin(order, spread)]])
    # loose reprojection gate: measured poses may be off by their tolerance; depths need not be precise
    filters = TrackOptions(max_reprojection_error_px=8.0, min_angle_deg=1.0)
    depths = []
    for k in order[: 3 * n_pairs]:
        i, j = int(iu[k]), int(ju[k])
        m = match_exhaustive(camera, features[i], features[j], options, i=i, j=j)
        if len(m) < options.min_matches:
            continue
        nm = len(m)
        tr = Tracks(np.repeat(np.arange(nm), 2), np.tile([0, 1], nm), np.zeros(2 * nm, np.int64),
                    np.stack([features[i].keypoints[m.idx_i], features[j].keypoints[m.idx_j]], 1).reshape(-1, 2),
                    np.zeros((nm, 3), np.uint8))
        tr = triangulate_tracks(camera, [poses[i].pose, poses[j].pose], tr, filters)
        if tr.n_tracks:
            depths.append(poses[i].pose.transform(tr.points)[:, 2])
        if len(depths) >= n_pairs:
            break
    if not depths or sum(len(d) for d in depths) < options.min_matches:
        raise ValueError("cannot estimate a depth prior: no overlapping frame pair has enough matches")
    z = np.concatenate(depths)
    lo, hi = np.percentile(z, percentiles)
    return DepthPrior(max(lo * (1 - margin), 1e-3), hi * (1 + margin))


def true_match_error_px(
    camera: Camera, true_i: Pose, true_j: Pose, depth_i: np.ndarray, kp_i: np.ndarray, kp_j: np.ndarray
) -> np.ndarray:
    """Error (px) of matches judged against the truth: keypoint of i lifted with frame i's true z-depth
    map (H, W, mm), sent through the true poses into j, compared with the matched keypoint of j.
    NaN where the depth map has no surface."""
    iu = np.clip(np.rint(kp_i[:, 0]).astype(int), 0, depth_i.shape[1] - 1)
    iv = np.clip(np.rint(kp_i[:, 1]).astype(int), 0, depth_i.shape[0] - 1)
    z = depth_i[iv, iu].astype(float)
    x_world = (camera.unproject(kp_i, z) - true_i.translation) @ true_i.rotation
    return np.linalg.norm(camera.project_world(true_j, x_world) - kp_j, axis=1)
