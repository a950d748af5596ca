"""Thin-plate-spline surface: fits a cap, keeps a plane flat, rejects wrong points, meshes, textures."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.feature.depth_prior import DepthPrior
from scope3d.geometry.plane import fit_plane
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at
from scope3d.scene.surface import Surface, SurfaceOptions, depth_map, fit_surface, off_surface_points, texture
from scope3d.sensor.camera import Camera

R_DOME, DEPTH = (15.0**2 + 10.0**2) / 20.0, 10.0


def _cap(xy):
    """Spherical cavity, 10 mm deep, 15 mm rim radius (the reference's dome), bottom at z = -10."""
    return -np.sqrt(R_DOME**2 - np.sum(xy**2, axis=1)) + R_DOME - DEPTH


def _cap_points(n=6000, noise=0.05, seed=0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-13, 13, (n, 2))
    xy = xy[np.hypot(*xy.T) < 13]
    return np.column_stack([xy, _cap(xy) + rng.normal(0, noise, len(xy))])


def test_cap_is_recovered_to_a_fraction_of_the_point_noise():
    noise = 0.05
    pts = _cap_points(noise=noise)
    s = fit_surface(pts, towards=np.array([0, 0, 1.0]))
    v = s.vertices()[s.valid]
    inner = np.hypot(v[:, 0], v[:, 1]) < 11
    err = v[inner, 2] - _cap(v[inner, :2])
    # The points are uniform over the 13 mm disc and reduced to one median per control cell (0.6 mm; the
    # 2500-centre cap would only raise it above sqrt(26^2 / 2500) = 0.52 mm), so a cell holds on average
    # k = density * cell^2 = 3.2 points. Averaging k independent errors of sigma leaves sigma / sqrt(k)
    # = 0.028 mm: the surface must be at least that good (the median is less efficient than the mean,
    # by up to sqrt(pi / 2), but the smoothing spline averages each vertex over neighbouring cells too).
    options = SurfaceOptions()
    cell = max(options.control_cell_mm, np.sqrt(26.0**2 / options.max_control_points))
    k = len(pts) / (np.pi * 13.0**2) * cell**2
    bound = noise / np.sqrt(k)
    assert np.sqrt(np.mean(err**2)) < bound
    # the raw points do not pass it: their error is the noise itself (sqrt(k) = 1.8 times the bound)
    near = np.hypot(pts[:, 0], pts[:, 1]) < 11
    assert np.sqrt(np.mean((pts[near, 2] - _cap(pts[near, :2])) ** 2)) > bound
    assert s.axes[2] @ [0, 0, 1] > 0.99  # normal faces the cameras


def test_plane_stays_flat_and_a_wrong_point_is_ignored():
    rng = np.random.default_rng(1)
    xy = rng.uniform(-10, 10, (3000, 2))
    pts = np.column_stack([xy, 0.3 * xy[:, 0] + rng.normal(0, 0.02, len(xy))])
    pts[0, 2] += 2.0  # a wrong track 2 mm off the sheet
    s = fit_surface(pts)
    v = s.vertices()[s.valid]
    assert np.abs(v[:, 2] - 0.3 * v[:, 0]).max() < 0.05


def test_isolated_point_does_not_bend_the_surface():
    rng = np.random.default_rng(2)
    xy = rng.uniform(-10, 10, (3000, 2))
    xy = xy[np.abs(xy[:, 0] - 8) > 2]  # a gap around x = 8
    pts = np.column_stack([xy, np.zeros(len(xy))])
    pts = np.vstack([pts, [[8.0, 0.0, -1.5]]])  # alone in the gap, far off
    s = fit_surface(pts, towards=np.array([0, 0, 1.0]))
    assert np.nanmax(np.abs(s.height)) < 0.05


def test_mesh_faces_wind_towards_the_normal():
    s = fit_surface(_cap_points(), towards=np.array([0, 0, 1.0]))
    m = s.mesh()
    a, b, c = (m.vertices[m.faces[:, k]] for k in range(3))
    face_n = np.cross(b - a, c - a)
    assert np.all(face_n @ s.axes[2] > 0)
    assert len(m.vertices) == int(s.valid.sum())


def test_ray_depths_hit_the_surface():
    s = fit_surface(_cap_points(noise=0.0), towards=np.array([0, 0, 1.0]))
    pose = Pose.from_centre(look_at(np.array([2.0, 1.0, 15.0]), np.array([2.0, 1.0, 0.0])), [2.0, 1.0, 15.0])
    cam = Camera.from_fov(200, 200, 50.0)
    pix = np.array([[100.0, 100.0], [60.0, 140.0], [150.0, 70.0]])
    rays = cam.unproject(pix, np.ones(3))
    z = s.ray_depths(pose, rays)
    world = (rays * z[:, None] - pose.translation) @ pose.rotation
    np.testing.assert_allclose(world[:, 2], _cap(world[:, :2]), atol=0.01)
    lo, hi = DepthPrior(1.0, 100.0).with_band(s, 0.5).ray_ranges(pose, rays)
    assert np.all(lo < z) and np.all(z < hi)


def test_texture_and_depth_map():
    s = fit_surface(_cap_points(), towards=np.array([0, 0, 1.0]))
    cam = Camera.from_fov(160, 160, 70.0)
    poses = [Pose.from_centre(look_at(np.array([x, 0.0, 15.0]), np.array([x, 0.0, 0.0])), [x, 0.0, 15.0]) for x in (-5.0, 5.0)]
    images = [np.full((160, 160, 3), 50 + 100 * k, np.uint8) for k in range(2)]
    colors, view = texture(s, cam, poses, images)
    seen = view >= 0
    assert seen.any()
    # each vertex takes the colour of the frame chosen for it
    assert np.all(colors[seen & (view == 0)] == 50) and np.all(colors[seen & (view == 1)] == 150)
    # on a flat field each camera wins the side beneath it (world x: a round cap's in-plane axes are
    # arbitrary)
    flat = Surface(s.origin, s.axes, s.s, s.t, np.where(s.valid, 0.0, np.nan))
    _, view_flat = texture(flat, cam, poses, images)
    ss = flat.vertices()[..., 0]
    assert np.all(view_flat[(view_flat >= 0) & (ss < -3)] == 0) and np.all(view_flat[(view_flat >= 0) & (ss > 3)] == 1)
    d = depth_map(s)
    # points reach r = 13 mm (cap height -3.5 mm), the grid extrapolates up to 1.5 mm beyond (r <= 14.5 mm,
    # height <= -1.2 mm); the bottom is at -10 mm: the depth span lies between those
    span = lambda r: 10.0 + _cap(np.array([[r, 0.0]]))[0]
    assert np.nanmin(d) == 0.0 and span(13.0) - 0.2 <= np.nanmax(d) <= span(14.5) + 0.2


def test_refined_grid_interpolates_the_heights():
    s = fit_surface(_cap_points(noise=0.0), towards=np.array([0, 0, 1.0]))
    r = s.refined(slice(20, 40), slice(20, 40), 4)
    assert r.step_mm == pytest.approx(s.step_mm / 4)
    np.testing.assert_allclose(r.height[::4, ::4], s.height[20:40, 20:40], atol=1e-5)


def test_bad_inputs():
    with pytest.raises(ValueError, match="at least 10"):
        fit_surface(np.zeros((5, 3)))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        fit_surface(np.zeros((50, 2)))
    with pytest.raises(ValueError):
        fit_plane(np.zeros((2, 3)))
    with pytest.raises(ValueError):
        SurfaceOptions(grid_step_mm=0)
    with pytest.raises(ValueError):
        SurfaceOptions(smoothing=-1)


def test_off_surface_points_catches_wrong_depths_and_spares_a_crease():
    """A plate with a spherical dome cut into it (a crease at the rim), 0.02 mm noise, and 3 % of the
    points moved 1-10 mm along z, as wrong two-view matches land along their rays."""
    rng = np.random.default_rng(4)
    xy = rng.uniform(-20, 20, (4000, 2))
    R, depth = 17.5, 10.0
    r2 = np.sum(xy**2, axis=1)
    rim2 = R**2 - (R - depth) ** 2
    z = np.where(r2 < rim2, (R - depth) - np.sqrt(np.maximum(R**2 - r2, 0)), 0.0) + rng.normal(0, 0.02, len(xy))
    pts = np.column_stack([xy, z])
    wrong = rng.choice(len(pts), 120, replace=False)
    pts[wrong, 2] += rng.choice([-1, 1], 120) * rng.uniform(1.0, 10.0, 120)
    flagged = off_surface_points(pts, towards=np.array([0, 0, 1.0]))
    is_wrong = np.zeros(len(pts), bool)
    is_wrong[wrong] = True
    assert flagged[is_wrong].mean() > 0.95
    assert flagged[~is_wrong].mean() < 0.02
    near_rim = np.abs(np.sqrt(r2) - np.sqrt(rim2)) < 1.0
    assert flagged[near_rim & ~is_wrong].mean() < 0.05
