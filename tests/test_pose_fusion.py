"""Fused bounds (scope3d.sfm.pose_fusion) without images: boxes and their intersection.

Exact arithmetic on boxes (tolerances 1e-9 mm / rad: float rounding); the map-level check, that fused bounds
make a more accurate map than the robot's, is in tests/test_localization.py (it needs a rendered dome).
"""
from __future__ import annotations

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.pose_fusion import FusionOptions, PoseEstimate, fuse_poses, intersect_boxes


def test_intersection_of_two_boxes():
    a = MeasuredPose(Pose.from_centre(np.eye(3), [0.0, 0.0, 10.0]), PoseTolerance([1.0, 1.0, 1.0], np.deg2rad(0.5)))
    b = MeasuredPose(Pose.from_centre(np.eye(3), [0.6, -2.5, 10.2]), PoseTolerance([0.5, 1.0, 0.1], np.deg2rad(1.0)))
    box = intersect_boxes(a, b)
    # x: [-1, 1] and [0.1, 1.1] -> [0.1, 1]; y: [-1, 1] and [-3.5, -1.5] do not meet -> a's; z: [0.1, 0.3]
    np.testing.assert_allclose(box.pose.centre, [0.55, 0.0, 10.2], atol=1e-9)
    np.testing.assert_allclose(box.tolerance.position_mm, [0.45, 1.0, 0.1], atol=1e-9)
    np.testing.assert_allclose(box.tolerance.orientation_rad, np.deg2rad(0.5), atol=1e-9)


def test_fused_box_stays_inside_the_robots():
    """A tracker vaguer than the robot in orientation (0.5 deg sigma against a +-0.5 deg box): 3 sigma of the
    fused estimate would reach beyond the robot's box, which is a hard bound."""
    truth = Pose.from_centre(rotvec_to_matrix([0.1, 0.2, 0.3]), [1.0, 2.0, 15.0])
    robot = MeasuredPose(truth, PoseTolerance(np.full(3, 1.0), np.full(3, np.deg2rad(0.5))))
    sd = np.r_[np.full(3, np.deg2rad(0.5)), 0.2, 0.2, 0.5]
    tracker = PoseEstimate(truth, np.diag(sd**2))
    loose = fuse_poses([robot], [[tracker]], options=FusionOptions(within_reported_box=False))[0]
    cut = fuse_poses([robot], [[tracker]])[0]
    assert np.all(loose.tolerance.orientation_rad > robot.tolerance.orientation_rad)
    assert np.all(cut.tolerance.orientation_rad <= robot.tolerance.orientation_rad + 1e-12)
    assert np.all(cut.tolerance.position_mm <= robot.tolerance.position_mm + 1e-12)
    # x and y: the tracker's 0.2 mm beats the robot's uniform 0.58 mm sigma, the box tightens
    assert np.all(cut.tolerance.position_mm[:2] < 0.7)
