"""Depth priors built from data (:class:`scope3d.feature.depth_prior.DepthPrior` is the data itself).

* :func:`box_depth_prior` — a calibrated object's bounding box;
* :func:`estimate_depth_prior` — the closest frame pairs matched exhaustively and triangulated with the
  measured poses;
* :func:`points_depth_prior` — the depths of points already reconstructed;
* :func:`surface_depth_prior` — a band around a coarse surface through a first matching pass.
"""
from __future__ import annotations

import numpy as np

from scope3d.estimators.triangulation import TrackOptions, triangulate_tracks
from scope3d.feature.depth_prior import DepthPrior, pose_error_px
from scope3d.feature.detection import Features
from scope3d.feature.matching import MatchOptions, PairMatches, match_exhaustive
from scope3d.feature.tracks import build_tracks
from scope3d.geometry.pose import Pose
from scope3d.scene.surface import SurfaceOptions, fit_surface
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose
from scope3d.utils.robust import robust_sigma


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

    return DepthPrior(near, far, box_min_mm=lo, box_max_mm=hi)


def estimate_depth_prior(
    camera: Camera,
    features: list[Features],
    poses: list[MeasuredPose],
    *,
    options: MatchOptions = MatchOptions(),
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


def points_depth_prior(poses: list[Pose], tracks: Tracks, *, percentiles: tuple[float, float] = (2.0, 98.0),
                       margin: float = 0.1) -> DepthPrior:
    """Depth prior from triangulated tracks: the ``percentiles`` of every observation's z-depth (mm, in
    its own camera), widened by ``margin`` (fraction). Raises ValueError when no point is in front."""
    rot_z = np.stack([p.rotation[2] for p in poses])
    t_z = np.stack([p.translation[2] for p in poses])
    z = np.einsum("mi,mi->m", rot_z[tracks.frame], tracks.points[tracks.track]) + t_z[tracks.frame]
    z = z[z > 0]
    if len(z) == 0:
        raise ValueError("no triangulated point lies in front of its cameras")
    near, far = np.percentile(z, percentiles)
    return DepthPrior(max((1 - margin) * near, 1e-3), (1 + margin) * far)


def surface_depth_prior(camera: Camera, features: list[Features], matches: list[PairMatches], depth_prior: DepthPrior,
                        poses: list[MeasuredPose], track_options: TrackOptions, surface_options: SurfaceOptions,
                        extra_band_mm: float) -> DepthPrior | None:
    """A per-ray depth band around a coarse surface through ``matches`` (a first matching pass),
    triangulated with ``poses`` (the ones the next pass predicts with); None if too few points (< 50) or
    no surface fits.

    The coarse surface has 4x the grid step and twice the control cell of ``surface_options``. The band's
    half-width is the points' robust spread about it (4 sigma), plus what a pose may be off along the
    normal (its tolerance's half-diagonal), plus ``extra_band_mm`` for the detail the coarse fit smooths away.
    """
    tracks = build_tracks(features, matches)
    if tracks.n_tracks < 50:
        return None
    slack = max(2.0 * pose_error_px(camera, m.tolerance, depth_prior) for m in poses)
    tracks = triangulate_tracks(camera, [m.pose for m in poses], tracks, track_options.widened_by(slack))
    if tracks.n_tracks < 50:
        return None
    coarse = SurfaceOptions(grid_step_mm=max(4 * surface_options.grid_step_mm, 0.5),
                            control_cell_mm=2 * surface_options.control_cell_mm, max_control_points=800,
                            max_extrapolation_mm=3.0)
    towards = -np.mean([m.pose.optical_axis for m in poses], axis=0)
    try:
        surface = fit_surface(tracks.points, options=coarse, towards=towards)
    except ValueError:
        return None
    stn = surface.to_plane(tracks.points)
    resid = stn[:, 2] - surface.height_at(stn[:, :2])
    resid = resid[np.isfinite(resid)]
    pos_tol = max(float(np.linalg.norm(m.tolerance.position_mm)) for m in poses)
    band = 4.0 * robust_sigma(resid) + pos_tol + extra_band_mm
    if not np.isfinite(band):
        return None
    return depth_prior.with_band(surface, band)
