"""Bundle adjustment through every lens model (issue 32): the kernels' residuals and Jacobians are the camera
models' (scope3d.sensor.camera_models, themselves checked by finite differences), and a fisheye / barrel
problem converges to the truth as the radial one does."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.estimators.bundle import BundleProblem, SolverOptions, solve
from scope3d.estimators.bundle.problem import camera_from_block, lens_block
from scope3d.estimators.bundle.solver import evaluate
from scope3d.geometry.rotation import hat, matrix_to_rotvec, rotvec_to_matrix
from scope3d.phantoms.lenses import LENSES
from scope3d.sensor.camera import Camera
from scope3d.sensor.camera_models import project_world_with_jacobians

CAMERAS = {
    "fisheye": LENSES["fisheye-140"].camera(304, 304, fov_deg=53.0, mask_radius_px=150.0),
    "barrel": LENSES["barrel-70"].camera(304, 304, fov_deg=53.0, mask_radius_px=150.0),
    "full": Camera.from_params(320, 240, "FULL_OPENCV",
                               [250.0, 252.0, 160.0, 120.0, -0.2, 0.05, 1e-3, -5e-4, 0.01, 0.02, -0.01, 0.005]),
    "pinhole": Camera.from_params(320, 240, "PINHOLE", [250.0, 252.0, 160.0, 120.0]),
}


def _scene(camera: Camera, *, seed: int, n_points: int = 300):
    """Nine cameras on a 3 x 3 grid 2 mm apart, turned up to 0.25 rad (which separates the principal point
    from the poses), looking along +z at points 6-12 mm away spread over the lens's field (up to 60 deg off
    axis for the fisheye)."""
    rng = np.random.default_rng(seed)
    n_cameras = 9
    rot = rotvec_to_matrix(rng.uniform(-0.25, 0.25, (n_cameras, 3)))
    grid = np.arange(3) * 2.0 - 2.0
    centres = np.c_[np.repeat(grid, 3), np.tile(grid, 3), np.zeros(n_cameras)]
    trans = -np.einsum("mij,mj->mi", rot, centres)
    half = np.deg2rad(60.0 if camera.lens.is_fisheye else 30.0)
    angle = half * np.sqrt(rng.uniform(0, 1, n_points))
    azimuth = rng.uniform(0, 2 * np.pi, n_points)
    depth = rng.uniform(6.0, 12.0, n_points)
    points = np.c_[np.sin(angle) * np.cos(azimuth), np.sin(angle) * np.sin(azimuth), np.cos(angle)] * depth[:, None]
    cam_idx, pt_idx = np.meshgrid(np.arange(n_cameras), np.arange(n_points))
    cam_idx, pt_idx = cam_idx.ravel(), pt_idx.ravel()
    p_cam = np.einsum("kij,kj->ki", rot[cam_idx], points[pt_idx]) + trans[cam_idx]
    pixels = camera.project(p_cam)
    keep = camera.in_image(pixels)
    return rot, trans, points, pixels[keep], cam_idx[keep], pt_idx[keep]


@pytest.mark.parametrize("name", list(CAMERAS))
@pytest.mark.parametrize("position", ["centre", "translation"])
def test_kernel_residuals_and_jacobians_are_the_camera_models(name, position):
    camera = CAMERAS[name]
    rot, trans, points, pixels, cam_idx, pt_idx = _scene(camera, seed=1)
    block, model, extra = lens_block(camera)
    rng = np.random.default_rng(2)
    observed = pixels + rng.normal(0, 0.5, pixels.shape)
    problem = BundleProblem(observed, cam_idx, pt_idx, rot, trans, points, block, model=model, extra=extra,
                            position_parameter=position)
    r, jc, jp = evaluate(problem, problem.initial)
    order = problem.observation_order
    px, d_point, d_pose, d_params = project_world_with_jacobians(
        model, camera.params, points[pt_idx[order]], matrix_to_rotvec(rot)[cam_idx[order]], trans[cam_idx[order]])
    scale = np.abs(px).max()
    np.testing.assert_allclose(r, px - observed[order], atol=1e-11 * scale)
    np.testing.assert_allclose(jp, d_point, rtol=1e-9, atol=1e-9 * np.abs(d_point).max())
    # the intrinsic block's columns are the model's fx, fy, cx, cy, k1, k2 (a PINHOLE has no k1, k2)
    names = list(camera.param_names)
    for col, n in enumerate(("fx", "fy", "cx", "cy", "k1", "k2")):
        expected = d_params[:, :, names.index(n)] if n in names else None
        if expected is not None:
            np.testing.assert_allclose(jc[:, :, 6 + col], expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())
    # the pose columns from d pixel / d P_cam: the position's (P = R (X - C) or R X + t) and, at w = 0 where
    # the problem starts, the rotation's (d P / d w = -[a]x, a = P or R X)
    d_pcam = d_point @ rot[cam_idx[order]].transpose(0, 2, 1)
    rotated = np.einsum("kij,kj->ki", rot[cam_idx[order]], points[pt_idx[order]])
    a = rotated + trans[cam_idx[order]] if position == "centre" else rotated
    expected_pose = np.concatenate([-d_pcam @ hat(a), -d_point if position == "centre" else d_pcam], axis=-1)
    np.testing.assert_allclose(jc[:, :, :6], expected_pose, rtol=1e-9, atol=1e-9 * np.abs(expected_pose).max())


@pytest.mark.parametrize("name", ["fisheye", "barrel", "full"])
def test_adjustment_through_the_lens_recovers_the_truth(name):
    """Exact pixels, perturbed points and intrinsics (focal lengths 1 %, principal point 1.5 px, k1 and k2
    10 %): the truth is the zero-cost minimum, and Levenberg-Marquardt reaches it only with the right
    Jacobians (a wrong one stalls far above it)."""
    camera = CAMERAS[name]
    rot, trans, points, pixels, cam_idx, pt_idx = _scene(camera, seed=3)
    rng = np.random.default_rng(4)
    block, model, extra = lens_block(camera)
    start = block * np.r_[1.01, 0.99, 1.0, 1.0, 0.9, 1.1] + np.r_[0, 0, 1.5, -1.0, 0, 0]
    problem = BundleProblem(pixels, cam_idx, pt_idx, rot, trans, points + rng.normal(0, 0.05, points.shape),
                            start, model=model, extra=extra)
    problem.fix("pose", [0])  # the gauge: one camera, and the scale by the next camera's y (2 mm away) held
    problem.fix("pose", [1], components=["py"])
    result = solve(problem, SolverOptions(max_iterations=200))
    assert result.rms_initial_px > 1.0 and result.rms_final_px < 1e-6
    adjusted = camera_from_block(camera, result.intrinsics[0])
    assert adjusted.model == camera.model
    # a residual of 1e-6 px leaves the parameters within ~1e-6 of their scale (pixels; k's unitless)
    np.testing.assert_allclose(adjusted.params, camera.params, atol=1e-4)
    np.testing.assert_allclose(result.points_world, points, atol=1e-6)


def test_block_round_trip_keeps_the_models_other_parameters():
    for camera in CAMERAS.values():
        block, model, extra = lens_block(camera)
        assert camera_from_block(camera, block) == camera and model == camera.model
