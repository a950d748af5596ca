"""Whether each frame's points form one wall in that frame's view, from the map alone (no truth): the
self-check of a map that is a cavity seen from inside but holds a wrong surface (docs/panorama.md, "A wrong
surface inside a right map").

A frame of a scope inside a cavity sees one smooth wall: the depths of the points it observes vary
smoothly across its image. A point whose depth in a frame is far from the plane through its neighbours in
that frame's image (neighbours that may come from other pairs and tracks) contradicts the frame's other
points: one of them is no wall. "Far" is from the noise model: the keypoint noise propagated through each
point's triangulation (depth over focal over the sine of its widest ray angle, per pixel of noise).

Units: the map's (mm or provisional); every figure here is a ratio or a count, so scale-free.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from scope3d.estimators.triangulation import ray_angles_deg
from scope3d.geometry.pose import Pose
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera

#: keypoint noise, px: the 95th percentile of the real keypoints' error against the truth on the phantom
#: (0.1 px median, 0.5 px p95, docs/panorama.md), so that the test is conservative
KEYPOINT_NOISE_PX = 0.5
#: a point this many standard deviations off its frame's local depth plane is inconsistent (a Gaussian
#: error exceeds it with probability 0.27 %)
N_SIGMA = 3.0
#: a frame is flagged when more of its points than this are inconsistent: the verified pairs keep up to
#: 10 % wrong matches (measured against the truth: 0-10 % on the spirals and wet walls, docs/panorama.md),
#: and a wrong match can be anywhere along its epipolar line; more than that is no longer stray matches
#: but a surface of them
MAX_INCONSISTENT_FRACTION = 0.10
#: neighbours in the frame's image for the local depth plane (three parameters; 8 leave 5 degrees of freedom)
NEIGHBOURS = 8
#: a frame with fewer points than this is not judged (too few for planes through neighbours)
MIN_POINTS = 3 * NEIGHBOURS


def frame_depth_inconsistency(camera: Camera, poses: list[Pose], tracks: Tracks,
                              registered: np.ndarray) -> np.ndarray:
    """(n_frames,) for each registered frame with at least :data:`MIN_POINTS` observations, the fraction of
    its observations whose depth lies more than :data:`N_SIGMA` standard deviations off the least-squares
    plane (depth against pixel) through its :data:`NEIGHBOURS` nearest neighbours in the same image; NaN for
    the other frames.

    The standard deviation of a point's depth is :data:`KEYPOINT_NOISE_PX` times depth / focal /
    sin(widest ray angle); that of the plane's prediction at most sqrt(3 / k) times its neighbours' RMS (a
    three-parameter fit of k points: mean leverage 3 / k); both add. The wall's curvature across a
    neighbourhood is not modelled: it only adds to the good maps' fraction (measured 1-6 % per frame on a
    0.32 mm map, against 13-27 % on the frames of a 2.5 mm one)."""
    n = len(poses)
    out = np.full(n, np.nan)
    if tracks.n_tracks == 0:
        return out
    angle = np.radians(np.maximum(ray_angles_deg(camera, poses, tracks), 1e-3))
    focal = 0.5 * (camera.fx + camera.fy)
    for j in np.flatnonzero(registered):
        obs = np.flatnonzero(tracks.frame == j)
        if len(obs) < MIN_POINTS:
            continue
        ids = tracks.track[obs]
        R, t = poses[j].rotation, poses[j].translation
        depth = (tracks.points[ids] @ R.T + t)[:, 2]
        sigma = KEYPOINT_NOISE_PX * depth / focal / np.sin(angle[ids])
        px = tracks.pixels[obs]
        _, nn = cKDTree(px).query(px, NEIGHBOURS + 1)
        nb = nn[:, 1:]  # the point itself is its own nearest
        # the plane in pixel offsets from the point itself: its depth there is the plane's constant term
        A = np.concatenate([px[nb] - px[:, None], np.ones(nb.shape + (1,))], axis=2)  # (m, k, 3)
        # pseudo-inverse: neighbours along one line (a vessel's edge) leave the plane's tilt across it free
        predicted = (np.linalg.pinv(A) @ depth[nb][..., None])[:, 2, 0]
        spread = np.hypot(sigma, np.sqrt(3.0 / NEIGHBOURS * np.mean(sigma[nb] ** 2, axis=1)))
        out[j] = float(np.mean(np.abs(depth - predicted) > N_SIGMA * spread))
    return out


def inconsistent_frames(fractions: np.ndarray) -> list[int]:
    """The frames whose fraction (:func:`frame_depth_inconsistency`) exceeds :data:`MAX_INCONSISTENT_FRACTION`."""
    return [int(j) for j in np.flatnonzero(np.nan_to_num(fractions, nan=0.0) > MAX_INCONSISTENT_FRACTION)]
