"""The dense map (issue 35): fusion keeps what the views agree on and rejects what they do not; on the
resection cavity the recess under the overhanging lip is reconstructed."""
import numpy as np
import pytest

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at
from scope3d.mvs.dense_map import DenseOptions, FrameDepth, frame_depths, fuse_depths, poisson_mesh
from scope3d.sensor.camera import Camera

SIGMA_MM = 0.01


def _plane_views(size=64):
    """Nine cameras 15 mm above the plane z = 0.2 x, 2 mm apart, looking down; their exact depth maps."""
    camera = Camera.from_fov(size, size, 53.0)
    poses = []
    for x in (-2.0, 0.0, 2.0):
        for y in (-2.0, 0.0, 2.0):
            eye = np.array([x, y, 15.0])
            poses.append(Pose.from_centre(look_at(eye, eye - [0.0, 0.0, 1.0], up=(0.0, -1.0, 0.0)), eye))
    grid = camera.pixel_grid().reshape(-1, 2)
    normal = np.array([-0.2, 0.0, 1.0])
    depths = []
    for pose in poses:
        rays = camera.unproject(grid, 1.0)  # z = 1 in the camera
        dirs = rays @ pose.rotation  # camera to world: R^T r as rows
        t = -(pose.centre @ normal) / (dirs @ normal)  # ray-plane: (c + t d) . n = 0
        z = t.reshape(camera.height, camera.width)
        depths.append(FrameDepth(z, np.full_like(z, SIGMA_MM), np.ones_like(z), [], (10.0, 20.0)))
    images = [np.zeros((camera.height, camera.width, 3), np.uint8) for _ in poses]
    return camera, poses, depths, images


def test_fusion_keeps_agreeing_depths_and_rejects_a_wrong_patch():
    camera, poses, depths, images = _plane_views()
    wrong = depths[4].depth_mm.copy()
    # 10 sigma off: three sigmas of the difference (sqrt 2 sigma) is 4.2 sigma, far below it
    wrong[20:40, 20:40] += 10 * SIGMA_MM
    depths[4] = FrameDepth(wrong, depths[4].sigma_mm, depths[4].score, [], (10.0, 20.0))
    fused = fuse_depths(camera, images, poses, depths, options=DenseOptions(merge_mm=0.0))
    keep = fused.consistent[4]
    assert not keep[20:40, 20:40].any()
    # every other pixel of the centre view is seen by its eight neighbours' maps wherever they reach; those
    # at least two of them see agree (exact depths: only interpolating a depth map between pixels errs,
    # by far less than a sigma on a plane 15 mm away)
    assert keep[5:59, 5:59].sum() == (54 * 54 - 20 * 20)
    assert fused.rejected >= 400


def test_fused_points_of_exact_depths_lie_on_the_surface():
    camera, poses, depths, images = _plane_views()
    fused = fuse_depths(camera, images, poses, depths, options=DenseOptions(merge_mm=0.0))
    # each is an inverse-variance mean of exact depths, read between pixels: a plane's depth is not linear in
    # the pixel (its inverse is), off by the depth's second difference over a pixel, ~ 1e-6 mm here
    p = fused.cloud.points
    assert np.abs(p[:, 2] - 0.2 * p[:, 0]).max() < 0.01 * SIGMA_MM
    # normals face the cameras: the plane's (-0.2, 0, 1), normalised
    n = fused.cloud.normals
    np.testing.assert_allclose(n, np.tile([-0.2, 0.0, 1.0] / np.hypot(0.2, 1.0), (len(n), 1)), atol=1e-6)


def test_fusion_reads_more_points_than_an_int16_holds():
    # 192 x 192 = 36,864 pixels per frame: more than cv2.remap's 32,767 a side, read where each frame's points
    # project into every other. The centre view's pixels whose points fall at least 3 pixels inside the
    # frame 2 mm away in x (~13 px at 15 mm) and in y agree with eight views' exact depths, all of them.
    camera, poses, depths, images = _plane_views(192)
    assert camera.width * camera.height > 32767
    fused = fuse_depths(camera, images, poses, depths, options=DenseOptions(merge_mm=0.0))
    keep = fused.consistent[4]
    assert keep[16:-16, 16:-16].all()
    assert fused.counts["consistent"] > 9 * 0.5 * camera.width * camera.height


def test_a_depth_needs_two_other_views():
    camera, poses, depths, images = _plane_views()
    only = [d if k in (4, 5) else None for k, d in enumerate(depths)]  # one other view
    fused = fuse_depths(camera, images, poses, only, options=DenseOptions())
    assert len(fused.cloud) == 0
    fused = fuse_depths(camera, images, poses, only, options=DenseOptions(min_consistent_views=1))
    assert len(fused.cloud) > 0


