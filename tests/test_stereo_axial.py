"""Axial-stereo geometry: eq. 7.3-7.4, the general (misaligned) case, polar resampling, input errors."""
from dataclasses import replace

import cv2
import numpy as np
import pytest

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at, rotvec_to_matrix
from scope3d.mvs.axial import (
    PolarGridOptions,
    aligned_poses,
    aligned_triangulate,
    epipole_px,
    make_axial_pair,
    triangulate_rays,
)
from scope3d.sensor.camera import Camera

CAM = Camera.from_fov(320, 320, 70.0, mask_radius_px=158.0)
DOWN = look_at(np.zeros(3), [0.0, 0.0, -1.0])  # looking down -z like the phantom's axial trajectory


def _bore_points(rng, n=500):
    """Points on a 3.5 mm radius bore 4-12 mm below the origin (world, mm)."""
    theta = rng.uniform(0, 2 * np.pi, n)
    z = rng.uniform(-12.0, -4.0, n)
    return np.stack([3.5 * np.cos(theta), 3.5 * np.sin(theta), z], axis=1)


def _grid_disparity(pair, points_world):
    """Exact polar disparity (columns) of world points, and their front-camera grid coordinates."""
    def grid_coords(pose):
        local = (points_world - pose.centre) @ pair.virtual_from_world.T
        return pair.grid.coordinates_of(local)
    front, rear = grid_coords(pair.pose_front), grid_coords(pair.pose_rear)
    return front[:, 1] - rear[:, 1], front


def test_aligned_case_matches_eq_7_3_and_7_4():
    rng = np.random.default_rng(0)
    pts = _bore_points(rng)
    rear = Pose.from_centre(DOWN, [0, 0, 0.0])
    front = Pose.from_centre(DOWN, [0, 0, -0.25])
    p1, p2 = CAM.project_world(rear, pts), CAM.project_world(front, pts)
    got = aligned_triangulate(CAM, p1, p2, 0.25)
    np.testing.assert_allclose(got, front.transform(pts), atol=1e-9)
    np.testing.assert_allclose(triangulate_rays(CAM, rear, front, p1, p2), pts, atol=1e-9)
    # The log-polar closed form is the same model: Z = b / (exp(d * step) - 1).
    pair = make_axial_pair(CAM, rear, front)
    d, coords = _grid_disparity(pair, pts)
    z = pair.depth_along_baseline(d[:, None])[:, 0]
    np.testing.assert_allclose(z, front.transform(pts)[:, 2], rtol=1e-9)


def test_epipole_is_the_other_centre():
    rear = Pose.from_centre(DOWN, [0, 0, 0.0])
    front = Pose.from_centre(DOWN, [0, 0, -0.25])
    e, ahead = epipole_px(CAM, rear, front.centre)
    np.testing.assert_allclose(e, [CAM.cx, CAM.cy], atol=1e-9)
    assert ahead
    e, ahead = epipole_px(CAM, front, rear.centre)
    np.testing.assert_allclose(e, [CAM.cx, CAM.cy], atol=1e-9)
    assert not ahead
    # A tilted scope: the epipole moves off-centre by f tan(tilt).
    tilted = Pose.from_centre(rotvec_to_matrix([np.deg2rad(3.0), 0, 0]) @ DOWN, [0, 0, 0.0])
    e, _ = epipole_px(CAM, tilted, [0, 0, -0.25])
    assert abs(np.hypot(e[0] - CAM.cx, e[1] - CAM.cy) - CAM.fx * np.tan(np.deg2rad(3.0))) < 1e-6


@pytest.mark.parametrize("offset_mm, tilt_deg", [(0.3, 0.0), (0.0, 3.0), (0.3, 3.0)])
def test_general_case_is_exact_when_misaligned_and_aligned_model_is_not(offset_mm, tilt_deg):
    rng = np.random.default_rng(1)
    pts = _bore_points(rng)
    # The scope is tilted w.r.t. its own motion (the motion stays along the hole axis, offset sideways).
    rot = rotvec_to_matrix([np.deg2rad(tilt_deg), 0.0, 0.0]) @ DOWN
    rear = Pose.from_centre(rot, [offset_mm, 0, 0.0])
    front = Pose.from_centre(rot, [offset_mm, 0, -0.25])
    pair = make_axial_pair(CAM, rear, front)
    d, coords = _grid_disparity(pair, pts)
    world = pair.triangulate_grid(coords, d)
    np.testing.assert_allclose(world, pts, atol=1e-8)
    p1, p2 = CAM.project_world(rear, pts), CAM.project_world(front, pts)
    aligned_world = front.inverse().transform(aligned_triangulate(CAM, p1, p2, 0.25))
    err = np.linalg.norm(aligned_world - pts, axis=1)
    if tilt_deg == 0.0:
        assert err.max() < 1e-8  # an offset alone keeps the motion along the optical axis: eq. 7.3 holds
    else:
        assert np.median(err) > 0.1  # 3 deg between motion and optical axis: mm-level errors


