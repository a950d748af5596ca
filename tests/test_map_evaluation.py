"""Evaluation against a true surface: distances, ICP from eight starts, summaries, figures."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from scope3d.estimators.icp import IcpOptions, icp_point_to_plane
from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.metrology.evaluation import (
    EvaluationOptions,
    distance_summary,
    icp_from_initial_poses,
    save_error_histogram_png,
    save_error_map_png,
    surface_distances,
)
from scope3d.scene.mesh import Mesh, SampledSurface


@pytest.fixture(scope="module")
def bowl():
    """An asymmetric bowl (ellipsoid cap) so that ICP has a unique answer."""
    s = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    v = s.vertices * [15.0, 11.0, 8.0]
    keep = v[:, 2] < 0
    faces = s.faces[np.all(keep[s.faces], axis=1)]
    mesh = Mesh(v, faces)
    return mesh, SampledSurface(mesh, 0.1)


def _points_on(mesh, n, seed=0):
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    pts, _ = trimesh.sample.sample_surface(tm, n, seed=seed)
    return np.asarray(pts)


def test_distance_of_points_on_and_off_the_surface(bowl):
    mesh, sampled = bowl
    pts = _points_on(mesh, 2000)
    assert surface_distances(pts, sampled).max() < 0.01  # sampling error only (faceted mesh vs samples)
    # moved 0.5 mm along the vertex normals: distance 0.5 mm
    grad = pts / np.array([15.0, 11.0, 8.0]) ** 2
    grad /= np.linalg.norm(grad, axis=1, keepdims=True)
    d = surface_distances(pts + 0.5 * grad, sampled)
    assert np.median(d) == pytest.approx(0.5, abs=0.02)
    far = surface_distances(np.array([[0.0, 0.0, 30.0]]), sampled)
    # beyond the rim the tangent plane of the nearest sample is not the surface: a real distance
    # (the nearest rim point is at (0, +-11, 0): 31.95 mm), and unreferenced vertices do not count
    assert far[0] == pytest.approx(np.hypot(30.0, 11.0), rel=0.02)


def test_icp_recovers_a_rigid_misplacement_from_any_of_eight_starts(bowl):
    mesh, sampled = bowl
    pts = _points_on(mesh, 3000, seed=1)
    R = rotvec_to_matrix(np.deg2rad([2.0, -1.5, 3.0]))
    moved = pts @ R.T + [0.8, -0.5, 0.4]
    assert distance_summary(surface_distances(moved, sampled))["mean"] > 0.3
    best, spread = icp_from_initial_poses(moved, sampled)
    assert len(spread) == 8
    assert max(spread) < 0.02 and max(spread) - min(spread) < 0.01
    aligned = best.apply(moved)
    assert distance_summary(surface_distances(aligned, sampled))["mean"] < 0.02


def test_icp_from_identity_on_aligned_points_stays_put(bowl):
    mesh, sampled = bowl
    pts = _points_on(mesh, 1000, seed=2)
    r = icp_point_to_plane(pts, sampled)
    assert np.abs(r.rotation - np.eye(3)).max() < 1e-3 and np.abs(r.translation).max() < 1e-2


def test_icp_on_a_symmetric_dome_stops_within_the_poses_uncertainty():
    """A paraboloid of revolution over a disc is symmetric about its axis: the distances do not constrain
    a spin about it, and ICP's steps along it are the sampling's noise. ICP corrects the tilt and offset
    in a few steps and stops there, at the distance 100 steps reach, instead of wandering about the axis
    until the iteration cap (what the 1 um step test alone did on the dome phantom)."""
    g = np.linspace(-10.0, 10.0, 81)
    xx, yy = np.meshgrid(g, g)
    v = np.c_[xx.ravel(), yy.ravel(), (xx.ravel() ** 2 + yy.ravel() ** 2) / 10.0]
    k = (np.arange(80 * 80).reshape(80, 80) + np.arange(80)[:, None]).ravel()  # each grid cell's corner
    faces = np.r_[np.c_[k, k + 1, k + 82], np.c_[k, k + 82, k + 81]]
    inside = np.hypot(v[:, 0], v[:, 1]) < 9.0
    mesh = Mesh(v, faces[np.all(inside[faces], axis=1)])
    sampled = SampledSurface(mesh, 0.25)
    pts = _points_on(mesh, 1000, seed=3)
    pts += np.random.default_rng(0).normal(0.0, 0.05, pts.shape)  # a map's noise, as on the dome phantom
    R0 = rotvec_to_matrix(np.deg2rad([2.0, -1.0, 4.0]))
    moved = pts @ R0.T + [0.3, -0.2, 0.4]
    r = icp_point_to_plane(moved, sampled)
    assert r.iterations < 20  # the cap is 100
    R = r.rotation @ R0  # truth to aligned
    assert np.degrees(np.arccos(np.clip(R[2, 2], -1, 1))) < 0.3  # the axis back on z (tilted by 2.2 deg)
    # the same distance as 100 steps: within sigma^2 / N of the weighted squares (~1e-6 of the mean here;
    # 1 um allows for the Huber weights' and the approximate search's differences between the two ends)
    capped = icp_point_to_plane(moved, sampled, IcpOptions(min_decrease_sigma2=0.0))
    assert capped.iterations == 100
    mean = np.mean(sampled.distances(r.apply(moved)))
    assert abs(mean - np.mean(sampled.distances(capped.apply(moved)))) < 1e-3
    assert mean < 0.045  # the noise floor: the mean |N(0, 0.05 mm)| along the normal is 0.040 mm


def test_summary_and_figures(tmp_path):
    d = np.array([0.1, 0.2, 0.3, 2.0])
    s = distance_summary(d)
    assert s["mean"] == pytest.approx(0.65) and s["within_1mm_fraction"] == 0.75 and s["n"] == 4
    assert distance_summary(np.array([np.nan]))["n"] == 0
    save_error_histogram_png(tmp_path / "h.png", d)
    save_error_map_png(tmp_path / "m.png", np.random.default_rng(0).random((4, 3)), d)
    assert (tmp_path / "h.png").stat().st_size > 1000 and (tmp_path / "m.png").stat().st_size > 1000


def test_figures_leave_the_callers_matplotlib_alone(tmp_path):
    """Library figures draw on their own Agg canvas: the program's backend stays what it chose, and
    pyplot (with its global figure registry) is never imported."""
    code = f"""
