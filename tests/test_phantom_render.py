"""Phantom rendering: photometric and geometric ground truth, determinism, fluorescence."""
import cv2
import numpy as np
import pytest

from scope3d.geometry.pose import Pose
from scope3d.phantoms import build_scene, generate, render_frame
from scope3d.phantoms.scenes import DOME_DEPTH_MM
from scope3d.sensor.camera import Camera

SIZE = (200, 200)


@pytest.fixture(scope="module")
def dome_pair():
    return generate("dome", size=SIZE, n_frames=2, seed=3)


def _grey(img):
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32)


def _warped_patch_ncc(seq, pose_b, *, half=4, step=5):
    """For 9x9 patches of view 0, move each pixel with its true depth into view 1 (posed at ``pose_b``) and
    correlate the intensities. Returns the NCC of every usable patch."""
    cam = seq.camera
    img_a, img_b = _grey(seq.frames[0]), _grey(seq.frames[1])
    depth_a, depth_b = seq.depths[0], seq.depths[1]
    pose_a = seq.true_poses[0]
    offs = np.stack(np.meshgrid(np.arange(-half, half + 1), np.arange(-half, half + 1)), -1).reshape(-1, 2)
    nccs = []
    for v in range(half, cam.height - half, step):
        for u in range(half, cam.width - half, step):
            pix = offs + [u, v]
            d = depth_a[pix[:, 1], pix[:, 0]]
            if not np.all(np.isfinite(d)):
                continue
            world = pose_a.inverse().transform(cam.unproject(pix.astype(float), d))
            uv_b = cam.project_world(seq.true_poses[1], world)
            if not np.all(cam.in_image(uv_b, margin_px=1.0)):
                continue
            # Visible in B: the true depth there agrees with the point's depth (no occlusion).
            z_b = pose_b.transform(world)[:, 2]
            db = depth_b[np.round(uv_b[:, 1]).astype(int), np.round(uv_b[:, 0]).astype(int)]
            if not np.all(np.abs(db - seq.true_poses[1].transform(world)[:, 2]) < 0.2):
                continue
            uv_s = cam.project_world(pose_b, world).astype(np.float32)
            if not np.all(cam.in_image(uv_s, margin_px=1.0)) or not np.all(z_b > 0):
                continue
            b = cv2.remap(img_b, uv_s[:, 0].reshape(1, -1), uv_s[:, 1].reshape(1, -1), cv2.INTER_LINEAR).ravel()
            a = img_a[pix[:, 1], pix[:, 0]]
            if a.std() < 8.0:  # textured patches: sensor noise (about 3 grey levels) is small beside them
                continue
            nccs.append(np.corrcoef(a, b)[0, 1])
    return np.array(nccs)


def test_true_surface_points_match_across_views_and_a_wrong_pose_does_not(dome_pair):
    true_ncc = _warped_patch_ncc(dome_pair, dome_pair.true_poses[1])
    assert len(true_ncc) > 50
    # A 0.5 mm error of the second camera centre is 7 px at this resolution (0.075 mm/px at 15 mm).
    wrong = dome_pair.true_poses[1]
    wrong = Pose.from_centre(wrong.rotation, wrong.centre + [0.5, 0.0, 0.0])
    wrong_ncc = _warped_patch_ncc(dome_pair, wrong)
    assert np.median(true_ncc) > 0.85
    assert np.median(wrong_ncc) < 0.4
    assert np.median(true_ncc) - np.median(wrong_ncc) > 0.4


def test_depth_maps_unproject_onto_the_dome_surface(dome_pair):
    info = dome_pair.scene_info["dome"]
    c = np.asarray(info["sphere_centre_mm"])
    cam = dome_pair.camera
    for pose, depth in zip(dome_pair.true_poses, dome_pair.depths):
        ok = np.isfinite(depth)
        assert ok.sum() > 0.5 * cam.mask().sum()
        assert not np.any(ok & ~cam.mask())  # nothing outside the circular field
        pix = cam.pixel_grid()[ok]
        world = pose.inverse().transform(cam.unproject(pix, depth[ok].astype(float)))
        in_cavity = world[:, 2] < -1e-3
        on_sphere = np.abs(np.linalg.norm(world[in_cavity] - c, axis=1) - info["radius_mm"])
        # float32 depth (~2e-6 mm at 25 mm) and tessellation chords (< 0.2 µm) keep points within 1 µm.
        assert on_sphere.max() < 1e-3
        assert np.abs(world[~in_cavity, 2]).max() < 1e-3
        assert world[:, 2].min() >= -DOME_DEPTH_MM - 1e-3


def _iso_internal_radius(s_mm, major, pitch):
    """Radius (mm) of the ISO 68-1 basic internal thread at axial phase s (crest flat starting at s = 0)."""
    h = np.sqrt(3.0) / 2.0 * pitch
    r_maj, r_min = major / 2, major / 2 - 0.625 * h
    s = np.mod(s_mm, pitch)
    return np.interp(s, [0, pitch / 4, 9 * pitch / 16, 11 * pitch / 16, pitch], [r_min, r_min, r_maj, r_maj, r_min])


