"""2-D mosaic of scope frames with the scope's path and a coverage map (reference sec. 2.3.3, Fig. 2.7).

Method, as in the reference with one change (global alignment instead of chaining):

1. SIFT features per frame (:mod:`scope3d.feature.detection`).
2. Every pair of frames matched (ratio test, mutual check) and verified by a RANSAC homography whose
   number of iterations OpenCV chooses from the inlier ratio for the requested success probability
   (``matching.ransac_confidence``, 0.99 in the reference, sec. 2.3.3). Pairs with too few inliers are not linked.
3. Global alignment: each frame ``i`` gets a homography ``H_i`` (frame pixels -> mosaic pixels, frame 0 is
   the mosaic's frame: ``H_0 = I``). Every inlier match ``(x in i, y in j)`` asks ``H_i(x) = H_j(y)``; all of
   them are solved together by least squares, first with affine ``H_i`` (a sparse linear problem,
   ``scipy.sparse.linalg.lsqr``), then with full homographies minimising the transfer error
   ``H_j^-1 H_i x - y`` in frame pixels (``scipy.optimize.least_squares`` with a sparse Jacobian), so that errors are spread over the loop of the scan instead of accumulating along a
   chain of pairwise homographies. Frames not connected to frame 0 by matches are left out (reported).
4. Blending: each frame is warped into the mosaic and averaged with weights that fall to zero at its field's
   edge (feathering by the distance transform), so seams between frames fade instead of cutting.
5. The scope's path: the mosaic position of each frame's centre, joined in order within each scan section
   (spiral turn), and the coverage map (which mosaic pixels some frame sees).

A planar mosaic is exact for a plane seen from any pose, or any surface seen from one centre of projection;
the inside of a closed organ seen from moving positions cannot be flattened without distortion, which shows
as the alignment's residual.

Any camera model: a homography relates two views of a plane only in *rectified* pixels, those of the camera's
distortion-free pinhole with the same ``fx, fy, cx, cy``. So the algorithm needs them, but it never resamples
a frame to get them: keypoints go to rectified pixels through the lens model (:func:`rectified_pixels`: the
model's unit ray, then the pinhole), and :func:`blend` reads each mosaic pixel's colour from the frame's own
pixels through the same model, in one resampling. The alignment's residuals are weighted back to each frame's
own pixels (:func:`own_per_rectified`), where a keypoint's noise is the same across the image. A rectified pixel exists only for a ray in front of the
camera plane: a fisheye's rays past 90 deg have none and stay out of the mosaic.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, lil_matrix
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import lsqr

from scope3d.feature.detection import FeatureOptions, Features, detect
from scope3d.feature.matching import MatchOptions, match_exhaustive
from scope3d.sensor.camera import Camera
from scope3d.utils.progress import advance


@dataclass(frozen=True)
class MosaicOptions:
    """features : SIFT options. matching : the pairwise matcher (:class:`~scope3d.feature.matching.MatchOptions`),
    verified by a homography: Lowe's ratio 0.8; inlier threshold 3 px (SIFT keypoints are good to ~0.5 px;
    3 px leaves room for the parallax of a curved wall); RANSAC confidence 0.99, the probability that RANSAC
    draws an all-inlier sample (reference sec. 2.3.3); a pair with fewer than ``min_matches`` (15) verified
    matches is not linked (a homography has 8 unknowns and a pair that weak is often a coincidence).
    max_matches_per_pair : matches kept per pair in the global adjustment (evenly subsampled; more add time,
    not accuracy). max_canvas_px : the mosaic's larger side is scaled down to at most this.
    """

    features: FeatureOptions = FeatureOptions(max_features=2000)
    matching: MatchOptions = MatchOptions(geometric_model="homography", ransac_threshold_px=3.0,
                                          ransac_confidence=0.99)
    max_matches_per_pair: int = 40
    max_canvas_px: int = 3000

    def __post_init__(self) -> None:
        if self.matching.geometric_model != "homography":
            raise ValueError(f"a mosaic's pairs are verified by a homography, got {self.matching.geometric_model!r}")
        if self.matching.min_matches < 4 or self.max_matches_per_pair < 4:
            raise ValueError("need matching.min_matches >= 4 and max_matches_per_pair >= 4")
        if self.max_canvas_px < 64:
            raise ValueError(f"max_canvas_px must be at least 64, got {self.max_canvas_px}")


@dataclass(frozen=True)
class FrameLink:
    """Verified matches between frames i and j: (M, 2) rectified pixels in each (:func:`rectified_pixels`).
    weights_j : (M,) frame j's own pixels per rectified pixel at ``points_j`` (:func:`own_per_rectified`), or
    None for a pinhole without distortion (1 everywhere)."""

    i: int
    j: int
    points_i: np.ndarray
    points_j: np.ndarray
    weights_j: np.ndarray | None = None


@dataclass
class Mosaic:
    """homographies : (N, 3, 3) rectified frame pixels (:func:`rectified_pixels`) -> mosaic pixels; NaN for frames left out.
    registered : (N,) bool. links : the verified pairs. residual_px : (M,) mosaic-pixel distance between
    the two ends of every linked match after the adjustment. image : (H, W, 3) uint8 blended mosaic, or
    None before :func:`blend`; coverage : (H, W) bool; canvas_from_mosaic : (3, 3) mosaic -> canvas pixels.
    """

    homographies: np.ndarray
    registered: np.ndarray
    links: list[FrameLink]
    residual_px: np.ndarray
    image: np.ndarray | None = None
    coverage: np.ndarray | None = None
    canvas_from_mosaic: np.ndarray | None = None


#: a ray closer to the camera plane than this (its z over its length: 2.6 deg) has its rectified pixel over
#: 20 focal lengths from the centre, where a keypoint's 0.5 px is stretched ~500-fold (1 / z^2): left out
_MIN_RAY_Z = 0.045


def rectified_pixels(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of the frame -> (N, 2) pixels of the same rays in the camera's distortion-free pinhole
    (``fx, fy, cx, cy``), any lens model: ``fx x + cx`` of the undistorted normalised coordinates for the
    pinhole family, of ``x / z`` of the unit ray (:meth:`Camera.unproject`) for a fisheye. NaN for a fisheye's
    ray at or behind the camera plane (within :data:`_MIN_RAY_Z` of it), which no pinhole images."""
    pixels = np.asarray(pixels, float).reshape(-1, 2)
    if not camera.lens.is_fisheye:  # the pinhole family sees in front of its plane only: no ray to drop
        xy = camera.pixel_to_normalised(pixels)
        return np.stack([camera.fx * xy[:, 0] + camera.cx, camera.fy * xy[:, 1] + camera.cy], axis=1)
    rays = camera.unproject(pixels)
    out = np.full((len(rays), 2), np.nan)
    front = rays[:, 2] > _MIN_RAY_Z
    out[front] = rays[front, :2] / rays[front, 2:3] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    return out


