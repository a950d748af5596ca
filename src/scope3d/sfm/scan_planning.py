"""Scan planning for a closed cavity: a spiral of views looking along the wall normal from a stand-off
distance, with a given lateral overlap, and the surface fraction those views see (reference sec. 2.3.2).

The planner walks a spherical spiral of directions from the cavity's centre, from the top pole (+z, where
the scope enters in the reference's set-up) to the bottom. Each direction meets the wall at a point ``S``
with the inward normal ``n``; the view sits at ``S + standoff * n`` looking along ``-n`` (perpendicular
views at a safe distance, sec. 2.3.2). Successive views are ``(1 - overlap) * footprint`` apart along the
spiral and the spiral's turns are the same distance apart on the wall, where the footprint is the
diameter of the circular field on the wall, measured by casting the field's edge rays from the view onto
the mesh (on a concave wall it is smaller than the flat-wall ``2 * standoff * tan(fov / 2)``). The
coverage computed afterwards (by ray casting every view onto the mesh) says what the plan really sees.

Bending limit: a steerable tip entering along ``insertion_axis`` cannot turn its optical axis more than
``bend_limit_deg`` away from it. Views needing more are dropped, and the coverage they would have added
is reported as lost (the reference's ±45° hinges give about 125° in total, sec. 2.4.2). This is a limit on
the tip direction, not a kinematic model of the segments.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at
from scope3d.phantoms.raycast import RayCaster
from scope3d.scene.mesh import Mesh
from scope3d.sensor.camera import Camera

# The scanning fibre endoscope's depth of focus ends at 50 mm (reference sec. 2.3.1): farther walls are
# not counted as seen.
SFE_MAX_RANGE_MM = 50.0
# Planning image: a circular field inscribed in a square frame; its size only sets pixel arithmetic.
_PLAN_IMAGE_PX = 600


@dataclass(frozen=True)
class ScanPlanOptions:
    """standoff_mm : distance from the wall along its normal, mm (15 or 30 in the reference).
    overlap : fraction of the footprint shared by neighbouring views along and across the spiral (0.5).
    fov_deg : full field of view across the circular field, degrees.
    bend_limit_deg : largest angle between the optical axis and ``insertion_axis`` (None: no limit).
    insertion_axis : (3,) direction in which the scope enters the cavity (world; default down, -z).
    pole_axis : (3,) the spiral's axis; it starts at the pole the axis points to.
    max_range_mm : walls farther than this from a view are not counted as seen.
    """

    standoff_mm: float = 15.0
    overlap: float = 0.5
    fov_deg: float = 70.0
    bend_limit_deg: float | None = None
    insertion_axis: tuple[float, float, float] = (0.0, 0.0, -1.0)
    pole_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    max_range_mm: float = SFE_MAX_RANGE_MM

    def __post_init__(self) -> None:
        if not (np.isfinite(self.standoff_mm) and self.standoff_mm > 0):
            raise ValueError(f"stand-off must be a positive number of mm, got {self.standoff_mm}")
        if not 0.0 <= self.overlap < 1.0:
            raise ValueError(f"overlap must be in [0, 1), got {self.overlap}")
        if not 0.0 < self.fov_deg < 180.0:
            raise ValueError(f"field of view must be in (0, 180) degrees, got {self.fov_deg}")
        if self.bend_limit_deg is not None and not 0.0 < self.bend_limit_deg <= 180.0:
            raise ValueError(f"bending limit must be in (0, 180] degrees, got {self.bend_limit_deg}")
        for name in ("insertion_axis", "pole_axis"):
            v = np.asarray(getattr(self, name), float)
            if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) == 0:
                raise ValueError(f"{name} must be a non-zero 3-vector, got {getattr(self, name)}")
        if not self.max_range_mm > self.standoff_mm:
            raise ValueError(f"max range ({self.max_range_mm} mm) must exceed the stand-off ({self.standoff_mm} mm)")

    @property
    def footprint_mm(self) -> float:
        """Diameter of the circular field on a flat wall at the stand-off, mm."""
        return 2.0 * self.standoff_mm * np.tan(np.deg2rad(self.fov_deg) / 2.0)



@dataclass(frozen=True)
class Coverage:
    """fraction : seen area / total area. seen_faces : (F,) bool per mesh face.
    views_per_face : (F,) int, how many views see each face's centroid."""

    fraction: float
    seen_faces: np.ndarray
    views_per_face: np.ndarray


