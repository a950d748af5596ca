"""The phantoms of the reference as exact triangle meshes in millimetres, with textures and targets.

World frame of every scene: z up, lengths in mm.

* ``dome``: the debulked brain-tumour cavity of sec. 4.2 (Fig. 4.2): a spherical dome of radius
  ``R`` (15–17.5 mm) and depth 10 mm sunk into the top face (z = 0) of a 40 mm square plate, centred on
  the origin, with eight fluorescent targets (sec. 4.2, Fig. 4.6: a 5-pointed star of 6 mm edges among
  discs, squares and triangles).
* ``sheet``: a flat printed sheet in the plane z = 0 (sec. 4.6).
* ``bladder``: an irregular ellipsoidal closed cavity about 90 x 76 x 64 mm centred on the origin,
  seen from inside, with four 6 mm star markers (sec. 2.2, Fig. 2.3).
* ``thread``: an ISO 68-1 internal thread in a blind hole in shiny aluminium (ch. 7–8): axis = z,
  opening at z = 0, hole towards -z.
* ``cavity``: a resection cavity as a surgeon leaves it after debulking (issue 35; the reference's ch. 9.3.1
  asks for a map that follows such tissue): an irregular pit 6–15 mm deep in the 40 mm plate, an
  overhanging lip on one side (not a height field), creases where the wall meets the plate and the floor, a
  2 mm step onto a shelf, a bundle of vessels crossing it, wet highlights, the 8 fluorescent targets.

A :class:`Scene` holds the mesh (with vertex normals; creases are split so that shading stays sharp
there), a world-anchored albedo function, a material, the fluorescent targets and ``info``, the
JSON-ready description written to ``ground_truth/scene.json``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Callable

import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.grid import grid_faces
from scope3d.geometry.iso_thread import THREAD_SIZES, basic_pitch_diameter, iso_thread_profile, profile_segments
from scope3d.phantoms.raycast import RayCaster
from scope3d.phantoms.textures import TextureMap, machined_texture, printed_texture, tissue_texture
from scope3d.scene.mesh import Mesh

REFERENCE = "dissertation (reference)"
DOME_RADIUS_RANGE_MM = (15.0, 17.5)
DOME_DEPTH_MM = 10.0
DOME_PLATE_MM = 40.0
SHEET_SIZE_MM = 60.0
BLADDER_SEMI_AXES_MM = (45.0, 38.0, 32.0)

# Trajectories that fit each scene, default first.
SCENE_TRAJECTORIES = {
    "dome": ("grid5x6", "grid7x8", "approach"),
    "sheet": ("grid5x6", "grid7x8"),
    "bladder": ("spiral",),
    "thread": ("axial", "quadrants"),
    "cavity": ("grid5x6", "grid7x8", "approach"),
}

# Mesh resolution. Chord errors of the tessellation stay below 1 µm (sagitta = edge² / 8R).
_DOME_EDGE_MM = 0.15
_N_THETA = 720
_THREAD_N_THETA = 720


@dataclass(frozen=True)
class Material:
    """Reflectance model: Lambertian albedo (from the texture) plus a white Blinn-Phong lobe.

    specular : float, peak specular reflectance relative to a white Lambertian surface.
    shininess : float, Blinn-Phong exponent (larger = smaller, sharper highlights).
    """

    specular: float = 0.0
    shininess: float = 1.0


@dataclass(frozen=True)
class TrueTarget:
    """A flat fluorescent film laid on the surface (sec. 4.2: dye-in-polymer targets).

    The target is the set of surface points whose projection along ``frame[2]`` onto the plane through
    ``origin_mm`` falls inside ``outline_uv_mm`` (coordinates along ``frame[0]`` and ``frame[1]``),
    within ``depth_range_mm`` below the plane (so that the far side of a closed cavity is excluded).

    id : int; shape : "star", "disc", "square" or "triangle"; size : dict of named sizes in mm.
    origin_mm : (3,) mm; frame : (3, 3) rows u, v, n (world, orthonormal).
    outline_uv_mm : (K, 2) mm, closed polygon (last vertex not repeated).
    """

    id: int
    shape: str
    size: dict
    origin_mm: np.ndarray
    frame: np.ndarray
    outline_uv_mm: np.ndarray
    depth_range_mm: float

    def to_uv(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """points : (N, 3) mm -> (N, 2) (u, v) mm and (N,) height above the plane along n (mm)."""
        rel = np.asarray(points, dtype=float) - self.origin_mm
        local = rel @ self.frame.T
        return local[:, :2], local[:, 2]

    def contains(self, points: np.ndarray) -> np.ndarray:
        """points : (N, 3) mm on the surface -> (N,) bool, True on the target."""
        from matplotlib.path import Path as MplPath

        points = np.asarray(points, dtype=float).reshape(-1, 3)
        inside = np.zeros(len(points), dtype=bool)
        # Cheap bounding-sphere rejection first: a frame sees hundreds of thousands of points, few on targets.
        rel = points - self.origin_mm
        reach2 = float(np.max(np.sum(self.outline_uv_mm**2, axis=1))) + self.depth_range_mm**2
        cand = np.flatnonzero(np.einsum("ij,ij->i", rel, rel) <= reach2)
        if cand.size == 0:
            return inside
        uv, h = self.to_uv(points[cand])
        lo, hi = self.outline_uv_mm.min(axis=0), self.outline_uv_mm.max(axis=0)
        near = np.all((uv >= lo) & (uv <= hi), axis=1) & (h <= 1e-9) & (h >= -self.depth_range_mm)
        if np.any(near):
            inside[cand[near]] = MplPath(self.outline_uv_mm).contains_points(uv[near])
        return inside


@dataclass
class Scene:
    """A phantom: geometry, appearance and what is known about it.

    mesh : true surface, mm, with vertex normals.
    albedo : function ``(points (N, 3) mm, normals (N, 3), footprint_mm (N,)) -> (N, 3) float32`` RGB in [0, 1];
        footprint_mm is the pixel's size on the surface, used to low-pass the texture (no aliasing).
    trajectories : names of the trajectories that make sense in this scene, default first.
    camera : ``"endoscope"`` or ``"borescope"``; fov_deg : default field of view across the width.
    info : JSON-ready parameters (written as ground_truth/scene.json).
    render_supersample : rays per pixel side when :class:`~scope3d.phantoms.render.RenderOptions` leaves
        ``supersample`` at None. 1 for the painted and printed phantoms (their textures are mip-mapped and
        their edges soft); 2 for the machined thread, whose sharp crests and specular edges alias badly
        with one ray per pixel.
    auto_exposure : the scope re-exposes every frame instead of keeping one setting for the sequence: the
        resection cavity's floor, 13 mm below the plate, is 3-4x darker than the plate at the scope's light.
    """

    name: str
    mesh: Mesh
    albedo: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
    material: Material
    targets: tuple[TrueTarget, ...]
    trajectories: tuple[str, ...]
    camera: str
    fov_deg: float
    info: dict = field(default_factory=dict)
    render_supersample: int = 1
    auto_exposure: bool = False
    _caster: RayCaster | None = field(default=None, repr=False)

    @property
    def default_trajectory(self) -> str:
        return self.trajectories[0]

    @property
    def caster(self) -> RayCaster:
        if self._caster is None:
            self._caster = RayCaster(self.mesh)
        return self._caster


# --- mesh helpers ------------------------------------------------------------------------------


def _assemble(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> Mesh:
    """Concatenate (vertices, faces, normals) parts; drop zero-area faces (collapsed poles, clamped ends)."""
    verts, faces, normals, offset = [], [], [], 0
    for v, f, n in parts:
        verts.append(v)
        faces.append(f + offset)
        normals.append(n)
        offset += len(v)
    v = np.concatenate(verts)
    f = np.concatenate(faces)
    n = np.concatenate(normals)
    area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    f = f[area2 > 1e-14]
    return Mesh(v, f, vertex_normals=n / np.linalg.norm(n, axis=1, keepdims=True))


def _square_annulus(r_inner: float, half_width: float, z: float, n_theta: int, n_rings: int, normal_z: float = 1.0):
    """Flat annulus at height z from a circle of radius ``r_inner`` (or a curve: one radius per azimuth) out to a square of half-width
    ``half_width``; ``n_theta`` must be a multiple of 8 so that the square's corners are vertices."""
    theta = np.arange(n_theta) * 2 * np.pi / n_theta
    r_square = half_width / np.maximum(np.abs(np.cos(theta)), np.abs(np.sin(theta)))
    k = np.linspace(0.0, 1.0, n_rings + 1)[:, None]
    rho = r_inner + (r_square - r_inner) * k
    v = np.stack([rho * np.cos(theta), rho * np.sin(theta), np.full_like(rho, z)], -1).reshape(-1, 3)
    n = np.tile([0.0, 0.0, normal_z], (len(v), 1))
    return v, grid_faces(n_rings + 1, n_theta, wrap=True), n


