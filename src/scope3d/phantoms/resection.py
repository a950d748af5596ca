"""Tissue that changes during a survey (issue 36): a pit resected from the dome's wall at a given time.

A surgeon resects tissue while the scope films: from ``time_s`` on, the frames show the dome with a pit
cut into its wall, and a map made from the earlier frames no longer agrees with them there. The pit is a
smooth depression of the spherical cap: a point of the wall at (chord) distance ``d`` from the pit's
centre moves outwards along the sphere's radius (into the material) by

    depth(d) = depth_mm * (1 - (d / radius_mm)^2)^2      for d < radius_mm, else 0,

flat-bottomed at the centre and meeting the wall with zero slope at its rim (steepest slope 1.54
depth / radius, at d = radius / sqrt 3). The exposed tissue is paler (deeper tissue: 40 % towards a
white-matter tone at the centre, in proportion to the depth), its texture kept at 60 % contrast so that
stereo still finds it. Where the pit lies is drawn from the seed (its own stream) within half the dome's
opening radius, so that the survey sees it whole, unless given.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from scope3d.errors import InputError
from scope3d.phantoms.scenes import Scene
from scope3d.scene.mesh import Mesh

#: the tone the exposed tissue tends to (white matter under the cortex), RGB in [0, 1]
EXPOSED_TISSUE_RGB = np.array([0.93, 0.86, 0.80], np.float32)
#: how far the exposed tissue's albedo moves towards that tone at the pit's deepest point
EXPOSED_BLEND = 0.4
#: the pit's centre is drawn within this fraction of the dome's opening radius (the floor and the lower wall)
PLACE_FRACTION = 0.5
#: the seed stream of the pit's place (apart from the sensor's and the poses' streams)
SEED_STREAM = 36


@dataclass(frozen=True)
class Resection:
    """time_s : when the tissue is removed (s; the frames at or after it see the pit). radius_mm,
    depth_mm : the pit's radius on the wall and depth at its centre. centre_xy_mm : (x, y) of its centre
    on the wall (world mm, seen from above), or None to draw it from the seed."""

    time_s: float
    radius_mm: float = 3.0
    depth_mm: float = 1.5
    centre_xy_mm: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if not np.isfinite(self.time_s) or self.time_s < 0:
            raise InputError(f"the resection's time must be a non-negative number of seconds, got {self.time_s}")
        sizes = (self.radius_mm, self.depth_mm)
        if not all(np.isfinite(v) and v > 0 for v in sizes):
            raise InputError(f"the pit needs a positive radius and depth, got {self.radius_mm} and {self.depth_mm} mm")
        if self.centre_xy_mm is not None and not all(np.isfinite(v) for v in self.centre_xy_mm):
            raise InputError(f"the pit's centre must be finite, got {self.centre_xy_mm}")


def pit_depth_mm(distance_mm: np.ndarray, radius_mm: float, depth_mm: float) -> np.ndarray:
    """How far the wall moved (mm) at ``distance_mm`` from the pit's centre (module docstring)."""
    s = np.clip(1.0 - (np.asarray(distance_mm, float) / radius_mm) ** 2, 0.0, None)
    return depth_mm * s * s


