"""Relative poses, rotation and position averaging, and the gauge fit, on synthetic scenes with known truth.

Bounds come from the construction: exact data must be recovered to numerical precision (the averaging is
a Gauss-Newton solve that converges to the exact solution), noisy data to a few sigma of the noise put in.
"""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.estimators.averaging import (
    RelativePose,
    average_positions,
    average_rotations,
    positions_from_points,
    refine_relative_pose,
    relative_pose,
)
from scope3d.estimators.gauge import gauge_from_measurements
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at, matrix_to_rotvec, rotation_angle_between, rotvec_to_matrix
from scope3d.geometry.similarity import Similarity
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance, perturb_poses_uniform


def _grid_poses(n_side: int = 4, spacing: float = 5.0, height: float = 15.0) -> list[Pose]:
    """Cameras on a planar grid above the origin, looking down at a point below the grid's centre."""
    poses = []
    for x in np.arange(n_side) * spacing - spacing * (n_side - 1) / 2:
        for y in np.arange(n_side) * spacing - spacing * (n_side - 1) / 2:
            c = np.array([x, y, height])
            poses.append(Pose.from_centre(look_at(c, np.array([0.3 * x, 0.3 * y, 0.0])), c))
    return poses


def _exact_pairs(poses: list[Pose], sigma: float = 1e-3) -> list[RelativePose]:
    out = []
    for i in range(len(poses)):
        for j in range(i + 1, len(poses)):
            if np.linalg.norm(poses[i].centre - poses[j].centre) < 8.0:
                R = poses[j].rotation @ poses[i].rotation.T
                t = poses[j].translation - R @ poses[i].translation
                out.append(RelativePose(i, j, R, t / np.linalg.norm(t), np.ones(1, bool), sigma, sigma))
    return out


def test_relative_pose_recovers_a_known_pose_from_noisy_matches():
    rng = np.random.default_rng(3)
    camera = Camera.from_fov(400, 400, 53.0)
    pose_i, pose_j = _grid_poses(2)[0], _grid_poses(2)[1]
    X = np.c_[rng.uniform(-6, 6, (300, 2)), rng.uniform(-2, 2, 300)]
    noise = 0.3
    px_i = camera.project_world(pose_i, X) + rng.normal(0, noise, (300, 2))
    px_j = camera.project_world(pose_j, X) + rng.normal(0, noise, (300, 2))
    ok = camera.in_image(px_i) & camera.in_image(px_j)
    rel = relative_pose(camera, px_i[ok], px_j[ok], threshold_px=4 * noise, noise_px=noise)
    R_true = pose_j.rotation @ pose_i.rotation.T
    t_true = pose_j.translation - R_true @ pose_i.translation
    assert rel is not None and rel.n_inliers > 0.95 * ok.sum()
    # within 4 sigma of the estimate's own (covariance-derived) uncertainty
    assert rotation_angle_between(rel.rotation, R_true) < 4 * rel.rotation_sigma_rad
    angle = np.arccos(np.clip(rel.direction @ t_true / np.linalg.norm(t_true), -1, 1))
    assert angle < 4 * rel.direction_sigma_rad
    assert rel.rotation_sigma_rad < np.deg2rad(0.5)


def _noisy_pair_rays(seed: int, noise_px: float = 0.3, n: int = 300, outliers: float = 0.0):
    """Normalised rays (M, 2) each of two grid cameras seeing a bumpy patch, with pixel noise and a
    fraction ``outliers`` of the matches replaced by random pixels, and the true (R_ji, unit t_ji)."""
    rng = np.random.default_rng(seed)
    camera = Camera.from_fov(400, 400, 53.0)
    pose_i, pose_j = _grid_poses(2)[0], _grid_poses(2)[1]
    X = np.c_[rng.uniform(-6, 6, (n, 2)), rng.uniform(-2, 2, n)]
    px_i = camera.project_world(pose_i, X) + rng.normal(0, noise_px, (n, 2))
    px_j = camera.project_world(pose_j, X) + rng.normal(0, noise_px, (n, 2))
    wrong = rng.random(n) < outliers
    px_j[wrong] = rng.uniform(0, 400, (wrong.sum(), 2))
    ok = camera.in_image(px_i) & camera.in_image(px_j)
    R = pose_j.rotation @ pose_i.rotation.T
    t = pose_j.translation - R @ pose_i.translation
    return camera, camera.pixel_to_normalised(px_i[ok]), camera.pixel_to_normalised(px_j[ok]), R, t / np.linalg.norm(t)


