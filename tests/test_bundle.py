"""Bound-constrained bundle adjustment: Jacobians, bounds (eq. 6.9-6.13), losses, shape bounds, bad inputs."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.errors import InputError
from scope3d.estimators.bundle import (
    BoundsWarning,
    BundleParameters,
    BundleProblem,
    SolverOptions,
    evaluate,
    kernels,
    solve,
)
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import matrix_to_rotvec, rotvec_to_matrix, so3_left_jacobian
from scope3d.phantoms.bundle_scene import make_scene
from scope3d.sensor.camera import Camera, project_with_jacobians
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance


def scene_problem(scene, **kw) -> BundleProblem:
    return BundleProblem(scene.observations_px, scene.camera_index, scene.point_index, scene.rotations,
                         scene.translations, scene.points, scene.intrinsics, **kw)


def perturbed(problem: BundleProblem, seed: int, *, rot=0.01, pos=0.05, pts=0.1, intr=(5, 5, 3, 3, 0.01, 0.005)):
    rng = np.random.default_rng(seed)
    x = problem.initial.copy()
    x.pose[:, :3] += rng.uniform(-rot, rot, x.pose[:, :3].shape)
    x.pose[:, 3:] += rng.uniform(-pos, pos, x.pose[:, 3:].shape)
    x.points += rng.uniform(-pts, pts, x.points.shape)
    x.intrinsics += rng.uniform(-1, 1, x.intrinsics.shape) * np.asarray(intr)
    return x


def gradient(problem: BundleProblem, params: BundleParameters):
    r, jc, jp = evaluate(problem, params)
    gc, _, gp, _ = kernels.gradient_and_diagonal(
        r, jc, jp, problem.cam_blocks(), problem.point_index, problem.num_cameras + problem.num_groups,
        problem.num_points,
    )
    return gc, gp


# --- residuals and Jacobians -----------------------------------------------------------------


def test_fused_kernel_matches_camera_project_with_jacobians():
    scene = make_scene(5, 40, seed=1)
    problem = scene_problem(scene, position_parameter="translation")
    r, jc, jp = evaluate(problem, problem.initial)
    cam, pt = problem.camera_index, problem.point_index
    rotvecs = matrix_to_rotvec(scene.rotations)
    pix, d_point, d_pose, d_intr = project_with_jacobians(
        scene.points[pt], rotvecs[cam], scene.translations[cam], scene.intrinsics)
    np.testing.assert_allclose(r, pix - problem.observations_px, atol=1e-9)
    np.testing.assert_allclose(jp, d_point, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(jc[:, :, 6:], d_intr, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(jc[:, :, 3:6], d_pose[:, :, 3:], rtol=1e-12, atol=1e-9)
    # camera.py differentiates the global rotation vector: d/dw_global = d/dw_left @ J_l(w_global)
    np.testing.assert_allclose(
        np.einsum("kij,kjl->kil", jc[:, :, :3], so3_left_jacobian(rotvecs[cam])), d_pose[:, :, :3],
        rtol=1e-9, atol=1e-7)


@pytest.mark.parametrize("position_parameter, square", [("centre", False), ("translation", True)])
def test_jacobians_match_finite_differences(position_parameter, square):
    scene = make_scene(6, 60, seed=2)
    problem = scene_problem(scene, position_parameter=position_parameter, square_pixels=square)
    problem.bound_points_to_shell(scene.points[:20].mean(axis=0) + [0, 0, 30.0], 20.0, 40.0, points=range(20))
    problem.bound_point_depth(scene.centres[0], scene.rotations[0][2], 0.0, 50.0, points=range(20, 40))
    x = perturbed(problem, 3, rot=0.2)  # w far from 0, so J_l(w) != I is exercised
    _, jc, jp = evaluate(problem, x)
    m, g = problem.num_cameras, problem.num_groups
    cam_blocks = problem.cam_blocks()

    def residual(p):
        return evaluate(problem, p)[0]

    for comp in range(6):
        for step_scale, which in ((1e-6, "pose"), (1e-5 * max(1.0, abs(x.intrinsics[0, comp])), "intrinsics")):
            plus, minus = x.copy(), x.copy()
            getattr(plus, which)[:, comp] += step_scale
            getattr(minus, which)[:, comp] -= step_scale
            fd = (residual(plus) - residual(minus)) / (2 * step_scale)
            col = comp if which == "pose" else 6 + comp
            if which == "intrinsics" and square and comp == 1:
                continue  # fy is tied to fx and has no column of its own
            np.testing.assert_allclose(jc[:, :, col], fd, rtol=2e-5, atol=2e-5 * np.abs(fd).max() + 1e-7,
                                       err_msg=f"{which} component {comp}")
    for comp in range(3):
        h = 1e-6
        plus, minus = x.copy(), x.copy()
        plus.points[:, comp] += h
        minus.points[:, comp] -= h
        fd = (residual(plus) - residual(minus)) / (2 * h)
        np.testing.assert_allclose(jp[:, :, comp], fd, rtol=2e-5, atol=2e-5 * np.abs(fd).max(),
                                   err_msg=f"point component {comp}")
    assert cam_blocks.shape == (problem.num_observations, 2) and cam_blocks[:, 1].min() == m and g == 1


# --- unconstrained correctness -----------------------------------------------------------------


def test_noise_free_data_recovered_to_machine_precision():
    scene = make_scene(8, 150, observations_per_point=5, seed=4)
    truth = scene_problem(scene)
    start = perturbed(truth, 5)
    problem = scene_problem(scene)
    problem.initial = start.copy()
    # gauge: first camera and the second's centre held at the truth (rotation, translation, scale)
    problem.initial.pose[:2] = truth.initial.pose[:2]
    problem.fix("pose", [0])
    problem.fix("pose", [1], ["px", "py", "pz"])
    result = solve(problem, SolverOptions(function_tolerance=0.0, parameter_tolerance=1e-14,
                                          gradient_tolerance=1e-12, max_iterations=60))
    assert result.initial_cost > 1e3
    assert result.final_cost < 1e-18
    np.testing.assert_allclose(result.points_world, scene.points, atol=1e-9)
    np.testing.assert_allclose(result.rotations, scene.rotations, atol=1e-11)
    np.testing.assert_allclose(result.intrinsics[0], scene.intrinsics, rtol=1e-9, atol=1e-11)


def test_linear_solvers_agree():
    scene = make_scene(10, 200, seed=6, pixel_noise_px=0.5)
    problem = scene_problem(scene)
    problem.initial = perturbed(problem, 7)
    problem.fix("pose", [0])
    costs = {}
    for method in ("dense", "sparse", "pcg"):
        opts = SolverOptions(linear_solver=method, max_iterations=8, pcg_tolerance=1e-10)
        result = solve(problem, opts)
        assert result.linear_solver == method
        costs[method] = result.final_cost
    assert costs["sparse"] == pytest.approx(costs["dense"], rel=1e-8)
    assert costs["pcg"] == pytest.approx(costs["dense"], rel=1e-4)


# --- bounds: eq. 6.9-6.13 -------------------------------------------------------------------------


def biased_bcba_problem(seed=8):
    """Measured centres biased by 0.6 mm on x with a 0.25 mm tolerance: the truth is outside the box."""
    scene = make_scene(8, 200, observations_per_point=4, seed=seed, pixel_noise_px=0.3)
    tol = PoseTolerance(position_mm=0.25, orientation_rad=0.0)
    measured = [
        MeasuredPose(Pose.from_centre(r, c + [0.6, 0.0, 0.0]), tol)
        for r, c in zip(scene.rotations, scene.centres)
    ]
    camera = Camera.from_intrinsics(640, 480, scene.intrinsics)
    problem = BundleProblem.from_measured_poses(
        measured, camera, scene.points, scene.observations_px, scene.camera_index, scene.point_index,
        refine_intrinsics=False)
    return scene, problem


def test_minimum_outside_box_ends_on_box_with_kkt():
    scene, problem = biased_bcba_problem()
    result = solve(problem, SolverOptions(max_iterations=200, function_tolerance=1e-12))
    x = result.parameters
    lower_c, upper_c, fixed_c = problem.camera_bounds()
    xc = x.camera_vector()
    at_lower = (xc <= lower_c) & ~fixed_c
    at_upper = (xc >= upper_c) & ~fixed_c
    assert at_lower.sum() + at_upper.sum() >= 1  # the solution sits on the box
    gc, gp = gradient(problem, x)
    g0c, _ = gradient(problem, problem.initial)
    scale = np.abs(g0c[~fixed_c]).max()
    # KKT for min f on a box: g >= 0 at a lower bound, g <= 0 at an upper bound, g = 0 inside
    inside = ~fixed_c & ~at_lower & ~at_upper
    assert np.abs(gc[inside]).max() < 1e-6 * scale
    assert np.all(gc[at_lower] > -1e-6 * scale)
    assert np.all(gc[at_upper] < 1e-6 * scale)
    assert np.abs(gp).max() < 1e-6 * scale
    assert result.log[-1].active_set_size >= 1
    # bound-constrained cost is above the unconstrained optimum with the same gauge freedom removed
    free = BundleProblem(scene.observations_px, scene.camera_index, scene.point_index,
                         problem.reference_rotations, np.stack([p.translation for p in problem.poses(problem.initial.pose)]),
                         scene.points, scene.intrinsics)
    free.fix("pose")
    fixed_result = solve(free)
    assert result.final_cost < fixed_result.final_cost  # BCBA improves on trusting the measured poses


def test_iterates_never_leave_the_box():
    _, problem = biased_bcba_problem(seed=9)
    lower_c, upper_c, _ = problem.camera_bounds()
    worst = []

    def check(record, params):
        xc = params.camera_vector()
        worst.append(min((xc - lower_c).min(), (upper_c - xc).min()))

    result = solve(problem, SolverOptions(max_iterations=50), callback=check)
    assert len(worst) == len(result.log) and len(worst) > 3
    assert min(worst) >= 0.0


def test_fixed_parameters_do_not_move():
    scene = make_scene(6, 100, seed=10, pixel_noise_px=0.5)
    problem = scene_problem(scene)
    problem.initial = perturbed(problem, 11)
    problem.fix("pose", [0, 3])
    problem.fix("intrinsics", components=["cx", "cy"])
    problem.fix("point", [5], ["y1"])
    result = solve(problem, SolverOptions(max_iterations=10))
    np.testing.assert_array_equal(result.parameters.pose[[0, 3]], problem.initial.pose[[0, 3]])
    np.testing.assert_array_equal(result.parameters.intrinsics[:, 2:4], problem.initial.intrinsics[:, 2:4])
    assert result.parameters.points[5, 1] == problem.initial.points[5, 1]
    assert result.final_cost < result.initial_cost


def test_initial_values_outside_bounds_are_clamped_with_warning():
    scene = make_scene(5, 60, seed=12)
    problem = scene_problem(scene)
    problem.fix("pose", [0])
    problem.set_bounds("intrinsics", None, ["fx"], 400.0, 480.0)  # initial fx = 500 lies outside
    with pytest.warns(BoundsWarning, match="clamped"):
        result = solve(problem, SolverOptions(max_iterations=5))
    assert result.clamped_initial_values == 1
    assert 400.0 <= result.parameters.intrinsics[0, 0] <= 480.0


# --- robust loss --------------------------------------------------------------------------------


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_robust_loss_downweights_an_outlier(loss):
    scene = make_scene(6, 120, seed=13, pixel_noise_px=0.2)
    scene.observations_px[7] += [40.0, -30.0]  # one gross mismatch
    problem = scene_problem(scene)
    problem.fix("pose", [0])
    problem.fix("pose", [1], ["px"])
    problem.fix("intrinsics")
    plain = solve(problem)
    robust = solve(problem, SolverOptions(loss=loss, loss_scale_px=1.0))
    err_plain = plain.reprojection_errors_px()
    err_robust = robust.reprojection_errors_px()
    inliers = np.arange(len(err_plain)) != 7
    # the robust fit leaves the outlier unexplained and fits the others better
    assert err_robust[7] > err_plain[7]
    assert np.sqrt(np.mean(err_robust[inliers] ** 2)) < np.sqrt(np.mean(err_plain[inliers] ** 2))
    assert np.abs(robust.points_world - scene.points).max() < np.abs(plain.points_world - scene.points).max()


# --- shape bounds -------------------------------------------------------------------------------


def test_shell_bound_respected_at_every_iterate():
    scene = make_scene(6, 120, seed=14, pixel_noise_px=0.3)
    centre = np.array([2.5, 0.0, 30.0])
    dist = np.linalg.norm(scene.points - centre, axis=1)
    r_min, r_max = np.percentile(dist, 20), np.percentile(dist, 80)  # tighter than the truth
    problem = scene_problem(scene)
    problem.fix("pose")
    problem.fix("intrinsics")
    with pytest.warns(BoundsWarning):
        problem.bound_points_to_shell(centre, r_min, r_max)
        radii = []
        result = solve(problem, callback=lambda rec, p: radii.append(
            np.linalg.norm(problem.points_world(p.points) - centre, axis=1)))
    all_r = np.concatenate(radii)
    assert all_r.min() >= r_min - 1e-9 and all_r.max() <= r_max + 1e-9
    final_r = np.linalg.norm(result.points_world - centre, axis=1)
    assert np.sum(np.isclose(final_r, r_max, atol=1e-9)) > 5 and np.sum(np.isclose(final_r, r_min, atol=1e-9)) > 5
    # points whose true radius is inside the shell are still recovered, to the triangulation noise:
    # depth sigma = z^2 sigma_px / (f b) with z <= 12 mm, 3 mm baseline, f = 500 px, 0.3 px; 5 sigma
    inside = (dist > r_min + 0.2) & (dist < r_max - 0.2)
    assert np.abs(result.points_world[inside] - scene.points[inside]).max() < 5 * 12**2 * 0.3 / (500 * 3.0)


def test_depth_bound_along_optical_axis():
    scene = make_scene(6, 120, seed=15, pixel_noise_px=0.3)
    axis = scene.rotations[0][2]
    origin = scene.centres[0]
    problem = scene_problem(scene)
    problem.fix("pose")
    problem.fix("intrinsics")
    problem.bound_point_depth(origin, axis, 9.0, 11.0)
    with pytest.warns(BoundsWarning):
        result = solve(problem)
    depth = (result.points_world - origin) @ axis
    assert depth.min() >= 9.0 - 1e-9 and depth.max() <= 11.0 + 1e-9
    true_depth = (scene.points - origin) @ axis
    assert np.sum(np.isclose(depth, 11.0)) == pytest.approx(np.sum(true_depth > 11.0), abs=3)


# --- results ------------------------------------------------------------------------------------


def test_result_summary_log_and_plot(tmp_path):
    scene = make_scene(5, 80, seed=16, pixel_noise_px=0.5)
    problem = scene_problem(scene)
    problem.initial = perturbed(problem, 17)
    problem.fix("pose", [0])
    result = solve(problem, SolverOptions(max_iterations=15))
    text = result.summary()
    assert "final cost" in text and result.termination in text
    assert result.log[0].iteration == 0 and result.log[-1].iteration == result.iterations
    costs = [rec.cost for rec in result.log]
    assert all(b <= a for a, b in zip(costs, costs[1:]))  # accepted steps only ever lower the cost
    d = result.to_dict()
    assert {"initial_cost", "final_cost", "iterations", "solve_time_s", "iteration_log"} <= set(d)
    # no robust loss: the RMS from the cost is the RMS of the reprojection errors
    assert result.rms_final_px == pytest.approx(np.sqrt(np.mean(result.reprojection_errors_px() ** 2)), rel=1e-9)
    assert result.rms_initial_px > result.rms_final_px and f"(RMS {result.rms_final_px:.4f} px)" in text
    result.plot_convergence(tmp_path / "curve.png")
    assert (tmp_path / "curve.png").read_bytes()[:4] == b"\x89PNG"


# --- bad inputs ---------------------------------------------------------------------------------


def small_arrays():
    scene = make_scene(4, 10, seed=18)
    return dict(observations_px=scene.observations_px.copy(), camera_index=scene.camera_index.copy(),
                point_index=scene.point_index.copy(), rotations=scene.rotations, translations=scene.translations,
                points_world=scene.points.copy(), intrinsics=scene.intrinsics)


def test_bad_inputs_raise_input_error_with_clear_messages():
    a = small_arrays()
    bad = dict(a, observations_px=a["observations_px"].copy())
    bad["observations_px"][3, 1] = np.nan
    with pytest.raises(InputError, match="observations row 3 has NaN"):
        BundleProblem(**bad)
    with pytest.raises(InputError, match="empty"):
        BundleProblem(**dict(a, observations_px=np.zeros((0, 2)), camera_index=np.zeros(0, int),
                             point_index=np.zeros(0, int)))
    idx = a["camera_index"].copy()
    idx[5] = 9
    with pytest.raises(InputError, match=r"observation row 5: camera index 9 out of range \[0, 4\)"):
        BundleProblem(**dict(a, camera_index=idx))
    idx = a["point_index"].copy()
    idx[2] = -1
    with pytest.raises(InputError, match="observation row 2: point index -1"):
        BundleProblem(**dict(a, point_index=idx))
    pts = a["points_world"].copy()
    pts[4] = np.inf
    with pytest.raises(InputError, match="points row 4"):
        BundleProblem(**dict(a, points_world=pts))

    problem = BundleProblem(**a)
    with pytest.raises(InputError, match="lower bound 3 > upper bound 2"):
        problem.set_bounds("point", [1], ["y0"], 3.0, 2.0)
    with pytest.raises(InputError, match="NaN"):
        problem.set_bounds("pose", [1], ["px"], np.nan, 2.0)
    with pytest.raises(InputError, match="unknown pose component"):
        problem.fix("pose", [0], ["qx"])
    problem.pose_lower[2, 4] = 1.0
    problem.pose_upper[2, 4] = 0.0
    with pytest.raises(InputError, match="pose 2 py: lower bound 1 > upper bound 0"):
        solve(problem)

    # a point observed by a single camera: all but one of point 6's observations dropped
    keep = (a["point_index"] != 6) | (a["camera_index"] == a["camera_index"][a["point_index"] == 6][0])
    lone = {k: (v[keep] if k in ("observations_px", "camera_index", "point_index") else v) for k, v in a.items()}
    problem = BundleProblem(**lone)
    with pytest.raises(InputError, match=r"point 6 is observed by 1 camera"):
        solve(problem)
    problem.fix("point", [6])  # once fixed, a single view is fine
    assert solve(problem, SolverOptions(max_iterations=2)).final_cost < 1e-12  # noise-free: at the minimum

    with pytest.raises(InputError, match="loss must be one of"):
        SolverOptions(loss="l1")
    with pytest.raises(InputError, match="max_iterations"):
        SolverOptions(max_iterations=-1)
    with pytest.raises(InputError, match="loss_scale_px"):
        SolverOptions(loss="huber", loss_scale_px=0.0)
    with pytest.raises(InputError, match="shell"):
        BundleProblem(**a).bound_points_to_shell([0, 0, 0], 5.0, 1.0)


def test_from_measured_poses_bounds_are_measured_plus_minus_tolerance():
    scene = make_scene(4, 30, seed=19)
    tol = PoseTolerance.from_degrees([0.25, 0.25, 0.5], [0.0, 1.0, np.inf])
    measured = [MeasuredPose(Pose(r, t), tol) for r, t in zip(scene.rotations, scene.translations)]
    problem = BundleProblem.from_measured_poses(measured, scene.intrinsics, scene.points, scene.observations_px,
                                                scene.camera_index, scene.point_index, refine_intrinsics=["fx", "fy"])
    np.testing.assert_allclose(problem.pose_upper[:, 3:] - problem.initial.pose[:, 3:], [[0.25, 0.25, 0.5]] * 4)
    np.testing.assert_allclose(problem.initial.pose[:, 3:], scene.centres)
    assert problem.pose_fixed[:, 0].all() and not problem.pose_fixed[:, 1:].any()
    np.testing.assert_allclose(problem.pose_upper[:, 1], np.deg2rad(1.0))
    assert np.isinf(problem.pose_upper[:, 2]).all()
    assert problem.intrinsics_fixed[0].tolist() == [False, False, True, True, True, True]
    # the rotation parameter is a left perturbation of the measured orientation
    x = problem.initial.copy()
    x.pose[:, 1] = 0.01
    rot = problem.camera_state(x.pose)[0]
    np.testing.assert_allclose(rot[0], rotvec_to_matrix([0, 0.01, 0]) @ scene.rotations[0], atol=1e-15)


def test_parallel_schur_assembly_matches_serial():
    scene = make_scene(12, 4000, seed=20, pixel_noise_px=0.5)
    problem = scene_problem(scene)
    problem.initial = perturbed(problem, 21)
    problem.fix("pose", [0])
    serial = solve(problem, SolverOptions(max_iterations=4, num_threads=1))
    parallel = solve(problem, SolverOptions(max_iterations=4, num_threads=2))
    assert serial.threads == 1 and parallel.threads == 2
    assert parallel.final_cost == pytest.approx(serial.final_cost, rel=1e-10)
    np.testing.assert_allclose(parallel.points_world, serial.points_world, rtol=0, atol=1e-9)
