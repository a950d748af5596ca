import numpy as np
import pytest

from scope3d.geometry.pose import Pose
from scope3d.sensor.camera import Camera, focal_from_fov, fov_from_focal, project_with_jacobians


def _scene(seed=0, n=40):
    rng = np.random.default_rng(seed)
    points = rng.uniform([-8, -8, 12], [8, 8, 25], size=(n, 3))
    rotvecs = rng.normal(scale=0.3, size=(n, 3))
    translations = rng.normal(scale=1.0, size=(n, 3))
    # keep points in front: express in camera, then shift world points accordingly
    from scope3d.geometry.rotation import rotvec_to_matrix

    r = rotvec_to_matrix(rotvecs)
    world = np.einsum("nji,nj->ni", r, points - translations)
    intr = np.array([500.0, 510.0, 303.5, 300.0, -0.12, 0.03])
    return world, rotvecs, translations, intr


def _numeric(f, x, eps=1e-6):
    cols = []
    for k in range(x.shape[-1]):
        dx = np.zeros_like(x)
        dx[..., k] = eps
        cols.append((f(x + dx) - f(x - dx)) / (2 * eps))
    return np.stack(cols, axis=-1)


def test_jacobians_match_finite_differences():
    world, rv, t, intr = _scene()
    n = len(world)
    _, j_pt, j_pose, j_intr = project_with_jacobians(world, rv, t, intr)
    intr_n = np.tile(intr, (n, 1))
    num_pt = _numeric(lambda x: project_with_jacobians(x, rv, t, intr_n)[0], world)
    num_rv = _numeric(lambda x: project_with_jacobians(world, x, t, intr_n)[0], rv)
    num_t = _numeric(lambda x: project_with_jacobians(world, rv, x, intr_n)[0], t)
    num_in = _numeric(lambda x: project_with_jacobians(world, rv, t, x)[0], intr_n)
    np.testing.assert_allclose(j_pt, num_pt, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(j_pose[:, :, :3], num_rv, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(j_pose[:, :, 3:], num_t, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(j_intr, num_in, rtol=1e-5, atol=1e-4)


def test_jacobian_at_zero_rotation_is_finite_and_correct():
    world, _, t, intr = _scene(1, 5)
    rv = np.zeros((5, 3))
    _, _, j_pose, _ = project_with_jacobians(world, rv, t, intr)
    num = _numeric(lambda x: project_with_jacobians(world, x, t, np.tile(intr, (5, 1)))[0], rv)
    np.testing.assert_allclose(j_pose[:, :, :3], num, rtol=1e-5, atol=1e-4)


def test_project_matches_batched_projection_and_opencv():
    import cv2

    world, rv, t, intr = _scene(2, 10)
    cam = Camera.from_intrinsics(608, 608, intr)
    pix, *_ = project_with_jacobians(world, rv, t, intr)
    for i in range(3):
        pose = Pose.from_rotvec(rv[i], t[i])
        np.testing.assert_allclose(cam.project_world(pose, world[i : i + 1])[0], pix[i], atol=1e-9)
        ocv, _ = cv2.projectPoints(world[i : i + 1], rv[i], t[i], cam.K, cam.distortion_coeffs)
        np.testing.assert_allclose(ocv.reshape(2), pix[i], atol=1e-6)


def test_project_unproject_round_trip():
    cam = Camera.from_fov(608, 608, 60.0, k1=-0.2, k2=0.05, mask_radius_px=300)
    rng = np.random.default_rng(3)
    pix = rng.uniform(10, 598, size=(500, 2))
    depth = rng.uniform(5, 40, size=500)
    pts = cam.unproject(pix, depth)
    np.testing.assert_allclose(pts[:, 2], depth)
    np.testing.assert_allclose(cam.project(pts), pix, atol=1e-8)


def test_distort_undistort_round_trip():
    cam = Camera.from_fov(608, 608, 70.0, k1=-0.25, k2=0.08)
    xy = np.random.default_rng(4).uniform(-0.6, 0.6, size=(1000, 2))
    np.testing.assert_allclose(cam.undistort(cam.distort(xy)), xy, atol=1e-11)


def test_fov_focal_round_trip_and_mask():
    f = focal_from_fov(608, 53.0)
    assert fov_from_focal(608, f) == pytest.approx(53.0)
    cam = Camera.from_fov(608, 608, 53.0, mask_radius_px=300)
    assert cam.fov_deg == pytest.approx(53.0)
    m = cam.mask()
    assert m.shape == (608, 608) and m[304, 304] and not m[0, 0]
    assert m.sum() == pytest.approx(np.pi * 300**2, rel=0.01)


def test_points_behind_camera_are_nan():
    cam = Camera.from_fov(100, 100, 60)
    out = cam.project(np.array([[0.0, 0.0, -5.0], [0.0, 0.0, 5.0]]))
    assert np.all(np.isnan(out[0])) and np.allclose(out[1], [49.5, 49.5])


@pytest.mark.parametrize(
    "kwargs",
    [dict(fx=-1.0), dict(fx=float("nan")), dict(width=0), dict(mask_radius_px=-3.0)],
)
def test_bad_intrinsics_raise(kwargs):
    base = dict(width=10, height=10, fx=5.0, fy=5.0, cx=4.5, cy=4.5)
    base.update(kwargs)
    with pytest.raises(ValueError):
        Camera(**base)


def test_nearest_pixels_keeps_the_points_in_view():
    camera = Camera.from_fov(64, 48, 60.0)
    pose = Pose.identity()
    inside = camera.unproject(np.array([[10.2, 20.7], [0.0, 0.0]]), 5.0)
    behind = np.array([[0.0, 0.0, -5.0]])
    outside = camera.unproject(np.array([[80.0, 20.0]]), 5.0)
    idx, ij, z = camera.nearest_pixels(pose, np.concatenate([inside, behind, outside]))
    np.testing.assert_array_equal(idx, [0, 1])
    np.testing.assert_array_equal(ij, [[10, 21], [0, 0]])
    np.testing.assert_allclose(z, 5.0)