def test_relative_pose_refinement_jacobian_matches_finite_differences():
    from scipy.optimize._numdiff import approx_derivative

    from scope3d.estimators.averaging import _RelativePoseModel

    camera, xi, xj, R, t = _noisy_pair_rays(5, outliers=0.1)  # outliers: residuals far into the loss's tail
    start_R = rotvec_to_matrix([0.02, -0.03, 0.01]) @ R
    model = _RelativePoseModel(xi, xj, start_R, t + [0.05, 0.0, -0.05])
    rng = np.random.default_rng(6)
    for x in (np.zeros(5), rng.normal(0, 0.05, 5)):  # at the start and away from it (J_l(w) != I there)
        analytic = model.jacobian(x)
        numeric = approx_derivative(model.residuals, x, method="3-point")
        # central differences err by ~h^2 |f'''| + eps |f| / h with h ~ eps^(1/3) ~ 6e-6: ~1e-10 for
        # distances and derivatives of order 1 (rays within ~0.5 of the axis); 1e-7 leaves room for f''' ~ 1e3
        assert np.abs(analytic - numeric).max() < 1e-7 * max(1.0, np.abs(numeric).max())


def test_relative_pose_refinement_reaches_the_finite_difference_minimum():
    """The analytic Jacobian changes the path, not the minimum: the pose equals the one least squares
    reaches on finite differences (the code before the analytic Jacobian) to far below its own sigma."""
    from scipy.optimize import least_squares

    from scope3d.estimators.averaging import _refine_relative_pose, _RelativePoseModel

    camera, xi, xj, R, t = _noisy_pair_rays(7)  # inliers only, as relative_pose refines
    scale = 1.2 / camera.fx  # the inlier threshold, normalised
    # a start as far off as RANSAC's minimal-sample models on short baselines (a few tenths of a degree)
    start_R, start_t = rotvec_to_matrix([0.003, 0.004, -0.002]) @ R, t + [0.02, -0.01, 0.0]
    R_fit, t_fit, cov = _refine_relative_pose(xi, xj, start_R, start_t, scale)
    model = _RelativePoseModel(xi, xj, start_R, start_t)
    numeric = least_squares(model.residuals, np.zeros(5), loss="soft_l1", f_scale=scale, x_scale=1e-2, max_nfev=50)
    R_num, t_num, _ = model.pose(numeric.x)
    sigma_rot = 0.3 / camera.fx * np.sqrt(np.linalg.eigvalsh(cov[:3, :3]).max())  # 0.3 px noise
    sigma_dir = 0.3 / camera.fx * np.sqrt(np.linalg.eigvalsh(cov[3:, 3:]).max())
    # both stop when the cost changes by less than 1e-8 of itself; near the minimum the cost is quadratic,
    # so the poses may differ by ~sqrt(1e-8) = 1e-4 of a sigma; 1e-2 sigma is still nothing to a user
    assert np.linalg.norm(matrix_to_rotvec(R_fit.T @ R_num)) < 1e-2 * sigma_rot
    assert np.linalg.norm(np.cross(t_fit, t_num)) < 1e-2 * sigma_dir
    # and the minimum is the truth to within the noise (4 sigma)
    assert np.linalg.norm(matrix_to_rotvec(R_fit.T @ R)) < 4 * sigma_rot


def test_averaging_exact_pairs_recovers_the_shape_and_the_measurements_fix_the_gauge():
    truth = _grid_poses()
    measured = perturb_poses_uniform(truth, 2.0, np.deg2rad(1.0), seed=4)
    pairs = _exact_pairs(truth)
    rotations, residual = average_rotations(measured, pairs)
    # the linearisation drops second-order terms in the deviation from the measurement (<= 1 deg per
    # axis here), so exact pairs are met to that order, (sqrt(3) * 1 deg)^2 ~ 1e-3 rad
    second_order = 3 * np.deg2rad(1.0) ** 2
    assert residual.max() < second_order
    # the relative rotations are exact, so only a common rotation (the gauge) may remain
    common = [rotations[k].T @ truth[k].rotation for k in range(len(truth))]
    assert max(rotation_angle_between(common[0], c) for c in common) < second_order
    # and it is what the measured orientations say on average: within 3 sigma of their mean error
    mean_err = np.deg2rad(1.0) / np.sqrt(3) / np.sqrt(len(truth))
    assert rotation_angle_between(common[0], np.eye(3)) < 3 * np.sqrt(3) * mean_err
    centres, used = average_positions(measured, np.stack([p.rotation for p in truth]), pairs)
    assert used.all()
    fit = gauge_from_measurements([Pose.from_centre(p.rotation, c) for p, c in zip(truth, centres)],
                                  [MeasuredPose(p) for p in truth])
    shape_error = np.linalg.norm(fit.apply(centres) - np.stack([p.centre for p in truth]), axis=1)
    # exact directions are soft constraints (sigma 1e-3 rad on baselines <= 8 mm) balanced against the
    # priors (sigma 1.2 mm): they must hold to a small fraction of their own sigma
    assert shape_error.max() < 0.1 * 1e-3 * 8.0


