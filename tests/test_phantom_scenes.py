"""Phantom geometry: ISO thread profile on the true mesh, dome shape, target ground truth."""
import numpy as np
import pytest

from scope3d.errors import InputError
from scope3d.geometry.iso_thread import iso_thread_profile
from scope3d.phantoms import build_scene
from scope3d.phantoms.scenes import star_outline, target_outline

ISO_MINOR_MM = {"M8x1.25": 6.647, "M6x1": 4.917, "M10x1.5": 8.376}


def _thread_vertices(scene):
    th = scene.info["thread"]
    v = scene.mesh.vertices
    keep = (v[:, 2] < th["thread_top_z_mm"] - 1e-9) & (v[:, 2] > th["thread_bottom_z_mm"] + 1e-9)
    return v[keep], th


@pytest.mark.parametrize("size", ["M8x1.25", "M6x1"])
def test_thread_mesh_has_iso_minor_major_diameters_and_pitch(size):
    scene = build_scene("thread", thread=size)
    v, th = _thread_vertices(scene)
    r = np.hypot(v[:, 0], v[:, 1])
    major, pitch = th["major_diameter_mm"], th["pitch_mm"]
    assert 2 * r.min() == pytest.approx(ISO_MINOR_MM[size], abs=1e-3)  # ISO 965 table value, 3 decimals
    assert 2 * r.max() == pytest.approx(major, abs=1e-6)
    # Pitch and flats along one generator line (theta = 0): crest flats at the minor radius are P/4 long,
    # root flats at the major radius P/8, and successive crests are one pitch apart.
    line = v[(np.abs(v[:, 1]) < 1e-9) & (v[:, 0] > 0)]
    line = line[np.argsort(line[:, 2])]
    rl = np.hypot(line[:, 0], line[:, 1])
    for radius, width in ((r.min(), pitch / 4), (r.max(), pitch / 8)):
        z = np.unique(np.round(line[np.abs(rl - radius) < 1e-9, 2], 9))
        groups = np.split(z, np.flatnonzero(np.diff(z) > pitch / 2) + 1)
        full = groups[1:-1]  # the first and last flats may be cut by the thread's run-out
        widths = np.array([g.max() - g.min() for g in full])
        centres = np.array([(g.max() + g.min()) / 2 for g in full])
        assert len(full) >= 5
        np.testing.assert_allclose(widths, width, atol=1e-6)
        np.testing.assert_allclose(np.diff(centres), pitch, atol=1e-6)
    # Flanks at 60° (ISO 68-1: by definition), measured on the mesh: every edge of the axial section between
    # two radii (the flanks; the flats keep their radius) runs at 30° to the radial direction, rising and
    # falling, so the two flanks of a tooth meet at 60°. The vertices are exact to rounding (a few eps of the
    # ~10 mm coordinates), so an edge's angle is good to 32 eps times the coordinates over the shortest edge.
    dz, dr = np.diff(line[:, 2]), np.diff(rl)
    flank = np.abs(dr) > 1e-9
    half_angle = np.arctan2(np.abs(dz[flank]), np.abs(dr[flank]))
    rounding = 32 * np.finfo(float).eps * np.abs(line).max() / np.hypot(dz, dr)[flank].min()
    assert np.abs(half_angle - np.deg2rad(30.0)).max() < rounding, np.degrees(half_angle)
    assert flank.sum() >= 4 * len(full) and np.any(dz[flank] * dr[flank] > 0) and np.any(dz[flank] * dr[flank] < 0)
    # Mesh rows are closer than P/8 so that every flat has vertices on it.
    assert np.diff(np.unique(np.round(line[:, 2], 9))).max() < pitch / 8 + 1e-9


def test_iso_profile_values():
    prof = iso_thread_profile(10.0, 1.5)
    assert prof["minor_diameter_mm"] == pytest.approx(ISO_MINOR_MM["M10x1.5"], abs=1e-3)
    assert prof["fundamental_triangle_height_mm"] == pytest.approx(0.866025 * 1.5, abs=1e-6)


def test_unknown_thread_size_is_an_input_error():
    with pytest.raises(InputError, match="M7"):
        build_scene("thread", thread="M7x1")


def test_dome_mesh_is_the_specified_dome():
    scene = build_scene("dome")
    d = scene.info["dome"]
    v = scene.mesh.vertices
    assert v[:, 2].min() == pytest.approx(-10.0)
    cav = v[v[:, 2] < -1e-9]
    np.testing.assert_allclose(np.linalg.norm(cav - d["sphere_centre_mm"], axis=1), 17.5, atol=1e-9)
    assert np.abs(v[:, :2]).max() == pytest.approx(20.0)
    with pytest.raises(InputError):
        build_scene("dome", dome_radius_mm=30.0)


def test_dome_targets_ground_truth():
    scene = build_scene("dome")
    targets = scene.info["targets"]
    assert len(targets) == 8
    assert sorted(t["shape"] for t in targets).count("star") == 1
    star = next(t for t in targets if t["shape"] == "star")
    assert star["size"]["edge_mm"] == 6.0
    for t in targets:
        c = np.asarray(t["centroid_mm"])
        # On the dome: the centroid lies on the sphere, and the surface area exceeds the flat outline's
        # by the slope stretch 1 / cos(slope) at that point, to within the variation across the target.
        dist = np.linalg.norm(c - scene.info["dome"]["sphere_centre_mm"])
        assert dist == pytest.approx(17.5, abs=1e-3)  # inside a triangle: chord error < 1 µm
        stretch = 17.5 / abs(c[2] - scene.info["dome"]["sphere_centre_mm"][2])
        assert t["area_mm2"] == pytest.approx(t["flat_area_mm2"] * stretch, rel=0.03)
        outline = np.asarray(t["outline_mm"])
        assert outline.shape[1] == 3 and len(outline) >= len(t["outline_uv_mm"])
    # Targets do not overlap: each target's outline points are on no other target.
    for t in scene.targets:
        others = [o for o in scene.targets if o.id != t.id]
        pts = np.asarray(next(x for x in targets if x["id"] == t.id)["outline_mm"])
        assert not any(o.contains(pts).any() for o in others)


def test_star_outline_is_a_regular_pentagram():
    pts = star_outline(6.0)
    tips = pts[::2]
    # Each stroke of the pentagram joins a tip to the tip two along it: 6 mm.
    np.testing.assert_allclose(np.linalg.norm(tips - np.roll(tips, 2, axis=0), axis=1), 6.0)
    _, sizes = target_outline("star", 6.0)
    assert sizes["inner_radius_mm"] / sizes["outer_radius_mm"] == pytest.approx((3 - np.sqrt(5)) / 2)


def test_bladder_is_a_closed_cavity_of_the_specified_size_with_star_markers():
    scene = build_scene("bladder")
    extent = np.asarray(scene.info["bladder"]["extent_mm"])
    assert np.all((extent >= 60.0) & (extent <= 100.0))
    assert scene.mesh.to_trimesh().is_watertight
    stars = scene.info["targets"]
    assert len(stars) == 4 and all(s["shape"] == "star" for s in stars)
    for s in stars:
        assert s["size"]["outer_diameter_mm"] == pytest.approx(6.0)
        assert 0.9 * s["flat_area_mm2"] < s["area_mm2"] < 1.1 * s["flat_area_mm2"]
