"""Ray casting: the Embree and the pure-NumPy backends of ``RayCaster`` give the same first hits.

Both backends only *find* the triangle; the distance is then recomputed on that triangle in float64
(Möller–Trumbore). So when both find the same triangle their distances are bit-identical, and when they find
two triangles sharing the edge the ray crosses, the two planes meet there and the distances differ by float64
rounding: ~1e-16 relative, times 1/sin(incidence) <= 300 for the most grazing ray below (0.2 deg), so
< 1e-13. A single-precision intersection (what Embree itself computes) is off by ~6e-8 of the 20 mm
coordinates, 1e-7 relative or more, again amplified at grazing incidence. The tolerance, 1e-9 relative, lies
between the two: it passes the float64 answer and would fail a float32 one.

Rays, on the dome phantom (plate top z = 0, spherical cavity of R = 17.5 mm about (0, 0, 7.5), 10 mm deep,
rim radius 15.81 mm; the mesh is only the plate's top and the cavity, both zero-thickness):

* views from above in a 60 deg cone: the steep ones hit the plate or the cavity, the wide ones pass beyond
  the 40 mm plate and miss;
* rays pointing up from above the plate: all miss;
* rays grazing the flat plate at 0.2-3 deg, landing on its ring outside the cavity: all hit, at the
  analytic distance h / sin(elevation);
* rays tangent to the cavity's sphere, starting delta inside it (hit at incidence asin(sqrt(2 R delta) / R),
  0.9 deg for delta = 2 um; the flat triangles lie at most ~0.3 um inside the sphere, far less) or delta
  outside it (never closer than delta to the sphere, and the mesh lies inside the sphere: near misses);
* rays from below: the back faces of the cavity and the plate count as hits for both.
"""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.phantoms import build_scene
from scope3d.phantoms import raycast
from scope3d.phantoms.raycast import RayCaster
from scope3d.scene.mesh import Mesh

R_MM = 17.5
CENTRE = np.array([0.0, 0.0, R_MM - 10.0])
PHI_OPEN = float(np.arcsin(np.sqrt(R_MM**2 - CENTRE[2] ** 2) / R_MM))  # polar angle of the rim, from -z
REL_TOL = 1e-9


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _cone(rng, n, axis, half_angle_deg):
    """n unit directions uniformly inside a cone about ``axis``."""
    cos_max = np.cos(np.radians(half_angle_deg))
    c = rng.uniform(cos_max, 1.0, n)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    s = np.sqrt(1.0 - c**2)
    local = np.column_stack([s * np.cos(phi), s * np.sin(phi), c])
    z = _unit(axis)
    x = _unit(np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0]))
    return local @ np.stack([x, np.cross(z, x), z])


def _ray_groups():
    """{name: (origins (n, 3), directions (n, 3), expected hit (n,) bool or None)}."""
    rng = np.random.default_rng(0)
    groups = {}
    origins = np.repeat([[0.0, 0.0, 15.0], [8.0, -5.0, 15.0], [-12.0, 10.0, 15.0]], 100, axis=0)
    groups["views from above"] = (origins, _cone(rng, 300, [0, 0, -1], 60.0), None)
    origins = np.column_stack([rng.uniform(-25, 25, (50, 2)), rng.uniform(0.1, 20, 50)])
    groups["pointing up"] = (origins, _cone(rng, 50, [0, 0, 1], 80.0), np.zeros(50, bool))
    # grazing the plate: from x = 19.9 mm towards -x, down at elevation e, 2 mm of horizontal travel to z = 0
    elevation = np.radians(np.repeat([0.2, 0.5, 1.0, 3.0], 15))
    y0 = np.tile(np.linspace(-3.0, 3.0, 15), 4)
    height = 2.0 * np.tan(elevation)
    origins = np.column_stack([np.full(60, 19.9), y0, height])
    directions = np.column_stack([-np.cos(elevation), np.zeros(60), -np.sin(elevation)])
    groups["grazing the plate"] = (origins, directions, np.ones(60, bool))
    # tangent to the sphere along a parallel, at polar angles inside the cap and all round
    phi = np.radians(rng.uniform(5.0, np.degrees(PHI_OPEN) - 5.0, 40))
    theta = rng.uniform(0.0, 2 * np.pi, 40)
    on_sphere = CENTRE + R_MM * np.column_stack([np.sin(phi) * np.cos(theta), np.sin(phi) * np.sin(theta), -np.cos(phi)])
    inward = (CENTRE - on_sphere) / R_MM
    along = np.column_stack([-np.sin(theta), np.cos(theta), np.zeros(40)])
    for delta in (0.002, 0.01, 0.05):
        groups[f"tangent, {delta} mm inside"] = (on_sphere + delta * inward, along, np.ones(40, bool))
        groups[f"tangent, {delta} mm outside"] = (on_sphere - delta * inward, along, np.zeros(40, bool))
    # from below, spreading at most 20 tan 20 deg = 7.3 mm by z = 0: all inside the 40 mm plate
    origins = np.column_stack([rng.uniform(-10, 10, (100, 2)), np.full(100, -20.0)])
    groups["from below"] = (origins, _cone(rng, 100, [0, 0, 1], 20.0), np.ones(100, bool))
    return groups


