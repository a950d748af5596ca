"""Camera models (issue 32): analytic Jacobians, project/unproject identity over each model's field, and
parity with pycolmap and OpenCV on the same parameters."""
import cv2
import numpy as np
import pycolmap
import pytest

from scope3d.geometry.pose import Pose
from scope3d.sensor.camera import Camera
from scope3d.sensor.camera_models import MODELS, lens_model, opencv_distortion, project_world_with_jacobians

W, H = 640, 480
# Parameters of real wide-angle scopes' order of magnitude: strong barrel distortion, small tangential
# terms, a rational denominator; the fisheye's field reaches past 90 deg (it folds at ~136 deg).
PARAMS = {
    "PINHOLE": [300.0, 310.0, 320.2, 239.7],
    "pinhole_radial_k1k2": [300.0, 310.0, 320.2, 239.7, -0.25, 0.06],
    "OPENCV": [300.0, 310.0, 320.2, 239.7, -0.25, 0.06, 0.0012, -0.0021],
    "FULL_OPENCV": [300.0, 310.0, 320.2, 239.7, -0.2, 0.05, 0.001, -0.002, 0.01, 0.1, 0.02, 0.003],
    "OPENCV_FISHEYE": [200.0, 205.0, 320.2, 239.7, 0.05, -0.01, 0.002, -0.0003],
}
# COLMAP puts the pixel origin at the top-left pixel's corner, scope3d and OpenCV at its centre.
COLMAP_SHIFT = 0.5


