"""Fluorescent targets: segmentation, carrying onto the surface, shapes and sizes, matching the truth."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at
from scope3d.metrology.fluorescence import (
    FluorescenceOptions,
    auto_threshold,
    carry_to_surface,
    match_targets,
    measure_targets,
    overlay,
    segment,
    targets_on_surface,
)
from scope3d.scene.surface import Surface
from scope3d.sensor.camera import Camera

STEP = 0.05


def _flat_surface(half=8.0, step=STEP):
    s = np.arange(-half, half + step / 2, step)
    return Surface(np.zeros(3), np.eye(3), s, s.copy(), np.zeros((len(s), len(s))))


def _draw(surface, shapes):
    """Rasterise shapes {kind: (centre (x, y) mm, size mm)} on the surface grid. Star size = stroke."""
    img = np.zeros(surface.height.shape, np.uint8)
    to_px = lambda p: np.round((np.asarray(p) - [surface.s[0], surface.t[0]]) / STEP * 16).astype(np.int32)
    for kind, (c, size) in shapes.items():
        c = np.asarray(c, float)
        if kind == "disc":
            cv2.circle(img, tuple(int(v) for v in to_px(c)), int(round(size / 2 / STEP * 16)), 1, -1, cv2.LINE_8, 4)
            continue
        if kind == "star":
            r_out = size / (2 * np.sin(np.deg2rad(72)))
            r = np.where(np.arange(10) % 2 == 0, r_out, r_out * (3 - np.sqrt(5)) / 2)
            ang = np.pi / 2 + np.arange(10) * np.pi / 5
        elif kind == "square":
            r, ang = np.full(4, size / np.sqrt(2)), np.pi / 4 + np.arange(4) * np.pi / 2
        else:
            r, ang = np.full(3, size / np.sqrt(3)), np.pi / 2 + np.arange(3) * 2 * np.pi / 3
        poly = c + np.stack([r * np.cos(ang), r * np.sin(ang)], 1)
        cv2.fillPoly(img, [to_px(poly)], 1, cv2.LINE_8, 4)
    return img.astype(bool)


SHAPES = {"star": ((-4.0, 4.0), 6.0), "disc": ((4.0, 4.0), 3.0), "square": ((-4.0, -4.0), 3.0),
          "triangle": ((4.0, -4.0), 4.0)}


def test_shapes_and_sizes_on_a_flat_field():
    s = _flat_surface()
    targets, labels = measure_targets(s, _draw(s, SHAPES))
    assert len(targets) == 4 and labels.max() == 4
    found = {t.shape: t for t in targets}
    assert set(found) == set(SHAPES)
    for kind, (c, size) in SHAPES.items():
        t = found[kind]
        # a few cells of 0.05 mm on outlines of 3-6 mm: 3 %
        assert t.size_mm == pytest.approx(size, rel=0.03), kind
        np.testing.assert_allclose(t.centroid_mm[:2], c, atol=0.05)
        assert t.size_in_plane_mm([0, 0, 1]) == pytest.approx(size, rel=0.03)


def test_size_in_design_plane_undoes_the_slope():
    # a disc drawn flat and dropped onto a 40 deg slope is 1/cos(40) longer on the surface
    s = _flat_surface()
    slope = np.tan(np.deg2rad(40.0))
    ss, _ = np.meshgrid(s.s, s.t)
    tilted = Surface(s.origin, s.axes, s.s, s.t, slope * ss)
    # the same disc seen from above: an ellipse on the slope
    on = _draw(s, {"disc": ((0.0, 0.0), 4.0)})
    (t,), _ = measure_targets(tilted, on)
    assert t.area_mm2 == pytest.approx(np.pi * 4 * (1 + slope**2) ** 0.5, rel=0.03)
    assert t.size_in_plane_mm([0, 0, 1]) == pytest.approx(4.0, rel=0.03)


def test_segment_removes_speckle_and_fills_pinholes():
    rng = np.random.default_rng(0)
    img = (rng.random((120, 120)) < 0.01).astype(np.uint8) * 200  # isolated hot pixels
    cv2.circle(img, (60, 60), 20, 200, -1)
    img[60, 60] = 0  # a pin-hole
    m = segment(img, 100, options=FluorescenceOptions())
    n, _ = cv2.connectedComponents(m.astype(np.uint8))
    assert n == 2 and m[60, 60]


def test_auto_threshold_separates_and_is_floored():
    rng = np.random.default_rng(0)
    dark = rng.integers(0, 10, (50, 50)).astype(np.uint8)
    bright = dark.copy()
    bright[10:20, 10:20] = 120
    t = auto_threshold([dark, bright])
    assert 10 <= t < 120
    assert auto_threshold([dark]) == FluorescenceOptions().min_threshold
    assert auto_threshold([bright], options=FluorescenceOptions(threshold=77)) == 77


def test_carry_to_surface_and_refine_through_cameras():
    s = _flat_surface(step=0.2)
    cam = Camera.from_fov(300, 300, 60.0)
    poses = [Pose.from_centre(look_at(np.array([x, 0.0, 15.0]), np.array([x, 0.0, 0.0])), [x, 0.0, 15.0]) for x in (-2.0, 2.0)]
    # each frame sees a 3 mm disc at the world origin
    masks = []
    for p in poses:
        ang = np.linspace(0, 2 * np.pi, 400)
        ring = np.stack([1.5 * np.cos(ang), 1.5 * np.sin(ang), np.zeros_like(ang)], 1)
        px = cam.project_world(p, ring)
        m = np.zeros((300, 300), np.uint8)
        cv2.fillPoly(m, [np.round(px * 16).astype(np.int32)], 1, cv2.LINE_8, 4)
        masks.append(m.astype(bool))
    on = carry_to_surface(s, cam, poses, masks)
    assert on.sum() > 0
    targets, _, labels = targets_on_surface(s, cam, poses, masks, options=FluorescenceOptions(refine_factor=4))
    assert len(targets) == 1 and labels.max() == 1
    assert targets[0].size_mm == pytest.approx(3.0, rel=0.05)
    np.testing.assert_allclose(targets[0].centroid_mm, 0.0, atol=0.05)


def test_match_targets_pairs_by_position_and_reports_misses():
    s = _flat_surface()
    targets, _ = measure_targets(s, _draw(s, SHAPES))
    truth = [{"name": k, "centre_mm": [*c, 0.0], "size_mm": size, "shape": k} for k, (c, size) in SHAPES.items()]
    truth.append({"name": "far away", "centre_mm": [50.0, 50.0, 0.0], "size_mm": 2.0})
    rows = match_targets(targets, truth)
    assert [r["found_shape"] for r in rows[:4]] == list(SHAPES)
    assert rows[4]["found_label"] is None
    assert all(abs(r["size_error_fraction"]) < 0.03 for r in rows[:4])


def test_overlay_marks_targets_green():
    refl = np.full((20, 20, 3), 100, np.uint8)
    on = np.zeros((20, 20), bool)
    on[5:10, 5:10] = True
    out = overlay(refl, on, None, draw_outlines=False)
    assert np.all(out[on][:, 1] > out[on][:, 0]) and np.all(out[~on] == 100)


def test_bad_inputs():
    with pytest.raises(ValueError):
        segment(np.zeros((5, 5, 3), np.uint8), 10)
    for bad in (dict(threshold=300), dict(min_vote=0), dict(star_solidity=1.5), dict(refine_factor=0)):
        with pytest.raises(ValueError):
            FluorescenceOptions(**bad)
