"""Bundle adjustment through every lens model (issue 32): the kernels' residuals and Jacobians are the camera
models' (scope3d.sensor.camera_models, themselves checked by finite differences), and a fisheye / barrel
problem converges to the truth as the radial one does."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.errors import InputError
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


# --- the models' later parameters (OPENCV's p1, p2; FULL_OPENCV's k3..k6; the fisheye's k3, k4) ---------------

LATER = {"fisheye": ("k3", "k4"), "barrel": ("p1", "p2"), "full": ("p1", "p2", "k3", "k4", "k5", "k6")}


def _free_later(problem: BundleProblem, names) -> None:
    problem.free("intrinsics", components=list(names))
    assert problem.refines_extra and problem.cam_blocks().shape[1] == 3


@pytest.mark.parametrize("name", list(LATER))
def test_later_parameters_jacobians_match_finite_differences_and_the_models(name):
    """Every intrinsic column the kernel writes with the later parameters free (the six and the later ones) is
    the central difference of its residuals (step 1e-6 on each unitless coefficient, 1e-4 px on fx..cy:
    truncation ~ h^2 |d3 r|, rounding ~ 1e-16 |r| / h, both below 1e-6 of the column's largest entry), and
    the later parameters' columns are the camera model's analytic ones."""
    camera = CAMERAS[name]
    rot, trans, points, pixels, cam_idx, pt_idx = _scene(camera, seed=5, n_points=120)
    block, model, extra = lens_block(camera)
    observed = pixels + np.random.default_rng(6).normal(0, 0.5, pixels.shape)
    problem = BundleProblem(observed, cam_idx, pt_idx, rot, trans, points, block, model=model, extra=extra)
    _free_later(problem, LATER[name])
    r, jc, _ = evaluate(problem, problem.initial)
    assert jc.shape[2] == 18
    layout = problem.intrinsic_names[6:]
    for col, pname in enumerate(problem.intrinsic_names):
        if problem.intrinsic_absent[col]:
            continue
        step = 1e-4 if col < 4 else 1e-6
        shifted = []
        for sign in (1.0, -1.0):
            params = problem.initial.copy()
            if col < 6:
                params.intrinsics[0, col] += sign * step
            else:
                params.extra[0, col - 6] += sign * step
            shifted.append(evaluate(problem, params)[0])
        numeric = (shifted[0] - shifted[1]) / (2 * step)
        analytic = jc[:, :, 6 + col]  # the intrinsic block's 6 columns, then the later block's
        np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-6 * np.abs(numeric).max(),
                                   err_msg=f"{name} {pname}")
    order = problem.observation_order
    _, _, _, d_params = project_world_with_jacobians(
        model, camera.params, points[pt_idx[order]], matrix_to_rotvec(rot)[cam_idx[order]], trans[cam_idx[order]])
    for slot, pname in enumerate(layout):
        if pname in camera.param_names:
            expected = d_params[:, :, camera.param_names.index(pname)]
            np.testing.assert_allclose(jc[:, :, 12 + slot], expected, rtol=1e-9,
                                       atol=1e-9 * np.abs(expected).max(), err_msg=f"{name} {pname}")
    # the fisheye's block is padded to six columns with zeros
    np.testing.assert_array_equal(jc[:, :, 12 + len(layout):], 0.0)


@pytest.mark.parametrize("name", list(LATER))
def test_adjustment_recovers_the_later_parameters(name):
    """Exact pixels; points, the six and every later parameter perturbed (each coefficient by 20 % of itself
    plus 1e-3): with all of them free the truth is the zero-cost minimum again. FULL_OPENCV's rational
    distortion is not identifiable coefficient by coefficient over a 30 deg field (numerator and denominator
    trade off), so there the lens's projection is compared, not its k's."""
    camera = CAMERAS[name]
    rot, trans, points, pixels, cam_idx, pt_idx = _scene(camera, seed=3)  # the scene of the test above
    rng = np.random.default_rng(8)
    block, model, extra = lens_block(camera)
    start = block * np.r_[1.01, 0.99, 1.0, 1.0, 0.9, 1.1] + np.r_[0, 0, 1.5, -1.0, 0, 0]
    problem = BundleProblem(pixels, cam_idx, pt_idx, rot, trans, points + rng.normal(0, 0.05, points.shape),
                            start, model=model, extra=extra)
    later = [camera.param_names.index(n) for n in LATER[name]]
    slots = [problem.intrinsic_names.index(n) - 6 for n in LATER[name]]
    problem.initial.extra[0, slots] = camera.params[later] * 1.2 + 1e-3
    _free_later(problem, LATER[name])
    problem.fix("pose", [0])
    problem.fix("pose", [1], components=["py"])
    result = solve(problem, SolverOptions(max_iterations=300))
    assert result.rms_initial_px > 1.0 and result.rms_final_px < 1e-6
    adjusted = camera_from_block(camera, result.intrinsics[0], result.extra[0])
    if name == "full":
        np.testing.assert_allclose(adjusted.params[:4], camera.params[:4], atol=1e-4)
        rays = np.einsum("kij,kj->ki", rot[cam_idx], points[pt_idx]) + trans[cam_idx]
        np.testing.assert_allclose(adjusted.project(rays), camera.project(rays), atol=1e-5)
    else:
        np.testing.assert_allclose(adjusted.params, camera.params, atol=1e-4)


def test_later_parameters_stay_in_their_box_and_start_held():
    """A box on p1 around a wrong value: the adjustment ends on its edge nearest the truth, inside the box; k1's
    box likewise. Held by default, named by fix/free, a term the model lacks stays held."""
    camera = CAMERAS["barrel"]
    rot, trans, points, pixels, cam_idx, pt_idx = _scene(camera, seed=9)
    block, model, extra = lens_block(camera)
    problem = BundleProblem(pixels, cam_idx, pt_idx, rot, trans, points, block, model=model, extra=extra)
    assert problem.intrinsic_names == ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
    assert problem.extra_fixed.all() and not problem.refines_extra and problem.cam_blocks().shape[1] == 2
    problem.free("intrinsics")  # all free: OPENCV's absent k3..k6 stay held at 0
    assert problem.extra_fixed.tolist() == [[False, False, True, True, True, True]]
    p1 = camera.params[camera.param_names.index("p1")]
    problem.initial.extra[0, 0] = p1 + 5e-3
    problem.set_bounds("intrinsics", None, ["p1"], p1 + 2e-3, p1 + 8e-3)
    problem.fix("pose", [0])
    problem.fix("pose", [1], components=["py"])
    result = solve(problem, SolverOptions(max_iterations=200))
    assert result.extra[0, 0] == pytest.approx(p1 + 2e-3, abs=1e-12)
    assert result.rms_final_px < result.rms_initial_px
    problem.fix("intrinsics")
    assert problem.intrinsic_fixed.all() and not problem.refines_extra
    with pytest.raises(InputError, match="unknown intrinsics component"):
        problem.fix("intrinsics", components=["k7"])


@pytest.mark.parametrize("groups", [1, 2])
@pytest.mark.parametrize("method", ["dense", "sparse"])
def test_reduced_camera_system_with_later_parameters_is_the_schur_complement(groups, method):
    """The reduced camera matrix the kernels assemble with the later parameters' blocks (per observation when
    a point's cameras share one group, per pair when two groups meet at a point) is the Schur complement of
    the damped normal equations formed densely from the Jacobian (eq. 6.7)."""
    from scope3d.estimators.bundle.solver import _ReducedSystem

    camera = CAMERAS["full"]
    rot, trans, points, pixels, cam_idx, pt_idx = _scene(camera, seed=11, n_points=40)
    block, model, extra = lens_block(camera)
    index = np.arange(9) % groups
    problem = BundleProblem(pixels + 0.3, cam_idx, pt_idx, rot, trans, points, np.tile(block, (groups, 1)),
                            model=model, extra=extra, intrinsics_index=index)
    problem.free("intrinsics")
    r, jc, jp = evaluate(problem, problem.initial)
    cam_blocks = problem.cam_blocks()
    n_c, n = 6 * problem.num_camera_blocks, problem.num_points
    rows = np.zeros((2 * len(r), n_c + 3 * n))
    for o in range(len(r)):
        for h, b in enumerate(cam_blocks[o]):
            rows[2 * o:2 * o + 2, 6 * b:6 * b + 6] += jc[o, :, 6 * h:6 * h + 6]
        j = problem.point_index[o]
        rows[2 * o:2 * o + 2, n_c + 3 * j:n_c + 3 * j + 3] = jp[o]
    damp_c, damp_p = np.full(n_c, 0.5), np.full((n, 3), 0.25)
    normal = rows.T @ rows + np.diag(np.r_[damp_c, damp_p.ravel()])
    gradient = rows.T @ r.ravel()
    hpp_inv = np.linalg.inv(normal[n_c:, n_c:])
    schur = normal[:n_c, :n_c] - normal[:n_c, n_c:] @ hpp_inv @ normal[n_c:, :n_c]
    rhs = -gradient[:n_c] + normal[:n_c, n_c:] @ hpp_inv @ gradient[n_c:]
    _, _, fixed_c = problem.camera_bounds()
    system = _ReducedSystem(problem, cam_blocks, method, fixed_c, 1)
    v_inv, gp = np.empty((n, 3, 3)), np.empty((n, 3))
    assert system.assemble(r, jc, jp, cam_blocks, problem.point_ptr, damp_c, damp_p, v_inv, gp, None)
    if method == "dense":
        upper = system.out.reshape(n_c, n_c)
    else:
        import scipy.sparse

        upper = scipy.sparse.bsr_matrix((system.data, system.indices, system.indptr), shape=(n_c, n_c)).toarray()
    scale = np.abs(schur).max()
    np.testing.assert_allclose(np.triu(upper), np.triu(schur), atol=1e-9 * scale)
    np.testing.assert_allclose(system.rhs, rhs, atol=1e-9 * np.abs(rhs).max())