def test_depth_maps_unproject_onto_the_iso_thread():
    seq = generate("thread", "axial", size=(128, 128), n_frames=30)
    th = seq.scene_info["thread"]
    cam, lead = seq.camera, th["pitch_mm"] / (2 * np.pi)
    n_checked = 0
    for pose, depth in zip(seq.true_poses[::10], seq.depths[::10]):
        ok = np.isfinite(depth)
        world = pose.inverse().transform(cam.unproject(cam.pixel_grid()[ok], depth[ok].astype(float)))
        z = world[:, 2]
        sel = (z < th["thread_top_z_mm"] - 0.05) & (z > th["thread_bottom_z_mm"] + 0.05)
        theta = np.mod(np.arctan2(world[sel, 1], world[sel, 0]), 2 * np.pi)
        r = np.hypot(world[sel, 0], world[sel, 1])
        expected = _iso_internal_radius(z[sel] - lead * theta, th["major_diameter_mm"], th["pitch_mm"])
        # Flanks: a radial error dr is an axial error dr * tan 30°; chords of 0.5° cells stay well under 1 µm.
        assert np.abs(r - expected).max() < 2e-3
        n_checked += sel.sum()
    assert n_checked > 1000


def test_rendering_is_deterministic_for_a_seed_and_noise_changes_with_it():
    a = generate("sheet", size=(64, 64), n_frames=2, seed=5)
    b = generate("sheet", size=(64, 64), n_frames=2, seed=5)
    c = generate("sheet", size=(64, 64), n_frames=2, seed=6)
    for fa, fb, fc in zip(a.frames, b.frames, c.frames):
        np.testing.assert_array_equal(fa, fb)
        assert np.any(fa != fc)
        # Different noise, same scene: the images differ by sensor noise only (a few grey levels).
        assert np.abs(fa.astype(float) - fc).mean() < 6.0


def test_outside_the_circular_field_is_black(dome_pair):
    mask = dome_pair.camera.mask()
    for frame, fluo in zip(dome_pair.frames, dome_pair.fluorescence):
        assert frame[~mask].max() == 0 and fluo[~mask].max() == 0
        assert frame[mask].mean() > 20


def test_fluorescent_targets_are_bright_in_fluorescence_and_nearly_invisible_in_reflectance():
    scene = build_scene("dome")
    star = next(t for t in scene.info["targets"] if t["shape"] == "star")
    centre = np.asarray(star["centroid_mm"])
    cam = Camera.from_fov(240, 240, 40.0)
    from scope3d.geometry.rotation import look_at

    eye = centre + [0.0, 0.0, 14.0]
    pose = Pose.from_centre(look_at(eye, centre, up=(0.0, -1.0, 0.0)), eye)
    out = render_frame(scene, cam, pose, seed=1)
    on = out.target_id == star["id"]
    ring = cv2.dilate(on.astype(np.uint8), np.ones((25, 25), np.uint8)).astype(bool) & ~cv2.dilate(
        on.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool) & (out.target_id == 0)
    assert on.sum() > 500 and ring.sum() > 500
    green = out.fluorescence[..., 1].astype(float)
    assert out.fluorescence[..., [0, 2]].max() == 0
    assert green[on].mean() > 8 * green[ring].mean() + 40
    grey = _grey(out.image)
    # Same vessel texture inside and around: the targets change reflectance by a few percent at most.
    contrast = abs(grey[on].mean() - grey[ring].mean()) / grey[ring].mean()
    assert contrast < 0.15
    assert abs(np.median(green[ring])) < 12


def test_rendered_star_area_matches_scene_json():
    scene = build_scene("dome")
    star = next(t for t in scene.info["targets"] if t["shape"] == "star")
    centre = np.asarray(star["centroid_mm"])
    cam = Camera.from_fov(400, 400, 30.0)
    eye = centre + [0.0, 0.0, 12.0]
    from scope3d.geometry.rotation import look_at

    pose = Pose.from_centre(look_at(eye, centre, up=(0.0, -1.0, 0.0)), eye)
    out = render_frame(scene, cam, pose, seed=0)
    on = out.target_id == star["id"]
    # Each pixel covers (z / f)^2 mm^2 of the (nearly flat-on) surface at its depth.
    pixel_area = (out.depth_mm[on].astype(float) / cam.fx) ** 2
    assert pixel_area.sum() == pytest.approx(star["flat_area_mm2"], rel=0.03)


