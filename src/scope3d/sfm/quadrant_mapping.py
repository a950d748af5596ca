"""Sparse reconstruction of one side-view quadrant with the stage's known axial poses (reference sec. 8.3).

Within a quadrant the scope only advances along the hole axis in known steps, so each frame's pose
relative to the others is known to the stage's micrometres: SIFT features are matched between frames a
few steps apart (RANSAC on the fundamental matrix), chained into tracks, and triangulated with those
poses (midpoint, reprojection and ray-angle gates). Every 3-D point keeps the SIFT descriptor of its
first observation, so that neighbouring quadrants can be matched in 3-D (:mod:`scope3d.registration`).

The sparse points lie mostly on the crests the view faces, too few to gauge flanks and roots.
:func:`scope3d.mvs.plane_sweep.dense_quadrant` adds a dense cloud: a multi-view plane sweep (:mod:`scope3d.mvs.plane_sweep`) of the
quadrant's first and last frames against the others, over a depth range bracketing the sparse points.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scope3d.estimators.triangulation import TrackOptions, triangulate_tracks
from scope3d.feature.detection import FeatureOptions, Features, detect
from scope3d.feature.matching import MatchOptions, match_exhaustive
from scope3d.feature.tracks import build_tracks
from scope3d.geometry.pose import Pose
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
    in a neighbouring quadrant: :func:`scope3d.registration.panorama.match_quadrants`)."""

    points: np.ndarray
    descriptors: np.ndarray
    colors: np.ndarray
    n_features: list[int]
    n_matches: dict
    observation_point: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    observation_frame: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    observation_descriptors: np.ndarray = field(default_factory=lambda: np.zeros((0, 128), np.float32))


def map_quadrant(images: list[np.ndarray], camera: Camera, poses: list[Pose],
                 options: QuadrantMapOptions = QuadrantMapOptions()) -> QuadrantMap:
    """Sparse map of one quadrant. images : (H, W[, 3]) uint8 frames in order of advance; poses : their
    ``cam_from_world`` (the stage's). Returns a :class:`QuadrantMap` (possibly empty)."""
    if len(images) != len(poses) or len(images) < 2:
        raise ValueError(f"need >= 2 frames with a pose each, got {len(images)} frames and {len(poses)} poses")
    features: list[Features] = [detect(img, camera, options.features) for img in images]
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
                       tracks.track.astype(np.int64), tracks.frame.astype(np.int64), obs_desc)