@dataclass(frozen=True)
class ScanPlan:
    """A planned scan.

    poses : the kept views' ``cam_from_world`` (mm), in scan order.
    wall_points_mm : (N, 3) where each kept view's optical axis meets the wall. sections : (N,) int, the
        spiral turn of each view (0 = the top). bend_deg : (N,) angle of each view to the insertion axis.
    camera : the planning camera (circular field of ``fov_deg``).
    n_planned : views on the spiral before the bending limit. coverage : what the kept views see.
    coverage_unlimited : what all planned views would see (equal to ``coverage`` without a limit).
    options : the options used.
    """

    poses: list[Pose]
    wall_points_mm: np.ndarray
    sections: np.ndarray
    bend_deg: np.ndarray
    camera: Camera
    n_planned: int
    coverage: Coverage
    coverage_unlimited: Coverage
    options: ScanPlanOptions

    @property
    def n_views(self) -> int:
        return len(self.poses)

    def summary(self) -> str:
        lost = self.coverage_unlimited.fraction - self.coverage.fraction
        text = (f"{self.n_views} views at {self.options.standoff_mm:g} mm stand-off, {self.options.overlap:.0%} overlap, "
                f"FOV {self.options.fov_deg:g}°: coverage {self.coverage.fraction:.1%}")
        if self.options.bend_limit_deg is not None:
            text += (f" (bending limit {self.options.bend_limit_deg:g}°: {self.n_planned - self.n_views} of "
                     f"{self.n_planned} views dropped, {lost:.1%} of the wall lost)")
        return text


def planning_camera(fov_deg: float) -> Camera:
    """A square frame with a circular field whose diameter spans ``fov_deg`` (the endoscope's image)."""
    size = _PLAN_IMAGE_PX
    return Camera.from_fov(size, size, fov_deg, mask_radius_px=(size - 1) / 2.0)


def cavity_centre(mesh: Mesh) -> np.ndarray:
    """(3,) mm: the enclosed volume's centroid of a closed mesh, else the mean of the face centroids by area."""
    tm = mesh.to_trimesh()
    if tm.is_watertight and abs(tm.volume) > 0:
        return np.asarray(tm.center_mass, dtype=float)
    return np.asarray(tm.triangles_center.T @ tm.area_faces / tm.area_faces.sum(), dtype=float)