def test_mip_levels_keep_the_pattern_in_place():
    """A ramp texture (value = column index) read at level k must return the column of the query point:
    cv2.pyrDown keeps a linear ramp and centres level k's texel i on level 0's i 2^k."""
    from scope3d.phantoms.textures import TextureMap

    ramp = np.tile(np.arange(256, dtype=np.uint8), (256, 1))
    tex = TextureMap(ramp, (0.0, 0.0), 0.01)
    uv = np.stack([np.linspace(0.6, 1.9, 50), np.full(50, 1.2)], axis=1)  # mm, far from the borders
    for level, footprint in ((0, 0.01), (1, 0.02), (2, 0.04), (3, 0.08)):
        got = tex.sample(uv, np.full(50, footprint))[:, 0] * 255.0
        # Bilinear reads of an 8-bit ramp are exact to quantisation (0.5 grey level = 0.5 texel).
        assert np.max(np.abs(got - uv[:, 0] / 0.01)) < 0.6, level


def test_supersampling_is_the_box_average_of_a_finer_render():
    """k x k rays per pixel = a k-times finer render averaged over k x k blocks (noise off, fixed gain)."""
    scene = build_scene("thread")
    from scope3d.phantoms import RenderOptions, axial_trajectory, default_camera

    pose = axial_trajectory(1, start_z_mm=-1.0).poses[0]
    cam = default_camera(scene, "axial", size=(64, 64))
    fine = Camera(128, 128, 2 * cam.fx, 2 * cam.fy, 2 * cam.cx + 0.5, 2 * cam.cy + 0.5, mask_radius_px=2 * cam.mask_radius_px)
    quiet = dict(read_noise=0.0, shot_noise=0.0)
    a = render_frame(scene, cam, pose, exposure=3.0, options=RenderOptions(supersample=2, **quiet))
    b = render_frame(scene, fine, pose, exposure=3.0, options=RenderOptions(supersample=1, **quiet))
    boxed = b.image.astype(float).reshape(64, 2, 64, 2, 3).mean(axis=(1, 3))
    inner = np.hypot(*np.meshgrid(np.arange(64) - cam.cx, np.arange(64) - cam.cy)) < cam.mask_radius_px - 2
    assert np.abs(a.image[inner] - boxed[inner]).max() <= 1.0  # rounding of the two 8-bit quantisations
    # Depth stays the centre ray's: identical to a one-ray render.
    c = render_frame(scene, cam, pose, exposure=3.0, options=RenderOptions(supersample=1, **quiet))
    np.testing.assert_array_equal(a.depth_mm, c.depth_mm)


def test_scene_default_supersampling_leaves_the_dome_unchanged():
    from scope3d.phantoms import RenderOptions

    scene = build_scene("dome")
    cam = Camera.from_fov(48, 48, 53.0, mask_radius_px=23.0)
    pose = Pose.from_centre(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 15.0])
    a = render_frame(scene, cam, pose, options=RenderOptions())
    b = render_frame(scene, cam, pose, options=RenderOptions(supersample=1))
    np.testing.assert_array_equal(a.image, b.image)
    assert build_scene("thread").render_supersample == 2 and scene.render_supersample == 1
    with pytest.raises(ValueError, match="supersample"):
        RenderOptions(supersample=0)


def test_target_ids_from_the_box_prefilter_equal_contains_on_every_point():
    # _target_ids asks TrueTarget.contains only about points inside each target's world box; the answer must be
    # exactly the one contains gives on all points (the box bounds the outline box times the depth range).
    from scope3d.phantoms.render import _target_ids

    scene = build_scene("dome")
    rng = np.random.default_rng(5)
    hits_on_targets = []
    for tgt in scene.targets:  # points on and around each target, lifted onto the surface along -n
        uv = rng.uniform(-1.5, 1.5, (400, 2)) * np.abs(tgt.outline_uv_mm).max()
        origins = tgt.origin_mm + uv @ tgt.frame[:2]
        hits = scene.caster.cast(origins, np.broadcast_to(-tgt.frame[2], origins.shape))
        hits_on_targets.append(hits.points[hits.hit])
    points = np.concatenate(hits_on_targets + [rng.uniform(-40, 40, (2000, 3))])
    expected = np.zeros(len(points), np.int16)
    for tgt in scene.targets:
        expected[tgt.contains(points)] = tgt.id
    assert np.count_nonzero(expected) > 100  # the check covers points on targets, not only misses
    np.testing.assert_array_equal(_target_ids(scene, points), expected)


def test_mip_level_grouping_gives_each_point_its_own_levels_lookup():
    # TextureMap.sample groups points by mip level; every point must get what a lookup at its level alone gives.
    from scope3d.phantoms.textures import TextureMap

    rng = np.random.default_rng(2)
    tex = TextureMap(rng.integers(0, 256, (300, 400, 3), dtype=np.uint8), (0.0, 0.0), 0.05)
    uv = rng.uniform(0, 15, (5000, 2))
    footprint = 0.05 * 2.0 ** rng.uniform(-1, 5, 5000)  # levels 0 to 5
    levels = np.clip(np.floor(np.log2(footprint / 0.05) + 0.5), 0, 8).astype(int)
    assert len(np.unique(levels)) >= 5
    expected = np.stack([tex._sample_level(uv[i:i + 1], int(levels[i]))[0] for i in range(len(uv))])
    np.testing.assert_array_equal(tex.sample(uv, footprint), expected)
