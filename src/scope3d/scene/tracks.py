"""Tracks: the observations of one scene point across frames, and the point itself.

Tracks are built from pairwise matches by :func:`scope3d.feature.tracks.build_tracks` and triangulated by
:func:`scope3d.estimators.triangulation.triangulate_tracks`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Tracks:
    """Observations grouped into tracks.

    track : (M,) int64, track id of each observation (0..n_tracks-1, sorted ascending).
    frame : (M,) int64, frame index of each observation.
    feature : (M,) int64, feature index within its frame.
    pixels : (M, 2) float64, observed keypoint (pixels, distorted image).
    points : (n_tracks, 3) float64 mm world, or None before triangulation.
    colors : (n_tracks, 3) uint8, mean RGB of the track's keypoints.
    """

    track: np.ndarray
    frame: np.ndarray
    feature: np.ndarray
    pixels: np.ndarray
    colors: np.ndarray
    points: np.ndarray | None = None

    @property
    def n_tracks(self) -> int:
        return int(self.track.max()) + 1 if len(self.track) else 0

    @property
    def n_observations(self) -> int:
        return len(self.track)

    def lengths(self) -> np.ndarray:
        return np.bincount(self.track, minlength=self.n_tracks)

    def subset(self, keep_obs: np.ndarray) -> "Tracks":
        """Keep the observations in the boolean mask ``keep_obs`` (M,), renumber tracks densely."""
        kept_tracks, new_ids = np.unique(self.track[keep_obs], return_inverse=True)
        return Tracks(
            new_ids.astype(np.int64), self.frame[keep_obs], self.feature[keep_obs], self.pixels[keep_obs],
            self.colors[kept_tracks], None if self.points is None else self.points[kept_tracks],
        )

    def strongest(self, max_tracks: int, priority: np.ndarray | None = None) -> "Tracks":
        """The ``max_tracks`` longest tracks, with all their observations. Ties: the highest ``priority``
        (n_tracks,) first when given (e.g. the tracks' ray angles), then the lowest id."""
        if self.n_tracks <= max_tracks:
            return self
        order = np.arange(self.n_tracks) if priority is None else -np.asarray(priority, float)
        keep_ids = np.lexsort((order, -self.lengths()))[:max_tracks]
        keep = np.zeros(self.n_tracks, bool)
        keep[keep_ids] = True
        return self.subset(keep[self.track])

    def untriangulated(self) -> "Tracks":
        """The same observations without points (to triangulate again with other poses)."""
        return Tracks(self.track, self.frame, self.feature, self.pixels, self.colors, None)