def _points_in_field(name, n=400, seed=0, fraction=0.95):
    """Points at 1-20 mm from the camera, at angles up to ``fraction`` of the model's field (and, for the
    pinhole family, inside 60 deg where distortion of this strength keeps the image inside a few frames)."""
    lens = lens_model(name)
    p = np.array(PARAMS[name])
    rng = np.random.default_rng(seed)
    limit = fraction * lens.max_half_angle(p)
    if not lens.is_fisheye:
        limit = min(limit, np.deg2rad(60.0))
    theta = np.arccos(rng.uniform(np.cos(limit), 1.0, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    rays = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)
    return rays * rng.uniform(1.0, 20.0, n)[:, None]


@pytest.mark.parametrize("name", list(MODELS))
def test_point_and_parameter_jacobians_match_finite_differences(name):
    lens = lens_model(name)
    p = np.array(PARAMS[name])
    pts = _points_in_field(name)
    pixels, d_point, d_params = lens.project_with_jacobians(p, pts)
    np.testing.assert_array_equal(pixels, lens.project(p, pts))
    # central differences: truncation ~h^2 f''' is negligible at this step; the rounding of the pixels
    # (eps * |u| ~ 1e-13 px) divided by the step gives the absolute tolerance, 1e-7 relative the rest.
    for i in range(3):
        h = 1e-6 * np.abs(pts[:, i:i + 1]).max()
        step = np.zeros(3)
        step[i] = h
        fd = (lens.project(p, pts + step) - lens.project(p, pts - step)) / (2 * h)
        np.testing.assert_allclose(d_point[:, :, i], fd, rtol=1e-6, atol=1e-13 * 1e3 / h)
    for i, pname in enumerate(lens.param_names):
        h = 1e-6 * max(1.0, abs(p[i]))
        step = np.zeros(len(p))
        step[i] = h
        fd = (lens.project(p + step, pts) - lens.project(p - step, pts)) / (2 * h)
        np.testing.assert_allclose(d_params[:, :, i], fd, rtol=1e-6, atol=1e-13 * 1e3 / h, err_msg=pname)


@pytest.mark.parametrize("name", list(MODELS))
def test_pose_jacobian_by_the_chain_rule(name):
    p = np.array(PARAMS[name])
    pose = Pose.from_rotvec(np.array([0.1, -0.2, 0.05]), np.array([0.5, -0.3, 2.0]))
    pts_cam = _points_in_field(name, n=50, seed=1)
    pts_world = pose.inverse().transform(pts_cam)
    n = len(pts_world)
    rv, t = np.broadcast_to(pose.rotvec, (n, 3)), np.broadcast_to(pose.translation, (n, 3))
    pixels, d_world, d_pose, d_params = project_world_with_jacobians(name, p, pts_world, rv, t)
    np.testing.assert_allclose(pixels, lens_model(name).project(p, pts_cam), atol=1e-9)
    h = 1e-7
    for k in range(6):
        step = np.zeros(6)
        step[k] = h
        plus = project_world_with_jacobians(name, p, pts_world, rv + step[:3], t + step[3:])[0]
        minus = project_world_with_jacobians(name, p, pts_world, rv - step[:3], t - step[3:])[0]
        np.testing.assert_allclose(d_pose[:, :, k], (plus - minus) / (2 * h), rtol=1e-5, atol=1e-13 * 1e3 / h)
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        plus = project_world_with_jacobians(name, p, pts_world + step, rv, t)[0]
        minus = project_world_with_jacobians(name, p, pts_world - step, rv, t)[0]
        np.testing.assert_allclose(d_world[:, :, k], (plus - minus) / (2 * h), rtol=1e-5, atol=1e-13 * 1e3 / h)


@pytest.mark.parametrize("name", list(MODELS))
def test_project_unproject_identity_over_the_field(name):
    camera = Camera.from_params(W, H, name, PARAMS[name])
    pts = _points_in_field(name, n=2000, seed=2, fraction=0.99)
    pixels = camera.project(pts)
    assert np.all(np.isfinite(pixels))
    rays = camera.unproject(pixels)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    expected = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    # Newton converges to rounding: 1e-9 rad is 1e-7 px at these focal lengths
    np.testing.assert_allclose(rays, expected, atol=1e-9)
    np.testing.assert_allclose(camera.project(rays), pixels, atol=1e-8)


def test_fisheye_sees_past_90_degrees_and_not_past_its_fold():
    camera = Camera.from_params(W, H, "OPENCV_FISHEYE", PARAMS["OPENCV_FISHEYE"])
    fold = camera.max_half_angle_rad
    assert np.deg2rad(120) < fold < np.pi
    theta = np.array([np.deg2rad(100), np.deg2rad(120), fold * 0.999, fold * 1.001])
    pts = np.stack([np.sin(theta), np.zeros(4), np.cos(theta)], axis=-1)
    px = camera.project(pts)
    assert np.all(np.isfinite(px[:3])) and np.all(np.isnan(px[3]))
    np.testing.assert_allclose(camera.unproject(px[:3]), pts[:3], atol=1e-9)
    # the image keeps growing with the angle up to the fold
    assert np.all(np.diff(px[:3, 0]) > 0)
    # a pixel beyond the fold's radius is not seen; the principal point is
    rd_fold = camera.project(np.array([[np.sin(fold * 0.999), 0, np.cos(fold * 0.999)]]))[0, 0] - camera.cx
    inside = camera.sees_pixels(np.array([[camera.cx, camera.cy], [camera.cx + 1.01 * rd_fold, camera.cy]]))
    assert inside.tolist() == [True, False]


def test_valid_mask_combines_the_circular_field_and_the_lens_field():
    # a strongly barrel-distorted radial lens folds back inside the frame: those pixels are no image
    camera = Camera.from_params(W, H, "pinhole_radial_k1k2", [150, 150, 319.5, 239.5, -0.5, 0.0],
                                mask_radius_px=230.0)
    fold_r = np.sqrt(1 / 1.5)  # d(r (1 - 0.5 r^2))/dr = 1 - 1.5 r^2 = 0
    np.testing.assert_allclose(camera.max_half_angle_rad, np.arctan(fold_r), atol=1e-10)
    fold_px = 150 * fold_r * (1 - 0.5 * fold_r ** 2)
    valid = camera.valid_mask()
    grid = camera.pixel_grid()
    dist = np.linalg.norm(grid - [319.5, 239.5], axis=-1)
    assert np.all(valid[dist < fold_px - 1]) and not np.any(valid[dist > fold_px + 1])
    assert not np.any(valid & ~camera.mask())


@pytest.mark.parametrize("name", [n for n, m in MODELS.items() if m.colmap_name])
def test_pycolmap_projects_to_the_same_pixels(name):
    lens = lens_model(name)
    p = np.array(PARAMS[name])
    colmap_params = p.copy()
    colmap_params[2:4] += COLMAP_SHIFT
    cam = pycolmap.Camera(model=lens.colmap_name, width=W, height=H, params=colmap_params)
    # COLMAP projects through x/z, as OpenCV does: the same only in front of the camera
    pts = _points_in_field(name, n=1000, seed=3)
    pts = pts[pts[:, 2] > 0.05 * np.linalg.norm(pts, axis=1)]
    ours = lens.project(p, pts)
    theirs = np.asarray(cam.img_from_cam(pts)) - COLMAP_SHIFT
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9)
    back = np.asarray(cam.cam_from_img(theirs + COLMAP_SHIFT))  # normalised (x, y)
    rays = lens.unproject(p, ours)
    np.testing.assert_allclose(rays[:, :2] / rays[:, 2:], back, atol=1e-9)


