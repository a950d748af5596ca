"""The dome benchmark (reference sec. 6.3) in small: rendered frames, real SIFT matches, noisy poses.

Runs the functions of ``benchmarks/bench_bundle_dome.py`` themselves (as pycolmap tests its examples) on
a reduced survey: 3 x 3 frames of 304 x 304 px (53° FOV, so fx = 152 / tan 26.5° = 304.9 px), 5 mm apart,
15 mm above the plate; camera centres reported with uniform noise in ±0.25 mm per axis.

The accuracy bound is derived from the physics and fixed before the test was first run:

* the camera rig may end anywhere inside its boxes, and a common displacement of all cameras moves
  the whole reconstruction with it: at most ``b √3`` = 0.433 mm;
* SIFT localisation, sigma = 0.5 px: laterally ``sigma z / f`` = 0.5 px x 0.082 mm/px = 0.041 mm at the
  deepest point (z = 25 mm), in depth ``z² sigma / (f B)`` = 0.205 mm for the shortest baseline B = 5 mm.

So the median distance of the BCBA points to the true dome (no alignment) must be below
0.433 + 0.041 + 0.205 = 0.68 mm, and the 90th percentile (a few wrong matches survive RANSAC) below
twice that.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from scope3d.estimators.bundle import BoundsWarning, SolverOptions, solve
from scope3d.geometry.pose import Pose
from scope3d.sensor.pose_tolerance import MeasuredPose, perturb_poses_uniform

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_bundle_dome.py"
BOUND_MM = 0.25
SIZE_PX = 304
SIFT_SIGMA_PX = 0.5
Z_MAX_MM = 25.0  # deepest surface point below the cameras: 15 mm stand-off + 10 mm dome depth
BASELINE_MM = 5.0  # shortest baseline of the grid


def _load_bench():
    spec = importlib.util.spec_from_file_location("bench_bundle_dome", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_bundle_dome"] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def dome():
    bench = _load_bench()
    survey = bench.render_survey(size_px=SIZE_PX, rows=3, cols=3)
    measured = perturb_poses_uniform(survey.true_poses, BOUND_MM, 0.0, seed=3)
    tracks = bench.initial_tracks(survey, measured, BOUND_MM)
    solved = {m: bench.solve_method(m, survey, measured, tracks, BOUND_MM) for m in ("BA", "BCBA")}
    return bench, survey, measured, tracks, solved


def physical_bound_mm(fx_px: float) -> float:
    """Median-distance bound (mm) derived in the module docstring."""
    rig = BOUND_MM * np.sqrt(3.0)
    lateral = SIFT_SIGMA_PX * Z_MAX_MM / fx_px
    depth = Z_MAX_MM**2 * SIFT_SIGMA_PX / (fx_px * BASELINE_MM)
    return rig + lateral + depth


def test_survey_has_real_matches(dome):
    _, survey, _, tracks, _ = dome
    assert survey.camera.width == SIZE_PX
    assert len(survey.frames) == 9
    assert sum(len(m) > 0 for m in survey.matches) >= 8  # at least the grid neighbours
    assert tracks.n_tracks >= 300


def test_bound_is_the_one_derived(dome):
    """The box BCBA applies is the dataset's tolerance around each reported centre, and it binds."""
    bench, survey, measured, tracks, solved = dome
    problem, result, _ = solved["BCBA"]
    # the dataset's tolerance: +-0.25 mm per axis on the centre, the orientation exact
    centres = np.stack([mp.pose.centre for mp in measured])
    half = np.stack([mp.tolerance.position_mm for mp in measured])
    assert np.all(half == BOUND_MM) and all(np.all(mp.tolerance.orientation_rad == 0) for mp in measured)
    # what the library put into the problem it solved: centre +- tolerance per world axis, orientation held
    np.testing.assert_allclose(problem.pose_lower[:, 3:], centres - half, rtol=0, atol=1e-12)
    np.testing.assert_allclose(problem.pose_upper[:, 3:], centres + half, rtol=0, atol=1e-12)
    assert problem.pose_fixed[:, :3].all() and not problem.pose_fixed[:, 3:].any()
    np.testing.assert_array_equal(result.parameters.pose[:, :3], 0.0)
    solved_c = result.parameters.pose[:, 3:]
    assert np.all(solved_c >= problem.pose_lower[:, 3:]) and np.all(solved_c <= problem.pose_upper[:, 3:])

    # It binds. Camera 4 (the grid's centre) is reported 0.6 mm too far along +x with the same +-0.25 mm, so
    # its true centre lies 0.35-0.85 mm below its box in x. Started at the truth (outside: clamped onto the
    # box, with a warning), it is pulled towards the truth by its images and held on the box's face.
    c = 4
    moved = Pose.from_centre(measured[c].pose.rotation, measured[c].pose.centre + [0.6, 0.0, 0.0])
    shifted = measured[:c] + [MeasuredPose(moved, measured[c].tolerance)] + measured[c + 1:]
    lower_x = moved.centre[0] - BOUND_MM
    assert survey.true_poses[c].centre[0] < lower_x - 0.1
    pushed = bench.build_problem("BCBA", survey.camera, shifted, tracks, BOUND_MM)
    pushed.initial.pose[c, 3:] = survey.true_poses[c].centre
    with pytest.warns(BoundsWarning, match="clamped"):
        out = solve(pushed, SolverOptions(max_iterations=bench.MAX_ITERATIONS))
    x = out.parameters.pose[:, 3]
    assert x[c] == pytest.approx(lower_x, abs=1e-9)  # on the face, not beyond it
    others = np.arange(len(measured)) != c
    assert np.all(np.abs(out.parameters.pose[others, 3:] - centres[others]) <= BOUND_MM + 1e-9)


