"""The quadrant scan plan (metrology.thread_scan_plan): the view's axial extent against the phantom's own
side-view camera, and the plan's step, gap and length rules for every thread size."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.metrology.thread_gauge import THREAD_SIZES
from scope3d.metrology.thread_scan_plan import ScanPlanOptions, plan_quadrant_scan, view_extent_mm
from scope3d.phantoms.trajectories import quadrant_trajectory
from scope3d.sensor.camera import Camera

CAMERA = Camera.from_fov(400, 320, 60.0)


@pytest.mark.parametrize("side_view", [45.0, 90.0])
def test_view_extent_matches_the_side_view_cameras_image_rows(side_view):
    radius = 3.6
    above, below = view_extent_mm(CAMERA, side_view, radius)
    pose = quadrant_trajectory(1, quadrants=1, side_view_deg=side_view, axis_offset_mm=(0.0, 0.0)).poses[0]
    centre_z = -1.5  # the trajectory's start
    # the wall points straight ahead of the camera's image column (quadrant 0 looks along +x) at the
    # extent's two ends must project onto the image's top and bottom edges
    pixels = CAMERA.project_world(pose, np.array([[radius, 0.0, centre_z + above], [radius, 0.0, centre_z - below]]))
    np.testing.assert_allclose(pixels[:, 1], [0.0, CAMERA.height], atol=1e-6)  # exact geometry: float round-off
    np.testing.assert_allclose(pixels[:, 0], CAMERA.cx, atol=1e-6)


@pytest.mark.parametrize("designation", list(THREAD_SIZES))
def test_plan_keeps_views_per_point_overlap_and_thread_length(designation):
    options = ScanPlanOptions()
    plan = plan_quadrant_scan(CAMERA, designation, 90.0, options)
    _, pitch = THREAD_SIZES[designation]
    # the step is E / views, rounded down to the stage's hundredths: each point is seen at least that often
    assert plan.view_extent_mm / plan.step_mm >= options.views_per_point
    assert plan.view_extent_mm / (plan.step_mm + 0.01) < options.views_per_point
    # matched frames overlap by at least half a view, and the largest such gap is used
    assert plan.frame_gap * plan.step_mm <= options.max_baseline_fraction * plan.view_extent_mm
    assert (plan.frame_gap + 1) * plan.step_mm > options.max_baseline_fraction * plan.view_extent_mm
    _, below = view_extent_mm(CAMERA, 90.0, plan.wall_radius_mm)
    shown = options.start_below_thread_mm + (plan.frames_per_quadrant - 1) * plan.step_mm + below
    assert options.thread_pitches * pitch <= shown < options.thread_pitches * pitch + plan.step_mm


def test_smaller_holes_get_smaller_steps_and_a_view_down_the_hole_is_refused():
    steps = [plan_quadrant_scan(CAMERA, d).step_mm for d in THREAD_SIZES]
    assert steps == sorted(steps)  # M6 < M8 < M10: the wall is nearer, the view shorter
    with pytest.raises(ValueError, match="looks"):
        view_extent_mm(CAMERA, 20.0, 3.0)
