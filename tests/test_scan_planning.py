"""Scan planning (sfm.scan_planning, io.scan_plan, ``scope3d plan-scan``): coverage arithmetic on spheres."""
from __future__ import annotations

import json

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at
from scope3d.io.ply import write_ply
from scope3d.io.scan_plan import read_scan_plan
from scope3d.scene.mesh import Mesh
from scope3d.sfm.scan_planning import ScanPlanOptions, coverage, plan_spiral_scan, planning_camera

RADIUS_MM = 40.0


def _sphere(subdivisions: int = 5) -> Mesh:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=RADIUS_MM)
    return Mesh(np.asarray(s.vertices), np.asarray(s.faces))


def _edge_mm(mesh: Mesh) -> float:
    tri = mesh.vertices[mesh.faces]
    return float(np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1).max())


@pytest.mark.parametrize("fov_deg", [40.0, 70.0, 120.0])
def test_coverage_from_the_centre_of_a_sphere_is_the_caps_solid_angle(fov_deg):
    mesh = _sphere()
    camera = planning_camera(fov_deg)
    pose = Pose.from_centre(look_at(np.zeros(3), [0.3, -0.2, 1.0]), np.zeros(3))
    got = coverage(mesh, camera, [pose]).fraction
    half = np.deg2rad(fov_deg) / 2
    expected = (1 - np.cos(half)) / 2  # solid angle of a cone of half-angle `half` over 4 pi
    # The face-centroid rule errs only on faces cut by the cap's rim: at most a band one edge wide along
    # a circle of radius R sin(half), i.e. 2 pi R sin(half) * edge of 4 pi R^2.
    tolerance = np.sin(half) * _edge_mm(mesh) / (2 * RADIUS_MM)
    assert abs(got - expected) <= tolerance


def test_coverage_counts_only_what_is_in_range_and_in_front():
    mesh = _sphere(4)
    camera = planning_camera(70.0)
    # 5 mm from the wall looking at it: the wall behind the camera is out of the view.
    centre = np.array([0.0, 0.0, RADIUS_MM - 5.0])
    pose = Pose.from_centre(look_at(centre, centre + [0, 0, 1.0]), centre)
    near = coverage(mesh, camera, [pose]).fraction
    assert 0 < near < 0.05
    # From the centre with a range shorter than the radius nothing is seen.
    pose0 = Pose.from_centre(look_at(np.zeros(3), [0, 0, 1.0]), np.zeros(3))
    assert coverage(mesh, camera, [pose0], max_range_mm=RADIUS_MM - 1).fraction == 0.0


def test_spiral_plan_on_a_sphere_covers_it_with_the_expected_number_of_views():
    mesh = _sphere()
    options = ScanPlanOptions(standoff_mm=15.0, overlap=0.5, fov_deg=70.0)
    plan = plan_spiral_scan(mesh, options=options, centre_mm=np.zeros(3))
    # Every view looks along the inward normal (radially outwards) from 15 mm off the wall.
    for pose, wall in zip(plan.poses, plan.wall_points_mm):
        assert np.linalg.norm(pose.centre) == pytest.approx(RADIUS_MM - 15.0, abs=0.05)  # facets: sagitta < 0.05
        assert np.dot(pose.rotation[2], wall / np.linalg.norm(wall)) > 0.999
    # Half-footprint spacing leaves no gaps: circles of diameter D, centres D/2 apart, cover the plane.
    assert plan.coverage.fraction > 0.995
    # One view per spacing^2 of wall: the spiral packs views on a square lattice of the spacing.
    half = np.deg2rad(35.0)
    # On a sphere the field's edge ray from 25 mm off the centre meets the wall at a chord c from the
    # axis point: solve |(0, 0, 25) + t (sin a, 0, cos a)| = 40.
    t = -25 * np.cos(half) + np.sqrt((25 * np.cos(half)) ** 2 - 25**2 + RADIUS_MM**2)
    point = np.array([t * np.sin(half), 0.0, 25 + t * np.cos(half)])
    footprint = 2 * np.linalg.norm(point - [0, 0, RADIUS_MM])
    spacing = 0.5 * footprint
    expected = 4 * np.pi * RADIUS_MM**2 / spacing**2
    assert 0.85 * expected <= plan.n_views <= 1.15 * expected


def test_bend_limit_drops_views_and_reports_the_coverage_lost():
    mesh = _sphere(4)
    free = plan_spiral_scan(mesh, options=ScanPlanOptions(standoff_mm=20.0, fov_deg=70.0), centre_mm=np.zeros(3))
    limited = plan_spiral_scan(mesh, options=ScanPlanOptions(standoff_mm=20.0, fov_deg=70.0, bend_limit_deg=120.0),
                               centre_mm=np.zeros(3))
    assert limited.n_planned == free.n_views
    assert limited.n_views < free.n_views
    assert np.all(limited.bend_deg <= 120.0)
    assert limited.coverage_unlimited.fraction == pytest.approx(free.coverage.fraction)
    # Views within 120° of -z look at wall points more than 60° from the top pole; only the cap of
    # half-angle 60° about +z (area fraction (1 - cos 60°)/2 = 25 %) can be lost, less what the kept
    # views' fields reach into it.
    lost = free.coverage.fraction - limited.coverage.fraction
    assert 0.0 < lost <= 0.25


def test_plan_scan_command_writes_a_plan_the_reader_takes_back(tmp_path):
    mesh = _sphere(4)
    write_ply(tmp_path / "sphere.ply", mesh)
    assert main(["plan-scan", str(tmp_path / "sphere.ply"), "--standoff", "20", "--fov", "70",
                 "--out", str(tmp_path / "plan")]) == 0
    data = json.loads((tmp_path / "plan" / "plan.json").read_text())
    plan = read_scan_plan(tmp_path / "plan" / "plan.json")
    assert data["n_views"] == len(plan.poses) and plan.fov_deg == 70.0
    assert 0.99 < data["coverage_fraction"] <= 1.0
    assert (tmp_path / "plan" / "plan.png").stat().st_size > 0


def test_plan_scan_refuses_bad_input(tmp_path, capsys):
    assert main(["plan-scan", str(tmp_path / "missing.ply"), "--out", str(tmp_path / "o")]) == 2
    assert main(["plan-scan", "bladder", "--overlap", "1.5", "--out", str(tmp_path / "o")]) == 2
    assert "overlap" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
    (tmp_path / "bad.json").write_text('{"kind": "scope3d scan plan", "fov_deg": 70, "views": [{"index": 0}]}')
    with pytest.raises(InputError, match="view 0"):
        read_scan_plan(tmp_path / "bad.json")