def test_bcba_keeps_every_camera_in_its_box(dome):
    _, _, measured, _, solved = dome
    _, result, _ = solved["BCBA"]
    for mp, pose in zip(measured, result.poses):
        assert np.all(np.abs(pose.centre - mp.pose.centre) <= BOUND_MM + 1e-9)
        np.testing.assert_allclose(pose.rotation, mp.pose.rotation, atol=1e-12)  # orientation fixed


def test_bcba_surface_error_below_physical_bound(dome):
    _, survey, _, _, solved = dome
    _, result, _ = solved["BCBA"]
    d = survey.truth.distances(result.points_world)
    bound = physical_bound_mm(survey.camera.fx)
    assert np.median(d) < bound
    assert np.percentile(d, 90) < 2 * bound


def test_unconstrained_ba_is_no_better_than_bcba(dome):
    _, survey, _, _, solved = dome
    d = {m: survey.truth.distances(solved[m][1].points_world) for m in solved}
    assert np.median(d["BA"]) >= np.median(d["BCBA"])
    assert np.mean(d["BA"]) >= np.mean(d["BCBA"])


def test_evaluate_reports_what_the_table_needs(dome):
    bench, survey, measured, _, solved = dome
    problem, result, _ = solved["BCBA"]
    row, direct, aligned = bench.evaluate(survey, problem, result, measured)
    for key in ("iterations", "time_s", "final_cost", "fov_x_deg", "q_z_p1_p99_mm", "surface_direct_mm",
                "surface_after_icp_mm", "camera_moved_from_measured_max_mm"):
        assert key in row
    assert row["camera_moved_from_measured_max_mm"] <= BOUND_MM + 1e-9
    assert len(direct) == len(aligned) == len(result.points_world)
    assert row["surface_direct_mm"]["n"] == row["surface_after_icp_mm"]["n"] == len(result.points_world)


def test_unknown_method_is_rejected(dome):
    bench, survey, measured, tracks, _ = dome
    with pytest.raises(ValueError, match="unknown method"):
        bench.build_problem("magic", survey.camera, measured, tracks, BOUND_MM)
