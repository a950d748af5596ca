"""A rigid body's poses sampled in time (a robot log), and the pose at any time between two samples.

Between two samples the position moves linearly and the orientation by slerp (constant angular velocity
about one axis): what a controller's 100-1000 Hz log allows to say about a 30 Hz camera's frame times
without a model of the robot's dynamics. The error of that interpolation grows with the square of the
interval between the samples (it is exact for constant velocity), so each interpolated pose carries the
length of the interval it was taken from, its *gap*, for a caller to refuse what was interpolated across a
hole in the log.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


@dataclass(frozen=True)
class Trajectory:
    """Poses of one body at increasing times.

    times_s : (N,) strictly increasing, N >= 2. rotations : (N, 3, 3) the body's orientation (any fixed
    convention, e.g. ``base_from_flange``). positions : (N, 3) the body's origin in the same frame (mm).
    """

    times_s: np.ndarray
    rotations: np.ndarray
    positions: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.times_s, dtype=float)
        if t.ndim != 1 or len(t) < 2 or not np.all(np.diff(t) > 0) or not np.all(np.isfinite(t)):
            raise ValueError("a trajectory needs two or more finite, strictly increasing times")
        if np.shape(self.rotations) != (len(t), 3, 3) or np.shape(self.positions) != (len(t), 3):
            raise ValueError("rotations must be (N, 3, 3) and positions (N, 3) for N times")

    def at(self, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Poses at ``times_s`` (M,): ``(rotations (M, 3, 3), positions (M, 3), gap_s (M,))``.

        ``gap_s`` is the interval between the two samples a pose was interpolated from (0 where a time
        falls on a sample); ``inf`` for times outside the trajectory, whose pose is then the nearest end's.
        """
        query = np.atleast_1d(np.asarray(times_s, dtype=float))
        t = np.asarray(self.times_s, dtype=float)
        inside = (query >= t[0]) & (query <= t[-1])
        clipped = np.clip(query, t[0], t[-1])
        upper = np.clip(np.searchsorted(t, clipped, side="left"), 1, len(t) - 1)
        lower = upper - 1
        on_sample = (t[upper] == clipped) | (t[lower] == clipped)
        gap = np.where(on_sample, 0.0, t[upper] - t[lower])
        gap = np.where(inside, gap, np.inf)
        fraction = ((clipped - t[lower]) / (t[upper] - t[lower]))[:, None]
        positions = (1.0 - fraction) * self.positions[lower] + fraction * self.positions[upper]
        rotations = Slerp(t, Rotation.from_matrix(self.rotations))(clipped).as_matrix()
        return rotations, positions, gap
