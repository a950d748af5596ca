"""The resection cavity (issue 35): its mesh is the surface its functions define, it overhangs (not a height
field), its depth, step and lip are as specified, and its targets lie flat on the floor."""
import numpy as np
import pytest

from scope3d.phantoms import build_scene
from scope3d.phantoms.scenes import (
    CAVITY_STEP_FRACTION,
    CAVITY_STEP_MM,
    cavity_floor_depth,
    cavity_floor_radius,
    cavity_rim_radius,
    cavity_shelf_weight,
    cavity_wall_depth,
    cavity_wall_radius,
)

# Coordinates of ~20 mm computed in float64: a vertex is on its function to a few ulp of them.
ROUNDING_MM = 64 * np.finfo(float).eps * 20.0


@pytest.fixture(scope="module")
def scene():
    return build_scene("cavity")


def _polar(v):
    return np.arctan2(v[:, 1], v[:, 0]), np.hypot(v[:, 0], v[:, 1])


def test_every_vertex_lies_on_the_defined_surface(scene):
    v = scene.mesh.vertices
    theta, r = _polar(v)
    plate = np.abs(v[:, 2]) <= ROUNDING_MM
    assert np.all(r[plate] >= cavity_rim_radius(theta[plate]) - ROUNDING_MM)
    inside = ~plate & (r > 1e-9)
    th, rr, d = theta[inside], r[inside], -v[inside, 2]
    foot = cavity_floor_radius(th)
    on_wall = np.abs(rr - cavity_wall_radius(th, np.minimum(d, cavity_wall_depth(th)))) <= ROUNDING_MM
    rho = rr / foot
    shelf = CAVITY_STEP_MM * cavity_shelf_weight(th)
    on_ring = (rho >= CAVITY_STEP_FRACTION - 1e-12) & (np.abs(d - cavity_floor_depth(th, rho) + shelf) <= ROUNDING_MM)
    on_inner = (rho <= CAVITY_STEP_FRACTION + 1e-12) & (np.abs(d - cavity_floor_depth(th, rho)) <= ROUNDING_MM)
    top = cavity_floor_depth(th, CAVITY_STEP_FRACTION) - shelf
    on_step = (np.abs(rho - CAVITY_STEP_FRACTION) <= 1e-12) & (d >= top - ROUNDING_MM) & (d <= top + shelf + ROUNDING_MM)
    assert np.all(on_wall | on_ring | on_inner | on_step)
    # the floor's middle is the one point the grids collapse to
    assert np.all(np.abs(v[~plate & ~inside, 2] + cavity_floor_depth(0.0, 0.0)) <= ROUNDING_MM)


def test_depth_step_and_lip_are_as_specified(scene):
    info = scene.info["cavity"]
    v = scene.mesh.vertices
    assert -v[:, 2].min() <= 15.0  # nothing deeper than 15 mm
    lo, hi = info["depth_range_mm"]
    assert 6.0 <= lo < 8.0 and 14.0 < hi <= 15.0  # the floor's shallowest and deepest: uneven over 6-15 mm
    # On the shelf's full-height sector the step face is a vertical 2 mm drop.
    th = np.deg2rad(info["step"]["azimuth_deg"])
    r = CAVITY_STEP_FRACTION * float(cavity_floor_radius(th))
    eps = 1e-3
    above = scene.caster.cast(np.array([[(r + eps) * np.cos(th), (r + eps) * np.sin(th), 1.0]]), np.array([[0, 0, -1.0]]))
    below = scene.caster.cast(np.array([[(r - eps) * np.cos(th), (r - eps) * np.sin(th), 1.0]]), np.array([[0, 0, -1.0]]))
    # the floor's slope moves each hit by at most eps x its gradient (< 1 mm/mm on the floor)
    assert above.points[0, 2] - below.points[0, 2] == pytest.approx(CAVITY_STEP_MM, abs=2 * eps)
    assert 0.8 < info["lip"]["max_overhang_mm"] < 1.5


