"""Phantom lab additions for thread metrology: a misaligned side-view mount reported as the stage's
nominal poses (whose tolerance holds the truth), the quadrant layout, as-made diameters and a chip."""
from __future__ import annotations

import json

import numpy as np

from scope3d.cli.main import main
from scope3d.phantoms import generate


def test_quadrant_mount_is_unknown_to_the_reported_poses():
    seq = generate("thread", "quadrants", size=(40, 32), n_frames=24, quadrant_mount=(0.2, -0.1, 1.5))
    true_c = np.array([p.centre for p in seq.true_poses])
    rep_c = np.array([m.pose.centre for m in seq.measured_poses])
    np.testing.assert_allclose(np.hypot(rep_c[:, 0], rep_c[:, 1]), 0.0, atol=1e-12)  # on the axis, nominally
    np.testing.assert_allclose(np.hypot(true_c[:, 0], true_c[:, 1]), np.hypot(0.2, 0.1))
    tilt = [np.degrees(np.arccos(np.clip((np.trace(t.rotation @ m.pose.rotation.T) - 1) / 2, -1, 1)))
            for t, m in zip(seq.true_poses, seq.measured_poses)]
    np.testing.assert_allclose(tilt, 1.5, atol=1e-9)
    assert all(m.contains(t) for t, m in zip(seq.true_poses, seq.measured_poses))


def test_cli_thread_options_reach_the_ground_truth(tmp_path):
    out = tmp_path / "hole"
    code = main(["phantom", "thread", "--trajectory", "quadrants", "--frames", "24", "--size", "40x32",
                 "--defect", "200:20:0.1", "--pitch-diameter-offset", "0.08", "--minor-diameter-offset", "0.1",
                 "--mount", "0.1:0.1:0.5", "--quadrant-step", "0.4", "--out", str(out), "--no-progress"])
    assert code == 0
    layout = json.loads((out / "quadrants.json").read_text())
    assert [q["angle_deg"] for q in layout["quadrants"]] == [30.0 * q for q in range(12)]
    assert layout["quadrants"][3]["frames"] == ["0006.png", "0007.png"]
    scene = json.loads((out / "ground_truth" / "scene.json").read_text())
    made = scene["thread"]["as_made"]
    assert abs(made["pitch_diameter_mm"] - (8 - 0.649519 * 1.25 + 0.08)) < 1e-6
    assert abs(made["minor_diameter_mm"] - (scene["thread"]["minor_diameter_mm"] + 0.1)) < 1e-9
    assert scene["thread"]["defects"][0]["angle_deg"] == 200.0
    assert scene["trajectory"]["step_mm"] == 0.4
    z = np.loadtxt(out / "ground_truth" / "poses.csv", delimiter=",", skiprows=1, usecols=3)
    np.testing.assert_allclose(z[1::2] - z[0::2], -0.4, atol=1e-9)  # two frames per quadrant, 0.4 mm apart
    for bad in (["--trajectory", "quadrants", "--quadrant-step", "-1"], ["--trajectory", "axial", "--quadrant-step", "1"]):
        assert main(["phantom", "thread", *bad, "--size", "40x32", "--out", str(tmp_path / "y")]) == 2
    assert main(["phantom", "thread", "--defect", "oops", "--out", str(tmp_path / "x")]) == 2


def test_chip_placed_at_a_height_lies_on_the_crest_turn_nearest_it():
    from scope3d.errors import InputError
    from scope3d.phantoms.scenes import build_thread

    # a 4.5 mm scan of an M8 shows thread from -1.5 to ~-7.5 mm; the default chip is at ~-7 mm
    info = build_thread("M8x1.25", defect=(200.0, 20.0, 0.15, -4.3)).info["thread"]["defects"][0]
    # the crest turns at the chip's angle are one pitch apart: the nearest is within half a pitch
    assert abs(info["crest_turn_z_mm"] - -4.3) <= 1.25 / 2 + 1e-9
    try:
        build_thread("M8x1.25", defect=(200.0, 20.0, 0.15, -0.5))  # above the thread
    except InputError as exc:
        assert "defect height" in str(exc)
    else:
        raise AssertionError("a chip above the thread must be refused")


def test_a_default_quadrant_scan_follows_the_scan_plan_and_a_short_one_is_refused(tmp_path, capsys):
    from scope3d.metrology.thread_scan_plan import minimum_frames, plan_quadrant_scan
    from scope3d.phantoms.lab import borescope_camera

    out = tmp_path / "hole"
    assert main(["phantom", "thread", "--trajectory", "quadrants", "--thread", "M10x1.5", "--side-view", "45",
                 "--size", "40x32", "--out", str(out), "--no-progress"]) == 0
    plan = plan_quadrant_scan(borescope_camera(size=(40, 32)), "M10x1.5", 45.0)
    layout = json.loads((out / "quadrants.json").read_text())
    assert layout["thread"] == "M10x1.5" and layout["step_mm"] == plan.step_mm
    assert all(len(q["frames"]) == plan.frames_per_quadrant for q in layout["quadrants"])
    assert json.loads((out / "report.json").read_text())["scan_plan"]["frame_gap"] == plan.frame_gap
    # the old default, 0.1 mm steps, 4 frames per quadrant: refused in one line with the least it needs
    capsys.readouterr()
    assert main(["phantom", "thread", "--trajectory", "quadrants", "--side-view", "90", "--quadrant-step", "0.1",
                 "--frames", "48", "--size", "40x32", "--out", str(tmp_path / "short"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    least = minimum_frames(borescope_camera(size=(40, 32)), "M8x1.25", 90.0, 0.1)
    assert "too short to gauge" in err and f"at least {least} frames per quadrant" in err
    assert len([line for line in err.splitlines() if "too short" in line]) == 1
    assert not (tmp_path / "short").exists()
