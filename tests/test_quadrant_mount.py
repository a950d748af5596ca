"""The camera's mount rotation measured from the quadrants' epipolar geometry, and the maps triangulated
again with the corrected poses (sfm.quadrant_mapping.estimate_mount_rotation, retriangulate): exact
synthetic observations of a hole's wall seen by a camera tilted on its mount, unknown to the stage."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.phantoms.trajectories import quadrant_trajectory
from scope3d.sensor.camera import Camera
from scope3d.sfm.quadrant_mapping import QuadrantMap, estimate_mount_rotation, retriangulate

CAMERA = Camera.from_fov(400, 320, 60.0)
FRAMES, QUADRANTS, STEP = 8, 4, 0.4


def _scan(side_view, tilt_deg, noise_px, seed=0):
    """Per quadrant: its map (true observations of wall points, with the reported poses' tracks) and the
    reported and true poses of its frames."""
    rng = np.random.default_rng(seed)
    kw = dict(step_mm=STEP, quadrants=QUADRANTS, angle_step_deg=90.0, side_view_deg=side_view, axis_offset_mm=(0.2, -0.1))
    true = quadrant_trajectory(FRAMES, axis_tilt_deg=tilt_deg, **kw).poses
    reported = quadrant_trajectory(FRAMES, axis_tilt_deg=0.0, axis_offset_mm=(0.0, 0.0), step_mm=STEP,
                                   quadrants=QUADRANTS, angle_step_deg=90.0, side_view_deg=side_view).poses
    maps, rep, tru, walls = [], [], [], []
    for q in range(QUADRANTS):
        poses_true = true[q * FRAMES:(q + 1) * FRAMES]
        # wall points of a 3.6 mm bore within the quadrant's view
        angle = np.deg2rad(90 * q) + rng.uniform(-0.45, 0.45, 600)  # the stage turns 90° per quadrant here
        z = rng.uniform(-7.5, 0.0, 600)
        wall = np.c_[3.6 * np.cos(angle), 3.6 * np.sin(angle), z]
        track, frame, pixels = [], [], []
        for f, pose in enumerate(poses_true):
            uv = CAMERA.project_world(pose, wall)
            depth = (wall @ pose.rotation.T + pose.translation)[:, 2]
            seen = np.flatnonzero(CAMERA.in_image(uv, 2.0) & (depth > 0))
            track.append(seen), frame.append(np.full(len(seen), f)), pixels.append(uv[seen])
        track, frame, pixels = np.concatenate(track), np.concatenate(frame), np.concatenate(pixels)
        keep = np.bincount(track, minlength=len(wall))[track] >= 2
        ids, track = np.unique(track[keep], return_inverse=True)
        frame, pixels = frame[keep], pixels[keep] + rng.normal(0.0, noise_px, (keep.sum(), 2))
        maps.append(QuadrantMap(np.zeros((len(ids), 3)), np.zeros((len(ids), 128), np.float32), np.zeros((len(ids), 3), np.uint8),
                                [], {}, track.astype(np.int64), frame.astype(np.int64),
                                np.zeros((len(track), 128), np.float32), pixels))
        rep.append(reported[q * FRAMES:(q + 1) * FRAMES])
        tru.append(poses_true)
        walls.append(wall[ids])
    return maps, rep, tru, walls


@pytest.mark.parametrize("side_view", [45.0, 90.0])
def test_the_mount_tilt_is_measured_and_the_corrected_maps_are_rigid_copies_of_the_wall(side_view):
    noise = 0.1  # px, SIFT-like keypoint noise
    maps, reported, true, walls = _scan(side_view, 0.5, noise)
    mount = estimate_mount_rotation(CAMERA, maps, reported)
    truth = rotvec_to_matrix([np.deg2rad(0.5), 0.0, 0.0])  # the trajectory tilts about the camera's x axis
    error_deg = np.rad2deg(np.linalg.norm(mount.rotvec_rad - [np.deg2rad(0.5), 0, 0]))
    # ~10^4 epipolar distances of 0.1 px noise: the tilt to a few hundredths of a degree; stated sigma honest
    assert error_deg < 0.03
    assert error_deg < 4 * np.rad2deg(np.linalg.norm(mount.sigma_rad))
    np.testing.assert_allclose(mount.rotation, truth, atol=6e-4)
    # re-triangulated with the corrected poses, each quadrant is its wall moved rigidly by the mount's
    # offset (the registration's job), to the keypoint noise: 0.1 px at ~4 mm over 346 px focal, / baseline
    for m, poses, wall in zip(maps, reported, walls):
        points = retriangulate(CAMERA, m, [mount.corrected(p) for p in poses]).points
        bent = retriangulate(CAMERA, m, poses).points
        shift = np.median(wall - points, axis=0)
        spread = np.median(np.linalg.norm(wall - points - shift, axis=1))
        spread_reported = np.median(np.linalg.norm(wall - bent - np.median(wall - bent, axis=0), axis=1))
        assert spread < 0.01 and spread < spread_reported / 2


def test_an_untilted_camera_measures_no_mount_rotation():
    maps, reported, _, _ = _scan(90.0, 0.0, 0.1, seed=1)
    mount = estimate_mount_rotation(CAMERA, maps, reported)
    assert np.rad2deg(np.linalg.norm(mount.rotvec_rad)) < 0.03  # as above: noise only
