"""Approach path planning: clearance from the mapped surface, the descent onto the target, re-planning."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.sfm.approach import ApproachOptions, plan_approach, replan, save_approach_png


def _bumpy_floor(step=0.2):
    """A floor z = 0 with a 4 mm Gaussian ridge along y at x = 0 (sigma 1.5 mm): the straight line from
    one side of the ridge to a target on the other passes through it."""
    x, y = np.meshgrid(np.arange(-10, 10, step), np.arange(-5, 5, step))
    z = 4.0 * np.exp(-x**2 / (2 * 1.5**2))
    return np.c_[x.ravel(), y.ravel(), z.ravel()]


def _distance_to(surface, path):
    from scipy.spatial import cKDTree

    return cKDTree(surface).query(path)[0]


def test_the_path_keeps_the_safety_distance_where_the_straight_line_would_not(tmp_path):
    dense = _bumpy_floor(0.05)  # the "true" surface, to judge the plan made from sparse map points
    sparse = _bumpy_floor(0.5)
    target, start = np.array([5.0, 0.0, 0.0]), np.array([-6.0, 0.0, 1.5])
    # the normal from points within 1.5 mm: the ridge's foot (x < 3 mm) would tilt it
    opts = ApproachOptions(safety_distance_mm=1.5, normal_radius_mm=1.5)
    straight = np.linspace(start, target, 200)
    assert _distance_to(dense, straight).min() < 0.1  # the straight line goes through the ridge
    plan = plan_approach(sparse, target, start, options=opts)
    assert plan.feasible
    # the floor's normal at the target, tilted by the ridge's foot (0.26 mm high at x = 3.5 mm): ~3 deg
    assert np.rad2deg(np.arccos(plan.normal[2])) < 5.0
    np.testing.assert_allclose(plan.goal_mm, target + 1.5 * plan.normal, atol=1e-9)
    np.testing.assert_allclose(plan.waypoints_mm[0], start)
    np.testing.assert_allclose(plan.waypoints_mm[-1], plan.goal_mm)
    # against the dense surface the clearance holds up to the sparse sampling's half spacing (0.25 mm)
    # minus what the spacing correction already took off: never below safety - 0.25 mm
    assert _distance_to(dense, plan.waypoints_mm).min() >= 1.5 - 0.25
    # the last stretch is a straight descent along the normal
    last = plan.waypoints_mm[-int(np.ceil(opts.descent_mm / opts.step_mm)) - 1:]
    off_axis = np.linalg.norm(np.cross(last - target, plan.normal), axis=1)
    assert off_axis.max() < 1e-9
    # re-planning from a point part-way along reaches the same goal and stays clear
    again = replan(plan, sparse, plan.waypoints_mm[len(plan.waypoints_mm) // 3], options=opts)
    assert again.feasible and again.length_mm < plan.length_mm
    np.testing.assert_allclose(again.goal_mm, plan.goal_mm)
    save_approach_png(tmp_path / "a.png", sparse, [plan, again])
    assert (tmp_path / "a.png").stat().st_size > 5000


def test_a_target_without_map_points_around_it_is_refused():
    with pytest.raises(ValueError, match="no normal"):
        plan_approach(_bumpy_floor(0.5), np.array([50.0, 0, 0]), np.array([0.0, 0, 10]))
    with pytest.raises(ValueError):
        ApproachOptions(safety_distance_mm=0)
