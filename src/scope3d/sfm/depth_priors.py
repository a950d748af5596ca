"""Depth priors built from data: a bounding box, or triangulated closest pairs."""
from __future__ import annotations

import numpy as np

from scope3d.feature.depth_prior import DepthPrior
from scope3d.feature.detection import Features
from scope3d.feature.matching import MatchOptions, match_exhaustive
from scope3d.geometry.pose import Pose
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose


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
    from scope3d.estimators.triangulation import TrackOptions, triangulate_tracks
    from scope3d.scene.tracks import Tracks  # imported late: tracks sits above matching

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
