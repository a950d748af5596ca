"""The multi-view plane sweep against the renderer's true depth maps: one tiny quadrant of the M8 hole
(three 320x256 frames of a 90° side view, 0.3 mm apart, the true poses)."""
from __future__ import annotations

import tracemalloc
from dataclasses import replace

import cv2
import numpy as np
import pytest

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at
from scope3d.mvs.plane_sweep import DenseQuadrantOptions, PlaneSweepOptions, depth_hypotheses, sweep
from scope3d.phantoms.lab import default_camera
from scope3d.phantoms.render import render_frame, sequence_exposure
from scope3d.phantoms.scenes import build_scene
from scope3d.phantoms.trajectories import quadrant_trajectory
from scope3d.sensor.camera import Camera


@pytest.fixture(scope="module")
def quadrant():
    scene = build_scene("thread", thread_offsets_mm=(0.132, 0.08, 0.05))
    camera = default_camera(scene, "quadrants", size=(320, 256))
    poses = quadrant_trajectory(3, step_mm=0.3, quadrants=1, side_view_deg=90.0, axis_offset_mm=(0.2, -0.1),
                                axis_tilt_deg=0.5).poses
    exposure = sequence_exposure(scene, camera, poses)
    frames = [render_frame(scene, camera, p, seed=0, frame_index=i, exposure=exposure) for i, p in enumerate(poses)]
    return camera, poses, frames


def test_sweep_matches_the_true_depth_within_its_noise_model(quadrant):
    camera, poses, frames = quadrant
    truth = frames[0].depth_mm
    near, far = np.nanpercentile(truth, [2, 98]) * np.array([0.9, 1.1])
    result = sweep(camera, frames[0].image, poses[0], [f.image for f in frames[1:]], poses[1:], (near, far),
                   options=PlaneSweepOptions(stride_px=1))
    kept = np.isfinite(result.depth_mm) & np.isfinite(truth)
    assert kept.sum() >= 0.4 * np.isfinite(truth).sum()  # the gates keep most of the textured wall
    error = result.depth_mm[kept] - truth[kept]
    sigma = result.sigma_mm[kept]
    # sigma is the depth change of a 0.1 px shift along the epipolar line (the module's noise model), so
    # error / sigma * 0.1 is each pixel's matching error in pixels.
    epipolar_px = np.abs(error) / sigma * PlaneSweepOptions().match_sigma_px
    # No depth bias beyond one match's noise; a parabola-refined NCC peak localises to a quarter pixel
    # (its pixel-locking bias) for most pixels, and within a pixel for all but windows that straddle a
    # crest's edge or see an occlusion.
    assert abs(np.median(error)) < np.median(sigma)
    assert np.median(epipolar_px) < 0.25
    assert np.mean(epipolar_px < 1.0) > 0.9
    # the points are the kept pixels at their depths, in the reference camera
    np.testing.assert_allclose(result.points_cam[:, 2], result.depth_mm[np.isfinite(result.depth_mm)], rtol=1e-9)


def test_sweep_options_are_checked():
    with pytest.raises(ValueError):
        PlaneSweepOptions(window_px=6)
    with pytest.raises(ValueError):
        PlaneSweepOptions(max_depth_sigma_mm=0.0)
    with pytest.raises(ValueError):
        DenseQuadrantOptions(max_frame_gap=0)


# --- a slanted textured plane, its images rendered exactly (the texture resampled where each ray meets it) ---

PLANE_SLOPE = 0.2  # the plane z = 0.2 x (mm world), 15 mm below the cameras


def _plane_images(camera, poses, texture_seed=0):
    rng = np.random.default_rng(texture_seed)
    # blurred noise, 20 texels per mm: ~4 px per texel at 15 mm with this camera, well above the 7 px
    # window's noise floor
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (1024, 1024)).astype(np.float32), (0, 0), 2.0)
    grid = camera.pixel_grid().reshape(-1, 2)
    normal = np.array([-PLANE_SLOPE, 0.0, 1.0])
    images, depths = [], []
    for pose in poses:
        rays = camera.unproject(grid, 1.0)  # z = 1 in the camera
        dirs = rays @ pose.rotation  # camera to world: R^T r as rows
        t = -(pose.centre @ normal) / (dirs @ normal)  # ray-plane: (c + t d) . n = 0; z = 1 so t is the depth
        x = pose.centre + t[:, None] * dirs
        u = (x[:, 0] * 20 + 512).astype(np.float32).reshape(camera.height, camera.width)
        v = (x[:, 1] * 20 + 512).astype(np.float32).reshape(camera.height, camera.width)
        images.append(np.clip(cv2.remap(texture, u, v, cv2.INTER_LINEAR), 0, 255).astype(np.uint8))
        depths.append(t.reshape(camera.height, camera.width))
    return images, depths