def test_aligned_poses_put_the_rear_camera_on_the_front_axis():
    rear = Pose.from_centre(rotvec_to_matrix([0.02, 0, 0]) @ DOWN, [0.1, 0, 0.0])
    front = Pose.from_centre(DOWN, [0, 0, -0.25])
    r, f = aligned_poses(rear, front)
    assert f is front
    np.testing.assert_allclose(r.rotation, front.rotation)
    np.testing.assert_allclose(front.transform(r.centre[None])[0], [0, 0, -np.linalg.norm(front.centre - rear.centre)], atol=1e-12)


def test_polar_round_trip():
    rng = np.random.default_rng(2)
    rear = Pose.from_centre(DOWN, [0, 0, 0.0])
    front = Pose.from_centre(DOWN, [0, 0, -0.25])
    pair = make_axial_pair(CAM, rear, front, grid_options=PolarGridOptions(radial_step_px=0.5, angular_step_px=0.5))
    # Grid coordinates of the grid's own points are their indices.
    coords = pair.grid.coordinates_of(pair.grid.virtual_points())
    rows, cols = np.meshgrid(np.arange(pair.grid.n_angles), np.arange(pair.grid.n_radii), indexing="ij")
    np.testing.assert_allclose(coords[..., 0], rows, atol=1e-6)
    np.testing.assert_allclose(coords[..., 1], cols, atol=1e-6)
    # Smooth image -> polar -> image: equal to interpolation accuracy in the annulus the grid covers.
    u, v = np.meshgrid(np.arange(CAM.width), np.arange(CAM.height))
    image = (128 + 60 * np.sin(u / 7.0) * np.cos(v / 5.0) + rng.normal(0, 0, u.shape)).astype(np.float32)
    polar = pair.to_polar(image, front)
    back = pair.from_polar(polar.astype(float), front)
    r = np.hypot(u - CAM.cx, v - CAM.cy)
    annulus = (r > 40) & (r < 150) & np.isfinite(back)
    assert annulus.mean() > 0.5
    assert np.abs(back - image)[annulus].max() < 2.0  # grey levels, of a 120-level swing


def test_zero_step_is_an_input_error():
    pose = Pose.from_centre(DOWN, [0, 0, 0.0])
    with pytest.raises(InputError, match="apart"):
        make_axial_pair(CAM, pose, pose)


def test_lateral_motion_is_not_axial():
    rear = Pose.from_centre(DOWN, [0, 0, 0.0])
    side = Pose.from_centre(DOWN, [0.25, 0, -0.05])  # 79 deg from the optical axis
    with pytest.raises(InputError, match="not axial"):
        make_axial_pair(CAM, rear, side)


def test_frame_order_does_not_matter():
    rear = Pose.from_centre(DOWN, [0, 0, 0.0])
    front = Pose.from_centre(DOWN, [0, 0, -0.25])
    a, b = make_axial_pair(CAM, rear, front), make_axial_pair(CAM, front, rear)
    assert not a.swapped and b.swapped
    np.testing.assert_allclose(a.virtual_from_world, b.virtual_from_world)
    assert a.grid == b.grid