def test_averaging_downweights_a_wrong_pair():
    truth = _grid_poses()
    measured = perturb_poses_uniform(truth, 1.0, np.deg2rad(0.5), seed=5)
    pairs = _exact_pairs(truth, sigma=np.deg2rad(0.05))
    bad = pairs[3]
    pairs[3] = RelativePose(bad.i, bad.j, rotvec_to_matrix([0.0, 0.3, 0.0]) @ bad.rotation, -bad.direction,
                            bad.inliers, bad.rotation_sigma_rad, bad.direction_sigma_rad)
    rotations, residual = average_rotations(measured, pairs)
    assert residual[3] > 0.25  # the wrong pair keeps its disagreement ...
    others = np.delete(residual, 3)
    assert others.max() < np.deg2rad(0.1)  # ... instead of spreading it over the others
    _, used = average_positions(measured, rotations, pairs)
    assert not used[3] and used.sum() >= len(pairs) - 2


def _row_of_cameras_and_tracks(noise_px: float, seed: int):
    """Six cameras in a row 2 mm apart looking down at points 13-17 mm below, and every point's
    observations (pixels, with Gaussian noise) in the cameras that see it."""
    rng = np.random.default_rng(seed)
    camera = Camera(width=600, height=600, fx=500.0, fy=500.0, cx=300.0, cy=300.0)
    centres = np.c_[np.arange(6) * 2.0, np.zeros(6), np.zeros(6)]
    rotations = np.stack([np.diag([1.0, -1.0, -1.0])] * 6)  # optical axes along -z
    points = np.c_[rng.uniform(-3, 13, 300), rng.uniform(-5, 5, 300), rng.uniform(-17, -13, 300)]
    track, frame, pixels = [], [], []
    for p, x in enumerate(points):
        for k in range(6):
            uv = camera.project((rotations[k] @ (x - centres[k]))[None])[0]
            if camera.in_image(uv[None])[0]:
                track.append(p), frame.append(k), pixels.append(uv + rng.normal(0, noise_px, 2))
    _, track = np.unique(track, return_inverse=True)
    tracks = Tracks(track, np.array(frame), np.zeros(len(track), np.int64), np.array(pixels),
                    np.zeros((track.max() + 1, 3), np.uint8))
    return camera, rotations, centres, tracks


@pytest.mark.parametrize("noise_px", [0.0, 0.5])
def test_positions_from_points_space_cameras_in_a_row(noise_px):
    """Baseline directions cannot space cameras along a line (every direction is the same); shared points
    can. From a start 1 mm off per axis and measurements 1 mm off, the row's shape must come out to the
    precision of the rays, and its scale and place from the measurements."""
    camera, rotations, centres, tracks = _row_of_cameras_and_tracks(noise_px, seed=3)
    rng = np.random.default_rng(4)
    measured = [MeasuredPose(Pose.from_centre(R, c + rng.uniform(-1, 1, 3)), PoseTolerance.from_degrees(1.0, 0.5))
                for R, c in zip(rotations, centres)]
    start = centres + rng.uniform(-1, 1, centres.shape)
    out, solved = positions_from_points(camera, measured, rotations, start, tracks)
    assert solved.all()
    a, b = out - out.mean(axis=0), centres - centres.mean(axis=0)
    scale = float(np.sum(a * b) / np.sum(a * a))
    shape_error = np.linalg.norm(scale * a - b, axis=1).max()
    if noise_px == 0:
        assert shape_error < 1e-6
    else:
        # ~100 points per camera at 15 mm, 0.5 px at f = 500: a centre is fixed to about
        # 15 mm * 1e-3 rad / sqrt(100) = 1.5 um per axis; 20 um is ten sigma of the worst of six
        assert shape_error < 0.02
    # the measurements (uniform 1 mm per axis: sigma 1 / sqrt 3) fix the scale along the row to
    # sigma / sqrt(sum of squared offsets from the middle), within 3 sigma
    sigma_scale = (1 / np.sqrt(3)) / np.sqrt(np.sum(b[:, 0] ** 2))
    assert abs(1 / scale - 1.0) < 3 * sigma_scale
    # and the place: the mean centre to sigma = (1 / sqrt 3) / sqrt 6 = 0.24 mm per axis, within 4 sigma
    assert np.abs(out.mean(axis=0) - centres.mean(axis=0)).max() < 4 * 0.24


def test_positions_from_points_leave_frames_with_no_shared_points_at_their_start():
    camera, rotations, centres, tracks = _row_of_cameras_and_tracks(0.0, seed=3)
    alone = tracks.subset(tracks.frame != 5)
    measured = [MeasuredPose(Pose.from_centre(R, c), PoseTolerance.from_degrees(1.0, 0.5))
                for R, c in zip(rotations, centres)]
    start = centres + 0.5
    out, solved = positions_from_points(camera, measured, rotations, start, alone)
    assert solved[:5].all() and not solved[5]
    np.testing.assert_array_equal(out[5], start[5])