def _revolution(radius: np.ndarray, z: np.ndarray, normal_rz: np.ndarray, n_theta: int):
    """Surface of revolution about z through profile rows (radius, z) with per-row normals (n_r, n_z)."""
    theta = np.arange(n_theta) * 2 * np.pi / n_theta
    c, s = np.cos(theta), np.sin(theta)
    v = np.stack([radius[:, None] * c, radius[:, None] * s, np.broadcast_to(z[:, None], (len(z), n_theta))], -1)
    n = np.stack([normal_rz[:, 0:1] * c, normal_rz[:, 0:1] * s,
                  np.broadcast_to(normal_rz[:, 1:2], (len(z), n_theta))], -1)
    return v.reshape(-1, 3), grid_faces(len(z), n_theta, wrap=True), n.reshape(-1, 3)


def _triplanar(texs: list[TextureMap], points: np.ndarray, normals: np.ndarray, footprint_mm: np.ndarray) -> np.ndarray:
    """Triplanar mapping: three planar projections (along x, y, z) blended by how squarely the surface faces
    each axis. -> (N, 3) float32."""
    w = np.abs(normals) ** 4
    w /= w.sum(axis=1, keepdims=True)
    out = texs[0].sample(points[:, [1, 2]], footprint_mm) * w[:, 0:1].astype(np.float32)
    out += texs[1].sample(points[:, [0, 2]], footprint_mm) * w[:, 1:2].astype(np.float32)
    out += texs[2].sample(points[:, [0, 1]], footprint_mm) * w[:, 2:3].astype(np.float32)
    return out


# --- targets -----------------------------------------------------------------------------------


def star_outline(tip_to_tip_mm: float) -> np.ndarray:
    """Regular 5-pointed star (pentagram outline), one tip on +v. ``tip_to_tip_mm`` is the length of one of
    the five strokes of the pentagram (tip to the tip two along). -> (10, 2) mm."""
    r_out = tip_to_tip_mm / (2.0 * np.sin(np.deg2rad(72.0)))
    r_in = r_out * (3.0 - np.sqrt(5.0)) / 2.0
    ang = np.pi / 2 + np.arange(10) * np.pi / 5
    r = np.where(np.arange(10) % 2 == 0, r_out, r_in)
    return np.stack([r * np.cos(ang), r * np.sin(ang)], 1)


def regular_polygon(n: int, circumradius_mm: float, rotation_rad: float = 0.0) -> np.ndarray:
    ang = rotation_rad + np.pi / 2 + np.arange(n) * 2 * np.pi / n
    return circumradius_mm * np.stack([np.cos(ang), np.sin(ang)], 1)


def target_outline(shape: str, size_mm: float) -> tuple[np.ndarray, dict]:
    """Outline (K, 2) mm and named sizes of a target. size_mm: star stroke, disc diameter, square or
    (equilateral) triangle edge."""
    if shape == "star":
        pts = star_outline(size_mm)
        r_out = float(np.linalg.norm(pts[0]))
        return pts, {"edge_mm": size_mm, "outer_radius_mm": r_out, "inner_radius_mm": float(np.linalg.norm(pts[1])),
                     "outer_diameter_mm": 2 * r_out}
    if shape == "disc":
        return regular_polygon(128, size_mm / 2), {"diameter_mm": size_mm, "polygon_vertices": 128}
    if shape == "square":
        return regular_polygon(4, size_mm / np.sqrt(2), np.pi / 4), {"edge_mm": size_mm}
    if shape == "triangle":
        return regular_polygon(3, size_mm / np.sqrt(3)), {"edge_mm": size_mm}
    raise ValueError(f"unknown target shape {shape!r}")


