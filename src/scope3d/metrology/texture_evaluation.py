"""How right a textured wall is, against a phantom's truth: its colours against the true albedo at the same
surface points, and the misregistration (mm) of its sharp features (vessel edges).

The coloured wall lives in the map's frame (a textured mesh, :func:`textured_errors`, or one coloured per
vertex, :func:`vertex_colour_errors`); a similarity ``truth_from_map`` (the 7-DoF fit of the map to the
truth, :func:`~scope3d.metrology.evaluation.errors_after_similarity`) relates the two. Both walls are
read along the same lines of sight from the true cavity's centre (taken to the map by the inverse
similarity), so the two samples of a line differ only by where each wall crosses it: the wall error moves
them along the line, not across it.

* Colour: the texture is the albedo up to a gain per channel (the light's strength and the exposure are not
  known), so one gain per channel is fitted (least squares) and the error is ``|texture - gain x albedo|`` in
  grey levels of the texture (and as a fraction of its mean).
* Misregistration: square patches of the true wall (``patch_texels`` texels of the texture's size a side, in
  its tangent plane, cast onto the wall from the centre), the true albedo and the texture sampled on the same
  grid, and their shift found by phase correlation (sub-texel); patches with too little contrast
  (vessel-free mucosa) are skipped. The shift's length in mm is the misregistration.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from scope3d.geometry.similarity import Similarity
from scope3d.metrology.evaluation import distance_summary
from scope3d.scene.mesh import Mesh


@dataclass(frozen=True)
class TextureEvaluationOptions:
    """n_points : wall points compared for colour; n_patches : patches tried for misregistration;
    patch_texels : a patch's side in texels; min_contrast : a patch's true albedo must vary by this
    standard deviation (of [0, 1]) at least; seed : the random choice of points and patches."""

    n_points: int = 100_000
    n_patches: int = 200
    patch_texels: int = 48
    min_contrast: float = 0.04
    seed: int = 0

    def __post_init__(self) -> None:
        if self.n_points < 10 or self.n_patches < 1 or self.patch_texels < 8:
            raise ValueError("need n_points >= 10, n_patches >= 1, patch_texels >= 8")
        if self.min_contrast < 0:
            raise ValueError("min_contrast must be >= 0")


def _inverse(sim: Similarity, points: np.ndarray) -> np.ndarray:
    return (np.asarray(points, float) - sim.target) @ sim.rotation / sim.scale + sim.origin


def _caster(mesh: Mesh):
    import trimesh

    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)


def _cast(tm, origins: np.ndarray, directions: np.ndarray):
    """First hits of rays on a trimesh: (ray index (K,), face (K,), barycentric (K, 3), points (K, 3))."""
    import trimesh

    points, ray, face = tm.ray.intersects_location(origins, directions, multiple_hits=False)
    bary = trimesh.triangles.points_to_barycentric(tm.triangles[face], points)
    return ray, face, np.clip(bary, 0, 1), points


def _face_normals(mesh: Mesh, faces: np.ndarray) -> np.ndarray:
    tri = mesh.vertices[mesh.faces[faces]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


class _Reader:
    """Both walls read along lines of sight from the true centre: true albedo and the colour at each."""

    def __init__(self, wall: Mesh, colour_at: Callable, coloured: np.ndarray, truth_from_map: Similarity,
                 true_mesh: Mesh, true_centre: np.ndarray, albedo: Callable, footprint_mm: float):
        self.wall, self.colour_at, self.coloured = wall, colour_at, coloured
        self.sim, self.true_mesh = truth_from_map, true_mesh
        self.centre, self.albedo, self.footprint = np.asarray(true_centre, float), albedo, footprint_mm
        self.true_caster, self.map_caster = _caster(true_mesh), _caster(wall)  # built once

    def read(self, targets: np.ndarray):
        """targets (N, 3) mm in the truth's frame -> (kept (K,) indices, true points (K, 3), albedo (K, 3)
        in [0, 1], texture (K, 3) grey levels) where both walls are hit and the texture is filled."""
        d = targets - self.centre
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
        ray_t, face_t, _, points_t = _cast(self.true_caster, np.broadcast_to(self.centre, d.shape), d)
        origin_m = _inverse(self.sim, self.centre[None])[0]
        d_m = d @ self.sim.rotation  # directions taken to the map's frame (rotation only)
        ray_m, face_m, bary_m, _ = _cast(self.map_caster, np.broadcast_to(origin_m, d.shape), d_m)
        seen = self.coloured[face_m]
        ray_m, face_m, bary_m = ray_m[seen], face_m[seen], bary_m[seen]
        both, it, im = np.intersect1d(ray_t, ray_m, return_indices=True)
        normals = _face_normals(self.true_mesh, face_t[it])
        footprint = np.full(len(both), self.footprint)
        albedo = np.asarray(self.albedo(points_t[it], normals, footprint), float)
        texture = self.colour_at(face_m[im], bary_m[im])
        return both, points_t[it], albedo, texture


def textured_errors(textured, truth_from_map: Similarity, true_mesh: Mesh, true_centre: np.ndarray, albedo: Callable,
                    *,
                    options: TextureEvaluationOptions = TextureEvaluationOptions()) -> dict:
    """:func:`colour_errors` of a textured mesh (:class:`scope3d.mvs.texturing.TexturedMesh`, passed as is:
    metrology does not import mvs): its atlas where a frame saw the face, its texel as the grid step."""
    return colour_errors(textured.mesh, textured.colour_at, textured.face_frame >= 0, textured.texel_mm,
                         truth_from_map, true_mesh, true_centre, albedo, options=options)


def vertex_colour_errors(mesh: Mesh, step_mm: float, truth_from_map: Similarity, true_mesh: Mesh,
                         true_centre: np.ndarray, albedo: Callable, *, options: TextureEvaluationOptions =
                         TextureEvaluationOptions()) -> dict:
    """The same measures for a mesh coloured per vertex (colours interpolated over each face), read on a
    grid of ``step_mm`` (map units) for the misregistration."""
    colours = mesh.vertex_colors.astype(float)
    return colour_errors(mesh, lambda f, b: np.einsum("ij,ijk->ik", b, colours[mesh.faces[f]]),
                         np.ones(len(mesh.faces), bool), step_mm, truth_from_map, true_mesh, true_centre, albedo,
                         options=options)


def colour_errors(wall: Mesh, colour_at: Callable[[np.ndarray, np.ndarray], np.ndarray], coloured: np.ndarray,
                  step_mm: float, truth_from_map: Similarity, true_mesh: Mesh, true_centre: np.ndarray,
                  albedo: Callable, *, options: TextureEvaluationOptions = TextureEvaluationOptions()) -> dict:
    """Colour error and misregistration of a coloured wall (map frame): ``colour_at(faces (N,), barycentric
    (N, 3)) -> (N, 3)`` grey levels on the faces where ``coloured`` (F,) is true; ``step_mm`` (map units) the
    patches' grid step (and the albedo's low-pass footprint)."""
    rng = np.random.default_rng(options.seed)
    texel_mm = step_mm * truth_from_map.scale
    reader = _Reader(wall, colour_at, coloured, truth_from_map, true_mesh, true_centre, albedo, texel_mm)
    tri = true_mesh.vertices[true_mesh.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(area), size=options.n_points, p=area / area.sum())
    r1, r2 = rng.random(options.n_points), rng.random(options.n_points)
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    targets = tri[face, 0] + r1[:, None] * (tri[face, 1] - tri[face, 0]) + r2[:, None] * (tri[face, 2] - tri[face, 0])
    _, points, truth, texture = reader.read(targets)
    if len(points) < 10:
        return {"n_points": int(len(points))}
    gain = (texture * truth).sum(axis=0) / np.maximum((truth * truth).sum(axis=0), 1e-300)
    error = np.abs(texture - gain * truth).mean(axis=1)
    luminance_t, luminance_a = texture.mean(axis=1), (gain * truth).mean(axis=1)
    colour = {
        "n_points": int(len(points)), "gain_per_channel": gain.tolist(),
        "mean_grey": float(error.mean()), "median_grey": float(np.median(error)),
        "p95_grey": float(np.percentile(error, 95)),
        "mean_fraction": float(error.mean() / max(luminance_t.mean(), 1e-300)),
        "luminance_correlation": float(np.corrcoef(luminance_t, luminance_a)[0, 1]),
    }

    shifts, responses = [], []
    side = options.patch_texels
    offsets = (np.arange(side) - (side - 1) / 2) * texel_mm
    window = cv2.createHanningWindow((side, side), cv2.CV_64F)
    for k in rng.choice(len(points), size=min(options.n_patches, len(points)), replace=False):
        p = points[k]
        n = p - reader.centre
        n /= np.linalg.norm(n)
        t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        a, b = np.meshgrid(offsets, offsets)
        grid = p + a.reshape(-1, 1) * t1 + b.reshape(-1, 1) * t2
        kept, _, truth_g, texture_g = reader.read(grid)
        if len(kept) < side * side:  # the patch leaves the textured wall
            continue
        truth_img = truth_g.mean(axis=1).reshape(side, side)
        if truth_img.std() < options.min_contrast:
            continue
        texture_img = texture_g.mean(axis=1).reshape(side, side)
        (dx, dy), response = cv2.phaseCorrelate(truth_img.astype(np.float64), texture_img.astype(np.float64), window)
        shifts.append(np.hypot(dx, dy) * texel_mm)
        responses.append(response)
    misregistration = {**distance_summary(np.array(shifts)), "patch_mm": float(side * texel_mm),
                       "patches_tried": int(min(options.n_patches, len(points))),
                       "median_response": float(np.median(responses)) if responses else None}
    misregistration.pop("within_1mm_fraction", None)
    return {"texel_mm": float(texel_mm), "colour_error": colour, "misregistration_mm": misregistration}