def test_the_lip_overhangs_so_the_surface_is_not_a_height_field(scene):
    # A vertical line 0.5 mm beyond the rim under the lip meets the plate, then the lip's underside (facing
    # down), then the floor: three surfaces above one point, which no height field holds.
    rim = float(cavity_rim_radius(0.0))
    p = np.array([[rim + 0.5, 0.0, 1.0]])
    down = np.array([[0.0, 0.0, -1.0]])
    hits = []
    for _ in range(4):
        h = scene.caster.cast(p, down)
        if not h.hit[0]:
            break
        hits.append((h.points[0].copy(), h.normals[0].copy()))
        p = h.points[:1] + 1e-3 * down  # past the hit by more than Embree's float32 resolution
    assert len(hits) == 3
    (plate, n0), (under, n1), (floor, n2) = hits
    assert plate[2] == pytest.approx(0.0, abs=ROUNDING_MM) and n0[2] > 0.99
    assert -CAVITY_STEP_MM > under[2] > floor[2] and n1[2] < 0 and n2[2] > 0
    # the underside is the wall where it reaches 0.5 mm beyond the rim
    assert float(cavity_wall_radius(0.0, -under[2])) == pytest.approx(rim + 0.5, abs=1e-4)


def _floor_depth_xy(x, y):
    th, r = np.arctan2(y, x), np.hypot(x, y)
    rho = r / cavity_floor_radius(th)
    return cavity_floor_depth(th, rho) - np.where(rho > CAVITY_STEP_FRACTION, CAVITY_STEP_MM * cavity_shelf_weight(th), 0.0)


def _longest_floor_edge_mm(scene):
    v, f = scene.mesh.vertices, scene.mesh.faces
    tri = v[f[np.all(v[f][..., 2] < -5.0, axis=1)]]
    return float(np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)))


def _chord_bound_mm(points, longest_mm):
    """How far a point inside a floor triangle of longest edge L can sit from the floor: linear interpolation
    errs by at most M L² / 2, M the largest second derivative of the depth in x and y within L of the point
    (central differences at the point and 8 around it at distance L)."""
    ang = np.arange(8) * np.pi / 4
    ring = np.concatenate([[[0.0, 0.0]], longest_mm * np.stack([np.cos(ang), np.sin(ang)], 1)])
    xy = (points[:, None, :2] + ring[None]).reshape(-1, 2)
    x, y, h = xy[:, 0], xy[:, 1], 1e-3
    fxx = (_floor_depth_xy(x + h, y) - 2 * _floor_depth_xy(x, y) + _floor_depth_xy(x - h, y)) / h**2
    fyy = (_floor_depth_xy(x, y + h) - 2 * _floor_depth_xy(x, y) + _floor_depth_xy(x, y - h)) / h**2
    fxy = (_floor_depth_xy(x + h, y + h) - _floor_depth_xy(x + h, y - h) - _floor_depth_xy(x - h, y + h)
           + _floor_depth_xy(x - h, y - h)) / (4 * h**2)
    m = np.max(np.abs(fxx) + np.abs(fxy) + np.abs(fyy))  # bounds the Hessian's norm
    return float(m * longest_mm**2 / 2)


def test_targets_lie_on_the_floor_and_do_not_overlap(scene):
    longest = _longest_floor_edge_mm(scene)
    targets = scene.info["targets"]
    assert len(targets) == 8 and [t["shape"] for t in targets].count("star") == 1
    for t in targets:
        pts = np.asarray(t["outline_mm"] + [t["centroid_mm"]])
        th, r = _polar(pts)
        rho = r / cavity_floor_radius(th)
        shelf = np.where(rho > CAVITY_STEP_FRACTION, CAVITY_STEP_MM * cavity_shelf_weight(th), 0.0)
        # each outline point is on one floor (inner or ring), never on the step or the wall; the outline is
        # sampled on the mesh, within the chord bound of the floor's function
        chord = _chord_bound_mm(pts, longest)
        assert np.all(rho < 1.0)
        assert np.all((rho < CAVITY_STEP_FRACTION) == (rho[-1] < CAVITY_STEP_FRACTION))
        np.testing.assert_allclose(-pts[:, 2], cavity_floor_depth(th, rho) - shelf, atol=chord)
        assert t["area_mm2"] >= t["flat_area_mm2"]
    for tt in scene.targets:
        pts = np.asarray(next(x for x in targets if x["id"] == tt.id)["outline_mm"])
        assert not any(o.contains(pts).any() for o in scene.targets if o.id != tt.id)