@pytest.fixture(scope="module")
def mesh():
    return build_scene("dome").mesh


@pytest.fixture(scope="module")
def casts(mesh):
    embree, numpy_ = RayCaster(mesh, backend="embree"), RayCaster(mesh, backend="numpy")
    assert (embree.backend, numpy_.backend) == ("embree", "numpy")
    out = {}
    for name, (origins, directions, expected) in _ray_groups().items():
        out[name] = (origins, directions, expected, embree.cast(origins, directions), numpy_.cast(origins, directions))
    return out


def test_backends_agree_on_hits_and_distances(casts):
    for name, (origins, directions, expected, a, b) in casts.items():
        np.testing.assert_array_equal(a.hit, b.hit, err_msg=name)
        if expected is not None:
            np.testing.assert_array_equal(a.hit, expected, err_msg=name)
        else:  # the cone from above both hits and misses
            assert 0 < a.hit.sum() < len(a.hit), name
        np.testing.assert_array_equal(np.isnan(a.distance_mm), ~a.hit, err_msg=name)
        np.testing.assert_array_equal(np.isnan(b.distance_mm), ~b.hit, err_msg=name)
        hit = a.hit
        np.testing.assert_allclose(a.distance_mm[hit], b.distance_mm[hit], rtol=REL_TOL, atol=0, err_msg=name)
        np.testing.assert_allclose(a.points[hit], b.points[hit], rtol=0, atol=REL_TOL * 50.0, err_msg=name)
        # where they found the same triangle (a ray through an edge may report either neighbour), the
        # normals agree too
        same = hit & (a.triangle == b.triangle)
        np.testing.assert_allclose(a.normals[same], b.normals[same], rtol=0, atol=1e-12, err_msg=name)


def test_grazing_hits_are_at_the_analytic_distance(casts, mesh):
    origins, directions, _, a, b = casts["grazing the plate"]
    elevation = np.arcsin(-directions[:, 2])
    exact = origins[:, 2] / np.sin(elevation)
    for hits in (a, b):
        np.testing.assert_allclose(hits.distance_mm, exact, rtol=REL_TOL, atol=0)
        np.testing.assert_allclose(hits.points[:, 2], 0.0, rtol=0, atol=1e-12)
        # they are grazing: the angle between ray and plate is the elevation (0.2-3 deg)
        incidence = np.degrees(np.arcsin(np.abs(np.einsum("ij,ij->i", directions, hits.normals))))
        np.testing.assert_allclose(incidence, np.degrees(elevation), atol=1e-9)
    tri = mesh.vertices[mesh.faces]
    on_cap = np.all(np.abs(np.linalg.norm(tri - CENTRE, axis=2) - R_MM) < 1e-9, axis=1)
    longest = np.linalg.norm(tri[on_cap] - np.roll(tri[on_cap], 1, axis=1), axis=2).max()
    sagitta = longest**2 / (6 * R_MM)
    assert sagitta < 1e-3  # the phantom's tessellation (0.15 mm edges)
    for delta in (0.002, 0.01, 0.05):
        origins, directions, _, a, b = casts[f"tangent, {delta} mm inside"]
        # from the closest approach to the sphere: sqrt(R^2 - (R - delta)^2). The mesh's flat triangles have
        # their vertices on the sphere and lie at most L^2 / (6 R) inside it (L: longest edge; the depth of an
        # equilateral triangle's centre, the deepest case), which moves the hit along this grazing ray by at
        # most that / sin(incidence), sin(incidence) = chord / R
        chord = np.sqrt(R_MM**2 - (R_MM - delta) ** 2)
        for hits in (a, b):
            assert np.all(np.abs(hits.distance_mm - chord) <= sagitta / (chord / R_MM) + 1e-9), delta