def _plane_rig(k1=0.0):
    camera = Camera.from_fov(96, 96, 53.0, k1=k1)
    poses = []
    for x, y in [(0, 0), (2, 0), (-2, 0), (0, 2), (0, -2)]:
        eye = np.array([x, y, 15.0])
        poses.append(Pose.from_centre(look_at(eye, eye - [0.0, 0.0, 1.0], up=(0.0, -1.0, 0.0)), eye))
    return camera, poses


def test_homography_warps_match_per_pixel_projection():
    # A camera without distortion is swept by one homography per plane and source; a distortion too small to
    # move a pixel (1e-12 at the corner) takes the per-pixel projection instead. Both resample the same
    # points: the depths differ only by the projection's float32 round-off, far below a match's noise.
    camera, poses = _plane_rig()
    images, _ = _plane_images(camera, poses)
    options = PlaneSweepOptions(stride_px=1)
    a = sweep(camera, images[0], poses[0], images[1:], poses[1:], (10.0, 20.0), options=options)
    b = sweep(replace(camera, k1=1e-12), images[0], poses[0], images[1:], poses[1:], (10.0, 20.0), options=options)
    kept = np.isfinite(a.depth_mm)
    assert kept.sum() > 1000
    np.testing.assert_array_equal(kept, np.isfinite(b.depth_mm))
    assert np.abs(a.depth_mm - b.depth_mm)[kept].max() < 0.01 * np.median(a.sigma_mm[kept])


def test_best_sources_ignore_sources_that_see_something_else():
    # Two of the four sources see another surface where the reference sees the plane (an occluder in front of
    # the plane, or the light's glint, in those views): their NCC there is noise about 0. Averaged over all
    # four the plane's peak drops to about (1 + 1 + 0 + 0) / 4, below min_ncc = 0.6, so most pixels are lost;
    # each pixel's best two still find it, within the sweep's noise model (0.1 px of parallax, the match's
    # sigma), for the pixels both clean sources see.
    camera, poses = _plane_rig()
    images, truth = _plane_images(camera, poses)
    other, _ = _plane_images(camera, poses, texture_seed=1)
    sources = [images[1], other[2], images[3], other[4]]
    every = sweep(camera, images[0], poses[0], sources, poses[1:], (10.0, 20.0),
                  options=PlaneSweepOptions(stride_px=1))
    best2 = sweep(camera, images[0], poses[0], sources, poses[1:], (10.0, 20.0),
                  options=PlaneSweepOptions(stride_px=1, best_sources=2))
    kept = np.isfinite(best2.depth_mm)
    # the pixels whose point falls inside both clean sources with a window's margin (and a pixel for the
    # bilinear read), and whose own window is inside the reference
    points = poses[0].inverse().transform(camera.unproject(camera.pixel_grid().reshape(-1, 2), truth[0].reshape(-1)))
    margin = PlaneSweepOptions().window_px // 2 + 1
    seen = np.ones(len(points), bool)
    for k in (1, 3):
        uv = camera.project_world(poses[k], points)
        seen &= np.all((uv >= margin) & (uv <= np.array([camera.width, camera.height]) - 1 - margin), axis=1)
    seen = seen.reshape(camera.height, camera.width)
    seen[:margin] = seen[-margin:] = seen[:, :margin] = seen[:, -margin:] = False
    assert seen.sum() > 2000
    assert kept[seen].mean() > 0.9
    assert np.isfinite(every.depth_mm)[seen].mean() < 0.25
    epipolar_px = np.abs(best2.depth_mm - truth[0])[kept] / best2.sigma_mm[kept] * PlaneSweepOptions().match_sigma_px
    assert np.median(epipolar_px) < 0.25 and np.mean(epipolar_px < 1.0) > 0.9


def test_sweep_memory_does_not_grow_with_the_planes():
    # Only running figures per pixel (a few per source, and the last window-width of planes' scores for the
    # second peak), never a score per depth plane: a sweep over 6x more planes, at the same step, peaks at
    # the same memory, where a stack of scores would grow by one image per added plane.
    camera, poses = _plane_rig()
    images, _ = _plane_images(camera, poses)
    options = PlaneSweepOptions(stride_px=1, step_px=0.5, max_depths=1000)
    peaks, planes = [], []
    for depth_range in ((10.0, 20.0), (3.0, 100.0)):
        tracemalloc.start()
        sweep(camera, images[0], poses[0], images[1:], poses[1:], depth_range, options=options)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        planes.append(len(depth_hypotheses(camera, poses[0], poses[1:], depth_range, options=options)))
    assert planes[1] >= 6 * planes[0]
    image_bytes = camera.width * camera.height * 4  # one float32 score per pixel
    assert peaks[1] - peaks[0] < 0.1 * (planes[1] - planes[0]) * image_bytes


def test_best_sources_is_checked():
    with pytest.raises(ValueError):
        PlaneSweepOptions(best_sources=0)
