"""The virtual thread gauge on clouds sampled from the phantom lab's true thread meshes (ISO 68-1 profile,
as made with chosen deviations), with 0.01 mm Gaussian noise (a sparse reconstruction's point noise)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from scope3d.geometry.iso_thread import THREAD_SIZES
from scope3d.metrology.thread_gauge import (GaugeOptions, _frame, _profile_residuals, gauge_thread, profile_parts,
                                           remeasure, unmeasured_sizes)
from scope3d.metrology.thread_tolerances import thread_limits
from scope3d.phantoms.scenes import build_thread

NOISE_MM = 0.01


def _mid_class(designation):
    lim = thread_limits(designation)
    return round((lim.d1_max_mm - lim.d1_min_mm) / 2, 4), round((lim.d2_max_mm - lim.d2_min_mm) / 2, 4), 0.05


# Mid-class 6H holes of every size the gauge knows: each diameter sits in the middle of its tolerance (M8:
# 0.132 mm over D1, 0.08 mm over D2) and the major diameter a little above its minimum, as a tap cuts.
MID_CLASS = {size: _mid_class(size) for size in THREAD_SIZES}


def _cloud(size, offsets=(0.0, 0.0, 0.0), defect=None, n=60000, seed=0):
    scene = build_thread(size, minor_diameter_offset_mm=offsets[0], pitch_diameter_offset_mm=offsets[1],
                         major_diameter_offset_mm=offsets[2], defect=defect)
    points, _ = trimesh.sample.sample_surface(scene.mesh.to_trimesh(), 2 * n, seed=seed)
    points = points[points[:, 2] < -0.05]  # inside the hole: a side-viewing scope never sees the top face
    rng = np.random.default_rng(seed)
    return points + rng.normal(0.0, NOISE_MM, points.shape), scene.info["thread"]["as_made"]


@pytest.mark.parametrize("size", list(MID_CLASS))
def test_conforming_hole_passes_with_accurate_sizes(size):
    points, truth = _cloud(size, MID_CLASS[size])
    result = gauge_thread(points, options=GaugeOptions(designation=size, max_points=10000))
    assert result.verdict == "pass", result.summary()
    # the accuracy targets: diameters within 0.02 mm, pitch within 0.005 mm
    assert abs(result.minor_diameter_mm.value - truth["minor_diameter_mm"]) < 0.02
    assert abs(result.major_diameter_mm.value - truth["major_diameter_mm"]) < 0.02
    assert abs(result.pitch_diameter_mm.value - truth["pitch_diameter_mm"]) < 0.02
    assert abs(result.pitch_mm.value - float(size.split("x")[1])) < 0.005
    assert abs(result.flank_angle_deg.value - 60.0) < 1.0
    # the stated uncertainty is of the size of the error (1 sigma: within 5 sigma + tessellation ~1 um)
    err = abs(result.minor_diameter_mm.value - truth["minor_diameter_mm"])
    assert err < 5 * result.minor_diameter_mm.uncertainty + 0.002
    assert not result.defects


@pytest.mark.parametrize("offsets, failing", [
    ((0.132, 0.25, 0.05), "no-go"),     # pitch diameter 0.09 mm above D2 max
    ((0.132, -0.04, 0.05), "(go)"),     # pitch diameter below D2 min
    ((0.32, 0.12, 0.05), "<= 6.912"),   # minor diameter above D1 max
])
def test_hole_outside_the_class_fails_on_the_right_limit(offsets, failing):
    points, _ = _cloud("M8x1.25", offsets)
    result = gauge_thread(points, options=GaugeOptions(max_points=10000))
    assert result.verdict == "fail"
    failed = [c["check"] for c in result.checks if not c["ok"]]
    assert len(failed) == 1 and failing in failed[0], failed


def test_chipped_crest_is_found_at_its_angle():
    points, _ = _cloud("M8x1.25", MID_CLASS["M8x1.25"], defect=(200.0, 20.0, 0.15))
    result = gauge_thread(points, options=GaugeOptions(max_points=10000))
    assert result.verdict == "fail"
    assert len(result.defects) == 1, result.defects
    d = result.defects[0]
    assert abs((d.angle_deg - 200.0 + 180) % 360 - 180) <= 10.0  # the issue's ±10°
    assert abs(d.depth_mm - 0.15) < 3 * NOISE_MM  # the crest bin's median: a few noise sigmas


def test_bad_input():
    with pytest.raises(ValueError):
        gauge_thread(np.zeros((10, 3)))
    with pytest.raises(ValueError):
        GaugeOptions(designation="M7x1")
    with pytest.raises(ValueError, match="no threaded stretch"):
        rng = np.random.default_rng(0)
        t, z = rng.uniform(0, 2 * np.pi, 5000), rng.uniform(-10, 0, 5000)
        gauge_thread(np.stack([4 * np.cos(t), 4 * np.sin(t), z], 1))  # a plain bore
    assert thread_limits("M8x1.25").d2_max_mm == pytest.approx(7.348)


def test_flank_angle_held_at_60_when_one_flank_is_seen():
    # A 45° side view sees the flanks facing the opening and hardly those facing the bottom: drop the
    # surface whose normal points down, and add twice the noise (a reconstruction's, not a scanner's).
    size, noise = "M8x1.25", 2 * NOISE_MM
    scene = build_thread(size, minor_diameter_offset_mm=0.132, pitch_diameter_offset_mm=0.08,
                         major_diameter_offset_mm=0.05)
    mesh = scene.mesh.to_trimesh()
    points, faces = trimesh.sample.sample_surface(mesh, 80000, seed=1)
    seen = (points[:, 2] < -0.05) & (mesh.face_normals[faces][:, 2] > -0.3)
    points = points[seen] + np.random.default_rng(1).normal(0.0, noise, (int(seen.sum()), 3))
    truth = scene.info["thread"]["as_made"]
    result = gauge_thread(points, options=GaugeOptions(max_points=10000, noise_mm=noise))
    assert result.profile["flank_angle_held"], result.summary()
    assert result.verdict == "pass", result.summary()
    for name in ("minor_diameter_mm", "pitch_diameter_mm", "major_diameter_mm"):  # the 0.02 mm
        assert abs(getattr(result, name).value - truth[name]) < 0.02, (name, result.summary())
    # the free fit still measures the angle (the true 60° within 3 of its sigmas + 0.2° of tessellation)
    assert abs(result.flank_angle_deg.value - 60.0) < 3 * result.flank_angle_deg.uncertainty + 0.2


def test_flank_angle_off_the_standard_is_measured_and_used():
    # Stretching the hole 2 % along its axis makes the pitch 1.275 mm and the flanks
    # 2 atan(1.02 tan 30°) = 60.98°, and leaves the diameters: the free fit must resolve the angle and give
    # the sizes (a profile held at 60° would bias them).
    points, truth = _cloud("M8x1.25", MID_CLASS["M8x1.25"])
    points[:, 2] *= 1.02
    result = gauge_thread(points, options=GaugeOptions(max_points=10000))
    assert not result.profile["flank_angle_held"]
    expected = np.rad2deg(2 * np.arctan(1.02 * np.tan(np.deg2rad(30.0))))
    assert abs(result.flank_angle_deg.value - expected) < 0.3  # ~0.2° of tessellation bias, as at 60°
    assert abs(result.pitch_mm.value - 1.275) < 0.005
    assert abs(result.pitch_diameter_mm.value - truth["pitch_diameter_mm"]) < 0.02


def test_sizes_of_parts_the_cloud_does_not_show_are_not_measured():
    # A 45° side view of the phantom sees the crests and the flanks facing the opening, neither the other
    # flanks nor the roots (docs/thread_metrology.md, "Defaults"): the symmetric profile would still place
    # D2 and D, by assumption only. They must be reported unmeasured and their limits left undecided (a
    # sound hole is then indeterminate, never failed on them); D1 is still judged, and a chip still fails.
    points, truth = _cloud("M8x1.25", MID_CLASS["M8x1.25"])
    full = gauge_thread(points, options=GaugeOptions(max_points=10000))
    assert full.unseen_parts == ()
    part, _ = profile_parts(full, points)  # of the fitted points: the zone's
    seen = points[full.fit_state["index"]][part <= 1]  # the crests and the flanks towards +z
    result = gauge_thread(seen, options=GaugeOptions(max_points=10000))
    assert set(result.unseen_parts) == {"flank towards -z", "root"}, result.summary()
    assert result.verdict == "indeterminate", result.summary()
    undecided = {c["quantity"] for c in result.checks if "quantity" in c and not c["decided"]}
    assert undecided == {"virtual pitch diameter", "pitch diameter", "major diameter"}, result.checks
    assert abs(result.minor_diameter_mm.value - truth["minor_diameter_mm"]) < 0.02
    assert unmeasured_sizes(result.unseen_parts) == ["major diameter", "pitch diameter"]
    # one flank with both flats still gives D2 (the tooth's centre from the flats)
    assert unmeasured_sizes(("flank towards -z",)) == []


def test_a_chip_on_a_seen_crest_fails_a_hole_seen_from_one_side():
    # the 45° cloud of a chipped hole: its root radius, unplaced, may stop at a bound; the chip still fails it
    points, _ = _cloud("M8x1.25", MID_CLASS["M8x1.25"], defect=(200.0, 20.0, 0.15))
    full = gauge_thread(points, options=GaugeOptions(max_points=10000))
    part, _ = profile_parts(full, points)
    result = gauge_thread(points[full.fit_state["index"]][part <= 1], options=GaugeOptions(max_points=10000))
    assert "root" in result.unseen_parts
    assert result.verdict == "fail", result.summary()
    assert any(abs((d.angle_deg - 200.0 + 180) % 360 - 180) <= 10.0 for d in result.defects)


def test_profile_jacobian_is_the_finite_difference_one():
    # the fit's Jacobian by the chain rule against central differences, at a pose off the base frame (tilt,
    # shift, a pitch and an angle off nominal) where every part of the profile has points
    points, _ = _cloud("M8x1.25", MID_CLASS["M8x1.25"], n=5000)
    points = points[(points[:, 2] < -2.0) & (points[:, 2] > -9.0)]
    p0, base = np.array([0.01, -0.02, -5.0]), _frame(np.array([0.002, -0.003, 1.0]))
    x = np.array([0.003, -0.002, 0.01, -0.015, 1.2505, 0.3, 3.39, 4.03, 3.64, np.deg2rad(29.5)])
    residuals, jac = _profile_residuals(points, p0, base, x, jacobian=True)
    np.testing.assert_array_equal(residuals, _profile_residuals(points, p0, base, x))
    step = 1e-7  # central differences: truncation ~ step^2, round-off ~ 1e-16 mm / step ~ 1e-9
    numeric = np.stack([(_profile_residuals(points, p0, base, x + step * e) -
                         _profile_residuals(points, p0, base, x - step * e)) / (2 * step) for e in np.eye(10)], 1)
    # a point within a step of a corner of the profile (or of w's wrap) has a kink between the two samples
    assert np.mean(np.abs(jac - numeric) > 1e-6) < 1e-3
    assert np.median(np.abs(jac - numeric)) < 1e-8


def test_a_radius_the_cloud_does_not_place_is_held_at_its_basic_size_and_not_claimed_measured():
    # the 45° cloud (crests and the flanks towards +z): the root's radius is held at the basic D / 2
    points, _ = _cloud("M8x1.25", MID_CLASS["M8x1.25"])
    full = gauge_thread(points, options=GaugeOptions(max_points=10000))
    part, _ = profile_parts(full, points)
    result = gauge_thread(points[full.fit_state["index"]][part <= 1], options=GaugeOptions(max_points=10000))
    major = result.major_diameter_mm
    assert major.value == pytest.approx(THREAD_SIZES["M8x1.25"][0]) and not major.measured
    assert major.uncertainty == np.inf and result.profile["held_at_basic"] == ["major diameter"]
    assert not result.pitch_diameter_mm.measured and result.minor_diameter_mm.measured
    report = json.dumps(result.to_dict(), allow_nan=False)  # no Infinity in the report
    assert json.loads(report)["major_diameter_mm"] == {"value": major.value, "uncertainty": None, "measured": False}
    assert "held at the basic size, not measured" in result.summary()
    # the re-fit of the systematic terms holds it too
    assert remeasure(result, points[full.fit_state["index"]][part <= 1])["major_diameter"] == pytest.approx(major.value)


def test_a_chip_on_a_sparsely_seen_crest_is_found_on_the_tooth_top_half():
    # A 45° view sees the crests at a grazing angle: 1-10 crest points per 10° of a turn, under the 5 a
    # crest bin needs; the flank facing the opening is seen densely. Thin the crest points to ~2 per 5° bin
    # per turn: the chip must still be found, from its tooth's top half, and no other bin flagged.
    points, _ = _cloud("M10x1.5", MID_CLASS["M10x1.5"], defect=(200.0, 20.0, 0.3))
    full = gauge_thread(points, options=GaugeOptions(designation="M10x1.5", max_points=10000))
    part, _ = profile_parts(full, points)
    zone = points[full.fit_state["index"]]
    rng = np.random.default_rng(3)
    crest = np.flatnonzero(part == 0)
    turns = np.ptp(zone[:, 2]) / 1.5
    sparse = rng.choice(crest, int(2 * 72 * turns), replace=False)  # ~2 per 5° bin and turn
    seen = np.concatenate([zone[part == 1], zone[sparse]])
    result = gauge_thread(seen, options=GaugeOptions(designation="M10x1.5", max_points=10000))
    assert result.verdict == "fail", result.summary()
    assert len(result.defects) == 1, result.defects
    assert abs((result.defects[0].angle_deg - 200.0 + 180) % 360 - 180) <= 10.0
