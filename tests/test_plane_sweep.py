"""The multi-view plane sweep against the renderer's true depth maps: one tiny quadrant of the M8 hole
(three 320x256 frames of a 90° side view, 0.3 mm apart, the true poses)."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.mvs.plane_sweep import DenseQuadrantOptions, PlaneSweepOptions, sweep
from scope3d.phantoms.lab import default_camera
from scope3d.phantoms.render import render_frame, sequence_exposure
from scope3d.phantoms.scenes import build_scene
from scope3d.phantoms.trajectories import quadrant_trajectory


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