@pytest.mark.parametrize("name", list(MODELS))
def test_opencv_projects_to_the_same_pixels(name):
    camera = Camera.from_params(W, H, name, PARAMS[name])
    pts = _points_in_field(name, n=1000, seed=4)
    pts = pts[pts[:, 2] > 0.05 * np.linalg.norm(pts, axis=1)]
    rvec, tvec = np.zeros(3), np.zeros(3)
    if camera.lens.is_fisheye:
        theirs, _ = cv2.fisheye.projectPoints(pts.reshape(1, -1, 3), rvec, tvec, camera.K, camera.distortion_coeffs)
    else:
        theirs, _ = cv2.projectPoints(pts, rvec, tvec, camera.K, camera.distortion_coeffs)
    np.testing.assert_allclose(camera.project(pts), theirs.reshape(-1, 2), rtol=0, atol=1e-9)


def test_default_model_is_the_original_k1_k2_model_bit_for_bit():
    camera = Camera(W, H, 300.0, 310.0, 320.2, 239.7, -0.25, 0.06)
    assert camera.model == "pinhole_radial_k1k2"
    pts = _points_in_field("pinhole_radial_k1k2", n=200, seed=5)
    x, y = pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2]
    xy = np.stack([x, y], axis=-1)
    r2 = np.sum(xy * xy, axis=-1, keepdims=True)
    xy_d = xy * (1.0 + camera.k1 * r2 + camera.k2 * r2 * r2)
    expected = np.stack([camera.fx * xy_d[:, 0] + camera.cx, camera.fy * xy_d[:, 1] + camera.cy], axis=-1)
    assert camera.project(pts).tobytes() == expected.tobytes()
    np.testing.assert_array_equal(camera.params, camera.intrinsics)


def test_camera_refuses_parameters_that_do_not_fit_the_model():
    with pytest.raises(ValueError, match="unknown camera model"):
        Camera.from_params(W, H, "KANNALA", [1, 1, 0, 0])
    with pytest.raises(ValueError, match="takes 8 parameters"):
        Camera.from_params(W, H, "OPENCV", [300, 300, 320, 240, 0.1])
    with pytest.raises(ValueError, match="finite"):
        Camera.from_params(W, H, "OPENCV_FISHEYE", [300, 300, 320, 240, 0.1, np.nan, 0, 0])
    with pytest.raises(ValueError, match="no distortion"):
        Camera(W, H, 300, 300, 320, 240, 0.1, model="PINHOLE")
    fisheye = Camera.from_params(W, H, "OPENCV_FISHEYE", PARAMS["OPENCV_FISHEYE"])
    with pytest.raises(ValueError, match="params"):
        fisheye.intrinsics  # noqa: B018 - the radial 6-vector would misread a fisheye's k1, k2


def test_opencv_distortion_vectors():
    np.testing.assert_array_equal(opencv_distortion("PINHOLE", PARAMS["PINHOLE"]), [0, 0, 0, 0])
    np.testing.assert_array_equal(opencv_distortion("FULL_OPENCV", PARAMS["FULL_OPENCV"]),
                                  [-0.2, 0.05, 0.001, -0.002, 0.01, 0.1, 0.02, 0.003])
    np.testing.assert_array_equal(opencv_distortion("OPENCV_FISHEYE", PARAMS["OPENCV_FISHEYE"]),
                                  [0.05, -0.01, 0.002, -0.0003])