def _polygon_area(uv: np.ndarray) -> float:
    x, y = uv[:, 0], uv[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _lift(caster: RayCaster, target: TrueTarget, uv: np.ndarray):
    """Drop points of the target plane onto the surface along -n. -> (points (N, 3), normals (N, 3), hit (N,))."""
    origins = target.origin_mm + uv @ target.frame[:2]
    dirs = np.broadcast_to(-target.frame[2], origins.shape)
    hits = caster.cast(origins, dirs)
    hit = hits.hit & (hits.distance_mm <= target.depth_range_mm)
    return hits.points, hits.normals, hit


def target_ground_truth(caster: RayCaster, target: TrueTarget, *, sample_mm: float = 0.02) -> dict:
    """Measure a target on the true surface: centroid, area, 3D outline.

    The area on the surface is the flat outline's area times the mean area stretch of the projection,
    ``1 / |n_surface . n|``, over a grid of ``sample_mm`` inside the outline (exact for the outline,
    and the stretch varies slowly across a few-mm target).
    """
    from matplotlib.path import Path as MplPath

    outline = target.outline_uv_mm
    lo, hi = outline.min(axis=0), outline.max(axis=0)
    gu, gv = np.meshgrid(np.arange(lo[0], hi[0], sample_mm) + sample_mm / 2,
                         np.arange(lo[1], hi[1], sample_mm) + sample_mm / 2)
    grid = np.stack([gu.ravel(), gv.ravel()], 1)
    grid = grid[MplPath(outline).contains_points(grid)]
    pts, nrm, hit = _lift(caster, target, grid)
    if not np.all(hit):
        raise ValueError(f"target {target.id} is not fully on the surface")
    stretch = 1.0 / np.abs(nrm @ target.frame[2])
    flat_area = _polygon_area(outline)
    x, y = outline[:, 0], outline[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    signed = 0.5 * cross.sum()
    centroid_uv = np.array([((x + np.roll(x, -1)) * cross).sum(), ((y + np.roll(y, -1)) * cross).sum()]) / (6 * signed)
    c_pt, c_n, _ = _lift(caster, target, centroid_uv[None])
    # Densify the outline so that the lifted polyline follows the curved surface (<= 0.1 mm steps).
    dense = []
    for a, b in zip(outline, np.roll(outline, -1, axis=0)):
        k = max(1, int(np.ceil(np.linalg.norm(b - a) / 0.1)))
        dense.append(a + (b - a) * (np.arange(k)[:, None] / k))
    dense = np.concatenate(dense)
    o_pt, _, o_hit = _lift(caster, target, dense)
    return {
        "id": target.id,
        "shape": target.shape,
        "size": target.size,
        "centroid_mm": c_pt[0].tolist(),
        "normal": c_n[0].tolist(),
        "area_mm2": float(flat_area * stretch.mean()),
        "flat_area_mm2": flat_area,
        "projection": {
            "origin_mm": target.origin_mm.tolist(),
            "u": target.frame[0].tolist(), "v": target.frame[1].tolist(), "n": target.frame[2].tolist(),
            "note": "outline_uv_mm is drawn in the plane (origin, u, v) and dropped onto the surface along -n",
        },
        "outline_uv_mm": outline.tolist(),
        "outline_mm": o_pt[o_hit].tolist(),
    }


def _frame_from_normal(n: np.ndarray, spin_rad: float) -> np.ndarray:
    n = n / np.linalg.norm(n)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, n)
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    c, s = np.cos(spin_rad), np.sin(spin_rad)
    return np.stack([c * u + s * v, -s * u + c * v, n])


# --- dome --------------------------------------------------------------------------------------

# (id, shape, size mm, ring radius mm, azimuth deg, spin deg). Star #4 as in Fig. 4.6 of the reference.
_DOME_TARGETS = [
    (1, "disc", 4.0, 5.5, 120.0, 0.0),
    (2, "square", 3.0, 5.5, 240.0, 20.0),
    (3, "disc", 2.0, 11.0, 36.0, 0.0),
    (4, "star", 6.0, 5.5, 0.0, 10.0),
    (5, "disc", 3.0, 11.0, 108.0, 0.0),
    (6, "square", 4.0, 11.0, 180.0, 35.0),
    (7, "triangle", 3.0, 11.0, 252.0, 15.0),
    (8, "triangle", 5.0, 11.0, 324.0, 50.0),
]


def build_dome(radius_mm: float = 17.5, *, texture_seed: int = 0, mm_per_texel: float = 0.015) -> Scene:
    """Spherical dome cavity of ``radius_mm`` and 10 mm depth in a 40 mm plate (top face z = 0)."""
    lo, hi = DOME_RADIUS_RANGE_MM
    if not lo <= radius_mm <= hi:
        raise InputError(f"dome radius must be within {lo}-{hi} mm (reference sec. 4.2), got {radius_mm}")
    depth = DOME_DEPTH_MM
    centre_z = radius_mm - depth  # sphere centre above the plate: the dome is less than a hemisphere
    r_open = float(np.sqrt(radius_mm**2 - centre_z**2))
    phi_open = float(np.arcsin(r_open / radius_mm))
    n_rings = int(np.ceil(radius_mm * phi_open / _DOME_EDGE_MM))
    phi = np.linspace(0.0, phi_open, n_rings + 1)
    radius = radius_mm * np.sin(phi)
    z = centre_z - radius_mm * np.cos(phi)
    z[-1] = 0.0  # exactly on the plate top despite rounding
    normals = np.stack([-np.sin(phi), np.cos(phi)], 1)  # towards the sphere centre, i.e. out of the cavity
    cap = _revolution(radius, z, normals, _N_THETA)
    plate = _square_annulus(r_open, DOME_PLATE_MM / 2, 0.0, _N_THETA, 24)
    mesh = _assemble([cap, plate])

    size = DOME_PLATE_MM + 2.0
    tex = TextureMap(tissue_texture((size, size), mm_per_texel, texture_seed), (-size / 2, -size / 2), mm_per_texel)

    def albedo(points, normals, footprint_mm):
        # Planar (top-down) projection: what a painter sees from above; stretches on steep walls.
        return tex.sample(points[:, :2], footprint_mm)

    scene = Scene("dome", mesh, albedo, Material(specular=0.04, shininess=20.0), (), SCENE_TRAJECTORIES["dome"],
                  "endoscope", 53.0)
    targets = []
    for tid, shape, size_mm, ring, az, spin in _DOME_TARGETS:
        outline, sizes = target_outline(shape, size_mm)
        a = np.deg2rad(az)
        origin = np.array([ring * np.cos(a), ring * np.sin(a), 1.0])
        frame = _frame_from_normal(np.array([0.0, 0.0, 1.0]), np.deg2rad(spin))
        targets.append(TrueTarget(tid, shape, sizes, origin, frame, outline, depth_range_mm=depth + 2.0))
    scene.targets = tuple(targets)
    scene.info = {
        "name": "dome",
        "description": "debulked brain-tumour cavity: spherical dome in a square plate, cortex-like texture, "
                       "8 fluorescent targets (reference sec. 4.2, Fig. 4.2 and 4.6)",
        "units": "mm",
        "world_frame": "z up; plate top face z = 0; dome axis = z through the origin",
        "dome": {"radius_mm": radius_mm, "depth_mm": depth, "sphere_centre_mm": [0.0, 0.0, centre_z],
                 "opening_radius_mm": r_open, "plate_size_mm": DOME_PLATE_MM},
        "texture": {"kind": "tissue (vessels, capillary dots), planar projection along z", "seed": texture_seed,
                    "mm_per_texel": mm_per_texel},
        "targets": [target_ground_truth(scene.caster, t) for t in targets],
    }
    return scene


# --- sheet -------------------------------------------------------------------------------------


def build_sheet(*, texture_seed: int = 0, mm_per_texel: float = 0.02, size_mm: float = SHEET_SIZE_MM) -> Scene:
    """A flat printed sheet, ``size_mm`` square (60 mm: reference sec. 4.6), in the plane z = 0. A larger
    sheet holds a longer survey (benchmarks/bench_map_scaling.py)."""
    if not size_mm > 0:
        raise ValueError(f"sheet size must be a positive number of mm, got {size_mm}")
    half = size_mm / 2
    g = np.linspace(-half, half, 5)
    gx, gy = np.meshgrid(g, g)
    v = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    mesh = _assemble([(v, grid_faces(5, 5, wrap=False), np.tile([0.0, 0.0, 1.0], (len(v), 1)))])
    size = size_mm + 2.0
    tex = TextureMap(printed_texture((size, size), mm_per_texel, texture_seed + 1), (-size / 2, -size / 2),
                     mm_per_texel)

    def albedo(points, normals, footprint_mm):
        return tex.sample(points[:, :2], footprint_mm)

    info = {
        "name": "sheet",
        "description": "flat printed sheet (reference sec. 4.6)",
        "units": "mm",
        "world_frame": "z up; sheet in the plane z = 0, centred on the origin",
        "sheet": {"size_mm": size_mm},
        "texture": {"kind": "printed tissue photograph", "seed": texture_seed, "mm_per_texel": mm_per_texel},
        "targets": [],
    }
    return Scene("sheet", mesh, albedo, Material(), (), SCENE_TRAJECTORIES["sheet"], "endoscope", 53.0, info)


# --- bladder -----------------------------------------------------------------------------------


def _bladder_radius_scale(d: np.ndarray) -> np.ndarray:
    """Smooth irregularity: radial scale factor (N,) of unit directions d (N, 3)."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return 1.0 + 0.06 * x * y + 0.05 * np.sin(2.0 * x + 1.0) * z + 0.04 * (z * z - 0.3) - 0.03 * y * z * z


def _bladder_shape_scale(d: np.ndarray, shape_seed: int) -> np.ndarray:
    """Radial scale (N,) of unit directions d (N, 3): today's shape for seed 0, else random smooth bumps
    of the same amplitude (quadratic and cubic terms of the direction, coefficients within ±0.06)."""
    if shape_seed == 0:
        return _bladder_radius_scale(d)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    terms = np.stack([x * y, y * z, x * z, x * x - y * y, z * z - 1.0 / 3.0, x * y * z, x * z * z, y * y * z,
                      np.sin(2.0 * x + 1.0) * z], axis=1)
    coef = np.random.default_rng([shape_seed, 2]).uniform(-0.06, 0.06, terms.shape[1])
    return 1.0 + terms @ coef


# Wet mucosa at the scope-tip light: a sharp, bright Blinn-Phong glint (the dry latex default: 0.06, 25).
WET_MATERIAL = Material(specular=0.6, shininess=120.0)


def build_bladder(*, texture_seed: int = 0, mm_per_texel: float = 0.05, semi_axes_mm=BLADDER_SEMI_AXES_MM,
                  shape_seed: int = 0, vessel_density: float = 1.0, wet: bool = False) -> Scene:
    """Irregular ellipsoidal closed cavity (about 90 x 76 x 64 mm) with vessels and four 6 mm star markers
    (reference sec. 2.2, Fig. 2.3).

    semi_axes_mm : (3,) the ellipsoid's semi-axes before the irregularity; shape_seed : 0 for the default
    irregularity, else a random one of the same size; vessel_density : fraction of the default vessel and
    capillary-dot density (a pale, sparsely vascular wall at 0.25); wet : specular glints of wet mucosa.
    """
    import trimesh

    a = np.asarray(semi_axes_mm, dtype=float).reshape(3)
    if not (np.all(np.isfinite(a)) and np.all(a > 0)):
        raise InputError(f"bladder semi-axes must be three positive lengths in mm, got {semi_axes_mm}")
    if not 0.0 <= vessel_density <= 4.0:
        raise InputError(f"vessel density must be a fraction from 0 to 4 of the default, got {vessel_density}")
    sphere = trimesh.creation.icosphere(subdivisions=6)
    d = np.asarray(sphere.vertices, dtype=float)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    verts = d * a * _bladder_shape_scale(d, int(shape_seed))[:, None]
    faces = np.asarray(sphere.faces, dtype=np.int64)
    tm = trimesh.Trimesh(verts, faces, process=False)
    normals = -np.asarray(tm.vertex_normals)  # into the cavity, towards the camera
    mesh = Mesh(verts, faces, vertex_normals=normals)

    size = 2 * a.max() * 1.25 + 4
    texs = [TextureMap(tissue_texture((size, size), mm_per_texel, texture_seed + 10 + k, vessel_width_mm=(0.15, 1.4),
                                      vessel_density_per_cm2=0.25 * vessel_density, speckle_mm=0.5,
                                      background_rgb=(0.90, 0.66, 0.58), dot_contrast=0.45 * min(vessel_density, 1.0)),
                       (-size / 2, -size / 2), mm_per_texel) for k in range(3)]

    def albedo(points, normals, footprint_mm):
        return _triplanar(texs, points, normals, footprint_mm)

    material = WET_MATERIAL if wet else Material(specular=0.06, shininess=25.0)
    scene = Scene("bladder", mesh, albedo, material, (), SCENE_TRAJECTORIES["bladder"],
                  "endoscope", 70.0)
    targets = []
    directions = [(0.3, 0.8, 0.3), (-0.7, 0.2, -0.1), (0.6, -0.5, -0.5), (-0.2, -0.4, 0.85)]
    for k, direction in enumerate(directions):
        dvec = np.asarray(direction) / np.linalg.norm(direction)
        h = scene.caster.cast(np.zeros((1, 3)), dvec[None])
        normal_in = h.normals[0] if np.dot(h.normals[0], dvec) < 0 else -h.normals[0]
        outline, sizes = target_outline("star", 6.0 * np.sin(np.deg2rad(72.0)))  # 6 mm outer diameter
        origin = h.points[0] + 2.0 * normal_in
        targets.append(TrueTarget(k + 1, "star", sizes, origin, _frame_from_normal(normal_in, 0.4 * k), outline,
                                  depth_range_mm=5.0))
    scene.targets = tuple(targets)
    scene.info = {
        "name": "bladder",
        "description": "irregular ellipsoidal bladder-like closed cavity seen from inside, vessel texture, "
                       "four 6 mm (outer diameter) fluorescent stars usable as scale references (reference sec. 2.2)",
        "units": "mm",
        "world_frame": "cavity centred on the origin; z up",
        "bladder": {"semi_axes_mm": a.tolist(), "shape_seed": int(shape_seed),
                    "radius_scale": "1 + 0.06xy + 0.05 sin(2x+1) z + 0.04 (z^2 - 0.3) - 0.03 y z^2 of the unit "
                                    "direction (x, y, z)" if shape_seed == 0 else
                                    "1 + sum of 9 quadratic/cubic terms of the unit direction, coefficients "
                                    "uniform in ±0.06 drawn with default_rng([shape_seed, 2])",
                    "vessel_density": float(vessel_density),
                    "material": {"specular": material.specular, "shininess": material.shininess,
                                 "kind": "wet mucosa" if wet else "latex"},
                    "extent_mm": (verts.max(0) - verts.min(0)).tolist()},
        "texture": {"kind": "tissue (vessels), triplanar projection", "seed": texture_seed,
                    "mm_per_texel": mm_per_texel},
        "targets": [target_ground_truth(scene.caster, t) for t in targets],
    }
    return scene


# --- resection cavity ----------------------------------------------------------------------------

# The cavity's shape, all in the plate's polar coordinates (theta about +z from +x, mm). Wall, floor and step
# are parametric, so the mesh's vertices lie exactly on the surface these functions define.
CAVITY_STEP_MM = 2.0  # the shelf's edge: a vertical drop of 2 mm (issue 35)
CAVITY_STEP_FRACTION = 0.55  # the step's radius as a fraction of the floor's (theta-dependent) radius
CAVITY_LIP_AZIMUTH_DEG = 0.0
CAVITY_LIP_HALF_WIDTH_DEG = 50.0
CAVITY_LIP_OVERHANG_MM = 1.6  # amplitude of the lip's undercut (the overhang reaches about 1 mm)
CAVITY_LIP_LEAN_DEPTH_MM = 11.8  # the undercut grows as sin(pi d / (2 this)): 12° past vertical at the rim
CAVITY_SHELF_AZIMUTH_DEG = 200.0
CAVITY_SHELF_HALF_WIDTH_DEG = (40.0, 55.0)  # full height within the first, tapering to nothing at the second
_CAVITY_N_THETA = 720
_CAVITY_ROWS = {"wall": 90, "outer_floor": 30, "step": 14, "inner_floor": 40}
# The targets (id, shape, size mm, azimuth deg, spin deg): the star in the middle of the floor, the others on
# the floor ring between the step and the wall, away from the lip (a film projected from above must not fall
# on it).
_CAVITY_TARGETS = [
    (1, "disc", 2.5, 50.0, 0.0),
    (2, "square", 2.0, 93.0, 20.0),
    (3, "disc", 2.0, 137.0, 0.0),
    (4, "star", 6.0, None, 10.0),
    (5, "disc", 2.5, 180.0, 0.0),
    (6, "square", 2.0, 223.0, 35.0),
    (7, "triangle", 2.5, 267.0, 15.0),
    (8, "triangle", 2.5, 310.0, 50.0),
]
_CAVITY_TARGET_RING = 0.775  # of the floor's radius: midway between the step (0.55) and the wall (1)


def _wrapped_deg(theta: np.ndarray, centre_deg: float) -> np.ndarray:
    """|theta - centre| in degrees, wrapped to [0, 180]."""
    return np.abs(np.rad2deg(np.angle(np.exp(1j * (np.asarray(theta) - np.deg2rad(centre_deg))))))


def cavity_rim_radius(theta: np.ndarray) -> np.ndarray:
    """Radius (mm) of the cavity's opening in the plate at azimuth theta (rad): 9.3 mm at the lip, 12.5 opposite."""
    theta = np.asarray(theta, dtype=float)
    return 10.5 - 1.5 * np.cos(theta) + 0.4 * np.sin(2 * theta + 0.5) + 0.25 * np.cos(3 * theta - 1.0)


def cavity_lip_weight(theta: np.ndarray) -> np.ndarray:
    """How much of the lip's undercut applies at azimuth theta: 1 at its middle, cos² to 0 at its ends."""
    off = _wrapped_deg(theta, CAVITY_LIP_AZIMUTH_DEG)
    return np.where(off < CAVITY_LIP_HALF_WIDTH_DEG, np.cos(0.5 * np.pi * off / CAVITY_LIP_HALF_WIDTH_DEG) ** 2, 0.0)


def cavity_shelf_weight(theta: np.ndarray) -> np.ndarray:
    """Fraction of the 2 mm the shelf is raised at azimuth theta: 1 on its middle, a cos² taper at its ends."""
    off = _wrapped_deg(theta, CAVITY_SHELF_AZIMUTH_DEG)
    flat, end = CAVITY_SHELF_HALF_WIDTH_DEG
    taper = 0.5 * (1.0 + np.cos(np.pi * np.clip((off - flat) / (end - flat), 0.0, 1.0)))
    return np.where(off <= flat, 1.0, taper)


def cavity_floor_depth(theta: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Depth (mm, below the plate) of the floor before the shelf is raised, at azimuth theta and rho, the
    fraction of the floor's radius (0 in the middle, 1 where the wall starts): 13 mm in the middle, a dip to
    about 14.6, rising to 8-12 at the wall."""
    theta, rho = np.asarray(theta, dtype=float), np.asarray(rho, dtype=float)
    tilt = -3.0 - 2.0 * np.cos(theta - np.deg2rad(CAVITY_SHELF_AZIMUTH_DEG)) + 0.6 * np.sin(2 * theta + 1.0)
    px, py = rho * np.cos(theta), rho * np.sin(theta)
    dip = 1.8 * np.exp(-((px + 0.2) ** 2 + (py + 0.15) ** 2) / (2 * 0.18**2))
    return 13.0 + rho**2 * tilt + dip


def cavity_wall_depth(theta: np.ndarray) -> np.ndarray:
    """Height (mm) of the wall at azimuth theta: the floor's depth at its edge less the raised shelf."""
    return cavity_floor_depth(theta, np.ones_like(np.asarray(theta, dtype=float))) - CAVITY_STEP_MM * cavity_shelf_weight(theta)


def cavity_wall_radius(theta: np.ndarray, depth_mm: np.ndarray) -> np.ndarray:
    """Radius (mm) of the wall at azimuth theta, ``depth_mm`` below the plate (0 to :func:`cavity_wall_depth`).

    The wall is vertical at the rim and draws in by ``k d² / wall depth`` (k = 0.25: 2-3 mm at the floor);
    under the lip k drops to 0.05 and the wall leans out by ``overhang sin(pi d / (2 lean depth))``, which
    carries it up to about 1 mm beyond the rim: an undercut the plate's edge overhangs.
    """
    theta, d = np.asarray(theta, dtype=float), np.asarray(depth_mm, dtype=float)
    lip = cavity_lip_weight(theta)
    k = 0.25 * (1.0 - 0.8 * lip)
    lean = CAVITY_LIP_OVERHANG_MM * lip * np.sin(0.5 * np.pi * d / CAVITY_LIP_LEAN_DEPTH_MM)
    return cavity_rim_radius(theta) - k * d**2 / cavity_wall_depth(theta) + lean


def cavity_floor_radius(theta: np.ndarray) -> np.ndarray:
    """Radius (mm) of the floor's edge (the wall's foot) at azimuth theta."""
    return cavity_wall_radius(theta, cavity_wall_depth(theta))


def _grid_normals(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Normals (rows, cols, 3) of a grid (rows, cols, 3) that wraps along its columns: column tangent x row
    tangent (the faces' winding, see :func:`~scope3d.geometry.grid.grid_faces`). Where the grid collapses
    (the floor's middle, a step of no height) ``fallback`` (3,) or (rows, cols, 3)."""
    along_col = np.roll(v, -1, axis=1) - np.roll(v, 1, axis=1)
    along_row = np.gradient(v, axis=0)
    n = np.cross(along_col, along_row)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    fallback = np.broadcast_to(fallback, v.shape)
    return np.where(length > 1e-12, n / np.maximum(length, 1e-300), fallback)


def _polar_grid(radius: np.ndarray, z: np.ndarray, theta: np.ndarray) -> np.ndarray:
    return np.stack([radius * np.cos(theta), radius * np.sin(theta), z], axis=-1)


def _vessel_bundle(points: np.ndarray, footprint_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coverage (N,) in [0, 1] and colour (N, 3) of three vessels crossing the cavity along x, painted as seen
    from above: centre lines y = 1.5 sin(0.2 x + 0.4) - 0.08 x + offset; edges soft over a pixel's footprint."""
    x, y = points[:, 0], points[:, 1]
    centre = 1.5 * np.sin(0.2 * x + 0.4) - 0.08 * x
    slope = 0.3 * np.cos(0.2 * x + 0.4) - 0.08
    cover = np.zeros(len(points))
    colour = np.zeros((len(points), 3))
    for offset, width, rgb in ((-0.8, 0.5, (0.62, 0.10, 0.10)), (0.0, 0.35, (0.70, 0.16, 0.14)),
                               (0.7, 0.45, (0.34, 0.12, 0.26))):
        dist = np.abs(y - centre - offset) / np.sqrt(1.0 + slope**2)
        a = np.clip((0.5 * width - dist) / np.maximum(footprint_mm, 0.02) + 0.5, 0.0, 1.0)
        colour = colour * (1 - a)[:, None] + np.asarray(rgb) * a[:, None]
        cover = np.maximum(cover, a)
    return cover, colour


def build_cavity(*, texture_seed: int = 0, mm_per_texel: float = 0.015) -> Scene:
    """A resection cavity in a 40 mm plate (top face z = 0): see the module docstring and the ``cavity_*``
    functions, which define every part. The mesh is five parametric grids over the azimuth (wall from the rim
    down, floor ring, the step's face, inner floor, plate); rows meet at the creases with separate vertices,
    so the shading stays sharp there."""
    n_th = _CAVITY_N_THETA
    theta = np.arange(n_th) * 2 * np.pi / n_th
    rim = cavity_rim_radius(theta)
    wall_depth = cavity_wall_depth(theta)
    shelf = CAVITY_STEP_MM * cavity_shelf_weight(theta)
    inward = -np.stack([np.cos(theta), np.sin(theta), np.zeros(n_th)], -1)
    parts = []
    rows = _CAVITY_ROWS

    u = np.linspace(0.0, 1.0, rows["wall"] + 1)[:, None]
    d = u * wall_depth[None, :]
    wall = _polar_grid(cavity_wall_radius(theta[None, :], d), -d, theta[None, :])
    parts.append(wall)
    foot = cavity_floor_radius(theta)
    rho = np.linspace(1.0, CAVITY_STEP_FRACTION, rows["outer_floor"] + 1)[:, None]
    parts.append(_polar_grid(rho * foot, -(cavity_floor_depth(theta[None, :], rho) - shelf), theta[None, :]))
    step_top = cavity_floor_depth(theta, CAVITY_STEP_FRACTION) - shelf
    s = np.linspace(0.0, 1.0, rows["step"] + 1)[:, None]
    parts.append(_polar_grid(np.broadcast_to(CAVITY_STEP_FRACTION * foot, (len(s), n_th)),
                             -(step_top + s * shelf), theta[None, :]))
    rho = np.linspace(CAVITY_STEP_FRACTION, 0.0, rows["inner_floor"] + 1)[:, None]
    parts.append(_polar_grid(rho * foot, -cavity_floor_depth(theta[None, :], rho), theta[None, :]))
    grids = []
    for k, v in enumerate(parts):
        fallback = np.array([0.0, 0.0, 1.0]) if k in (1, 3) else inward[None]
        n = _grid_normals(v, fallback)
        if k == 3:  # the floor's middle collapses to a point: its normal is the next row's mean
            n[-1] = n[-2].mean(axis=0) / np.linalg.norm(n[-2].mean(axis=0))
        grids.append((v.reshape(-1, 3), grid_faces(len(v), n_th, wrap=True), n.reshape(-1, 3)))
    pv, pf, pn = _square_annulus(rim, DOME_PLATE_MM / 2, 0.0, n_th, 24)
    mesh = _assemble([*grids, (pv, pf[:, ::-1], pn)])  # its rows run outwards: reversed, it winds as its normals

    size = DOME_PLATE_MM + 2.0
    texs = [TextureMap(tissue_texture((size, size), mm_per_texel, texture_seed + 30 + k), (-size / 2, -size / 2),
                       mm_per_texel) for k in range(3)]

    def albedo(points, normals, footprint_mm):
        # Triplanar (as the bladder's): the walls, steep or undercut, get a texture of their own instead of
        # a planar projection's streaks.
        out = _triplanar(texs, points, normals, footprint_mm)
        cover, colour = _vessel_bundle(points, np.asarray(footprint_mm, dtype=float))
        return (out * (1 - cover)[:, None] + colour * cover[:, None]).astype(np.float32)

    scene = Scene("cavity", mesh, albedo, WET_MATERIAL, (), SCENE_TRAJECTORIES["cavity"], "endoscope", 53.0,
                  auto_exposure=True)
    targets = []
    for tid, shape, size_mm, az, spin in _CAVITY_TARGETS:
        outline, sizes = target_outline(shape, size_mm)
        if az is None:
            xy = np.zeros(2)
        else:
            a = np.deg2rad(az)
            xy = _CAVITY_TARGET_RING * float(cavity_floor_radius(a)) * np.array([np.cos(a), np.sin(a)])
        origin = np.array([xy[0], xy[1], 1.0])
        frame = _frame_from_normal(np.array([0.0, 0.0, 1.0]), np.deg2rad(spin))
        targets.append(TrueTarget(tid, shape, sizes, origin, frame, outline, depth_range_mm=17.0))
    scene.targets = tuple(targets)
    overhang = wall[..., :2]
    beyond = np.linalg.norm(overhang, axis=-1) - rim[None, :]
    floor_z = np.concatenate([parts[1][..., 2].ravel(), parts[3][..., 2].ravel()])
    scene.info = {
        "name": "cavity",
        "description": "resection cavity after debulking: irregular pit 6-15 mm deep, an overhanging lip, creases, "
                       "a 2 mm step, a bundle of vessels crossing it, wet tissue, 8 fluorescent targets (issue 35)",
        "units": "mm",
        "world_frame": "z up; plate top face z = 0; the pit's opening around the z axis",
        "cavity": {
            "plate_size_mm": DOME_PLATE_MM,
            "rim_radius_mm": "10.5 - 1.5 cos t + 0.4 sin(2t + 0.5) + 0.25 cos(3t - 1) at azimuth t from +x",
            "rim_radius_range_mm": [float(rim.min()), float(rim.max())],
            "floor_depth_mm": "13 + rho^2 (-3 - 2 cos(t - 200°) + 0.6 sin(2t + 1)) + 1.8 exp(-|rho (cos t, sin t) "
                              "- (-0.2, -0.15)|^2 / (2 0.18^2)), rho = fraction of the floor radius",
            "depth_range_mm": [float(-floor_z.max()), float(-floor_z.min())],
            "lip": {"azimuth_deg": CAVITY_LIP_AZIMUTH_DEG, "half_width_deg": CAVITY_LIP_HALF_WIDTH_DEG,
                    "max_overhang_mm": float(beyond.max()),
                    "max_overhang_depth_mm": float(-wall[..., 2].ravel()[np.argmax(beyond)]),
                    "undercut_at_rim_deg": float(np.degrees(np.arctan(
                        CAVITY_LIP_OVERHANG_MM * 0.5 * np.pi / CAVITY_LIP_LEAN_DEPTH_MM)))},
            "step": {"height_mm": CAVITY_STEP_MM, "radius_fraction_of_floor": CAVITY_STEP_FRACTION,
                     "azimuth_deg": CAVITY_SHELF_AZIMUTH_DEG, "full_height_half_width_deg": CAVITY_SHELF_HALF_WIDTH_DEG[0],
                     "taper_to_deg": CAVITY_SHELF_HALF_WIDTH_DEG[1], "face": "vertical, facing the axis"},
            "creases": ["rim: plate to wall (vertical or undercut)", "wall foot: wall to floor",
                        "step: shelf to step face and step face to inner floor"],
            "vessels": "three vessels (0.35-0.5 mm) crossing the pit along x, painted as seen from above",
            "material": {"specular": WET_MATERIAL.specular, "shininess": WET_MATERIAL.shininess, "kind": "wet tissue"},
        },
        "texture": {"kind": "tissue (vessels, capillary dots), triplanar projection", "seed": texture_seed,
                    "mm_per_texel": mm_per_texel},
        "targets": [target_ground_truth(scene.caster, t) for t in targets],
    }
    return scene


# --- threaded hole ------------------------------------------------------------------------------


def build_thread(size: str = "M8x1.25", *, texture_seed: int = 0, mm_per_texel: float = 0.006,
                 minor_diameter_offset_mm: float = 0.0, pitch_diameter_offset_mm: float = 0.0,
                 major_diameter_offset_mm: float = 0.0, defect: tuple | None = None) -> Scene:
    """Blind hole with an ISO 68-1 internal thread (right-handed), counterbore and drill point.

    Axis = z, opening at z = 0. From the top: a plain scored counterbore of diameter D + 0.4 mm and depth
    1 mm, the helical thread over 1.5 D, a plain bore at the minor diameter for 1 mm, and a 118° drill point.
    The helical surface is a grid in (theta, s) with z = s + P theta / (2 pi) and r = profile(s), so its
    vertices lie exactly on the crest and root flats (rows < P/8 apart) and on the crease helices.

    minor_diameter_offset_mm, pitch_diameter_offset_mm, major_diameter_offset_mm : the tapped hole's
        deviations from the basic sizes D1, D2, D (mm; a real 6H hole sits above them, within its
        tolerances), with 60° flanks kept.
    defect : (angle_deg, width_deg, depth_mm[, z_mm]) or None: a chipped crest on the turn nearest the
        middle of the thread (or, with ``z_mm``, the crest turn nearest that height at ``angle_deg``: a
        scan that shows only part of the thread can then have the chip in view), centred at ``angle_deg``
        (about +z from +x), ``width_deg`` wide, its crest cut back outwards by ``depth_mm`` (less than
        the thread depth).
    """
    if size not in THREAD_SIZES:
        raise InputError(f"unknown thread size {size!r} (use one of {', '.join(THREAD_SIZES)})")
    major, pitch = THREAD_SIZES[size]
    prof = iso_thread_profile(major, pitch)
    r_major = (major + major_diameter_offset_mm) / 2
    r_minor = (prof["minor_diameter_mm"] + minor_diameter_offset_mm) / 2
    r_pitch = (basic_pitch_diameter(major, pitch) + pitch_diameter_offset_mm) / 2
    if not r_minor < r_pitch < r_major:
        raise InputError(f"thread diameters out of order: D1 {2 * r_minor:.3f}, D2 {2 * r_pitch:.3f}, "
                         f"D {2 * r_major:.3f} mm")
    if defect is not None:
        if len(defect) not in (3, 4):
            raise InputError(f"defect needs angle, width, depth and optionally z, got {len(defect)} values")
        d_angle, d_width, d_depth = (float(v) for v in defect[:3])
        if not (0 < d_width < 360 and 0 < d_depth < r_major - r_minor):
            raise InputError(f"defect needs a width in (0, 360) degrees and a depth in (0, {r_major - r_minor:.3f}) "
                             f"mm, got {d_width} degrees and {d_depth} mm")
    cb_radius, cb_depth = r_major + 0.2, 1.0
    z_top, z_bottom = -cb_depth, -cb_depth - 1.5 * major
    z_bore_end = z_bottom - 1.0
    drill_half_angle = np.deg2rad(59.0)
    z_apex = z_bore_end - r_minor / np.tan(drill_half_angle)

    parts = []
    n_th = _THREAD_N_THETA
    theta = np.arange(n_th + 1) * 2 * np.pi / n_th  # last column repeats the first one turn on (seam)
    lead = pitch / (2 * np.pi)
    # Pitches so that, for every theta, the helical grid spans [z_bottom, z_top]; clamped beyond.
    k_lo = int(np.floor((z_bottom - pitch) / pitch)) - 1
    k_hi = int(np.ceil(z_top / pitch)) + 1
    defect_turn = int(round(((z_top + z_bottom) / 2 - pitch / 8) / pitch))  # crest turn in the middle
    if defect is not None and len(defect) == 4:
        # the crest turn nearest z_mm at the chip's angle (crest centre z = k P + P/8 + lead * angle)
        d_z = float(defect[3])
        if not z_bottom + pitch <= d_z <= z_top - pitch:
            raise InputError(f"defect height {d_z} mm is not on the thread (z from {z_bottom + pitch:.2f} to "
                             f"{z_top - pitch:.2f} mm, a pitch in from its ends)")
        defect_turn = int(round((d_z - pitch / 8 - lead * np.deg2rad(d_angle % 360)) / pitch))
    defect_info = None
    for k in range(k_lo, k_hi):
        for s0, s1, r0, r1, n_rows in profile_segments(pitch, r_minor, r_major, r_pitch):
            s = k * pitch + np.linspace(s0, s1, n_rows + 1)
            r = np.linspace(r0, r1, n_rows + 1)
            slope = (r1 - r0) / (s1 - s0)  # dr/ds, constant on a segment
            z = s[:, None] + lead * theta[None, :]
            rr = np.broadcast_to(r[:, None], z.shape)
            if defect is not None and k == defect_turn:
                # The chip: the crest (and the flanks' inner parts) cut back to r_minor + depth over the
                # angular window; the cut face's normals point at the axis.
                off = np.rad2deg(np.angle(np.exp(1j * (theta - np.deg2rad(d_angle)))))
                window = np.broadcast_to(np.abs(off)[None, :] <= d_width / 2, z.shape)
                cut = window & (rr < r_minor + d_depth)
                rr = np.where(cut, r_minor + d_depth, rr)
                defect_info = {"angle_deg": d_angle, "width_deg": d_width, "depth_mm": d_depth,
                               "crest_turn_z_mm": float(k * pitch + pitch / 8 + lead * np.deg2rad(d_angle % 360)),
                               "kind": "chipped crest, cut back to r_minor + depth"}
            c, sn = np.cos(theta)[None, :], np.sin(theta)[None, :]
            # Normal of X(s, t) = (r cos t, r sin t, s + lead t): X_s x X_t, pointed at the axis.
            xs = np.stack(np.broadcast_arrays(slope * c, slope * sn, np.ones_like(z)), -1)
            xt = np.stack(np.broadcast_arrays(-rr * sn, rr * c, np.full_like(z, lead)), -1)
            nrm = np.cross(xs, xt)
            radial = np.stack(np.broadcast_arrays(c, sn, np.zeros_like(z)), -1)
            nrm *= -np.sign(np.sum(nrm * radial, axis=-1, keepdims=True))
            if defect is not None and k == defect_turn:
                nrm[cut] = -radial[cut]
            # Beyond the thread's ends the helical surface is flattened onto the end planes (the thread
            # run-out): the shoulder under the counterbore faces up, the last flank's underside faces down.
            top, bottom = z > z_top, z < z_bottom
            nrm[top] = [0.0, 0.0, 1.0]
            nrm[bottom] = [0.0, 0.0, -1.0]
            zc = np.clip(z, z_bottom, z_top)
            v = np.stack([rr * c, rr * sn, zc], -1)
            if np.all(top) or np.all(bottom):
                continue
            parts.append((v.reshape(-1, 3), grid_faces(n_rows + 1, n_th + 1, wrap=False), nrm.reshape(-1, 3)))
    # Shoulder from the major diameter to the counterbore at z_top, counterbore wall, top face.
    parts.append(_revolution(np.array([r_major, cb_radius]), np.array([z_top, z_top]),
                             np.array([[0.0, 1.0], [0.0, 1.0]]), n_th))
    zc = np.linspace(z_top, 0.0, 41)
    parts.append(_revolution(np.full_like(zc, cb_radius), zc, np.tile([-1.0, 0.0], (len(zc), 1)), n_th))
    parts.append(_square_annulus(cb_radius, 10.0, 0.0, n_th, 12))
    # Plain bore below the thread, and the drill point (cone to the apex).
    zb = np.linspace(z_bore_end, z_bottom, 9)
    parts.append(_revolution(np.full_like(zb, r_minor), zb, np.tile([-1.0, 0.0], (len(zb), 1)), n_th))
    t = np.linspace(0.0, 1.0, 41)
    cone_n = np.array([-np.cos(drill_half_angle), np.sin(drill_half_angle)])
    parts.append(_revolution(r_minor * (1 - t), z_bore_end + (z_apex - z_bore_end) * t, np.tile(cone_n, (len(t), 1)),
                             n_th))
    mesh = _assemble(parts)

    circumference = 2 * np.pi * cb_radius
    mm_per_texel = circumference / round(circumference / mm_per_texel)  # a whole number of texels per turn
    v_lo, v_hi = z_apex - pitch - 1.0, 1.0
    wall = TextureMap(machined_texture((circumference, v_hi - v_lo), mm_per_texel, texture_seed + 20, periodic_u=True),
                      (0.0, v_lo), mm_per_texel, wrap_u=True)
    face = TextureMap(machined_texture((22.0, 22.0), 0.01, texture_seed + 21, along_mm=0.6, across_mm=0.03),
                      (-11.0, -11.0), 0.01)
    score_rng = np.random.default_rng(texture_seed + 22)
    score_levels = score_rng.uniform(0.7, 1.15, 4096)
    score_period = 0.04  # mm between the scored rings of the counterbore

    def albedo(points, normals, footprint_mm):
        x, y, z = points[:, 0], points[:, 1], points[:, 2]
        ang = np.mod(np.arctan2(y, x), 2 * np.pi)
        out = np.empty((len(points), 1), np.float32)
        on_face = z > -1e-9
        inside = ~on_face
        # Turned and tapped surfaces: tool marks run round the bore (the thread's lead, 0.2 mm per mm of
        # circumference, is too small to matter for the marks, and a helical coordinate would leave a seam).
        uv = np.stack([ang[inside] * cb_radius, z[inside]], 1)
        out[inside] = wall.sample(uv, footprint_mm[inside])
        out[on_face] = face.sample(points[on_face, :2], footprint_mm[on_face])
        bore = inside & (z > z_top + 1e-9)
        ring = np.floor(-z[bore] / score_period).astype(np.int64) % len(score_levels)
        out[bore] *= score_levels[ring][:, None].astype(np.float32)
        return np.repeat(out, 3, axis=1) * np.array([0.97, 0.98, 1.0], np.float32)  # aluminium, slightly cool

    info = {
        "name": "thread",
        "description": f"{size} ISO 68-1 internal thread in a blind hole, shiny machined aluminium "
                       "(reference ch. 7-8)",
        "units": "mm",
        "world_frame": "hole axis = z through the origin; opening (top face) at z = 0; hole towards -z",
        "thread": {
            "designation": size, "standard": "ISO 68-1 basic profile, right-handed", **prof,
            "thread_top_z_mm": z_top, "thread_bottom_z_mm": z_bottom,
            "profile_phase": "crest flat (minor diameter) centred at z = P/8 + P*theta/(2 pi) + k P, "
                             "theta = atan2(y, x)",
            "as_made": {"minor_diameter_mm": 2 * r_minor, "pitch_diameter_mm": 2 * r_pitch,
                        "major_diameter_mm": 2 * r_major, "flank_angle_deg": 60.0,
                        "offsets_mm": {"minor": minor_diameter_offset_mm, "pitch": pitch_diameter_offset_mm,
                                       "major": major_diameter_offset_mm}},
            "defects": [defect_info] if defect_info else [],
        },
        "counterbore": {"diameter_mm": 2 * cb_radius, "depth_mm": cb_depth, "surface": "scored rings 0.04 mm apart"},
        "bore_below_thread": {"diameter_mm": 2 * r_minor, "from_z_mm": z_bottom, "to_z_mm": z_bore_end},
        "drill_point": {"angle_deg": 118.0, "apex_z_mm": z_apex},
        "material": {"kind": "machined aluminium", "specular": 0.6, "shininess": 40.0},
        "targets": [],
    }
    return Scene("thread", mesh, albedo, Material(specular=0.6, shininess=40.0), (), SCENE_TRAJECTORIES["thread"],
                 "endoscope", 70.0, info, render_supersample=2)


# --- registry -----------------------------------------------------------------------------------

SCENES = {
    "dome": "debulked brain-tumour cavity: spherical dome R 15-17.5 mm, depth 10 mm, 40 mm plate, 8 fluorescent targets",
    "sheet": "flat printed sheet, 60 mm square, z = 0",
    "bladder": "irregular ellipsoidal cavity ~90 x 76 x 64 mm seen from inside, 4 star markers of 6 mm",
    "thread": "ISO internal thread in a blind hole (M5x0.8 to M12x1.75), shiny aluminium",
    "cavity": "resection cavity 6-15 mm deep with an overhanging lip, creases, a 2 mm step, vessels, wet tissue, "
              "8 fluorescent targets",
}


@lru_cache(maxsize=8)
def build_scene(name: str, *, thread: str = "M8x1.25", dome_radius_mm: float = 17.5, texture_seed: int = 0,
                thread_offsets_mm: tuple = (0.0, 0.0, 0.0), thread_defect: tuple | None = None,
                bladder: tuple = ()) -> Scene:
    """Build (and cache) a scene by name. Unknown names or sizes raise :class:`InputError`.
    thread_offsets_mm : (minor, pitch, major) diameter offsets and thread_defect : (angle_deg, width_deg,
    depth_mm) or None, for the thread (see :func:`build_thread`). bladder : keyword arguments of
    :func:`build_bladder` as sorted ``(name, value)`` pairs (hashable)."""
    if name == "dome":
        return build_dome(dome_radius_mm, texture_seed=texture_seed)
    if name == "sheet":
        return build_sheet(texture_seed=texture_seed)
    if name == "cavity":
        return build_cavity(texture_seed=texture_seed)
    if name == "bladder":
        return build_bladder(texture_seed=texture_seed, **dict(bladder))
    if name == "thread":
        minor, pitch_d, major = (float(v) for v in thread_offsets_mm)
        return build_thread(thread, texture_seed=texture_seed, minor_diameter_offset_mm=minor,
                            pitch_diameter_offset_mm=pitch_d, major_diameter_offset_mm=major,
                            defect=None if thread_defect is None else tuple(float(v) for v in thread_defect))
    raise InputError(f"unknown scene {name!r} (use one of {', '.join(SCENES)})")