def _numpy_refinement(caster, origins, directions, ray_idx, tri_idx):
    """The refinement in NumPy (Möller–Trumbore, point, interpolated normal), as RayCaster did it before
    its compiled kernel: the reference the kernel must match bit for bit (the rendered images depend on it)."""
    tri = caster._v0_e1_e2[tri_idx]
    v0, e1, e2 = tri[:, 0], tri[:, 1], tri[:, 2]
    d, o = directions[ray_idx], origins[ray_idx]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o - v0
        b1 = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        b2 = np.einsum("ij,ij->i", d, q) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
    t[np.abs(det) < 1e-300] = np.nan
    ok = np.isfinite(t) & (t > 0)
    n = len(origins)
    distance, bary, normals = np.full(n, np.nan), np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    ray_idx, tri_idx, b1, b2 = ray_idx[ok], tri_idx[ok], b1[ok], b2[ok]
    distance[ray_idx] = t[ok]
    bary[ray_idx] = np.column_stack([1.0 - b1 - b2, b1, b2])
    nrm = (np.einsum("mk,mkj->mj", bary[ray_idx], caster._face_vertex_normals[tri_idx])
           if caster._face_vertex_normals is not None else caster._face_normals[tri_idx])
    normals[ray_idx] = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    return distance, origins + distance[:, None] * directions, bary, normals


class _NumpyKernels:
    """Stands in for the compiled kernel module: the refinement in NumPy, written into the same outputs."""

    @staticmethod
    def refine_hits(origins, directions, ray_idx, tri_idx, v0_e1_e2, face_vertex_normals, face_normals,
                    vertex_normals, distance, triangle, barycentric, points, normals):
        caster = type("Caster", (), dict(_v0_e1_e2=v0_e1_e2, _face_normals=face_normals,
                                         _face_vertex_normals=face_vertex_normals if vertex_normals else None))
        d, p, b, n = _numpy_refinement(caster, origins, directions, ray_idx, tri_idx)
        hit = ~np.isnan(d)
        distance[:], points[:], barycentric[:], normals[:] = d, p, b, n
        triangle[ray_idx[hit[ray_idx]]] = tri_idx[hit[ray_idx]]

    @staticmethod
    def embree_rays(origins, directions, shift, scale, origins32, directions32):
        """What trimesh's Embree wrapper did before the query: unitize the directions, shift and scale the
        origins, cast both to float32."""
        import trimesh

        origins32[:] = ((np.array(origins, dtype=np.float64) - shift) * scale).astype(np.float32)
        directions32[:] = trimesh.util.unitize(directions).astype(np.float32)


class _NumpySensor:
    """Stands in for the renderer's compiled shading and sensor model: NumPy's whole-array expressions they
    replaced."""

    @staticmethod
    def depth_along(points, hit, centre, axis, depth):
        depth[:] = np.nan
        depth[hit] = (points[hit] - centre) @ axis

    @staticmethod
    def incidence(normals, directions, distance, footprint_scale, root_focal, cos_i, falloff, footprint):
        cos_i[:] = np.abs(np.einsum("ij,ij->i", normals, directions))
        falloff[:] = (cos_i / distance**2).astype(np.float32)
        footprint[:] = footprint_scale * distance / root_focal / np.sqrt(np.maximum(cos_i, 0.1))

    @staticmethod
    def shade(albedo, target, falloff, cos_i, distance, target_factor, specular, shininess, efficiency, background,
              rows, reflect, fluor, target_out):
        albedo = albedo.copy()
        on_target = target > 0
        albedo[on_target] *= 1.0 - 0.03  # RenderOptions' default target_reflectance_contrast, as a Python float
        assert target_factor == np.float32(1.0 - 0.03)
        value = albedo * falloff[:, None]
        if specular > 0:
            value += (specular * cos_i**shininess / distance**2).astype(np.float32)[:, None]
        reflect[rows] = value
        fluor[rows] = falloff * np.where(on_target, efficiency, background)
        target_out[rows] = target

    @staticmethod
    def noisy_uint8(values, packed, valid, normal, gain, shot2, read2, out):
        image = np.zeros(out.shape, np.float32)
        if packed:
            image[valid] = values * gain
        else:
            image[:] = (values * gain).reshape(out.shape)
        noisy = np.clip(image, 0.0, None)
        noisy *= shot2
        noisy += read2
        np.sqrt(noisy, out=noisy)
        noisy *= normal
        noisy += image
        noisy[~valid] = 0.0
        noisy *= 255.0
        np.round(noisy, out=noisy)
        np.clip(noisy, 0, 255, out=noisy)
        out[:] = noisy.astype(np.uint8)


