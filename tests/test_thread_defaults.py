"""The default path of thread metrology (issue 38): ``scope3d phantom thread --trajectory quadrants`` with no
scan settings renders the scan plan's scan, and ``scope3d thread-scan`` with no options gauges it.

A 90° view of a mid-class M8x1.25 hole with a chipped crest (the phantom's default turn, the thread's
middle), on 320x256 frames to keep the render and the scan short (the plan's step, frames and gap depend
on the field of view, not on the pixel count). Every size at 45° and 90°: benchmarks/bench_thread_defaults.py."""
from __future__ import annotations

import json

from scope3d.cli.main import main
from scope3d.metrology.thread_scan_plan import plan_quadrant_scan
from scope3d.phantoms.lab import borescope_camera

CHIP_DEG = 200.0


def test_a_default_scan_gets_a_verdict_and_finds_the_chip(tmp_path):
    hole, scan = tmp_path / "hole", tmp_path / "scan"
    assert main(["phantom", "thread", "--trajectory", "quadrants", "--side-view", "90", "--size", "320x256",
                 "--seed", "1", "--defect", f"{CHIP_DEG}:20:0.3", "--minor-diameter-offset", "0.132",
                 "--pitch-diameter-offset", "0.08", "--major-diameter-offset", "0.05", "--out", str(hole),
                 "--no-progress"]) == 0
    plan = plan_quadrant_scan(borescope_camera(size=(320, 256)), "M8x1.25", 90.0)
    layout = json.loads((hole / "quadrants.json").read_text())
    assert layout["step_mm"] == plan.step_mm and len(layout["quadrants"][0]["frames"]) == plan.frames_per_quadrant
    assert main(["thread-scan", str(hole), "--out", str(scan), "--no-progress"]) == 0
    report = json.loads((scan / "report.json").read_text())
    gauge, reg = report["gauge"], report["registration"]
    assert report["scan"]["frame_gap"] == [plan.frame_gap] * 12 and not report["scan"]["coverage"]["below_plan"]
    # a damaged crest fails the hole whatever its sizes; the chip is found in the 5° bins within 10° of it
    assert gauge["verdict"] == "fail"
    assert any(abs((d["angle_deg"] - CHIP_DEG + 180) % 360 - 180) <= 10 for d in gauge["defects"])
    # issue 13's targets: registration 0.5° / 0.02 mm, diameters 0.02 mm, pitch 0.005 mm
    assert reg["rotation_error_deg"] <= 0.5 and reg["offset_error_mm"] <= 0.02
    errors = reg["gauge_errors_mm"]
    assert all(abs(errors[k]) <= 0.02 for k in ("minor_diameter", "pitch_diameter", "major_diameter"))
    assert abs(errors["pitch"]) <= 0.005


def test_a_default_45_degree_scan_finds_the_chip_and_fails_the_hole(tmp_path):
    # A 45° side view sees the crests at a grazing angle (a few crest points per 10° of a turn: a chipped
    # M10's chip was missed) and neither the roots nor the far flanks: the chip must be found on its tooth's
    # top half and fail the hole; D2 and D are not measured, D held at its basic size with no uncertainty.
    # (Seed 1, never one of the benchmark's.)
    hole, scan = tmp_path / "hole", tmp_path / "scan"
    assert main(["phantom", "thread", "--trajectory", "quadrants", "--thread", "M10x1.5", "--side-view", "45",
                 "--size", "320x256", "--seed", "1", "--defect", f"{CHIP_DEG}:20:0.3", "--minor-diameter-offset",
                 "0.15", "--pitch-diameter-offset", "0.09", "--major-diameter-offset", "0.05", "--out", str(hole),
                 "--no-progress"]) == 0
    assert main(["thread-scan", str(hole), "--out", str(scan), "--no-progress"]) == 0
    report = json.loads((scan / "report.json").read_text())
    gauge, reg = report["gauge"], report["registration"]
    assert gauge["verdict"] == "fail"
    assert any(abs((d["angle_deg"] - CHIP_DEG + 180) % 360 - 180) <= 10 for d in gauge["defects"])
    assert gauge["major_diameter_mm"]["measured"] is False and gauge["major_diameter_mm"]["uncertainty"] is None
    assert gauge["pitch_diameter_mm"]["measured"] is False
    # what a 45° view does measure meets issue 13's targets; on these small frames the crest, too, gathers
    # under 20 of the fit's points (400x320: D1 measured, benchmarks/bench_thread_defaults.py), and a size
    # not measured is named in the one line
    assert reg["rotation_error_deg"] <= 0.5 and reg["offset_error_mm"] <= 0.02
    assert abs(reg["gauge_errors_mm"]["pitch"]) <= 0.005
    for key in ("minor_diameter", "pitch_diameter", "major_diameter"):
        size = gauge[f"{key}_mm"]
        if size.get("measured", True):
            assert abs(reg["gauge_errors_mm"][key]) <= 0.02, key
        else:
            assert key.replace("_", " ") in gauge["message"]
