"""The quadrant scan plan (metrology.thread_scan_plan): the view's axial extent against the phantom's own
side-view camera, and the plan's step, gap and length rules for every thread size."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.geometry.iso_thread import THREAD_SIZES
from scope3d.metrology.thread_scan_plan import (QuadrantScanPlanOptions, measured_quadrant_scan, minimum_frames,
                                                plan_quadrant_scan, scan_coverage, view_extent_mm)
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
    options = QuadrantScanPlanOptions()
    plan = plan_quadrant_scan(CAMERA, designation, 90.0, options=options)
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


@pytest.mark.parametrize("designation,side_view", [(d, 90.0) for d in THREAD_SIZES] + [("M8x1.25", 45.0)])
def test_a_scan_read_off_its_poses_gets_the_plans_frame_gap(designation, side_view):
    plan = plan_quadrant_scan(CAMERA, designation, side_view)
    # the stage's reported poses of a scan taken by the plan (camera nominally on the axis, untilted)
    trajectory = quadrant_trajectory(plan.frames_per_quadrant, step_mm=plan.step_mm, quadrants=4,
                                     side_view_deg=side_view, axis_offset_mm=(0.0, 0.0))
    for q in range(4):  # every quadrant, each turned by the stage about the hole axis
        poses = trajectory.poses[q * plan.frames_per_quadrant:(q + 1) * plan.frames_per_quadrant]
        scan = measured_quadrant_scan(CAMERA, poses, designation)
        assert scan.frame_gap == plan.frame_gap and scan.frames_per_quadrant == plan.frames_per_quadrant
        # read off float poses: the same step and extent to round-off
        np.testing.assert_allclose([scan.step_mm, scan.view_extent_mm, scan.wall_radius_mm],
                                   [plan.step_mm, plan.view_extent_mm, plan.wall_radius_mm], rtol=1e-9)


def test_a_scan_that_does_not_advance_or_looks_upside_down_is_refused():
    poses = quadrant_trajectory(4, quadrants=1, side_view_deg=90.0, axis_offset_mm=(0.0, 0.0)).poses
    with pytest.raises(ValueError, match="do not advance"):
        measured_quadrant_scan(CAMERA, [poses[0]] * 4, "M8x1.25")
    with pytest.raises(ValueError, match="rows run up"):
        measured_quadrant_scan(CAMERA, poses[::-1], "M8x1.25")  # withdrawing: rows point against the motion


@pytest.mark.parametrize("designation,side_view", [(d, v) for d in THREAD_SIZES for v in (45.0, 90.0)])
def test_the_plans_scan_shows_what_the_gauge_needs_and_one_frame_less_does_not(designation, side_view):
    options = QuadrantScanPlanOptions()
    plan = plan_quadrant_scan(CAMERA, designation, side_view, options=options)
    # the scope crosses a whole view: each wall point is seen views_per_point times, even where a 45° view
    # would show the thread's length in two frames
    assert plan.frames_per_quadrant >= options.views_per_point
    cover = scan_coverage(CAMERA, designation, side_view, plan.step_mm, plan.frames_per_quadrant, options=options)
    assert not cover.short and cover.pitches >= options.thread_pitches
    assert cover.views_per_point == pytest.approx(min(plan.frames_per_quadrant, plan.view_extent_mm / plan.step_mm))
    least = minimum_frames(CAMERA, designation, side_view, plan.step_mm, options=options)
    assert least <= plan.frames_per_quadrant
    if least > 2:  # one frame fewer than the least shows less than the gauge needs
        short = scan_coverage(CAMERA, designation, side_view, plan.step_mm, least - 1, options=options)
        assert short.short and short.pitches < options.thread_pitches
        line = short.message()
        assert "\n" not in line and f"{plan.frames_per_quadrant} frames per quadrant" in line


def test_an_imposed_step_keeps_the_plans_rules():
    plan = plan_quadrant_scan(CAMERA, "M8x1.25", 90.0, step_mm=0.2)
    assert plan.step_mm == 0.2 and plan.frames_per_quadrant == minimum_frames(CAMERA, "M8x1.25", 90.0, 0.2)
    assert plan.frame_gap * 0.2 <= 0.5 * plan.view_extent_mm < (plan.frame_gap + 1) * 0.2
    # a step over the whole view sees each wall point once: nothing to triangulate, however long the scan
    far = scan_coverage(CAMERA, "M8x1.25", 90.0, plan.view_extent_mm * 1.1, 40)
    assert far.short and far.views_per_point < 1
    with pytest.raises(ValueError, match="positive"):
        plan_quadrant_scan(CAMERA, "M8x1.25", 90.0, step_mm=0.0)