def plan_spiral_scan(mesh: Mesh, *, options: ScanPlanOptions, caster: RayCaster | None = None,
                     centre_mm: np.ndarray | None = None) -> ScanPlan:
    """Plan a spiral scan of the inside of a closed, star-shaped cavity (see the module docstring).

    mesh : the wall, mm. caster : a ray caster of ``mesh`` (built if None). centre_mm : (3,) the point the
    spiral's directions start from (default :func:`cavity_centre`); every wall point must be visible from it.
    Raises ValueError when rays from the centre miss the mesh (not a closed cavity around the centre).
    """
    caster = caster or RayCaster(mesh)
    centre = cavity_centre(mesh) if centre_mm is None else np.asarray(centre_mm, dtype=float).reshape(3)
    pole = np.asarray(options.pole_axis, float)
    pole /= np.linalg.norm(pole)
    # An orthonormal frame (e1, e2, pole) for the spherical coordinates of the spiral.
    e1 = np.cross(pole, [1.0, 0.0, 0.0] if abs(pole[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(pole, e1)

    def wall(theta: np.ndarray, phi: np.ndarray):
        d = (np.sin(theta)[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
             + np.cos(theta)[:, None] * pole)
        hits = caster.cast(np.broadcast_to(centre, d.shape), d)
        if not np.all(hits.hit):
            raise ValueError("rays from the cavity centre leave the mesh: the surface is not a closed cavity "
                             "around its centre")
        return hits

    # March along the spiral theta = pitch(theta) * phi / (2 pi), one spacing per step on the wall.
    eps = 1e-4
    theta, phi = 0.0, 0.0
    thetas, phis = [0.0], [0.0]
    while True:
        h = wall(np.array([theta, theta + eps, theta]), np.array([phi, phi, phi + eps]))
        step = (1.0 - options.overlap) * _footprint_on_wall(caster, h.points[0], h.normals[0], centre, options)
        d_theta = (h.points[1] - h.points[0]) / eps  # dS/dtheta, mm/rad
        d_phi = (h.points[2] - h.points[0]) / eps  # dS/dphi, mm/rad
        pitch = step / max(np.linalg.norm(d_theta), 1e-9)  # theta advance per turn: turns `step` apart
        tangent = d_phi + pitch / (2 * np.pi) * d_theta
        d_phi_step = step / max(np.linalg.norm(tangent), 1e-9)
        theta += pitch / (2 * np.pi) * d_phi_step
        phi += d_phi_step
        if theta >= np.pi:
            break
        thetas.append(theta)
        phis.append(phi)
    # The last view looks at the bottom pole unless the spiral's last view already covers it.
    thetas.append(np.pi)
    phis.append(phi)
    thetas, phis = np.asarray(thetas), np.asarray(phis)
    hits = wall(thetas, phis)
    normals = hits.normals * np.sign(np.einsum("ij,ij->i", hits.normals, centre - hits.points))[:, None]
    eyes = hits.points + options.standoff_mm * normals
    view = -normals
    insertion = np.asarray(options.insertion_axis, float)
    insertion /= np.linalg.norm(insertion)
    bend = np.degrees(np.arccos(np.clip(view @ insertion, -1.0, 1.0)))
    poses = [Pose.from_centre(look_at(eye, eye + v, up=-pole if abs(v @ pole) < 0.99 else np.cross(v, e1)), eye)
             for eye, v in zip(eyes, view)]
    sections = np.floor(phis / (2 * np.pi)).astype(int)

    camera = planning_camera(options.fov_deg)
    unlimited = coverage(mesh, camera, poses, caster=caster, max_range_mm=options.max_range_mm)
    keep = np.ones(len(poses), bool) if options.bend_limit_deg is None else bend <= options.bend_limit_deg
    kept = [p for p, k in zip(poses, keep) if k]
    limited = unlimited if keep.all() else coverage(mesh, camera, kept, caster=caster,
                                                    max_range_mm=options.max_range_mm)
    return ScanPlan(kept, hits.points[keep], sections[keep], bend[keep], camera, len(poses), limited, unlimited,
                    options)


def _footprint_on_wall(caster: RayCaster, point: np.ndarray, normal: np.ndarray, centre: np.ndarray,
                       options: ScanPlanOptions, n_rays: int = 12) -> float:
    """Diameter (mm) of the circular field on the wall, seen from the stand-off along the normal at
    ``point``: twice the mean chord from ``point`` to where the field's edge rays meet the wall. On a
    concave wall this is smaller than the flat-wall footprint; a ray that misses counts as flat."""
    n = normal if np.dot(normal, centre - point) > 0 else -normal
    eye = point + options.standoff_mm * n
    view = -n
    a = np.cross(view, [1.0, 0.0, 0.0] if abs(view[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(view, a)
    half = np.deg2rad(options.fov_deg) / 2.0
    psi = 2 * np.pi * np.arange(n_rays) / n_rays
    rays = np.cos(half) * view + np.sin(half) * (np.cos(psi)[:, None] * a + np.sin(psi)[:, None] * b)
    hits = caster.cast(np.broadcast_to(eye, rays.shape), rays)
    chord = np.linalg.norm(hits.points - point, axis=1)
    chord = np.where(hits.hit, chord, options.footprint_mm / 2.0)
    return float(2.0 * chord.mean())


def coverage(mesh: Mesh, camera: Camera, poses: list[Pose], *, caster: RayCaster | None = None,
             max_range_mm: float = np.inf) -> Coverage:
    """Fraction of the wall's area the views see: a face counts as seen when its centroid projects inside
    some view's image (circular field included), lies in front of it within ``max_range_mm``, and the ray
    from that view's centre to the centroid meets nothing before it (ray casting on the mesh).

    mesh : mm. camera : intrinsics (and mask) of every view. poses : ``cam_from_world``.
    The face-centroid rule misjudges faces cut by a view's edge, so the fraction is exact to about the
    area of one row of faces along the seen region's boundary.
    """
    caster = caster or RayCaster(mesh)
    tri = mesh.vertices[mesh.faces]
    centroids = tri.mean(axis=1)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    count = np.zeros(len(mesh.faces), dtype=np.int64)
    for pose in poses:
        local = pose.transform(centroids)
        dist = np.linalg.norm(local, axis=1)
        cand = np.flatnonzero((local[:, 2] > 0) & (dist <= max_range_mm))
        if cand.size == 0:
            continue
        cand = cand[camera.in_image(camera.project(local[cand]))]
        if cand.size == 0:
            continue
        rays = (centroids[cand] - pose.centre) / dist[cand, None]
        hits = caster.cast(np.broadcast_to(pose.centre, rays.shape), rays)
        # Visible: the first hit is the face itself (or, at a shared edge, a point at the same distance).
        visible = (hits.triangle == cand) | (np.abs(hits.distance_mm - dist[cand]) <= 1e-6 * dist[cand] + 1e-9)
        count[cand[visible]] += 1
    seen = count > 0
    return Coverage(float(area[seen].sum() / area.sum()), seen, count)
