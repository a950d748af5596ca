"""Triangulation of tracks with known poses, and the checks that keep a point.

* :func:`triangulate_tracks` — multi-view triangulation, vectorised over all tracks at once:
  ``"midpoint"`` minimises the sum of squared distances from the point to every observation ray
  (a 3x3 linear system per track), ``"dlt"`` is the homogeneous direct linear transform (the 4x4
  normal matrix's smallest eigenvector per track; Hartley & Zisserman 12.2). Both work on the lens's unit
  bearing vectors, so a fisheye's rays past 90 deg from the axis triangulate too. Then reprojection error,
  triangulation angle and cheirality (ahead along every observation's ray) checks; bad observations are
  dropped and the point re-triangulated once.

With exact poses and noise-free observations both methods are exact (tested).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.triangulation import triangulate_midpoint
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera


@dataclass(frozen=True)
class TrackOptions:
    """Triangulation and filtering.

    method : "midpoint" (default: best conditioned for the short baselines of a scope) or "dlt".
    max_reprojection_error_px : float, observations farther than this from their point's projection
        are dropped (default 2.0 px, ~4 sigma of SIFT localisation).
    min_angle_deg : float, minimum largest angle between the rays of a track (default 1.0 deg: at
        15 mm working distance a 0.5 px error then moves the point by < 0.3 mm in depth).
    min_track_length : int, observations per track (default 2).
    max_refine_rounds : int, rounds of dropping each bad track's worst observation (default 3).
    split_inconsistent : bool, the map splits a component of the match graph that holds two features of one
        frame into consistent tracks instead of dropping it (:func:`scope3d.feature.tracks.split_components`).
    """

    method: str = "midpoint"
    max_reprojection_error_px: float = 2.0
    min_angle_deg: float = 1.0
    min_track_length: int = 2
    max_refine_rounds: int = 3
    split_inconsistent: bool = True

    def __post_init__(self) -> None:
        if self.method not in ("midpoint", "dlt"):
            raise ValueError(f"method must be 'midpoint' or 'dlt', got {self.method!r}")
        if self.max_reprojection_error_px <= 0 or self.min_angle_deg < 0 or self.min_track_length < 2:
            raise ValueError("need max_reprojection_error_px > 0, min_angle_deg >= 0, min_track_length >= 2")

    def widened_by(self, slack_px: float, *, cap_px: float = 200.0) -> "TrackOptions":
        """These options with the reprojection gate widened by ``slack_px`` (at most ``cap_px``): for
        triangulating with poses not yet adjusted, whose error moves every observation."""
        return replace(self, max_reprojection_error_px=self.max_reprojection_error_px + min(slack_px, cap_px))


def _rays_world(camera: Camera, poses: list[Pose], frame: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origins (M, 3) mm and unit directions (M, 3) in the world of each observation's ray: the lens's unit
    bearing vectors (:meth:`Camera.unproject`), so a fisheye's rays past 90 deg from the axis keep their
    direction (a normalised ``(x, y, 1)`` cannot hold them)."""
    rot = np.stack([p.rotation for p in poses])[frame]
    centres = np.stack([p.centre for p in poses])[frame]
    d_world = np.einsum("mji,mj->mi", rot, camera.unproject(pixels))
    return centres, d_world / np.linalg.norm(d_world, axis=1, keepdims=True)


