"""Pairwise pose covariances after an adjustment (what narrows the guided matcher's windows)."""
from __future__ import annotations

import numpy as np

from scope3d.estimators.bundle import BundleProblem
from scope3d.estimators.bundle.covariance import marginal_sigmas, pairwise_pose_covariances
from scope3d.geometry.pose import Pose
from scope3d.phantoms.bundle_scene import make_scene
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance

TOL_MM, TOL_RAD = 0.5, 0.01
NOISE_PX = 0.3


def _problem(scene, keep):
    measured = [MeasuredPose(Pose(r, t), PoseTolerance(np.full(3, TOL_MM), np.full(3, TOL_RAD)))
                for r, t in zip(scene.rotations, scene.translations)]
    return BundleProblem.from_measured_poses(measured, scene.intrinsics, scene.points, scene.observations_px[keep],
                                             scene.camera_index[keep], scene.point_index[keep], refine_intrinsics=False)


def _prior(m):
    return np.tile(np.r_[np.full(3, TOL_RAD), np.full(3, TOL_MM)] / np.sqrt(3.0), (m, 1))


def test_a_loose_camera_does_not_loosen_the_others():
    """Camera 0 keeps 6 observations; cameras 3 and 4 share ~150 points. With the measured boxes as priors the
    pair (3, 4) is as well fixed as when camera 0 is fully observed (within 10 %; the minimum-norm gauge spread
    a loose camera's freedom over every pair). The pair (0, 1) loses information, so its sigmas can only grow,
    and never beyond what the two priors alone allow."""
    scene = make_scene(8, 300, observations_per_point=4, seed=3)
    every = np.ones(len(scene.camera_index), bool)
    loose = every.copy()
    loose[np.flatnonzero(scene.camera_index == 0)[6:]] = False
    pairs = [(0, 1), (3, 4)]
    sig = {}
    for name, keep in (("full", every), ("loose", loose)):
        problem = _problem(scene, keep)
        cov = pairwise_pose_covariances(problem, problem.initial, pairs, noise_px=NOISE_PX,
                                        prior_sigmas=_prior(problem.num_cameras))
        sig[name] = np.sqrt(np.einsum("kii->ki", cov))  # (pairs, 6) sigmas: w (rad), centre (mm)
    np.testing.assert_allclose(sig["loose"][1], sig["full"][1], rtol=0.1)
    assert np.all(sig["loose"][0] >= sig["full"][0]) and np.any(sig["loose"][0] > 2.0 * sig["full"][0])
    prior_pair = np.sqrt(2.0) * np.r_[np.full(3, TOL_RAD), np.full(3, TOL_MM)] / np.sqrt(3.0)
    assert np.all(sig["loose"][0] <= prior_pair + 1e-12)


def test_pair_covariance_shrinks_with_the_keypoint_noise():
    """The covariance is the inverse of the images' information scaled by the noise: halving the keypoint
    noise must shrink the images' part, so the posterior sigmas shrink (the priors' part cannot grow)."""
    scene = make_scene(6, 200, observations_per_point=4, seed=5)
    problem = _problem(scene, np.ones(len(scene.camera_index), bool))
    a = pairwise_pose_covariances(problem, problem.initial, [(2, 3)], noise_px=NOISE_PX, prior_sigmas=_prior(6))
    b = pairwise_pose_covariances(problem, problem.initial, [(2, 3)], noise_px=NOISE_PX / 2, prior_sigmas=_prior(6))
    assert np.all(np.diag(b[0]) < np.diag(a[0]))
    assert np.all(np.linalg.eigvalsh(a[0]) > 0)


def test_marginal_sigmas_match_the_inverse_and_stay_finite_or_inf_when_the_information_is_singular():
    """A well-conditioned information gives the inverse's diagonal; a nearly singular one (a camera the
    images leave free along one direction, in mm and rad at once) gives inf for the parameters on that
    direction and the exact marginal for the others, never NaN from round-off in the inverse."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(12, 12))
    information = a @ a.T + np.eye(12)
    np.testing.assert_allclose(marginal_sigmas(information), np.sqrt(np.diag(np.linalg.inv(information))), rtol=1e-9)

    # parameters 0-1 are fixed only in their sum (a rank-1 block); 2-3 independently, on scales 1e6 apart
    scale = np.array([1.0, 1.0, 1e3, 1e-3])
    block = np.array([[1.0, 1.0, 0, 0], [1.0, 1.0, 0, 0], [0, 0, 4.0, 0], [0, 0, 0, 9.0]])
    singular = block * np.outer(scale, scale)
    sigmas = marginal_sigmas(singular)
    assert not np.isnan(sigmas).any()
    assert np.isinf(sigmas[:2]).all()
    np.testing.assert_allclose(sigmas[2:], [0.5 / 1e3, 1.0 / 3 / 1e-3], rtol=1e-9)
    assert np.isinf(marginal_sigmas(np.zeros((3, 3)))).all()
