import numpy as np
import pytest

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import (
    look_at,
    matrix_to_rotvec,
    rotation_angle_between,
    rotvec_to_matrix,
    so3_left_jacobian,
)
from scope3d.sensor.pose_tolerance import (
    MeasuredPose,
    PoseTolerance,
    perturb_poses_biased,
    perturb_poses_drift,
    perturb_poses_uniform,
)


def test_rotvec_matrix_quaternion_round_trips():
    rng = np.random.default_rng(0)
    rv = rng.normal(size=(50, 3))
    rv *= np.minimum(1.0, 3.0 / np.linalg.norm(rv, axis=1))[:, None]
    r = rotvec_to_matrix(rv)
    np.testing.assert_allclose(matrix_to_rotvec(r), rv, atol=1e-9)
    for i in range(5):
        p = Pose(r[i], rng.normal(size=3))
        q = Pose.from_quaternion(p.quaternion, p.translation)
        np.testing.assert_allclose(q.rotation, p.rotation, atol=1e-12)


# Each entry of R_a^T (R_a E) carries the rounding of two 3-term products of numbers <= 1 (at most
# ~6 eps, Higham's gamma_3 twice); the angle reads the skew part (two entries' difference, three of them,
# halved) and the trace: |error| <= ~sqrt(3) * 12 eps / 2 + rounding of atan2 < 16 eps. 32 eps leaves 2x.
ANGLE_RESOLUTION_RAD = 32 * np.finfo(float).eps


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-10, 3e-9, 1e-8, 2e-8, 1e-6, 1e-3, 0.5, 2.0,
                                   np.pi - 1e-3, np.pi - 1e-8, np.pi - 1e-12, np.pi])
def test_angle_between_rotations_is_exact_near_zero_and_pi(angle):
    """arccos((trace - 1) / 2) read every angle below ~2e-8 rad as 0 or 2.1e-8 (issue 30)."""
    rng = np.random.default_rng(5)
    for _ in range(20):
        r_a = rotvec_to_matrix(rng.normal(size=3))
        axis = rng.normal(size=3)
        r_b = r_a @ rotvec_to_matrix(angle * axis / np.linalg.norm(axis))
        assert abs(rotation_angle_between(r_a, r_b) - angle) <= ANGLE_RESOLUTION_RAD
        assert abs(rotation_angle_between(r_b, r_a) - angle) <= ANGLE_RESOLUTION_RAD


def test_angle_between_a_rotation_and_itself_computed_two_ways_is_zero_to_rounding():
    """The same rotation from two association orders of a product differs in the last bits only."""
    rng = np.random.default_rng(6)
    a, b, c = rotvec_to_matrix(rng.normal(size=(3, 50, 3)))
    angles = rotation_angle_between((a @ b) @ c, a @ (b @ c))
    assert angles.shape == (50,)
    assert np.all(angles <= ANGLE_RESOLUTION_RAD)


def test_left_jacobian_is_derivative_of_exp():
    rv = np.array([0.3, -1.1, 0.7])
    d = 1e-7 * np.array([1.0, 2.0, -1.5])
    lhs = rotvec_to_matrix(rv + d)
    rhs = rotvec_to_matrix(so3_left_jacobian(rv) @ d) @ rotvec_to_matrix(rv)
    np.testing.assert_allclose(lhs, rhs, atol=1e-12)


def test_compose_inverse_centre():
    a = Pose.from_rotvec([0.1, 0.2, -0.3], [1.0, 2.0, 3.0])
    b = Pose.from_rotvec([-0.4, 0.0, 0.2], [0.5, -1.0, 4.0])
    ident = a @ a.inverse()
    np.testing.assert_allclose(ident.matrix, np.eye(4), atol=1e-12)
    np.testing.assert_allclose((a @ b).matrix, a.matrix @ b.matrix, atol=1e-12)
    np.testing.assert_allclose(a.transform(a.centre[None])[0], 0.0, atol=1e-12)


def test_interpolate_endpoints_and_midpoint():
    a = Pose.from_centre(np.eye(3), [0, 0, 0])
    b = Pose.from_centre(rotvec_to_matrix([0, 0, 0.5]), [2, 0, 0])
    np.testing.assert_allclose(a.interpolate(b, 0.0).matrix, a.matrix, atol=1e-12)
    np.testing.assert_allclose(a.interpolate(b, 1.0).matrix, b.matrix, atol=1e-12)
    mid = a.interpolate(b, 0.5)
    np.testing.assert_allclose(mid.centre, [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(mid.rotvec, [0, 0, 0.25], atol=1e-12)


def test_look_at_points_optical_axis_at_target():
    r = look_at(np.array([0.0, 0.0, 15.0]), np.zeros(3))
    pose = Pose.from_centre(r, [0, 0, 15])
    np.testing.assert_allclose(pose.transform(np.zeros((1, 3)))[0], [0, 0, 15], atol=1e-12)


def test_uniform_noise_stays_inside_tolerance_and_is_seeded():
    truth = [Pose.from_centre(np.eye(3), [i * 5.0, 0, 15]) for i in range(20)]
    m1 = perturb_poses_uniform(truth, 0.25, np.deg2rad(0.5), seed=7)
    m2 = perturb_poses_uniform(truth, 0.25, np.deg2rad(0.5), seed=7)
    assert all(m.contains(t) for m, t in zip(m1, truth))
    assert all(np.allclose(a.pose.matrix, b.pose.matrix) for a, b in zip(m1, m2))
    errs = np.array([m.pose.centre - t.centre for m, t in zip(m1, truth)])
    assert np.abs(errs).max() <= 0.25 and np.abs(errs).max() > 0.1


def test_biased_and_drift_noise_models():
    truth = [Pose.from_centre(np.eye(3), [i * 5.0, 0, 15]) for i in range(10)]
    biased = perturb_poses_biased(truth, [2.0, -1.0, 0.5], [0.02, 0, 0], 0.3, 0.005, seed=1)
    errs = np.array([m.pose.centre - t.centre for m, t in zip(biased, truth)])
    np.testing.assert_allclose(errs.mean(axis=0), [2.0, -1.0, 0.5], atol=0.3)
    assert all(m.contains(t) for m, t in zip(biased, truth))
    drift = perturb_poses_drift(truth, [0.1, 0, 0])
    np.testing.assert_allclose(drift[9].pose.centre - truth[9].centre, [0.9, 0, 0], atol=1e-12)
    assert all(m.contains(t) for m, t in zip(drift, truth))


def test_bad_poses_and_tolerances_raise():
    with pytest.raises(ValueError):
        Pose(np.eye(3) * 2, np.zeros(3))
    with pytest.raises(ValueError):
        Pose(np.eye(3), [np.nan, 0, 0])
    with pytest.raises(ValueError):
        PoseTolerance([-1, 0, 0], 0)
    assert MeasuredPose(Pose.identity()).tolerance.is_exact