def _in_front(camera: Camera, poses: list[Pose], frame: np.ndarray, pixels: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(M,) bool: each observation's point lies ahead along its own ray (positive range), the test that
    holds at any angle from the axis; for rays in front of the camera plane it is the positive z-depth."""
    centres, d = _rays_world(camera, poses, frame, pixels)
    return np.einsum("mi,mi->m", X - centres, d) > 0


def triangulate_observations(
    camera: Camera, poses: list[Pose], track: np.ndarray, frame: np.ndarray, pixels: np.ndarray,
    n_tracks: int, method: str = "midpoint",
) -> np.ndarray:
    """Triangulate all tracks at once.

    track, frame : (M,) int; pixels : (M, 2) distorted pixels; poses : ``cam_from_world`` per frame.
    Returns (n_tracks, 3) mm world points (NaN where a track's rays are degenerate).
    """
    if method == "midpoint":
        c, d = _rays_world(camera, poses, frame, pixels)
        return triangulate_midpoint(c, d, track, n_tracks)
    if method == "dlt":
        # rows of b x (P X) = 0 for the unit bearing b: the two that hold b's largest component (on
        # normalised coordinates, b_z largest: x P3 - P1 and y P3 - P2 up to scale), well conditioned at any
        # angle from the axis, past 90 deg too; A^T A summed per track
        b = camera.unproject(pixels)
        P = np.stack([np.hstack([p.rotation, p.translation[:, None]]) for p in poses])[frame]  # (M, 3, 4)
        rows = (b[:, 1:2] * P[:, 2] - b[:, 2:3] * P[:, 1],   # (b x PX)_x
                b[:, 2:3] * P[:, 0] - b[:, 0:1] * P[:, 2],   # (b x PX)_y
                b[:, 0:1] * P[:, 1] - b[:, 1:2] * P[:, 0])   # (b x PX)_z
        largest = np.argmax(np.abs(b), axis=1)[:, None]
        # b_z largest: rows y, x; b_x largest: rows y, z; b_y largest: rows x, z
        r1 = np.where(largest == 0, rows[1], rows[0])
        r2 = np.where(largest == 2, rows[1], rows[2])
        r1 /= np.linalg.norm(r1, axis=1, keepdims=True)
        r2 /= np.linalg.norm(r2, axis=1, keepdims=True)
        M = np.zeros((n_tracks, 4, 4))
        np.add.at(M, track, r1[:, :, None] * r1[:, None, :] + r2[:, :, None] * r2[:, None, :])
        _, vecs = np.linalg.eigh(M)
        h = vecs[:, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            X = h[:, :3] / h[:, 3:4]
        X[~np.all(np.isfinite(X), axis=1)] = np.nan
        return X
    raise ValueError(f"method must be 'midpoint' or 'dlt', got {method!r}")


def reprojection_errors(camera: Camera, poses: list[Pose], tracks: Tracks, points: np.ndarray | None = None) -> np.ndarray:
    """(M,) pixel distance of each observation from its point's projection (NaN behind the camera)."""
    X = tracks.points if points is None else points
    rot = np.stack([p.rotation for p in poses])[tracks.frame]
    trans = np.stack([p.translation for p in poses])[tracks.frame]
    p_cam = np.einsum("mij,mj->mi", rot, X[tracks.track]) + trans
    return np.linalg.norm(camera.project(p_cam) - tracks.pixels, axis=1)


def _max_ray_angle_deg(camera: Camera, poses: list[Pose], tracks: Tracks, X: np.ndarray) -> np.ndarray:
    """(n_tracks,) largest angle between a track's viewing rays, from the mean ray (half the max pair
    angle at least), computed without pair enumeration."""
    centres = np.stack([p.centre for p in poses])[tracks.frame]
    v = X[tracks.track] - centres
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    mean = np.zeros((len(X), 3))
    np.add.at(mean, tracks.track, v)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    ang = np.degrees(np.arccos(np.clip(np.einsum("mi,mi->m", v, mean[tracks.track]), -1, 1)))
    out = np.zeros(len(X))
    np.maximum.at(out, tracks.track, ang)
    return 2.0 * out  # the spread about the mean ray, doubled ~ the largest pairwise angle


def triangulate_tracks(camera: Camera, poses: list[Pose], tracks: Tracks, options: TrackOptions = TrackOptions()) -> Tracks:
    """Triangulate; drop each bad track's worst observation and re-triangulate (a few rounds); then drop
    the tracks that are still bad. Returns new Tracks with
    ``points`` set; every kept observation reprojects within ``max_reprojection_error_px`` and lies in
    front of its camera, and every kept track spans at least ``min_angle_deg``."""
    if len(poses) <= int(tracks.frame.max(initial=-1)):
        raise ValueError(f"tracks reference frame {int(tracks.frame.max())} but only {len(poses)} poses given")
    current = tracks
    for _ in range(options.max_refine_rounds):
        if current.n_observations == 0:
            break
        X = triangulate_observations(camera, poses, current.track, current.frame, current.pixels, current.n_tracks, options.method)
        current = Tracks(current.track, current.frame, current.feature, current.pixels, current.colors, X)
        err = reprojection_errors(camera, poses, current)
        ahead = _in_front(camera, poses, current.frame, current.pixels, X[current.track])
        err = np.where(np.isfinite(err) & ahead, err, np.inf)
        # one wrong observation pulls its point and so raises the others' errors too: drop only the
        # worst observation of each bad track per round, then re-triangulate
        worst = np.full(current.n_tracks, -1.0)
        np.maximum.at(worst, current.track, err)
        is_worst = (err == worst[current.track]) & (err > options.max_reprojection_error_px)
        # (ties: drop them all; they are equally bad)
        if not is_worst.any():
            break
        good = ~is_worst
        length = np.bincount(current.track[good], minlength=current.n_tracks)
        good &= length[current.track] >= options.min_track_length
        current = current.subset(good)
    if current.n_observations == 0:
        return current
    X = triangulate_observations(camera, poses, current.track, current.frame, current.pixels, current.n_tracks, options.method)
    current = Tracks(current.track, current.frame, current.feature, current.pixels, current.colors, X)
    err = reprojection_errors(camera, poses, current)
    worst = np.zeros(current.n_tracks)
    np.maximum.at(worst, current.track, np.nan_to_num(err, nan=np.inf))
    angle = _max_ray_angle_deg(camera, poses, current, X)
    good_track = np.all(np.isfinite(X), axis=1) & (worst <= options.max_reprojection_error_px) & (angle >= options.min_angle_deg)
    return current.subset(good_track[current.track])


def ray_angles_deg(camera: Camera, poses: list[Pose], tracks: Tracks) -> np.ndarray:
    """(n_tracks,) largest angle (deg) between the viewing rays of each triangulated track (its depth is
    good to about the keypoint noise over this angle)."""
    return _max_ray_angle_deg(camera, poses, tracks, tracks.points)
