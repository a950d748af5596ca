"""Hand-eye calibration (sensor.hand_eye, pipelines.hand_eye, `scope3d calibrate-hand-eye`) on rendered
board views from a robot whose reported flange poses carry tracker-like noise."""
from __future__ import annotations

import json

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.io.camera_json import camera_to_dict
from scope3d.io.images import write_image
from scope3d.io.poses_csv import format_poses_csv, read_poses_csv
from scope3d.phantoms.boards import BoardRenderOptions, render_board_views
from scope3d.sensor.calibration import BoardSpec
from scope3d.sensor.camera import Camera
from scope3d.sensor.hand_eye import board_pose, calibrate_hand_eye
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance, perturb_poses_uniform
from scope3d.utils.jsonio import write_json

CAMERA = Camera.from_fov(320, 240, 70.0, k1=-0.25, k2=0.08)
BOARD = BoardSpec(9, 6, 2.0)  # odd x even: its orientation is unambiguous to the detector
FLANGE_FROM_CAM = Pose.from_rotvec([0.05, -0.1, 1.2], [3.0, -2.0, 40.0])  # a scope 40 mm beyond the flange
BASE_FROM_BOARD = Pose.from_rotvec([3.0, 0.2, 0.1], [200.0, 50.0, 10.0])
# An optical tracker's error (uniform per axis): +-0.2 mm on the flange position, +-0.1 deg on its orientation.
NOISE_MM, NOISE_DEG = 0.2, 0.1


@pytest.fixture(scope="module")
def robot_views():
    views = render_board_views(CAMERA, BOARD, n_views=15, seed=21, options=BoardRenderOptions(max_tilt_deg=50))
    true_flange = [BASE_FROM_BOARD @ c.inverse() @ FLANGE_FROM_CAM.inverse() for c in views.poses]
    # perturb_poses_uniform perturbs cam_from_world poses; the flange's is flange_from_base.
    reported = perturb_poses_uniform([b.inverse() for b in true_flange], NOISE_MM, np.deg2rad(NOISE_DEG), seed=3)
    return views, true_flange, [m.pose for m in reported]


def test_cli_hand_eye_recovers_the_transform_within_tracker_noise(robot_views, tmp_path):
    views, true_flange, reported = robot_views
    names = [f"view{i:02d}.png" for i in range(len(views.images))]
    for name, image in zip(names, views.images):
        write_image(tmp_path / name, image)
    write_image(tmp_path / "blank.png", np.zeros_like(views.images[0]))
    tol = PoseTolerance(np.full(3, NOISE_MM), np.full(3, np.deg2rad(NOISE_DEG)))
    (tmp_path / "robot.csv").write_text(format_poses_csv(
        names + ["blank.png"], [MeasuredPose(p, tol) for p in reported + [reported[0]]]))
    write_json(tmp_path / "camera.json", camera_to_dict(CAMERA))
    out = tmp_path / "he"
    rc = main(["calibrate-hand-eye", *(str(tmp_path / n) for n in names + ["blank.png"]),
               "--robot-poses", str(tmp_path / "robot.csv"), "--camera", str(tmp_path / "camera.json"),
               "--board", "9x6", "--square", "2", "--out", str(out)])
    assert rc == 0
    report = json.loads((out / "hand_eye.json").read_text())
    assert report["n_views_used"] == 15 and "blank.png" in report["skipped"]
    got = Pose(np.array(report["flange_from_cam"]["rotation"]), np.array(report["flange_from_cam"]["translation_mm"]))
    # Issue 14's targets: rotation within 0.1 deg, translation within 0.2 mm.
    _, angle = got.distance_to(FLANGE_FROM_CAM)
    assert np.rad2deg(angle) <= 0.1
    assert np.linalg.norm(got.translation - FLANGE_FROM_CAM.translation) <= 0.2
    # The poses written for a dataset: the true camera centre lies inside the written tolerance box in at
    # least 13 of 15 views (3 residual RMS per axis; uniform noise never exceeds ~1.7 RMS, the board's own
    # pose error adds a little).
    names_out, measured = read_poses_csv(out / "poses.csv")
    inside = 0
    for name, m in zip(names_out[:15], measured[:15]):
        true_cam = views.poses[names.index(name)] @ BASE_FROM_BOARD.inverse()
        inside += bool(np.all(np.abs(m.pose.centre - true_cam.centre) <= m.tolerance.position_mm))
    assert inside >= 13, inside


def test_hand_eye_needs_three_views_and_two_rotation_axes(robot_views):
    views, _, reported = robot_views
    obj = [BOARD.object_points()] * 2
    with pytest.raises(InputError, match="at least 3 views"):
        calibrate_hand_eye(reported[:2], views.poses[:2], camera=CAMERA, object_points=obj,
                           pixels=views.corners_px[:2])
    spin = [Pose.from_rotvec([0, 0, a], [a, 0, 0]) for a in (0.1, 0.4, 0.8)]
    with pytest.raises(InputError, match="one axis"):
        calibrate_hand_eye(spin, spin, camera=CAMERA, object_points=[BOARD.object_points()] * 3,
                           pixels=views.corners_px[:3])


def test_the_tolerance_holds_a_focal_length_error_that_the_residuals_cannot_show(robot_views):
    # exact robot and exact corners, seen through a camera whose fx and fy are 2 sigma long: every board is
    # 2 sigma x its distance too far in every view alike, so the loop residuals stay near zero while X moves
    # along the optical axis. The intrinsics' share (X solved again per sigma) must state that move.
    views, true_flange, _ = robot_views
    obj = BOARD.object_points()
    pixels = [CAMERA.project(c.transform(obj)) for c in views.poses]
    sigma = np.array([0.5, 0.5, 0.3, 0.3, 1e-3, 1e-3])  # px, px, px, px, -, -
    wrong = CAMERA.with_params(CAMERA.params + np.array([2.0, 2.0, 0, 0, 0, 0]) * sigma)
    boards = [board_pose(wrong, obj, px) for px in pixels]
    objs = [obj] * len(pixels)
    plain = calibrate_hand_eye(true_flange, boards, camera=wrong, object_points=objs, pixels=pixels)
    shared = calibrate_hand_eye(true_flange, boards, camera=wrong, object_points=objs, pixels=pixels,
                                intrinsic_sigmas=sigma)
    # the camera poses the robot predicts, against the truth, per base axis
    truth = [FLANGE_FROM_CAM.inverse() @ b.inverse() for b in true_flange]
    error = np.abs([(shared.flange_from_cam.inverse() @ b.inverse()).centre - t.centre
                    for b, t in zip(true_flange, truth)]).max(axis=0)
    assert np.linalg.norm(error) > 0.02  # fx 1 px long over ~20-40 mm boards: a real move
    # the residuals alone do not hold it (tilted boards make them grow too, but less: 0.08 against 0.15 mm)
    assert np.linalg.norm(error) > 1.5 * np.linalg.norm(plain.tolerance.position_mm)
    assert np.all(error <= shared.tolerance.position_mm)  # with the share (3 sigma) they do
    assert np.all(shared.intrinsics_share_mm > 0) and np.all(plain.intrinsics_share_mm == 0)
