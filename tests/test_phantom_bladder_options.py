"""The bladder's cavity shape, vessel density and wetness, and rendering scan plans (phantom lab, ch. 2)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.errors import InputError
from scope3d.io.scan_plan import PlanFile, write_scan_plan
from scope3d.phantoms import generate
from scope3d.phantoms.lab import plan_trajectory
from scope3d.phantoms.scenes import build_bladder
from scope3d.phantoms.trajectories import spiral_trajectory


def test_cavity_semi_axes_and_shape_seed_change_the_wall():
    default = build_bladder(mm_per_texel=0.2)
    small = build_bladder(semi_axes_mm=(30.0, 30.0, 30.0), mm_per_texel=0.2)
    other = build_bladder(shape_seed=3, mm_per_texel=0.2)
    ext_default = np.ptp(default.mesh.vertices, axis=0)
    ext_small = np.ptp(small.mesh.vertices, axis=0)
    # The irregularity scales the radius by 1 ± ~0.15, so a 30 mm sphere spans 60 mm within ±15 %.
    assert np.all(np.abs(ext_small / 60.0 - 1.0) < 0.15)
    assert ext_default[0] > ext_small[0] + 20
    radius_default = np.linalg.norm(default.mesh.vertices, axis=1)
    radius_other = np.linalg.norm(other.mesh.vertices, axis=1)
    assert np.abs(radius_other - radius_default).max() > 1.0  # another shape, same vertices' directions
    assert other.info["bladder"]["shape_seed"] == 3
    with pytest.raises(InputError):
        build_bladder(semi_axes_mm=(30.0, -1.0, 30.0))


def test_lower_vessel_density_gives_a_paler_wall_with_less_contrast():
    dense = build_bladder(vessel_density=1.0, mm_per_texel=0.1)
    pale = build_bladder(vessel_density=0.25, mm_per_texel=0.1)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hits = dense.caster.cast(np.zeros_like(d), d)
    a_dense = dense.albedo(hits.points, hits.normals, 0.1).astype(float)
    a_pale = pale.albedo(hits.points, hits.normals, 0.1).astype(float)
    # Vessels and capillary dots are darker than the background: fewer of them, brighter and flatter wall.
    assert a_pale.mean() > a_dense.mean()
    assert a_pale.std(axis=0).mean() < a_dense.std(axis=0).mean()


def _plan(tmp_path, n=4):
    traj = spiral_trajectory(n)
    write_scan_plan(tmp_path / "plan.json", traj.poses, [0, 0, 1, 1][:n], 70.0, info={"standoff_mm": 30.0})
    return tmp_path / "plan.json"


def test_plan_video_interpolates_between_planned_views():
    traj = spiral_trajectory(3)
    plan = PlanFile(traj.poses, np.array([0, 0, 1]), 70.0, {})
    video = plan_trajectory(plan, video_fps=10.0, seconds_per_view=0.5)
    assert len(video) == 2 * 5 + 1  # 5 frames from each view to the next, plus the last view
    assert video.params["sections"] == [0] * 10 + [1]
    np.testing.assert_allclose(video.times_s, np.arange(11) / 10.0)  # poses.csv's time_s column
    for k, pose in enumerate(traj.poses):
        assert np.allclose(video.poses[5 * k].matrix, pose.matrix)


def test_phantom_command_renders_a_plan_with_bladder_options(tmp_path):
    plan = _plan(tmp_path)
    out = tmp_path / "ds"
    assert main(["phantom", "bladder", "--plan", str(plan), "--size", "48x48", "--vessel-density", "0.5",
                 "--wet", "--cavity-mm", "40,36,30", "--out", str(out), "--no-progress"]) == 0
    scene = json.loads((out / "ground_truth" / "scene.json").read_text())
    assert scene["trajectory"]["kind"] == "plan" and scene["trajectory"]["views"] == 4
    assert scene["bladder"]["vessel_density"] == 0.5 and scene["bladder"]["material"]["kind"] == "wet mucosa"
    assert scene["bladder"]["semi_axes_mm"] == [40.0, 36.0, 30.0]
    assert len(list((out / "frames").glob("*.png"))) == 4
    assert main(["phantom", "bladder", "--video", "30", "--out", str(tmp_path / "x")]) == 2
    assert main(["phantom", "dome", "--vessel-density", "0.5", "--out", str(tmp_path / "y")]) == 2
    with pytest.raises(InputError):
        generate("bladder", "spiral", plan=PlanFile([], np.zeros(0, int), 70.0, {}))