@pytest.mark.parametrize("vertex_normals", [True, False])
def test_compiled_refinement_is_numpys(mesh, vertex_normals, monkeypatch):
    caster = RayCaster(mesh if vertex_normals else Mesh(mesh.vertices, mesh.faces))
    assert (caster._face_vertex_normals is not None) == vertex_normals  # both normal paths run
    rng = np.random.default_rng(1)
    origins = caster.mesh.vertices.mean(axis=0) + rng.normal(0.0, 3.0, (20_000, 3))
    directions = _unit(rng.normal(size=(20_000, 3)))
    hits = caster.cast(origins, directions)
    assert 0.2 < hits.hit.mean() < 1.0
    monkeypatch.setattr(raycast, "_kernels", _NumpyKernels)
    reference = caster.cast(origins, directions)
    np.testing.assert_array_equal(hits.triangle, reference.triangle)
    # the same formulas; NumPy's vectorised dot products may add their three terms in another order, so
    # the last bits differ (~1e-14 relative, measured; far below the 1e-9 of test_backends_agree...)
    for name in ("distance_mm", "points", "barycentric", "normals"):
        np.testing.assert_allclose(getattr(hits, name), getattr(reference, name), rtol=1e-12, atol=1e-12,
                                   err_msg=name)


def test_rendered_frame_is_the_numpy_renderers_bit_for_bit(monkeypatch):
    """The compiled passes change no bit of what the renderer writes (8-bit images with their noise,
    float32 depth, target ids): the NumPy refinement, trimesh's preparation of Embree's rays (unitize
    included), the shading, depth and noise expressions and the BLAS products they replaced, monkeypatched
    back, render the same frame."""
    from scope3d.phantoms import render
    from scope3d.phantoms.lab import generate

    seq = generate("dome", "approach", target=2, n_frames=2, size=(200, 200))
    scene = build_scene("dome")
    # the second frame with optical blur: the sensor model's other path (the frame blurred before the noise)
    options = [render.RenderOptions(), render.RenderOptions(blur_sigma_px=1.2)]
    frames = [render.render_frame(scene, seq.camera, pose, frame_index=k, options=options[k])
              for k, pose in enumerate(seq.true_poses)]
    monkeypatch.setattr(raycast, "_kernels", _NumpyKernels)
    monkeypatch.setattr(render, "_rows_times", lambda a, b: a @ b)
    monkeypatch.setattr(render, "_kernels", _NumpySensor)
    for k, pose in enumerate(seq.true_poses):
        before = render.render_frame(scene, seq.camera, pose, frame_index=k, options=options[k])
        for name in ("image", "fluorescence", "depth_mm", "target_id"):
            np.testing.assert_array_equal(getattr(frames[k], name), getattr(before, name), err_msg=name)
        assert (frames[k].target_id > 0).any()  # the approach looks at a target: its ids are compared too


def test_threaded_cast_gives_the_single_threaded_hits(mesh):
    rng = np.random.default_rng(2)
    origins = np.repeat([[0.0, 0.0, 15.0]], 60_000, axis=0)  # above the split threshold (50,000 rays)
    directions = _cone(rng, 60_000, [0, 0, -1], 60.0)
    one, three = RayCaster(mesh, threads=1).cast(origins, directions), RayCaster(mesh, threads=3).cast(origins, directions)
    assert 0 < one.hit.sum() < len(origins)
    np.testing.assert_array_equal(one.triangle, three.triangle)
    np.testing.assert_array_equal(one.points, three.points)