@pytest.mark.parametrize("scale", [0.9, 1.0, 1.1])
def test_gauge_fit_recovers_a_known_similarity_on_a_planar_trajectory(scale):
    """On a planar grid the centres alone leave the tilt to noise; the orientations fix it."""
    truth = _grid_poses()
    sim = Similarity(scale, rotvec_to_matrix([0.02, -0.03, 0.5]), np.zeros(3), np.array([3.0, -2.0, 1.0]))
    moved = [Pose(*sim.apply_to_cam_from_world(p.rotation, p.translation)) for p in truth]
    measured = [MeasuredPose(p, PoseTolerance(np.full(3, 0.5), np.full(3, np.deg2rad(0.5)))) for p in truth]
    back = gauge_from_measurements(moved, measured)
    restored = [Pose(*back.apply_to_cam_from_world(p.rotation, p.translation)) for p in moved]
    for p, t in zip(restored, truth):
        assert np.linalg.norm(p.centre - t.centre) < 1e-6
        assert rotation_angle_between(p.rotation, t.rotation) < 1e-8


def test_similarity_fraction_runs_from_identity_to_the_whole():
    sim = Similarity(1.2, rotvec_to_matrix([0.1, 0.2, -0.3]), np.array([1.0, 2.0, 3.0]), np.array([0.0, -1.0, 5.0]))
    X = np.random.default_rng(0).normal(size=(10, 3))
    assert np.allclose(sim.fraction(0.0).apply(X), X)
    assert np.allclose(sim.fraction(1.0).apply(X), sim.apply(X))


def test_positions_from_points_solve_two_groups_that_share_no_point():
    """Two rows of cameras whose tracks never meet are two rigid groups: each is solved on its own (its
    shape from its rays), and the other group's points must not enter its solve (they made it singular)."""
    camera, rotations, centres, tracks = _row_of_cameras_and_tracks(0.0, seed=3)
    second = Tracks(tracks.track + tracks.n_tracks, tracks.frame + 6, tracks.feature, tracks.pixels, tracks.colors)
    both = Tracks(np.r_[tracks.track, second.track], np.r_[tracks.frame, second.frame],
                  np.r_[tracks.feature, second.feature], np.r_[tracks.pixels, second.pixels],
                  np.r_[tracks.colors, second.colors])
    all_rotations = np.r_[rotations, rotations]
    all_centres = np.r_[centres, centres + [0.0, 40.0, 0.0]]  # the second row 40 mm aside
    measured = [MeasuredPose(Pose.from_centre(R, c), PoseTolerance.from_degrees(1.0, 0.5))
                for R, c in zip(all_rotations, all_centres)]
    start = all_centres + np.random.default_rng(5).uniform(-0.5, 0.5, all_centres.shape)
    out, solved = positions_from_points(camera, measured, all_rotations, start, both)
    assert solved.all()
    # exact rays and exact measurements: both rows come back exactly (to the solver's round-off)
    np.testing.assert_allclose(out, all_centres, atol=1e-6)


def test_refinement_from_a_start_degrees_off_needs_its_first_inliers_selected_wide():
    """A start 5 deg off (the bearings' rotation of a scope turning inside a cavity is off by the parallax)
    puts 40 right matches tens of pixels off: selected at the 1.5 px threshold, fewer than eight are inliers
    and the refinement gives up; selected within the start's error and narrowed, it reaches the truth."""
    camera, xi, xj, R, t = _noisy_pair_rays(3, n=40)
    px_i, px_j = (camera.project(np.c_[x, np.ones(len(x))]) for x in (xi, xj))
    start = rotvec_to_matrix([0.0, np.deg2rad(5.0), 0.0]) @ R
    tight = refine_relative_pose(camera, px_i, px_j, start, t, threshold_px=1.5, noise_px=0.3)
    assert tight is None
    # 5 deg of a 400 px / 53 deg field is ~35 px: a start error of f tan(6 deg) covers it
    wide = refine_relative_pose(camera, px_i, px_j, start, t, threshold_px=1.5, noise_px=0.3,
                                start_error_px=camera.fx * np.tan(np.deg2rad(6.0)))
    assert wide is not None and wide.n_inliers >= 0.9 * len(px_i)
    # the truth within 4 of the estimate's own sigmas (0.3 px noise)
    assert rotation_angle_between(wide.rotation, R) < 4 * wide.rotation_sigma_rad
    assert np.arccos(np.clip(wide.direction @ t, -1, 1)) < 4 * wide.direction_sigma_rad
