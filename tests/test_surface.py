"""Thin-plate-spline surface: fits a cap, keeps a plane flat, rejects wrong points, meshes, textures."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.feature.depth_prior import DepthPrior
from scope3d.geometry.grid import grid_faces
from scope3d.geometry.plane import fit_plane, plane_residuals, plane_rms, principal_axes
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at
from scope3d.io.ply import write_ply
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


def test_mesh_normals_are_defined_at_the_edge_and_unchanged_inside(tmp_path):
    """A central difference at the surveyed disc's edge reaches outside it (NaN): the mesh took 1041 NaN
    normals into the default demo's mesh.ply, which trimesh warned about on load (issue 33)."""
    s = fit_surface(_cap_points(), towards=np.array([0, 0, 1.0]))
    m = s.mesh()
    inside = np.all(np.isfinite(s.normals()[s.valid]), axis=1)
    assert (~inside).sum() > 20  # the edge is there to be tested
    assert np.all(np.isfinite(m.vertex_normals))
    np.testing.assert_allclose(np.linalg.norm(m.vertex_normals, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(m.vertex_normals[inside], s.normals()[s.valid][inside], atol=1e-12)
    # at the edge the one-sided normal agrees with the mesh's own faces as well as the central one does
    # inside (the faces' area-weighted normals): both differ by the cap's turn over a cell, ~step / R / 2
    import trimesh

    from_faces = trimesh.Trimesh(m.vertices, m.faces, process=False).vertex_normals
    angle = np.degrees(np.arccos(np.clip(np.sum(m.vertex_normals * from_faces, axis=1), -1, 1)))
    assert angle[~inside].max() <= max(angle[inside].max(), np.degrees(s.step_mm / R_DOME))
    write_ply(tmp_path / "mesh.ply", m)
    loaded = trimesh.load(tmp_path / "mesh.ply", process=False)
    assert np.all(np.isfinite(loaded.vertex_normals))


def test_plane_residuals_and_rms():
    rng = np.random.default_rng(3)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    offsets = rng.normal(0, 0.2, 400)
    local = np.column_stack([rng.uniform(-20, 20, (400, 2)), offsets - offsets.mean()])
    pts = local @ R.T + [5.0, -3.0, 40.0]  # a tilted, shifted sheet 0.2 mm thick
    r = plane_residuals(pts)
    assert r.shape == (400,)
    np.testing.assert_allclose(np.abs(r), np.abs(local[:, 2]), atol=0.03)  # the plane is (almost) the sheet's
    assert abs(r.mean()) < 1e-9
    assert plane_rms(pts) == pytest.approx(np.sqrt(np.mean(r**2)), rel=1e-9)
    assert plane_rms(pts) <= np.sqrt(np.mean(local[:, 2] ** 2))  # least squares: no plane does better
    assert plane_rms(pts[:, [0, 1, 1]]) < 1e-12  # points on a plane
    centroid, axes = principal_axes(pts)
    np.testing.assert_allclose(axes @ axes.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(abs(axes[2] @ R[:, 2]), 1.0, atol=1e-5)


@pytest.mark.parametrize("anti_diagonal", [False, True])
@pytest.mark.parametrize("clockwise", [False, True])
def test_grid_faces_cover_each_cell_once_with_one_winding(anti_diagonal, clockwise):
    rows, cols = 4, 5
    f = grid_faces(rows, cols, anti_diagonal=anti_diagonal, clockwise=clockwise)
    assert f.shape == (2 * (rows - 1) * (cols - 1), 3) and f.dtype == np.int64
    xy = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), -1).reshape(-1, 2).astype(float)  # (column, row)
    a, b, c = xy[f[:, 0]], xy[f[:, 1]], xy[f[:, 2]]
    cross = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]
    np.testing.assert_allclose(cross, -1.0 if clockwise else 1.0)  # half a unit cell each, one winding
    diagonal = {1, cols} if anti_diagonal else {0, cols + 1}  # both halves of cell 0 hold its diagonal
    assert diagonal <= set(f[0]) and diagonal <= set(f[len(f) // 2])
    ring = grid_faces(rows, cols, wrap=True)  # the last column joins the first
    assert len(ring) == 2 * (rows - 1) * cols and {0, cols - 1} <= set(ring[cols - 1])
    keep = np.zeros((rows - 1, cols - 1), bool)
    keep[1, 2] = True
    np.testing.assert_array_equal(grid_faces(rows, cols, keep=keep), [[7, 8, 13], [7, 13, 12]])
    only_second = grid_faces(rows, cols, keep=(np.zeros_like(keep), keep))
    np.testing.assert_array_equal(only_second, [[7, 13, 12]])


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


@pytest.mark.parametrize("k1, k2", [(0.0, 0.0), (-0.45, 0.02)])
def test_best_views_scores_only_frames_that_can_see_a_point_with_the_same_result(k1, k2):
    """best_views skips the cells outside each frame's viewing cone: the views and pixels must be those of
    scoring every point in every frame (written out here), also for a barrel lens strong enough to fold
    points from outside its field back into the image (k1 = -0.45: r (1 + k1 r^2) turns at r = 0.86)."""
    from scope3d.scene.surface import best_views

    s = fit_surface(_cap_points(), towards=np.array([0, 0, 1.0]))
    points, normals = s.vertices()[s.valid], s.normals()[s.valid]
    cam = Camera.from_fov(120, 100, 60.0, k1=k1, k2=k2, mask_radius_px=55.0)
    rng = np.random.default_rng(3)
    centres = np.column_stack([rng.uniform(-14, 14, (12, 2)), rng.uniform(3, 12, 12)])
    poses = [Pose.from_centre(look_at(c, c * [1, 1, 0] + rng.normal(0, 3, 3) * [1, 1, 0]), c) for c in centres]
    view, pix = best_views(cam, poses, points, normals)
    best = np.full(len(points), -np.inf)
    view_all, pix_all = np.full(len(points), -1), np.full((len(points), 2), np.nan)
    for k, pose in enumerate(poses):
        uv = cam.project_world(pose, points)
        to_cam = pose.centre - points
        cosang = np.einsum("vi,vi->v", normals, to_cam) / np.linalg.norm(to_cam, axis=1)
        rad = np.linalg.norm(uv - [59.5, 49.5], axis=1) / 55.0
        score = np.where(cam.in_image(uv, margin_px=2.0) & (cosang > 0.1), cosang - 0.5 * rad * rad, -np.inf)
        better = score > best
        best[better], view_all[better], pix_all[better] = score[better], k, uv[better]
    assert (view_all >= 0).mean() > 0.3  # the frames see the field
    np.testing.assert_array_equal(view, view_all)
    np.testing.assert_array_equal(pix, pix_all)


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


def test_far_wrong_points_neither_tilt_the_plane_nor_stretch_the_grid():
    """A cluster of five wrong points 1.5 m away (each within 1 mm of the others, so the support test keeps
    them) set the plane's principal axis and a 1.8 m grid before (issue 34: a ring's map died texturing it).
    The surface must be the one fitted without them, its grid spanning the 26 mm cap plus the extrapolation."""
    pts = _cap_points()
    far = np.array([1500.0, 900.0, 3.0]) + np.random.default_rng(5).normal(0, 0.2, (5, 3))
    clean = fit_surface(pts, towards=np.array([0, 0, 1.0]))
    s = fit_surface(np.vstack([pts, far]), towards=np.array([0, 0, 1.0]))
    assert s.axes[2] @ [0, 0, 1] > 0.99
    assert s.height.shape == clean.height.shape
    np.testing.assert_array_equal(s.valid, clean.valid)
    np.testing.assert_allclose(s.vertices()[s.valid], clean.vertices()[clean.valid], atol=1e-9)


def test_a_field_larger_than_the_memory_budget_is_gridded_coarser_within_it():
    pts = _cap_points()
    s = fit_surface(pts, options=SurfaceOptions(max_grid_vertices=10_000), towards=np.array([0, 0, 1.0]))
    # the least step that fits, not a coarser one: the search raises the step 1 % at a time, which removes
    # ~2 % of a square grid's vertices, and whole rows and columns (1 % each on a 100 x 100 grid) come and go
    # with the floor: the grid holds at least 96 % of the budget
    assert 0.96 * 10_000 <= s.height.size <= 10_000
    assert s.step_mm > SurfaceOptions().grid_step_mm


def test_a_grid_coarsened_for_memory_keeps_a_vertex_near_every_point():
    """Clusters of 4 points (0.2 mm apart: each supported by the others) every 20 mm over a 400 mm field,
    on a budget that forces a step of ~8 mm, beyond the 1.5 mm extrapolation distance: the mesh must still
    hold a vertex within one step of every cluster (before, a vertex had to lie within 1.5 mm of a point,
    and most clusters had none: a 20 m facade's map kept 183 of 2 million vertices)."""
    rng = np.random.default_rng(4)
    centres = np.stack(np.meshgrid(np.arange(-200, 201, 20.0), np.arange(-200, 201, 20.0)), axis=-1).reshape(-1, 2)
    centres += rng.uniform(-3, 3, centres.shape)
    xy = np.repeat(centres, 4, axis=0) + rng.normal(0, 0.1, (4 * len(centres), 2))
    pts = np.column_stack([xy, 0.001 * xy[:, 0]])
    s = fit_surface(pts, options=SurfaceOptions(max_grid_vertices=2500), towards=np.array([0, 0, 1.0]))
    assert s.step_mm > 5 * SurfaceOptions().max_extrapolation_mm
    ss, tt = np.meshgrid(s.s, s.t)
    kept = np.column_stack([ss[s.valid], tt[s.valid]])
    cluster_in_plane = s.to_plane(np.column_stack([centres, 0.001 * centres[:, 0]]))[:, :2]
    nearest = np.min(np.linalg.norm(cluster_in_plane[:, None] - kept[None], axis=2), axis=1)
    # within one step, plus the clusters' 0.1 mm spread about their centres
    assert np.all(nearest <= s.step_mm + 0.5)
    with pytest.raises(ValueError):
        SurfaceOptions(max_grid_vertices=3)


def test_sample_images_takes_more_samples_per_frame_than_remap_can_map_in_one_column():
    """cv2.remap asserts its maps are under SHRT_MAX = 32767 in each dimension: 100,000 samples of one
    frame failed as one column. Each sample is the bilinear interpolation of its four pixels."""
    from scope3d.scene.surface import sample_images

    rng = np.random.default_rng(2)
    img = rng.integers(0, 256, (60, 80)).astype(np.uint8)
    pix = rng.uniform(0, 1, (100_000, 2)) * [78.999, 58.999]
    got = sample_images([img], np.zeros(len(pix), np.int64), pix)[:, 0]
    x0, y0 = np.floor(pix).astype(int).T
    fx, fy = (pix - np.floor(pix)).T
    a = img.astype(float)
    y0 = np.minimum(y0, 58)
    fy = np.minimum(pix[:, 1] - y0, 1.0)
    want = ((1 - fx) * (1 - fy) * a[y0, x0] + fx * (1 - fy) * a[y0, x0 + 1] + (1 - fx) * fy * a[y0 + 1, x0]
            + fx * fy * a[y0 + 1, x0 + 1])
    # remap's fixed-point weights are 1/32 of a pixel (INTER_TAB_SIZE): at most 255 / 32 off in value
    assert np.max(np.abs(got - want)) <= 255 / 32
