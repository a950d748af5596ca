"""Sparse reconstruction of one side-view quadrant with the stage's known axial poses (reference sec. 8.3).

Within a quadrant the scope only advances along the hole axis in known steps, so each frame's pose
relative to the others is known to the stage's micrometres: SIFT features are matched between frames a
few steps apart (RANSAC on the fundamental matrix), chained into tracks, and triangulated with those
poses (midpoint, reprojection and ray-angle gates). Every 3-D point keeps the SIFT descriptor of its
first observation, so that neighbouring quadrants can be matched in 3-D (:mod:`scope3d.registration`).

The sparse points lie mostly on the crests the view faces, too few to gauge flanks and roots.
:func:`scope3d.mvs.plane_sweep.dense_quadrant` adds a dense cloud: a multi-view plane sweep (:mod:`scope3d.mvs.plane_sweep`) of the
quadrant's first and last frames against the others, over a depth range bracketing the sparse points.

The stage reports where the scope is, not how the camera sits on it: a camera tilted on its mount sees
the scope's advance along a direction tilted from the one the reported poses give, and triangulating with
those poses bends each quadrant's cloud (not rigidly: a point's error depends on where in the frames it
was seen, so no registration can undo it). :func:`estimate_mount_rotation` measures the camera's rotation
on its mount from every quadrant's epipolar geometry (the epipole is the direction of advance seen from
the camera) and :func:`retriangulate` maps the quadrants again with the corrected poses.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from scipy.optimize import least_squares

from scope3d.estimators.triangulation import TrackOptions, triangulate_observations, triangulate_tracks
from scope3d.feature.detection import FeatureOptions, Features, detect
from scope3d.feature.matching import MatchOptions, match_exhaustive
from scope3d.feature.tracks import build_tracks
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.sensor.camera import Camera


@dataclass(frozen=True)
class QuadrantMapOptions:
    """features : SIFT detection (default contrast threshold 0.01, a quarter of OpenCV's: the turned and
        tapped aluminium's tool marks are faint, and at 0.04 a 400x320 frame of an M8 hole gives ~250
        features, at 0.01 ~1300 and four times the 3-D points; 0.005 adds few more). matching : pairwise matching (fundamental-matrix RANSAC).
    max_frame_gap : int, frames up to this many steps apart are matched (default 7, a whole quadrant of 8
        frames: at 0.1 mm steps the longest baseline is 0.7 mm, ~5° of triangulation angle at 5 mm, and a
        point's depth error falls with the baseline; the views still overlap by far).
    tracks : triangulation gates (default: 1.5 px reprojection, 1° minimum ray angle)."""

    features: FeatureOptions = FeatureOptions(max_features=4000, contrast_threshold=0.01, mask_margin_px=4.0)
    matching: MatchOptions = MatchOptions(min_matches=12, threads=1)
    max_frame_gap: int = 7
    tracks: TrackOptions = field(default_factory=lambda: TrackOptions(max_reprojection_error_px=1.5, min_angle_deg=1.0))

    def __post_init__(self) -> None:
        if self.max_frame_gap < 1:
            raise ValueError("max_frame_gap must be >= 1")


@dataclass
class QuadrantMap:
    """points : (N, 3) float64 mm in the frame of the poses given; descriptors : (N, 128) float32, the
    first observation's SIFT descriptor; colors : (N, 3) uint8; n_features : features per frame;
    n_matches : verified matches per frame pair. observation_point, observation_frame : (M,) int64, each
    observation's point and frame (index in the quadrant's frames); observation_descriptors : (M, 128)
    float32, its SIFT descriptor (every view of a point, for matching frames taken at the same advance
    in a neighbouring quadrant: :func:`scope3d.registration.panorama.match_quadrants`);
    observation_pixels : (M, 2) float64 px, where it was seen (for :func:`retriangulate`)."""

    points: np.ndarray
    descriptors: np.ndarray
    colors: np.ndarray
    n_features: list[int]
    n_matches: dict
    observation_point: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    observation_frame: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    observation_descriptors: np.ndarray = field(default_factory=lambda: np.zeros((0, 128), np.float32))
    observation_pixels: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


def map_quadrant(images: list[np.ndarray], camera: Camera, poses: list[Pose],
                 *,
                 options: QuadrantMapOptions = QuadrantMapOptions()) -> QuadrantMap:
    """Sparse map of one quadrant. images : (H, W[, 3]) uint8 frames in order of advance; poses : their
    ``cam_from_world`` (the stage's). Returns a :class:`QuadrantMap` (possibly empty)."""
    if len(images) != len(poses) or len(images) < 2:
        raise ValueError(f"need >= 2 frames with a pose each, got {len(images)} frames and {len(poses)} poses")
    features: list[Features] = [detect(img, camera, options=options.features) for img in images]
    matches, counts = [], {}
    for i in range(len(images)):
        for j in range(i + 1, min(len(images), i + options.max_frame_gap + 1)):
            m = match_exhaustive(camera, features[i], features[j], options.matching, i=i, j=j)
            counts[f"{i}-{j}"] = len(m)
            if len(m):
                matches.append(m)
    tracks = build_tracks(features, matches, min_track_length=2)
    empty = QuadrantMap(np.zeros((0, 3)), np.zeros((0, 128), np.float32), np.zeros((0, 3), np.uint8),
                        [len(f) for f in features], counts)
    if tracks.n_tracks == 0:
        return empty
    tracks = triangulate_tracks(camera, poses, tracks, options.tracks)
    if tracks.n_tracks == 0:
        return empty
    first = np.searchsorted(tracks.track, np.arange(tracks.n_tracks))  # tracks are sorted by id
    obs_desc = np.stack([features[f].descriptors[k] for f, k in zip(tracks.frame, tracks.feature)]).astype(np.float32)
    return QuadrantMap(tracks.points, obs_desc[first], tracks.colors, [len(f) for f in features], counts,
                       tracks.track.astype(np.int64), tracks.frame.astype(np.int64), obs_desc,
                       np.asarray(tracks.pixels, float))


@dataclass(frozen=True)
class MountOptions:
    """loss_scale_px : scale of the robust (Cauchy) loss on the epipolar distances (default 0.3 px: SIFT
    keypoints across a crest edge; along it they slide by more, and those pairs are the loss' outliers)."""

    loss_scale_px: float = 0.3

    def __post_init__(self) -> None:
        if not self.loss_scale_px > 0:
            raise ValueError("loss_scale_px must be > 0")


@dataclass(frozen=True)
class MountEstimate:
    """rotation : (3, 3) the camera's rotation on its mount, in its own frame: the corrected
    ``cam_from_world`` is ``Pose(rotation, 0) @ reported`` (a rotation about the camera centre).
    rotvec_rad : (3,) its rotation vector (camera frame); sigma_rad : (2,) standard uncertainty of its two
    observable components (about the axes normal to the direction of advance; the rotation about that
    direction is a turn about the stage's axis, the registration's gauge); n_pairs : observation pairs
    used; rms_px : robust RMS of their epipolar distances after the fit."""

    rotation: np.ndarray
    rotvec_rad: np.ndarray
    sigma_rad: np.ndarray
    n_pairs: int
    rms_px: float

    def corrected(self, pose: Pose) -> Pose:
        """A reported ``cam_from_world`` with the mount rotation applied about the camera centre."""
        return Pose(self.rotation, np.zeros(3)) @ pose

    def to_dict(self) -> dict:
        return {"rotation_deg": float(np.rad2deg(np.linalg.norm(self.rotvec_rad))),
                "rotvec_deg": np.rad2deg(self.rotvec_rad).tolist(), "sigma_deg": np.rad2deg(self.sigma_rad).tolist(),
                "n_pairs": self.n_pairs, "rms_px": self.rms_px}


def estimate_mount_rotation(camera: Camera, maps: list[QuadrantMap], poses: list[list[Pose]],
                            *,
                            options: MountOptions = MountOptions()) -> MountEstimate:
    """The camera's rotation on its mount, common to every frame, from the quadrants' epipolar geometry.

    Two frames of a quadrant differ by the stage's advance: with the reported poses, the frames'
    relative rotation ``R_b R_a^T`` and the baseline ``R_a (c_b - c_a)`` in the first camera's frame; a
    camera rotated by ``M`` on its mount sees them as ``M R_b R_a^T M^T`` and ``M R_a (c_b - c_a)``. The
    robust fit of ``M`` minimises every consecutive pair of a track's views' Sampson distance (px) to the
    epipolar line of ``E = [t]x R``. Only the two components of ``M`` normal to the direction of advance
    change the epipoles; the third is fixed at 0. maps : quadrant maps (with observation pixels); poses :
    per quadrant its frames' reported ``cam_from_world``. Raises ValueError with no observation pairs."""
    rel, base, xa, xb = [], [], [], []
    for m, ps in zip(maps, poses):
        if len(m.observation_point) < 2:
            continue
        order = np.lexsort((m.observation_frame, m.observation_point))
        same = m.observation_point[order[1:]] == m.observation_point[order[:-1]]
        a, b = order[:-1][same], order[1:][same]
        fa, fb = m.observation_frame[a], m.observation_frame[b]
        rot = np.stack([p.rotation for p in ps])
        centre = np.stack([p.centre for p in ps])
        rel.append(np.einsum("nij,nkj->nik", rot[fb], rot[fa]))
        base.append(np.einsum("nij,nj->ni", rot[fa], centre[fb] - centre[fa]))
        xa.append(camera.pixel_to_normalised(m.observation_pixels[a]))
        xb.append(camera.pixel_to_normalised(m.observation_pixels[b]))
    if not base:
        raise ValueError("no track seen twice: the mount rotation cannot be measured")
    rel, base = np.concatenate(rel), np.concatenate(base)
    xa = np.c_[np.concatenate(xa), np.ones(len(rel))]
    xb = np.c_[np.concatenate(xb), np.ones(len(rel))]
    advance = np.mean(base / np.linalg.norm(base, axis=1, keepdims=True), axis=0)
    advance /= np.linalg.norm(advance)
    e1 = np.cross(advance, [0.0, 0.0, 1.0] if abs(advance[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(advance, e1)

    def rotation(x):
        return rotvec_to_matrix(x[0] * e1 + x[1] * e2)

    def residual(x):
        m = rotation(x)
        t = base @ m.T
        r = np.einsum("ij,njk,lk->nil", m, rel, m)
        tx = np.zeros((len(t), 3, 3))
        tx[:, 0, 1], tx[:, 0, 2], tx[:, 1, 2] = -t[:, 2], t[:, 1], -t[:, 0]
        tx[:, 1, 0], tx[:, 2, 0], tx[:, 2, 1] = t[:, 2], -t[:, 1], t[:, 0]
        e = tx @ r
        ex_a = np.einsum("nij,nj->ni", e, xa)
        etx_b = np.einsum("nji,nj->ni", e, xb)
        num = np.sum(xb * ex_a, axis=1)
        den = np.sqrt(ex_a[:, 0] ** 2 + ex_a[:, 1] ** 2 + etx_b[:, 0] ** 2 + etx_b[:, 1] ** 2)
        return camera.fx * num / np.maximum(den, 1e-12)

    sol = least_squares(residual, np.zeros(2), loss="cauchy", f_scale=options.loss_scale_px, x_scale=1e-3)
    res = sol.fun
    core = np.abs(res) < 3 * options.loss_scale_px
    jac = sol.jac[core]
    s2 = float(np.sum(res[core] ** 2) / max(1, int(core.sum()) - 2))
    try:
        sigma = np.sqrt(np.diag(np.linalg.inv(jac.T @ jac) * s2))
    except np.linalg.LinAlgError:
        sigma = np.full(2, np.inf)
    rotvec = sol.x[0] * e1 + sol.x[1] * e2
    return MountEstimate(rotation(sol.x), rotvec, sigma, len(res), float(np.sqrt(np.mean(res[core] ** 2))))


def retriangulate(camera: Camera, quadrant_map: QuadrantMap, poses: list[Pose]) -> QuadrantMap:
    """The same tracks triangulated again (midpoint) with other ``cam_from_world`` poses of its frames,
    e.g. corrected for the mount (:class:`MountEstimate`); every other field is kept."""
    if len(quadrant_map.points) == 0:
        return quadrant_map
    points = triangulate_observations(camera, poses, quadrant_map.observation_point, quadrant_map.observation_frame,
                                      quadrant_map.observation_pixels, len(quadrant_map.points))
    return replace(quadrant_map, points=points)
