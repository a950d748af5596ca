"""Exact first-hit ray casting against a triangle mesh: Embree finds the triangle, float64 maths the point.

Embree (through trimesh and embreex) works in single precision, which would put hit points a few
micrometres off the mesh at 15 mm range. Ground truth must be exact, so the triangle Embree reports
is intersected again in double precision (Möller–Trumbore), which puts every hit on the mesh to
~1e-12 mm. Without Embree the same interface falls back to trimesh's pure-NumPy intersector (slower).
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from scope3d.scene.mesh import Mesh
from scope3d.utils.aot import load_kernels
from scope3d.utils.threads import check_threads, resolve_threads

# compiled at install (scope3d.utils.aot) or, failing that, by numba on first use
_kernels = load_kernels("scope3d.phantoms.raycast_kernels")

# below this many rays a cast runs on one thread (starting threads costs more than it saves)
_THREADED_CAST_RAYS = 50_000


@dataclass(frozen=True)
class Hits:
    """First hits of N rays. Rays that miss have ``triangle == -1`` and NaN elsewhere.

    distance_mm : (N,) float64, along the unit ray direction.
    triangle : (N,) int64 face index.
    barycentric : (N, 3) float64 weights of the face's three vertices.
    points : (N, 3) float64 mm, world frame.
    normals : (N, 3) float64 unit, interpolated vertex normals (face normals if the mesh has none).
    """

    distance_mm: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    points: np.ndarray
    normals: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(N,) bool."""
        return self.triangle >= 0


class RayCaster:
    """First-hit ray casting against one mesh.

    mesh : :class:`~scope3d.scene.mesh.Mesh` in mm; its ``vertex_normals`` (if any) are used for shading.
    backend : ``"auto"`` (Embree when available), ``"embree"`` or ``"numpy"``.
    threads : Embree queries of a large cast (>= 50,000 rays) split over this many threads (Embree releases
        the GIL; every ray is independent, so the hits are the same); 0 (default): every available core
        (:mod:`scope3d.utils.threads`).
    """

    def __init__(self, mesh: Mesh, *, backend: str = "auto", threads: int = 0) -> None:
        import trimesh

        if backend not in ("auto", "embree", "numpy"):
            raise ValueError(f"unknown ray-casting backend {backend!r}")
        check_threads(threads)
        self.threads = resolve_threads(threads)
        if backend == "embree" and not trimesh.ray.has_embree:
            raise ValueError("Embree is not available (install embreex)")
        self.mesh = mesh
        tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        if backend != "numpy" and trimesh.ray.has_embree:
            from trimesh.ray.ray_pyembree import RayMeshIntersector

            self.backend = "embree"
        else:
            from trimesh.ray.ray_triangle import RayMeshIntersector

            self.backend = "numpy"
        self._intersector = RayMeshIntersector(tm)
        tri = mesh.vertices[mesh.faces]
        # v0, e1, e2 of every face side by side: the refinement reads one (3, 3) block per hit
        self._v0_e1_e2 = np.ascontiguousarray(np.stack([tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], axis=1))
        face_normals = np.cross(self._v0_e1_e2[:, 1], self._v0_e1_e2[:, 2])
        self._face_normals = face_normals / np.maximum(np.linalg.norm(face_normals, axis=1, keepdims=True), 1e-300)
        # The three vertex normals of every face, gathered once here rather than twice per cast.
        self._face_vertex_normals = (None if mesh.vertex_normals is None
                                     else np.ascontiguousarray(mesh.vertex_normals[mesh.faces]))

    def _first_triangles(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ray_idx, tri_idx) of the rays that hit something and the face each hits first, rays ascending."""
        # trimesh's own scaled Embree scene, queried in one call: its intersects_id wraps the same query in
        # copies and bookkeeping that cost more than the query itself for first hits. The scene is a private
        # attribute of trimesh's Embree intersector (a wrapper holding embreex's scene and the shift and scale
        # of its copy of the mesh): where a trimesh version lacks it, intersects_id answers
        wrapper = getattr(self._intersector, "_scene", None) if self.backend == "embree" else None
        embree = getattr(wrapper, "scene", None)
        if embree is not None and hasattr(embree, "run") and hasattr(wrapper, "origin") and hasattr(wrapper, "scale"):
            # The rays as embreex takes them (float32, in the scaled frame), made in one compiled pass instead
            # of the wrapper's three copies and trimesh's unitize (~25 ms of a 608 x 608 frame): the
            # directions are unit already (see cast), and Embree's first hit does not depend on their length.
            n = len(origins)
            origins32, directions32 = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
            _kernels.embree_rays(origins, directions, np.ascontiguousarray(wrapper.origin, float),
                                 float(wrapper.scale), origins32, directions32)
            parts = self.threads if n >= _THREADED_CAST_RAYS else 1
            bounds = np.linspace(0, n, parts + 1).astype(int)
            query = np.empty(n, np.int64)

            def run(a: int, b: int) -> None:
                query[a:b] = embree.run(origins32[a:b], directions32[a:b])

            with ThreadPoolExecutor(max_workers=max(1, parts - 1)) as pool:
                others = [pool.submit(run, a, b) for a, b in zip(bounds[1:-1], bounds[2:])]
                run(bounds[0], bounds[1])
                for other in others:
                    other.result()  # raises what the thread raised
            ray_idx = np.flatnonzero(query >= 0)
            return ray_idx, query[ray_idx]
        tri_idx, ray_idx = self._intersector.intersects_id(origins, directions, multiple_hits=False)[:2]
        return np.asarray(ray_idx, dtype=np.int64), np.asarray(tri_idx, dtype=np.int64)

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """origins : (N, 3) mm; directions : (N, 3) unit, world frame -> :class:`Hits`."""
        # C-contiguous and writable (a read-only array would make numba compile another specialisation of the
        # kernel on the JIT path; the compiled module takes these exact types)
        origins = np.require(origins, float, ("C", "W")).reshape(-1, 3)
        directions = np.require(directions, float, ("C", "W")).reshape(-1, 3)
        n = len(origins)
        distance = np.full(n, np.nan)
        triangle = np.full(n, -1, dtype=np.int64)
        bary = np.full((n, 3), np.nan)
        points = np.empty((n, 3))
        normals = np.full((n, 3), np.nan)
        ray_idx, tri_idx = self._first_triangles(origins, directions) if n else (np.zeros(0, np.int64),) * 2
        # one compiled pass: Möller–Trumbore in float64, the point and the interpolated normal (NumPy's
        # (M, 3) temporaries for the same maths were a third of a rendered frame)
        _kernels.refine_hits(origins, directions, np.ascontiguousarray(ray_idx, np.int64),
                             np.ascontiguousarray(tri_idx, np.int64), self._v0_e1_e2,
                             self._face_vertex_normals if self._face_vertex_normals is not None else self._v0_e1_e2,
                             self._face_normals, self._face_vertex_normals is not None,
                             distance, triangle, bary, points, normals)
        return Hits(distance, triangle, bary, points, normals)