def frame_pixels(camera: Camera, rectified: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rectified_pixels`: (N, 2) rectified pixels -> (N, 2) pixels of the frame through the
    lens model (NaN where the lens does not see the ray)."""
    r = np.asarray(rectified, float).reshape(-1, 2)
    rays = np.c_[(r[:, 0] - camera.cx) / camera.fx, (r[:, 1] - camera.cy) / camera.fy, np.ones(len(r))]
    return camera.project(rays)


def own_per_rectified(camera: Camera, rectified: np.ndarray, step_px: float = 0.5) -> np.ndarray:
    """(N,) how many of the frame's own pixels one rectified pixel spans at each of ``rectified`` (N, 2): the
    square root of the area ratio, ``sqrt|det d own / d rectified|`` by forward differences of ``step_px``.
    1 for a pinhole without distortion; below 1 towards a wide lens's rim (0.26 at fisheye-140's 70 deg)."""
    r = np.asarray(rectified, float).reshape(-1, 2)
    p0 = frame_pixels(camera, r)
    du = (frame_pixels(camera, r + [step_px, 0.0]) - p0) / step_px
    dv = (frame_pixels(camera, r + [0.0, step_px]) - p0) / step_px
    return np.sqrt(np.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0]))


def _is_plain_pinhole(camera: Camera) -> bool:
    """The camera's pixels are already rectified (a pinhole without distortion)."""
    return not np.any(camera.params[4:])


def link_frames(frames: list[np.ndarray], cameras: list[Camera], *, options: MosaicOptions = MosaicOptions(),
                pairs: list[tuple[int, int]] | None = None, features: list[Features] | None = None,
                progress=None) -> list[FrameLink]:
    """Match frames pairwise and keep the pairs a RANSAC homography verifies (steps 1-2).

    frames : list of (H, W, 3) uint8; cameras : the camera of each frame (several datasets may differ).
    pairs : (i, j) to try (default every pair). features : precomputed per frame (default detected).
    """
    if len(frames) != len(cameras):
        raise ValueError("one camera per frame is needed")
    feats = features or [detect(f, c, options=options.features) for f, c in zip(frames, cameras)]
    pairs = pairs if pairs is not None else [(i, j) for i in range(len(frames)) for j in range(i + 1, len(frames))]
    links = []
    for i, j in pairs:
        # Matching verifies with the camera of frame i; frames from another dataset are undistorted first.
        m = match_exhaustive(cameras[i], feats[i], feats[j], options.matching, i=i, j=j)
        pi = rectified_pixels(cameras[i], feats[i].keypoints[m.idx_i])
        pj = rectified_pixels(cameras[j], feats[j].keypoints[m.idx_j])
        seen = np.all(np.isfinite(pi), axis=1) & np.all(np.isfinite(pj), axis=1)
        if seen.sum() >= options.matching.min_matches:
            wj = None if _is_plain_pinhole(cameras[j]) else own_per_rectified(cameras[j], pj[seen])
            links.append(FrameLink(i, j, pi[seen], pj[seen], wj))
        advance(progress)
    return links


def align_globally(n_frames: int, links: list[FrameLink], sizes: list[tuple[int, int]],
                   *,
                   options: MosaicOptions = MosaicOptions(), reference: int = 0) -> Mosaic:
    """Global least-squares alignment of all frames (step 3). sizes : (width, height) of each frame.

    Frames not connected to ``reference`` through links get NaN homographies and ``registered = False``.
    Raises ValueError when no link touches the reference frame (the frames do not overlap).
    """
    if not links or not any(reference in (ln.i, ln.j) for ln in links):
        raise ValueError("no frame overlaps the reference frame: nothing to mosaic")
    graph = coo_matrix((np.ones(len(links)), ([ln.i for ln in links], [ln.j for ln in links])),
                       shape=(n_frames, n_frames))
    _, label = connected_components(graph, directed=False)
    registered = label == label[reference]
    free = [i for i in range(n_frames) if registered[i] and i != reference]
    col = {f: k for k, f in enumerate(free)}
    used = [ln for ln in links if registered[ln.i]]
    rng = np.random.default_rng(0)
    sampled = []
    for ln in used:
        keep = np.arange(len(ln.points_i))
        if len(keep) > options.max_matches_per_pair:
            keep = np.sort(rng.choice(keep, options.max_matches_per_pair, replace=False))
        sampled.append((ln.i, ln.j, ln.points_i[keep], ln.points_j[keep],
                        np.ones(len(keep)) if ln.weights_j is None else ln.weights_j[keep]))
    # Conditioning: each frame's pixels centred and divided by its size before fitting.
    norm = []
    for w, h in sizes:
        s = 2.0 / max(w, h)
        norm.append(np.array([[s, 0, -s * (w - 1) / 2], [0, s, -s * (h - 1) / 2], [0, 0, 1.0]]))
    ref_scale = norm[reference]

    # Affine pass: unknowns a_i (6 per free frame) with A_i [x 1] - A_j [y 1] = 0, reference fixed to N_ref.
    n_rows = 2 * sum(len(s[2]) for s in sampled)
    mat = lil_matrix((n_rows, 6 * len(free)))
    rhs = np.zeros(n_rows)
    row = 0
    for i, j, pi, pj, _ in sampled:
        xi = _apply(norm[i], pi)
        xj = _apply(norm[j], pj)
        for frame, x, sign in ((i, xi, 1.0), (j, xj, -1.0)):
            for k in range(2):
                rows = row + 2 * np.arange(len(x)) + k
                if frame == reference:
                    rhs[rows] -= sign * x[:, k]  # the reference's mosaic coordinates are its normalised pixels
                else:
                    c = 6 * col[frame] + 3 * k
                    mat[rows, c] = sign * x[:, 0]
                    mat[rows, c + 1] = sign * x[:, 1]
                    mat[rows, c + 2] = sign
        row += 2 * len(xi)
    affine = lsqr(mat.tocsr(), rhs, atol=1e-12, btol=1e-12)[0] if free else np.zeros(0)
    params0 = np.concatenate([np.concatenate([affine[6 * k:6 * k + 6], [0.0, 0.0]]) for k in range(len(free))]) \
        if free else np.zeros(0)

    def homs(params):
        out = {reference: np.eye(3)}
        for f, k in col.items():
            p = params[8 * k:8 * k + 8]
            out[f] = np.array([[p[0], p[1], p[2]], [p[3], p[4], p[5]], [p[6], p[7], 1.0]])
        return out

    # Stacked observations: link index, frame i's normalised point (homogeneous), frame j's normalised point.
    link_of = np.concatenate([np.full(len(s[2]), k) for k, s in enumerate(sampled)])
    xi_h = np.concatenate([np.column_stack([_apply(norm[i], pi), np.ones(len(pi))]) for i, _, pi, _, _ in sampled])
    xj = np.concatenate([_apply(norm[j], pj) for _, j, _, pj, _ in sampled])
    # each residual in frame j's own pixels: a rectified pixel at a wide lens's rim spans a fraction of one,
    # and its keypoint's noise is stretched by as much (all 1 for a pinhole without distortion)
    weight = np.repeat(np.concatenate([s[4] for s in sampled]), 2)
    link_i = np.array([s[0] for s in sampled])
    link_j = np.array([s[1] for s in sampled])

    def residuals(params):
        h = homs(params)
        stack = np.stack([h[f] if f in h else np.eye(3) for f in range(n_frames)])
        # Transfer error in frame j's own (normalised) pixels: invariant to a homography applied to the
        # whole mosaic, so the fit cannot lower its cost by shrinking or tilting the mosaic away from the
        # reference frame (which a residual measured in mosaic coordinates rewards).
        transfer = np.linalg.solve(stack[link_j], stack[link_i])  # (L, 3, 3) frame i -> frame j
        p = np.einsum("nab,nb->na", transfer[link_of], xi_h)
        return (p[:, :2] / p[:, 2:3] - xj).ravel() * weight

    if free:
        sparsity = lil_matrix((n_rows, 8 * len(free)), dtype=np.int8)
        row = 0
        for i, j, pi, _, _ in sampled:
            for frame in (i, j):
                if frame != reference:
                    sparsity[row:row + 2 * len(pi), 8 * col[frame]:8 * col[frame] + 8] = 1
            row += 2 * len(pi)
        # lsmr's inner iterations capped: on long scans the exact inner solve of this ill-conditioned
        # system took minutes per step; an inexact Newton step still converges (measured on the sheet).
        sol = least_squares(residuals, params0, jac_sparsity=sparsity.tocsr(), x_scale="jac", method="trf",
                            tr_solver="lsmr", tr_options={"maxiter": 100}, max_nfev=30)
        params = sol.x
    else:
        params = params0
    h = homs(params)
    homographies = np.full((n_frames, 3, 3), np.nan)
    to_pixels = np.linalg.inv(ref_scale)
    for f, hf in h.items():
        homographies[f] = to_pixels @ hf @ norm[f]
    res_px = [np.linalg.norm(_apply(homographies[ln.i], ln.points_i) - _apply(homographies[ln.j], ln.points_j), axis=1)
              for ln in used]
    return Mosaic(homographies, registered, used, np.concatenate(res_px) if res_px else np.zeros(0))


def _apply(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(3, 3) homography applied to (N, 2) points."""
    p = points @ h[:, :2].T + h[:, 2]
    return p[:, :2] / p[:, 2:3]


def _footprint(camera: Camera) -> np.ndarray:
    """(M, 2) rectified pixels bounding a frame's image in the mosaic: the frame's four corners for a pinhole
    without distortion (as the mosaic always took them), else the rectified border of its valid field (a
    distorted frame's corners bend, and a fisheye's lie outside its field)."""
    w, h = camera.width, camera.height
    if _is_plain_pinhole(camera):
        return np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1.0]])
    valid = camera.valid_mask().astype(np.uint8)
    contours, _ = cv2.findContours(valid, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    border = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(float)
    rect = rectified_pixels(camera, border)
    return rect[np.all(np.isfinite(rect), axis=1)]


def _warp(image: np.ndarray, camera: Camera, canvas_from_frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``image`` (H, W[, C]) float32 of the frame resampled (bilinear) into the canvas of ``size`` (width,
    height) through ``canvas_from_frame`` (3, 3), a homography on rectified pixels. A pinhole without
    distortion is warped directly; any other lens by each canvas pixel's rectified pixel taken back through
    the lens model (:func:`frame_pixels`), within the bounding box of the frame's footprint; 0 elsewhere."""
    if _is_plain_pinhole(camera):
        return cv2.warpPerspective(image, canvas_from_frame, size, flags=cv2.INTER_LINEAR)
    out = np.zeros((size[1], size[0]) + image.shape[2:], np.float32)
    box = _apply(canvas_from_frame, _footprint(camera))
    lo = np.clip(np.floor(box.min(axis=0)).astype(int) - 1, 0, [size[0] - 1, size[1] - 1])
    hi = np.clip(np.ceil(box.max(axis=0)).astype(int) + 1, 0, [size[0] - 1, size[1] - 1])
    u, v = np.meshgrid(np.arange(lo[0], hi[0] + 1, dtype=float), np.arange(lo[1], hi[1] + 1, dtype=float))
    rect = _apply(np.linalg.inv(canvas_from_frame), np.c_[u.ravel(), v.ravel()])
    src = np.nan_to_num(frame_pixels(camera, rect), nan=-1e6).astype(np.float32).reshape(u.shape + (2,))
    out[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1] = cv2.remap(image, src[..., 0], src[..., 1], cv2.INTER_LINEAR,
                                                      borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out


def blend(mosaic: Mosaic, frames: list[np.ndarray], cameras: list[Camera], *,
          options: MosaicOptions = MosaicOptions()) -> Mosaic:
    """Warp the registered frames into one canvas with feathered weights (step 4). Fills ``image``,
    ``coverage`` and ``canvas_from_mosaic``. Each frame is resampled once, through its lens model
    (:func:`_warp`): a distorted frame is never rectified into an image of its own first."""
    idx = np.flatnonzero(mosaic.registered)
    corners = np.concatenate([_apply(mosaic.homographies[i], _footprint(cameras[i])) for i in idx])
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    scale = min(1.0, options.max_canvas_px / max(hi - lo))
    canvas_from_mosaic = np.array([[scale, 0, -scale * lo[0]], [0, scale, -scale * lo[1]], [0, 0, 1.0]])
    size = (int(np.ceil(scale * (hi[0] - lo[0]))) + 1, int(np.ceil(scale * (hi[1] - lo[1]))) + 1)
    acc = np.zeros((size[1], size[0], 3), np.float32)
    wsum = np.zeros((size[1], size[0]), np.float32)
    for i in idx:
        cam = cameras[i]
        # the weight falls to zero at the edge of what the lens sees (its circular field, a fisheye's rim)
        valid = cam.mask() if _is_plain_pinhole(cam) else cam.valid_mask()
        weight = cv2.distanceTransform(valid.astype(np.uint8), cv2.DIST_L2, 5).astype(np.float32)
        warp = canvas_from_mosaic @ mosaic.homographies[i]
        w_img = _warp(frames[i].astype(np.float32), cam, warp, size)
        w_wt = _warp(weight, cam, warp, size)
        acc += w_img * w_wt[..., None]
        wsum += w_wt
    covered = wsum > 0
    image = np.zeros_like(acc)
    image[covered] = acc[covered] / wsum[covered, None]
    mosaic.image = np.clip(image, 0, 255).astype(np.uint8)
    mosaic.coverage = covered
    mosaic.canvas_from_mosaic = canvas_from_mosaic
    return mosaic


def frame_centres(mosaic: Mosaic, cameras: list[Camera]) -> np.ndarray:
    """(N, 2) canvas pixels of each frame's principal point (NaN for frames left out): the scope's path."""
    out = np.full((len(cameras), 2), np.nan)
    for i in np.flatnonzero(mosaic.registered):
        c = np.array([[cameras[i].cx, cameras[i].cy]])
        out[i] = _apply(mosaic.canvas_from_mosaic @ mosaic.homographies[i], c)[0]
    return out


def coverage_fraction(covered: np.ndarray) -> float:
    """Covered pixels over the convex hull of the covered region: 1 when the mosaic has no holes, less
    where the scan missed parts of the area it swept."""
    pts = cv2.findNonZero(covered.astype(np.uint8))
    if pts is None:
        return 0.0
    hull = cv2.convexHull(pts)
    hull_mask = np.zeros(covered.shape, np.uint8)
    cv2.fillConvexPoly(hull_mask, hull, 1)
    return float(covered.sum() / max(hull_mask.sum(), 1))


def draw_path(image: np.ndarray, centres: np.ndarray, sections: np.ndarray) -> np.ndarray:
    """The mosaic with frame centres as dots joined within each section, a colour per section."""
    out = image.copy()
    palette = [(255, 255, 0), (0, 255, 255), (255, 0, 255), (0, 255, 0), (255, 128, 0), (0, 128, 255),
               (255, 255, 255), (128, 255, 128)]
    thick = max(1, int(round(max(image.shape) / 600)))
    for n, k in enumerate(np.unique(sections)):
        sel = np.flatnonzero((sections == k) & np.all(np.isfinite(centres), axis=1))
        colour = palette[n % len(palette)]
        pts = np.round(centres[sel]).astype(np.int32)
        if len(pts) > 1:
            cv2.polylines(out, [pts.reshape(-1, 1, 2)], False, colour, thick, cv2.LINE_AA)
        for p in pts:
            cv2.circle(out, (int(p[0]), int(p[1])), 2 * thick + 1, colour, -1, cv2.LINE_AA)
    return out


def true_plane_homographies(cameras: list[Camera], poses, plane_origin_mm: np.ndarray, plane_normal: np.ndarray,
                            *, reference: int = 0) -> np.ndarray:
    """(N, 3, 3) the exact frame -> mosaic mapping of frames of a plane (ground truth): frame ``i``'s
    rectified pixels (:func:`rectified_pixels`) carried through the plane into the reference frame's pixels.

    poses : true ``cam_from_world`` per frame; the plane passes through ``plane_origin_mm`` (3,) with
    ``plane_normal`` (3,).
    """
    n = np.asarray(plane_normal, float) / np.linalg.norm(plane_normal)
    o = np.asarray(plane_origin_mm, float)
    e1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    world_from_plane = np.column_stack([e1, e2, o])  # (u, v, 1) -> X = o + u e1 + v e2
    pixel_from_plane = []
    for cam, pose in zip(cameras, poses):
        r, t = pose.rotation, pose.translation
        m = cam.K @ np.column_stack([r @ world_from_plane[:, 0], r @ world_from_plane[:, 1], r @ o + t])
        pixel_from_plane.append(m)
    ref = pixel_from_plane[reference]
    return np.stack([ref @ np.linalg.inv(m) for m in pixel_from_plane])


def alignment_errors_px(mosaic: Mosaic, true_homographies: np.ndarray, cameras: list[Camera],
                        samples_per_side: int = 12) -> np.ndarray:
    """Distances (mosaic pixels, i.e. the reference frame's rectified pixels) between where the estimated and
    the true mappings put a grid of the frame's pixels inside each registered frame's field (rectified
    through the lens model first). -> (M,) float."""
    out = []
    for i in np.flatnonzero(mosaic.registered):
        cam = cameras[i]
        u, v = np.meshgrid(np.linspace(0, cam.width - 1, samples_per_side), np.linspace(0, cam.height - 1, samples_per_side))
        pts = np.stack([u.ravel(), v.ravel()], axis=1)
        pts = pts[cam.in_image(pts)]
        if not _is_plain_pinhole(cam):  # the grid of the frame's own pixels, where the lens sees, rectified
            pts = rectified_pixels(cam, pts[cam.sees_pixels(pts)])
            pts = pts[np.all(np.isfinite(pts), axis=1)]
        out.append(np.linalg.norm(_apply(mosaic.homographies[i], pts) - _apply(true_homographies[i], pts), axis=1))
    return np.concatenate(out) if out else np.zeros(0)


def alignment_errors_frame_px(mosaic: Mosaic, true_homographies: np.ndarray, cameras: list[Camera],
                              samples_per_side: int = 12) -> np.ndarray:
    """The alignment error in each frame's own pixels, comparable across lenses: a grid of the frame's pixels
    where its lens sees is carried into the mosaic by the true mapping and back by the estimated one (then
    through the lens model, :func:`frame_pixels`); the distance to where it started. A rectified pixel of a
    wide lens's rim stands for several of its own (1 / cos^2 of the ray's angle: 8.5 at 70 deg), so
    :func:`alignment_errors_px` weighs a fisheye's rim that much more. -> (M,) float, pixels."""
    out = []
    for i in np.flatnonzero(mosaic.registered):
        cam = cameras[i]
        u, v = np.meshgrid(np.linspace(0, cam.width - 1, samples_per_side), np.linspace(0, cam.height - 1, samples_per_side))
        pts = np.stack([u.ravel(), v.ravel()], axis=1)
        pts = pts[cam.in_image(pts) & cam.sees_pixels(pts)]
        rect = rectified_pixels(cam, pts)
        ok = np.all(np.isfinite(rect), axis=1)
        back = frame_pixels(cam, _apply(np.linalg.inv(mosaic.homographies[i]), _apply(true_homographies[i], rect[ok])))
        out.append(np.linalg.norm(back - pts[ok], axis=1))
    return np.concatenate(out) if out else np.zeros(0)
