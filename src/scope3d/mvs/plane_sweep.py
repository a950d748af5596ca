"""Multi-view plane sweep with known poses: a dense depth map of one reference frame from a few source
frames, for camera motions that are neither lateral nor axial (a side-viewing scope advancing along its
probe axis at 45°, where no single rectification suits both this module's neighbours).

For each depth hypothesis ``z`` (planes parallel to the reference's image plane, sampled uniformly in
inverse depth so that every step moves a pixel by about the same amount in the sources), every reference
pixel's point at depth ``z`` is projected into each source (the poses are known: a micro-stage's steps),
the source is resampled there (for a camera without distortion the plane's homography warps the whole
source image at once, cv2.warpPerspective; else cv2.remap of each pixel's projection), and the zero-mean
normalised cross-correlation (NCC) of a square window scores the hypothesis. The scores of the sources are
averaged (multi-baseline stereo, Okutomi & Kanade 1993: the longest baseline gives precision, the shorter
ones remove the ambiguity of repeated texture), or only each pixel's ``best_sources`` best (Kang et al.
2001: robust to a source that is occluded there). Per pixel the best hypothesis is refined by a parabola
through its neighbours' scores. The planes are swept one at a time and only running figures are kept per
pixel, so memory does not grow with the number of planes.

A pixel is kept only when (1) its mean NCC reaches ``min_ncc``, (2) at least ``min_sources`` sources
each score it at least ``min_ncc`` at the chosen depth *and* each has its own best depth within one step
of it (consistency across ``min_sources + 1`` frames: occlusions and mismatches seldom agree), and (3)
the best score stands out of the curve (the second-best separate peak lower by ``min_peak_margin``),
and (4) its predicted depth error is small: ``match_sigma_px`` divided by how fast the point's image
moves with depth in the agreeing source that sees it move fastest (the longest effective baseline) is at most
``max_depth_sigma_mm`` (far, grazing pixels see too little parallax to be worth keeping).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.sensor.camera import Camera


@dataclass(frozen=True)
class PlaneSweepOptions:
    """window_px : odd NCC window side (default 7: enough texture on a machined surface at 400 px, small
        enough not to straddle a thread crest and its flanks at 1 mm pitch, ~10 px per pitch at 5 mm).
    step_px : largest image shift of one depth step in the longest-baseline source (default 0.5 px; the
        parabola refinement then interpolates within a step).
    max_depths : cap on the number of hypotheses (default 256).
    min_ncc : NCC a source must reach at the chosen depth (default 0.6).
    min_sources : sources that must agree (default 2: three frames with the reference).
    min_peak_margin : the best mean score must beat the best score of hypotheses that shift the window
        by more than its width by this much (default 0.05; repeated thread rings give a second peak one pitch away).
    stride_px : the output keeps every stride-th pixel in both directions (default 2; neighbouring
        windows overlap, so their errors are correlated and more points add little).
    match_sigma_px : standard deviation of a refined NCC match along the epipolar line (default 0.1 px:
        measured on the phantom lab's machined-aluminium texture at 400x320, depth errors of ±0.045 mm
        between the 10th and 90th percentiles at 4-5 mm with 2.9 px/mm of parallax).
    max_depth_sigma_mm : gate (4) of the module docstring (default None: no gate).
    best_sources : a pixel's score at a depth is the mean NCC of its best this-many sources there (default
        None: every source, multi-baseline stereo). Fewer is Kang, Szeliski & Chai's "temporal selection"
        (CVPR 2001): a source that cannot see the pixel's surface there (occluded, or the scope's moving light
        glinting on it) is left out of that pixel's score instead of pulling it down.
    """

    window_px: int = 7
    step_px: float = 0.5
    max_depths: int = 256
    min_ncc: float = 0.6
    min_sources: int = 2
    min_peak_margin: float = 0.05
    stride_px: int = 2
    match_sigma_px: float = 0.1
    max_depth_sigma_mm: float | None = None
    best_sources: int | None = None

    def __post_init__(self) -> None:
        if self.window_px < 3 or self.window_px % 2 == 0:
            raise ValueError("window_px must be odd and >= 3")
        if not (0 < self.step_px <= 2 and self.max_depths >= 8 and -1 < self.min_ncc < 1):
            raise ValueError("need step_px in (0, 2], max_depths >= 8 and min_ncc in (-1, 1)")
        if self.min_sources < 1 or self.stride_px < 1 or self.min_peak_margin < 0:
            raise ValueError("need min_sources >= 1, stride_px >= 1 and min_peak_margin >= 0")
        if self.match_sigma_px <= 0 or (self.max_depth_sigma_mm is not None and self.max_depth_sigma_mm <= 0):
            raise ValueError("match_sigma_px and max_depth_sigma_mm must be positive")
        if self.best_sources is not None and self.best_sources < 1:
            raise ValueError("best_sources must be None (every source) or >= 1")


@dataclass
class SweepDepth:
    """depth_mm : (H, W) float64 z-depth in the reference camera, NaN where not kept; score : (H, W)
    mean NCC at that depth; sigma_mm : (H, W) predicted depth standard deviation (gate 4), NaN where gates
    1-3 dropped the pixel; points_cam :
    (N, 3) mm the kept pixels (every stride-th) in the reference camera frame; pixels : (N, 2) their pixel
    coordinates; n_depths : hypotheses swept."""

    depth_mm: np.ndarray
    score: np.ndarray
    sigma_mm: np.ndarray
    points_cam: np.ndarray
    pixels: np.ndarray
    n_depths: int


def _gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return img.astype(np.float32)


def _box(img: np.ndarray, w: int) -> np.ndarray:
    return cv2.boxFilter(img, -1, (w, w), normalize=True, borderType=cv2.BORDER_REFLECT)


def depth_hypotheses(camera: Camera, reference: Pose, sources: list[Pose], depth_range_mm: tuple[float, float],
                     *,
                     options: PlaneSweepOptions) -> np.ndarray:
    """Depths (mm) uniform in inverse depth, so fine that the image centre's point moves by at most
    ``step_px`` per step in every source."""
    near, far = depth_range_mm
    centre = np.array([[(camera.width - 1) / 2.0, (camera.height - 1) / 2.0]])
    world = [reference.inverse().transform(camera.unproject(centre, z)) for z in (near, far)]
    shift = max(float(np.linalg.norm(camera.project_world(s, world[0]) - camera.project_world(s, world[1])))
                for s in sources)
    n = int(np.clip(np.ceil(shift / options.step_px) + 1, 8, options.max_depths))
    return 1.0 / np.linspace(1.0 / near, 1.0 / far, n)


def _plane_warp(camera: Camera, source_from_reference: list[Pose], sources: list[np.ndarray],
                shape: tuple[int, int]):
    """A function (source index, depth z mm) -> (H, W) float32: the source image resampled at each reference
    pixel's point on the plane z = const of the reference camera, NaN where that point falls outside the
    source (bilinear, so next to its border too) or behind it.

    Without distortion the map is the plane's homography, ``x_src ~ K (R + t n^T / z) K^-1 x_ref`` with
    n = (0, 0, 1) (Hartley & Zisserman eq. 13.2), one cv2.warpPerspective of the whole image; the point is in
    front of the source where the homography's third row is positive, a linear function of the pixel, so
    the four corners tell whether any pixel is behind. With distortion every pixel's point is projected
    through the lens and resampled by cv2.remap."""
    h, wd = shape
    if not np.any(camera.distortion_coeffs):
        K = camera.K
        K_inv = np.linalg.inv(K)
        rotation = [K @ p.rotation @ K_inv for p in source_from_reference]
        shift = [np.outer(K @ p.translation, K_inv[2]) for p in source_from_reference]
        corners = np.array([[0.0, 0.0, 1.0], [wd - 1.0, 0.0, 1.0], [0.0, h - 1.0, 1.0], [wd - 1.0, h - 1.0, 1.0]])
        u, v = np.meshgrid(np.arange(wd, dtype=np.float32), np.arange(h, dtype=np.float32))

        def homography(s: int, z: float) -> np.ndarray:
            H = rotation[s] + shift[s] / z
            warped = cv2.warpPerspective(sources[s], H, (wd, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                         borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
            if np.any(corners @ H[2] <= 0):
                warped[H[2, 0] * u + H[2, 1] * v + H[2, 2] <= 0] = np.nan
            return warped

        return homography
    rays = camera.unproject(camera.pixel_grid().reshape(-1, 2), 1.0)  # z = 1: the point at depth z is z * ray
    # per source, the reference rays in its frame once: a point at depth z is z * (R ray) + t there
    rays_src = [rays @ p.rotation.T for p in source_from_reference]

    def projected(s: int, z: float) -> np.ndarray:
        uv = camera.project(z * rays_src[s] + source_from_reference[s].translation)
        uv[~np.isfinite(uv).all(axis=1)] = -1e6  # behind the source, or outside a fisheye's field
        uv = uv.astype(np.float32).reshape(h, wd, 2)
        return cv2.remap(sources[s], uv[..., 0].copy(), uv[..., 1].copy(), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)

    return projected


def sweep(camera: Camera, reference_image: np.ndarray, reference_pose: Pose, source_images: list[np.ndarray],
          source_poses: list[Pose], depth_range_mm: tuple[float, float],
          *,
          options: PlaneSweepOptions = PlaneSweepOptions()) -> SweepDepth:
    """Dense depth of ``reference_image`` (poses ``cam_from_world``) between ``depth_range_mm`` (near, far
    z-depths, mm) from ``source_images``; see the module docstring.

    reference_image, source_images : (H, W) or (H, W, 3) uint8, the camera's size. The planes are swept one
    at a time, each source warped onto the reference for the plane (a homography of the whole image for a
    camera without distortion, a per-pixel projection otherwise); per pixel only running figures are kept
    (the best plane and its neighbours' scores, each source's own best, the best score far from the best
    plane), never a score per plane, so memory does not grow with the number of planes."""
    if len(source_images) != len(source_poses) or len(source_images) < options.min_sources:
        raise ValueError(f"need >= {options.min_sources} source frames with a pose each")
    near, far = depth_range_mm
    if not 0 < near < far:
        raise ValueError(f"depth range must be 0 < near < far, got {depth_range_mm}")
    w = options.window_px
    ref = _gray(reference_image)
    h, wd = ref.shape
    ref_mean = _box(ref, w)
    inv_ref_std = 1.0 / np.sqrt(np.maximum(_box(ref * ref, w) - ref_mean ** 2, 1e-6))
    depths = depth_hypotheses(camera, reference_pose, source_poses, depth_range_mm, options=options)
    n_planes = len(depths)
    srcs = [_gray(s) for s in source_images]
    rel = [s @ reference_pose.inverse() for s in source_poses]  # source_from_reference
    warp = _plane_warp(camera, rel, srcs, (h, wd))
    kernel = np.ones((w, w), np.uint8)
    n_src = len(srcs)
    k_best = n_src if options.best_sources is None else min(options.best_sources, n_src)
    far_away = int(np.ceil(w / options.step_px))  # hypotheses that shift the window by its own width

    def plane_figures(shape, value):
        return np.full(shape, value, np.float32)

    best_score = plane_figures((h, wd), -np.inf)
    best = np.zeros((h, wd), np.int32)
    s_before, s_after = plane_figures((h, wd), -1.0), plane_figures((h, wd), -1.0)  # scores at best -+ 1
    previous = plane_figures((h, wd), -1.0)
    # the second peak: the best score more than far_away planes before the best (kept when the best moves)
    # and after it; `older` is the best of the planes more than far_away before the current one, from a ring
    # of the last far_away + 1 planes' scores
    second_before, second_after = plane_figures((h, wd), -1.0), plane_figures((h, wd), -1.0)
    older = plane_figures((h, wd), -1.0)
    ring = np.empty((far_away + 1, h, wd), np.float32)
    source_max = plane_figures((n_src, h, wd), -1.0)
    source_arg = np.zeros((n_src, h, wd), np.int32)
    tops = np.empty((k_best, h, wd), np.float32)  # per pixel, the best k_best sources' scores at this plane
    for k, z in enumerate(depths):
        if k > far_away:
            np.maximum(older, ring[(k - far_away - 1) % (far_away + 1)], out=older)
        tops.fill(-np.inf if k_best < n_src else 0.0)
        for s in range(n_src):
            warped = warp(s, z)
            outside = warped != warped  # NaN outside the source (or behind it)
            np.copyto(warped, ref_mean, where=outside)  # outside the source: no correlation
            m = _box(warped, w)
            cov = _box(warped * ref, w)
            cov -= m * ref_mean
            var = _box(warped * warped, w)
            var -= m * m
            np.maximum(var, 1e-6, out=var)
            ncc = cov * inv_ref_std
            ncc /= np.sqrt(var, out=var)
            # the window must lie inside the source
            np.copyto(ncc, -1.0, where=cv2.dilate(outside.view(np.uint8), kernel).view(bool))
            np.copyto(source_arg[s], k, where=ncc > source_max[s])
            np.maximum(source_max[s], ncc, out=source_max[s])
            if k_best == n_src:  # every source: the plain sum
                tops[0] += ncc
                continue
            # the pixel's k_best best sources so far, best first: insertion into the sorted tops
            for t in range(k_best - 1):
                hi = np.maximum(tops[t], ncc)
                np.minimum(tops[t], ncc, out=ncc)
                tops[t] = hi
            np.maximum(tops[-1], ncc, out=tops[-1])
        score = tops[0] / n_src if k_best == n_src else tops.mean(axis=0)
        ring[k % (far_away + 1)] = score
        moved = score > best_score
        stays = ~moved
        np.copyto(s_after, score, where=stays & (best == k - 1))
        np.copyto(second_after, np.maximum(second_after, score), where=stays & (k - best > far_away))
        best_score[moved] = score[moved]
        best[moved] = k
        s_before[moved] = previous[moved]
        s_after[moved] = -1.0
        second_before[moved] = older[moved]
        second_after[moved] = -1.0
        previous = score
    # sub-step refinement: parabola through the scores at best-1, best, best+1 (in inverse depth)
    inner = (best > 0) & (best < n_planes - 1)
    denom = s_before - 2 * best_score + s_after
    offset = np.where(inner & (denom < 0), 0.5 * (s_before - s_after) / np.where(denom < 0, denom, -1.0), 0.0)
    inv = 1.0 / depths
    inv_step = inv[1] - inv[0]
    depth = 1.0 / (inv[best] + np.clip(offset, -0.5, 0.5) * inv_step)
    # the gates of the module docstring (a source's own best within one step scores about what it
    # scores at the chosen depth)
    keep = inner & (best_score >= options.min_ncc)
    agree = (np.abs(source_arg - best[None]) <= 1) & (source_max >= options.min_ncc)
    keep &= agree.sum(axis=0) >= options.min_sources
    keep &= best_score - np.maximum(second_before, second_after) >= options.min_peak_margin
    # gate (4): parallax per mm of depth at the chosen depth, in the fastest-moving source that agrees (one
    # that does not, occluded or glinting there, did not fix the depth); only where gates 1-3 kept the pixel
    cand = np.flatnonzero(keep)
    z_cand = depth.reshape(-1)[cand]
    rays = camera.unproject(camera.pixel_grid().reshape(-1, 2)[cand], 1.0)  # z = 1
    rate = np.zeros(len(cand))
    for s, pose in enumerate(rel):
        # the point z * ray in the source is z * (R ray) + t, without a matrix product of every point
        r_ray = sum(rays[:, j:j + 1] * pose.rotation[:, j] for j in range(3))
        near_uv = camera.project(z_cand[:, None] * (1 - 1e-3) * r_ray + pose.translation)
        far_uv = camera.project(z_cand[:, None] * (1 + 1e-3) * r_ray + pose.translation)
        moved_per_mm = np.linalg.norm(far_uv - near_uv, axis=1) / (2e-3 * z_cand)
        rate = np.fmax(rate, np.where(agree[s].reshape(-1)[cand], moved_per_mm, 0.0))
    sigma = np.full(h * wd, np.nan)
    sigma[cand] = options.match_sigma_px / np.maximum(rate, 1e-9)
    sigma = sigma.reshape(h, wd)
    if options.max_depth_sigma_mm is not None:
        keep &= sigma <= options.max_depth_sigma_mm
    depth = np.where(keep, depth, np.nan)
    ii, jj = np.indices((h, wd))
    sel = np.zeros_like(keep)
    sel[::options.stride_px, ::options.stride_px] = True
    sel &= keep
    px = np.stack([jj[sel], ii[sel]], axis=-1).astype(float)
    return SweepDepth(depth, best_score, sigma, camera.unproject(px, depth[sel]), px, len(depths))


@dataclass(frozen=True)
class DenseQuadrantOptions:
    """sweep : the plane sweep's options (default: a 7 px window, a predicted depth sigma of at most
        0.05 mm, a quarter of an M6's 6H pitch-diameter tolerance: farther, grazing pixels add error faster
        than they add information).
    max_frame_gap : sources are the frames up to this many steps from the reference (default 7).
    depth_margin : the sweep's depth range is the sparse points' 2nd-98th percentile depth widened by this
        fraction of their median depth on each side (default 0.2: an M8's 0.68 mm thread depth seen at 45°
        from ~5.7 mm spans ~1 mm, 17 %, and the sparse points sit mostly on the crests)."""

    sweep: PlaneSweepOptions = PlaneSweepOptions(max_depth_sigma_mm=0.05, stride_px=4)
    max_frame_gap: int = 7
    depth_margin: float = 0.2

    def __post_init__(self) -> None:
        if self.max_frame_gap < 1 or not 0 < self.depth_margin < 0.9:
            raise ValueError("need max_frame_gap >= 1 and depth_margin in (0, 0.9)")


def dense_quadrant(images: list[np.ndarray], camera: Camera, poses: list[Pose], sparse_points: np.ndarray,
                   *,
                   options: DenseQuadrantOptions = DenseQuadrantOptions()) -> tuple[np.ndarray, np.ndarray]:
    """Plane-sweep clouds of the quadrant's first and last frames, each against the frames within
    ``max_frame_gap``, merged. poses : ``cam_from_world`` of each frame; sparse_points : (N, 3) mm in the
    same world, to bracket the depths. Returns (M, 3) mm points in that world and (M, 3) uint8 colours."""
    points, colors = [], []
    for ref in sorted({0, len(images) - 1}):
        others = [k for k in range(len(images)) if k != ref and abs(k - ref) <= options.max_frame_gap]
        z = poses[ref].transform(sparse_points)[:, 2] if len(sparse_points) else np.zeros(0)
        z = z[z > 0]
        if len(others) < options.sweep.min_sources or len(z) < 10:
            continue
        lo, mid, hi = np.percentile(z, [2, 50, 98])
        near, far = max(lo - options.depth_margin * mid, 0.1 * mid), hi + options.depth_margin * mid
        depth = sweep(camera, images[ref], poses[ref], [images[k] for k in others], [poses[k] for k in others],
                      (near, far), options=options.sweep)
        points.append(poses[ref].inverse().transform(depth.points_cam))
        img = images[ref] if images[ref].ndim == 3 else np.repeat(images[ref][..., None], 3, axis=2)
        colors.append(img[depth.pixels[:, 1].astype(int), depth.pixels[:, 0].astype(int)])
    if not points:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    return np.concatenate(points), np.concatenate(colors).astype(np.uint8)