import sys
import matplotlib
matplotlib.use("svg")
import numpy as np
from scope3d.estimators.bundle import solver
from scope3d.metrology.evaluation import save_error_histogram_png, save_error_map_png
from scope3d.pipelines import axial
from scope3d.scene import surface
save_error_histogram_png({str(tmp_path / "h.png")!r}, np.array([0.1, 0.2, 0.3]))
save_error_map_png({str(tmp_path / "m.png")!r}, np.zeros((3, 3)), np.array([0.1, 0.2, 0.3]))
assert matplotlib.get_backend() == "svg", matplotlib.get_backend()
assert "matplotlib.pyplot" not in sys.modules
"""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "h.png").read_bytes()[:4] == b"\x89PNG" and (tmp_path / "m.png").read_bytes()[:4] == b"\x89PNG"


def test_bad_inputs(bowl):
    mesh, _ = bowl
    with pytest.raises(ValueError):
        surface_distances(np.zeros((3, 2)), mesh)
    with pytest.raises(ValueError):
        SampledSurface(Mesh(np.zeros((3, 3)), np.zeros((0, 3), int)))
    with pytest.raises(ValueError):
        EvaluationOptions(icp=IcpOptions(trim_fraction=0.7))
    with pytest.raises(ValueError):
        EvaluationOptions(icp=IcpOptions(min_decrease_sigma2=-1.0))