@pytest.fixture(scope="module")
def cavity():
    from scope3d.phantoms import generate

    return generate("cavity", size=(304, 304), seed=0)


def test_the_recess_under_the_lip_is_reconstructed(cavity):
    from scope3d.metrology.evaluation import visible_true_points
    from scope3d.phantoms.scenes import cavity_rim_radius
    from scope3d.scene.mesh import SampledSurface

    seq = cavity
    # the frames that look under the lip (x = 0 and 5 mm, y within 7.5 mm) and their neighbours
    frames = [6, 7, 12, 13, 16, 17, 22, 23]
    camera, poses = seq.camera, [seq.true_poses[k] for k in frames]
    images = [seq.frames[k] for k in frames]
    # the sparse map only brackets the depths: the true points these frames see stand in for it
    sparse = visible_true_points(camera, poses, lambda k: seq.depths[frames[k]], max_points=3000)
    options = DenseOptions(neighbours=6)
    depths = frame_depths(camera, images, poses, sparse, options=options)
    fused = fuse_depths(camera, images, poses, depths, options=options)
    p = fused.cloud.points
    theta, r = np.arctan2(p[:, 1], p[:, 0]), np.hypot(p[:, 0], p[:, 1])
    truth = SampledSurface(seq.surface, 0.02)
    # under the lip: more than 0.1 mm beyond the rim's edge, below the plate
    under = (r > cavity_rim_radius(theta) + 0.1) & (p[:, 2] < -1.0)
    assert under.sum() >= 50
    err = truth.distances(p[under])
    # The sweep steps its depths by 1 px of parallax in the longest-baseline source and refines within a step
    # by a parabola; its predicted sigma is 0.1 px of parallax (PlaneSweepOptions.match_sigma_px), so a
    # quarter step is 2.5 of one depth's sigma (a fused point's sigma times the root of its support undoes
    # the averaging). The recess is seen at grazing angles, where a square window matches worst: its median
    # error stays within a quarter step.
    single_sigma = fused.sigma_mm[under] * np.sqrt(fused.support[under])
    sweep = options.sweep
    quarter_step = 0.25 * sweep.step_px / sweep.match_sigma_px * single_sigma
    assert np.median(err) <= np.median(quarter_step)
    mesh = poisson_mesh(fused.cloud, options=options)
    v = mesh.vertices
    tv, rv = np.arctan2(v[:, 1], v[:, 0]), np.hypot(v[:, 0], v[:, 1])
    assert np.sum((rv > cavity_rim_radius(tv) + 0.1) & (v[:, 2] < -1.0)) >= 50


@pytest.fixture(scope="module")
def dome():
    from scope3d.phantoms import generate

    return generate("dome", size=(304, 304), seed=0)


def test_a_dome_frame_from_its_best_two_of_eight_sources(dome):
    # One frame of the dome (true poses) swept against its eight neighbours, scored per pixel by the best two
    # sources or by all eight. The moving light's highlights and the plate's edge leave some sources without
    # a match at a pixel; all eight averaged lose that pixel, the best two keep it. Both hold the sweep's noise
    # model against the true depth: 0.1 px of parallax per match (PlaneSweepOptions.match_sigma_px), so a
    # parabola-refined NCC peak within a quarter pixel for most kept pixels and a pixel for nearly all.
    from dataclasses import replace

    from scope3d.metrology.evaluation import visible_true_points
    from scope3d.mvs.dense_map import select_neighbours
    from scope3d.mvs.plane_sweep import sweep

    seq = dome
    camera, poses, images = seq.camera, seq.true_poses, list(seq.frames)
    sparse = visible_true_points(camera, poses, lambda k: seq.depths[k], max_points=3000)
    options = DenseOptions()
    frame = 7
    sources = select_neighbours(camera, poses, sparse, options=options)[frame]
    assert len(sources) == options.neighbours
    truth = seq.depths[frame]
    near, far = np.nanpercentile(truth, [1, 99]) * np.array([0.85, 1.15])
    kept = {}
    for name, sweep_options in (("best two", options.sweep), ("all eight", replace(options.sweep, best_sources=None))):
        d = sweep(camera, images[frame], poses[frame], [images[k] for k in sources], [poses[k] for k in sources],
                  (near, far), options=sweep_options)
        ok = np.isfinite(d.depth_mm) & np.isfinite(truth)
        epipolar_px = np.abs(d.depth_mm - truth)[ok] / d.sigma_mm[ok] * sweep_options.match_sigma_px
        assert np.median(epipolar_px) < 0.25, name
        assert np.mean(epipolar_px < 1.0) > 0.9, name
        kept[name] = ok.sum()
    assert kept["best two"] > 1.3 * kept["all eight"]