def _zoom_pair(z_mm, step_mm=0.25, seed=0):
    """Rear and front views of a fronto-parallel textured plane ``z_mm`` ahead of the front camera: the
    front image is the rear one zoomed by ``s = (z + step) / z`` about the principal point, so on the
    log-polar grid the disparity is exactly ``log(s) / log_rho_step`` columns everywhere. The texture is a
    sum of sinusoids below the Nyquist rate, so both 8-bit images sample one band-limited pattern."""
    rng = np.random.default_rng(seed)
    k = rng.uniform(0.05, 1.5, 60)
    a = rng.uniform(0, 2 * np.pi, 60)
    ph = rng.uniform(0, 2 * np.pi, 60)
    u, v = np.meshgrid(np.arange(CAM.width, dtype=float) - CAM.cx, np.arange(CAM.height, dtype=float) - CAM.cy)

    def texture(x, y):
        return np.cos(k * (np.cos(a) * x[..., None] + np.sin(a) * y[..., None]) + ph).sum(axis=-1)

    s = (z_mm + step_mm) / z_mm
    rear, front = texture(u, v), texture(u / s, v / s)
    scale = 40.0 / rear.std()
    return (np.clip(128 + scale * rear, 0, 255).astype(np.uint8),
            np.clip(128 + 1.1 * scale * front, 0, 255).astype(np.uint8), s)  # the front view is brighter


@pytest.mark.parametrize("z_mm", [3.0, 8.0])
def test_polar_sgm_has_no_disparity_bias_on_a_radial_zoom(z_mm):
    """Catches any half-pixel slip between the log-polar maps, cv2.remap (pixel centres at integers), the
    SGBM sign convention and the sub-pixel refinement: a shift of the whole chain shows as a median bias."""
    from scope3d.mvs.dense_matching import SgmOptions, sgm_disparity

    rear_img, front_img, s = _zoom_pair(z_mm)
    rear = Pose.from_centre(DOWN, [0, 0, 0.0])
    front = Pose.from_centre(DOWN, [0, 0, -0.25])
    pair = make_axial_pair(CAM, rear, front, grid_options=PolarGridOptions(min_radius_px=20.0))
    d_true = np.log(s) / pair.grid.log_rho_step
    fp, rp = pair.to_polar(front_img, front), pair.to_polar(rear_img, rear)
    d = sgm_disparity(fp, rp, options=SgmOptions(num_disparities=32, wrap_rows=True)).disparity
    # Cells seen by both views, away from the disc's edge, whose rear partner is on the grid, and where a
    # column spans at least half a pixel (nearer the epipole the window covers under 3 px of image: the
    # estimate is ill-conditioned there and the confidence mask drops it anyway).
    both = pair.valid_polar(front) & pair.valid_polar(rear)
    ok = cv2.erode(both.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0
    radius_px = CAM.fx * pair.grid.radii()
    ok &= (radius_px * pair.grid.log_rho_step >= 0.5)[None, :]
    ok[:, : int(np.ceil(d_true)) + 8] = False
    err = (d - d_true)[ok & np.isfinite(d)]
    assert err.size > 0.8 * ok.sum()
    assert abs(np.median(err)) < 0.02  # columns
    assert np.percentile(np.abs(err), 90) < 0.1


@pytest.mark.parametrize("tilt_deg", [0.0, 2.0])
def test_polar_maps_are_one_projection_of_the_whole_grid(tilt_deg):
    """The maps come from one compiled pass over the grid and are cached per camera orientation (issue 17):
    they must be exactly (bit for bit) Camera.project and Camera.in_image of every grid direction, for each
    frame of a pair, whether the two frames share their orientation (pure step) or not (tilted front frame),
    with and without the scope's circular field."""
    rear = Pose.from_centre(DOWN, [0, 0, 0.0])
    tilt = rotvec_to_matrix(np.deg2rad([tilt_deg, 0.0, 0.0]))
    front = Pose.from_centre(tilt @ DOWN, [0, 0, -0.25])
    for camera in (CAM, replace(CAM, mask_radius_px=None)):
        pair = make_axial_pair(camera, rear, front)
        for pose in (rear, front):
            directions = pair.grid.virtual_points() @ pair.virtual_from_camera(pose)
            pixels = camera.project(directions.reshape(-1, 3))
            pixels[~camera.in_image(pixels)] = -1.0
            pixels = pixels.reshape(pair.grid.shape + (2,)).astype(np.float32)
            map_u, map_v = pair.polar_maps(pose)
            assert np.array_equal(map_u, pixels[..., 0]) and np.array_equal(map_v, pixels[..., 1])
            assert 0 < np.count_nonzero(map_u < 0) < map_u.size  # both outcomes of the image test occur
    shared = pair.polar_maps(rear)[0] is pair.polar_maps(front)[0]
    assert shared == (tilt_deg == 0.0)