def resect(scene: Scene, resection: Resection, *, seed: int) -> tuple[Scene, dict]:
    """The dome ``scene`` with the pit cut into its wall, and the pit's ground truth (JSON-ready:
    ``time_s``, ``centre_mm`` on the wall before, ``radius_mm``, ``depth_mm``, ``sphere_centre_mm``, the
    profile). InputError for another scene or a pit that does not lie whole on the spherical wall."""
    if scene.name != "dome":
        raise InputError(f"a resection applies to the dome only, not {scene.name!r}")
    dome = scene.info["dome"]
    R, centre_z, r_open = dome["radius_mm"], dome["sphere_centre_mm"][2], dome["opening_radius_mm"]
    if resection.centre_xy_mm is None:
        rng = np.random.default_rng([seed, SEED_STREAM])
        rho = PLACE_FRACTION * r_open * np.sqrt(rng.uniform())
        phi = rng.uniform(0.0, 2.0 * np.pi)
        xy = np.array([rho * np.cos(phi), rho * np.sin(phi)])
    else:
        xy = np.asarray(resection.centre_xy_mm, float)
    # the pit must end short of the rim: its chord radius, seen from above, at most the opening's distance
    if np.hypot(*xy) + resection.radius_mm > r_open:
        raise InputError(f"a pit of {resection.radius_mm:g} mm centred {np.hypot(*xy):.2f} mm off the dome's axis "
                         f"reaches past its rim ({r_open:.2f} mm from the axis)")
    sphere_centre = np.array([0.0, 0.0, centre_z])
    top = np.array([xy[0], xy[1], centre_z - np.sqrt(R * R - xy @ xy)])  # on the wall below (x, y)
    v = scene.mesh.vertices
    outward = v - sphere_centre
    on_sphere = np.abs(np.linalg.norm(outward, axis=1) - R) < 1e-6
    move = np.where(on_sphere, pit_depth_mm(np.linalg.norm(v - top, axis=1), resection.radius_mm,
                                            resection.depth_mm), 0.0)
    moved = v + move[:, None] * outward / np.linalg.norm(outward, axis=1, keepdims=True)
    mesh = Mesh(moved, scene.mesh.faces, vertex_normals=_vertex_normals(moved, scene.mesh.faces,
                                                                          scene.mesh.vertex_normals))
    albedo_before = scene.albedo
    radius, depth = resection.radius_mm, resection.depth_mm

    def albedo(points, normals, footprint_mm):
        base = albedo_before(points, normals, footprint_mm)
        # the exposed fraction from the wall's original place (the displacement keeps a point's direction
        # from the sphere's centre: its distance from the pit's centre is read on the sphere)
        original = sphere_centre + R * _unit(points - sphere_centre)
        f = (EXPOSED_BLEND / depth * pit_depth_mm(np.linalg.norm(original - top, axis=1), radius, depth))[:, None]
        return (base * (1.0 - f) + f * EXPOSED_TISSUE_RGB).astype(np.float32)

    truth = {"time_s": float(resection.time_s), "centre_mm": top.tolist(), "radius_mm": float(radius),
             "depth_mm": float(depth), "sphere_centre_mm": sphere_centre.tolist(), "sphere_radius_mm": float(R),
             "placed": "given" if resection.centre_xy_mm is not None else f"drawn from seed {seed}",
             "profile": "the wall moves outwards along the sphere's radius by depth_mm (1 - (d / radius_mm)^2)^2, "
                        "d its distance from centre_mm; the exposed tissue is paler"}
    return replace(scene, mesh=mesh, albedo=albedo, info={**scene.info, "resection": truth}, _caster=None), truth


def wall_moved_mm(points: np.ndarray, truth: dict) -> np.ndarray:
    """(N,) how far the wall moved (mm) under each point of the dome's wall as it was before, from the
    resection's ground truth (:func:`resect`'s dict, ``scene.json``'s ``resection``): 0 outside the pit."""
    c = np.asarray(truth["sphere_centre_mm"], float)
    on_wall = c + truth["sphere_radius_mm"] * _unit(np.asarray(points, float) - c)
    d = np.linalg.norm(on_wall - np.asarray(truth["centre_mm"], float), axis=1)
    return pit_depth_mm(d, truth["radius_mm"], truth["depth_mm"])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray, before: np.ndarray) -> np.ndarray:
    """Area-weighted face normals summed at each vertex, on the side of the normals ``before`` (out of the
    cavity)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    n = np.stack([np.bincount(faces.ravel(), np.repeat(cross[:, k], 3), minlength=len(vertices))
                  for k in range(3)], axis=1)
    n *= np.where(np.sum(n * before, axis=1) < 0, -1.0, 1.0)[:, None]
    length = np.linalg.norm(n, axis=1, keepdims=True)
    # a vertex of no face (the cap's collapsed pole row) keeps its normal
    return np.where(length > 0, n / np.where(length > 0, length, 1.0), before)
