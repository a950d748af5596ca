"""Point clouds and triangle meshes: arrays with units (mm) and colours."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class PointCloud:
    """points : (N, 3) float64 mm; colors : (N, 3) uint8 RGB or None; normals : (N, 3) float or None."""

    points: np.ndarray
    colors: np.ndarray | None = None
    normals: np.ndarray | None = None

    def __post_init__(self) -> None:
        pts = np.asarray(self.points, dtype=float).reshape(-1, 3)
        object.__setattr__(self, "points", pts)
        if self.colors is not None:
            object.__setattr__(self, "colors", np.asarray(self.colors, dtype=np.uint8).reshape(len(pts), 3))
        if self.normals is not None:
            object.__setattr__(self, "normals", np.asarray(self.normals, dtype=float).reshape(len(pts), 3))

    def __len__(self) -> int:
        return len(self.points)


@dataclass(frozen=True)
class Mesh:
    """vertices : (V, 3) float64 mm; faces : (F, 3) int64 vertex indices, counter-clockwise seen from
    the side the normals point to; vertex_colors : (V, 3) uint8 or None; vertex_normals : (V, 3) or None."""

    vertices: np.ndarray
    faces: np.ndarray
    vertex_colors: np.ndarray | None = None
    vertex_normals: np.ndarray | None = None

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=float).reshape(-1, 3)
        f = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise ValueError("mesh faces index vertices that do not exist")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)
        if self.vertex_colors is not None:
            object.__setattr__(self, "vertex_colors", np.asarray(self.vertex_colors, np.uint8).reshape(len(v), 3))
        if self.vertex_normals is not None:
            object.__setattr__(self, "vertex_normals", np.asarray(self.vertex_normals, float).reshape(len(v), 3))

    def to_trimesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, vertex_colors=self.vertex_colors, process=False)


class SampledSurface:
    """A triangle mesh sampled densely with normals, with a KD-tree for nearest queries.

    Every face gets ``ceil(area / step_mm²)`` seeded random points, with the face's normal: at least one
    unless it is degenerate, and on the phantoms' fine meshes that floor, not the area, sets the count.
    Every vertex that a face uses is a sample too, with the area-weighted vertex normal.
    """

    def __init__(self, mesh: Mesh, step_mm: float = 0.1):
        self._mesh = mesh
        self.step_mm = float(step_mm)
        v, f = mesh.vertices, mesh.faces
        if len(f) == 0:
            raise ValueError("true surface has no faces")
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        cross = np.cross(b - a, c - a)
        area2 = np.linalg.norm(cross, axis=1)
        normals = cross / np.maximum(area2, 1e-300)[:, None]
        # Stratified: a fixed count per face. trimesh.sample.sample_surface draws the faces at random in
        # proportion to their area instead; at the same total count its samples leave larger gaps, and the
        # distances of points lying on the dome, bladder and thread came out 10-50 % larger on average
        # (0.10-0.13 vs 0.09 um on the dome at 0.25 mm, 0.19 vs 0.13 um on the thread at 0.05 mm), with
        # area / step² samples in all, up to 3x larger. The accuracy figures rest on these distances.
        counts = np.ceil(0.5 * area2 / step_mm**2).astype(np.int64)
        face = np.repeat(np.arange(len(f)), counts)
        rng = np.random.default_rng(0)
        r1, r2 = rng.random(len(face)), rng.random(len(face))
        flip = r1 + r2 > 1
        r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
        self.points = a[face] + r1[:, None] * (b - a)[face] + r2[:, None] * (c - a)[face]
        # each vertex's sum of its faces' cross products, added in the faces' order (np.add.at's sums, bit
        # for bit, without its per-element overhead)
        corner = f.ravel()
        vn = np.stack([np.bincount(corner, np.repeat(cross[:, k], 3), minlength=len(v)) for k in range(3)], axis=1)
        vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)
        # vertices no face refers to are not part of the surface
        used = np.flatnonzero(np.bincount(corner, minlength=len(v)))
        self.points = np.concatenate([self.points, v[used]])
        self.normals = np.concatenate([normals[face], vn[used]])
        self.tree = cKDTree(self.points)

    def nearest(self, points: np.ndarray, *, eps: float = 0.0, max_distance_mm: float = np.inf):
        """(N, 3) -> nearest samples (N, 3), their normals (N, 3), Euclidean distances (N,).

        eps > 0: approximate search (within a factor 1 + eps). Points farther than ``max_distance_mm``
        get distance inf and NaN sample/normal (a KD-tree search far from a dense surface visits a
        large part of the tree, so bounding it keeps outliers cheap)."""
        d, i = self.tree.query(points, eps=eps, distance_upper_bound=max_distance_mm)
        far = ~np.isfinite(d)
        i = np.where(far, 0, i)
        q, n = self.points[i], self.normals[i]
        q[far] = np.nan
        n[far] = np.nan
        return q, n, d

    def distances(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) mm -> (N,) unsigned point-to-surface distance (mm): point-to-plane at the nearest
        sample, never more than the distance to the sample itself. Points within 2 mm of the surface
        are queried first with a bounded search; the few farther ones (outliers) then unbounded."""
        points = np.asarray(points, float)
        q, n, d = self.nearest(points, max_distance_mm=2.0)
        far = ~np.isfinite(d)
        if far.any():
            q[far], n[far], d[far] = self.nearest(points[far])
        plane = np.abs(np.einsum("ij,ij->i", points - q, n))
        # the tangent plane stands for the surface only near its sample: where the perpendicular's
        # foot is farther than a few sample spacings (beyond a rim, say), the sample itself is nearest
        tangential = np.sqrt(np.maximum(d * d - plane * plane, 0.0))
        return np.where(tangential <= 2.0 * self.step_mm, np.minimum(plane, d), d)
