"""The textured wall of a cavity: the registered frames projected onto its mesh (reference sec. 2.4; issue 11 §4).

The organ panorama's wall mesh is star-shaped about the cavity's centre (``cavity_mesh`` triangulates the
points' directions from it), so one texture atlas holds the whole wall as a **cube map of directions**:
six square cells (3 x 2), each the gnomonic projection of one face of a cube around the centre, with the
tangent adjustment of S2-style cube maps (``a = 4/pi atan(s)``) that keeps texel sizes within ~1.4x over a
cell instead of 5x. Every mesh face goes to the cell of its centroid's direction; its three corners get
that cell's coordinates, beyond the cell's square for a face straddling a cube edge, so each cell has a
margin. Faces no frame sees point at a grey strip below the cells.

Texels are filled as a renderer reads them: each face is rasterised into its triangle of the atlas (and a
gutter of ``gutter_px`` texels around it, so that bilinear lookups at a chart's edge read the same
surface), and a texel's 3-D point is its barycentric mix of the face's corners. For each texel, every
frame that sees its face (the face inside the circular field, facing the camera, and not hidden: one ray
cast per face and frame) scores ``cos(view angle) x focal / distance`` (the frame's pixels per mm on the
wall: most frontal and closest win) times a feather that falls to 0 at the field's edge; the weights
``(score / best score) ^ blend_power`` keep one view per texel except where the best view changes, where
the views blend over a few pixels instead of leaving a seam. One pass over the frames, each frame read once:
the sums are kept against the best score so far and rescaled when a better view comes.

Cost: the texels times the views per texel (5.4 on the 15 mm spiral, 3.1 on the 36-frame one): the atlas's
size (``max_atlas_px``) is the budget. Bounding each view's score over a face to skip the views whose
weight stays below 1/256 of the best there was measured and dropped: it skipped 0.5 % of the views (the
views of a face score within a factor of 2 of each other).

Light: the scope's light is at its tip, so a frame's pixel is ``gain x albedo x cos i / d^2`` (plus a
specular glint). Dividing by ``cos i / d^2`` (``compensate_light``) makes the texture the wall's albedo up to
one gain, the same from every frame, and per-frame gains fitted on the texels frames share (log domain,
alternating means; ``level_gains``, off by default) absorb auto-exposure. The atlas is scaled so that its 99.5th percentile is
``white_level``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import cv2
import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.scene.mesh import Mesh
from scope3d.sensor.camera import Camera
from scope3d.utils.robust import robust_sigma

GREY = np.uint8(128)


@dataclass(frozen=True)
class TextureOptions:
    """texel_mm : texel size on the wall at a cell's centre (mm); None: the median over faces of the best
        frame's pixel footprint (distance / focal), the frames' own resolution.
    max_atlas_px : the atlas's longest side at most (a texel budget: texels get coarser to fit). Time,
        memory and files grow with the texels: default 2048 (2048 x 1369, 2.8 M texels; measured on the unseen
        cavity's 15 mm spiral, 165 views at 608 px whose pixels are 0.035 mm on the wall: 0.103 mm texels in
        8.9 CPU-s, where 4096 gives 0.051 mm in 30 CPU-s, the vessels a little sharper when zoomed in; on the
        36-frame spiral at 30 mm 0.109 mm instead of its frames' 0.069 mm; docs/panorama.md).
    gutter_px : texels filled around each face's triangle (bilinear lookups at a chart's edge).
    blend_power : exponent of the views' score ratio in the blend (large: one view per texel, sharp; a
        seam blends where two views score within a few percent).
    feather_px : the score falls linearly to 0 over this many pixels inside the circular field's edge
        (or the image border), so a frame's edge never makes a seam.
    min_cos : views seeing the wall more obliquely than this cosine are not used (their light correction
        and resolution are poor).
    compensate_light : divide by the tip light's ``cos i / d^2``. level_gains : fit one gain per frame (for
        auto-exposed videos; off by default: on the lab's fixed-exposure spiral at 200 px, with the true
        poses and wall, it absorbed specular glints into the gains, +/-5 %, and raised the colour error
        from 4.9 to 5.5 grey levels).
    white_level : the atlas's 99.5th percentile maps to this grey level.
    """

    texel_mm: float | None = None
    max_atlas_px: int = 2048
    gutter_px: int = 2
    blend_power: float = 8.0
    feather_px: float = 24.0
    min_cos: float = 0.25
    compensate_light: bool = True
    level_gains: bool = False
    white_level: float = 235.0

    def __post_init__(self) -> None:
        if self.texel_mm is not None and not self.texel_mm > 0:
            raise ValueError("texel_mm must be > 0 or None")
        if self.max_atlas_px < 48:
            raise ValueError("max_atlas_px must be >= 48")
        if self.gutter_px < 0 or self.feather_px < 0 or self.blend_power <= 0:
            raise ValueError("gutter_px and feather_px must be >= 0 and blend_power > 0")
        if not 0 <= self.min_cos < 1:
            raise ValueError("min_cos must be in [0, 1)")
        if not 0 < self.white_level <= 255:
            raise ValueError("white_level must be in (0, 255]")


@dataclass(frozen=True)
class TexturedMesh:
    """A mesh with a texture atlas (what OBJ + MTL + PNG hold).

    mesh : the geometry (mm). uv : (T, 2) float texture coordinates in [0, 1], OBJ's convention (u to the
    right, v up from the atlas's bottom row). face_uv : (F, 3) int indices into uv per face corner.
    image : (H, W, 3) uint8 RGB atlas, row 0 at the top. texel_mm : texel size at a cell's centre.
    face_frame : (F,) int the frame scoring best for each face, -1 where none sees it.
    textured_fraction : the mesh's area seen by some frame. gains : (n_frames,) the per-frame gains used
    (1 where not levelled or not used).
    """

    mesh: Mesh
    uv: np.ndarray
    face_uv: np.ndarray
    image: np.ndarray
    texel_mm: float
    face_frame: np.ndarray
    textured_fraction: float
    gains: np.ndarray

    def colour_at(self, faces: np.ndarray, barycentric: np.ndarray) -> np.ndarray:
        """The atlas's colour (N, 3) float at surface points (faces (N,), barycentric (N, 3)); see
        :func:`sample_texture`."""
        return sample_texture(self, faces, barycentric)


# --- the cube map ------------------------------------------------------------------------------------


def _cell_coordinates(directions: np.ndarray, cell: np.ndarray) -> np.ndarray:
    """(N, 3) directions, (N,) cube cells 0..5 (+x, -x, +y, -y, +z, -z) -> (N, 2) tangent-adjusted
    coordinates (in [-1, 1] inside the cell; beyond it for directions across an edge; NaN behind it)."""
    axis, sign = cell // 2, np.where(cell % 2 == 0, 1.0, -1.0)
    rows = np.arange(len(directions))
    major = sign * directions[rows, axis]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = directions[rows, (axis + 1) % 3] / major
        t = directions[rows, (axis + 2) % 3] / major
    out = np.stack([np.arctan(s), np.arctan(t)], axis=1) * (4.0 / math.pi)
    out[major <= 1e-9] = np.nan
    return out


def _cube_cell(directions: np.ndarray) -> np.ndarray:
    axis = np.argmax(np.abs(directions), axis=1)
    negative = directions[np.arange(len(directions)), axis] < 0
    return 2 * axis + negative


@dataclass(frozen=True)
class _Atlas:
    """cell_px : side of a cell; half_extent : the cell spans [-half_extent, half_extent] in cube
    coordinates; width, height : atlas size (two rows of cells plus a grey strip)."""

    cell_px: int
    half_extent: float

    @property
    def width(self) -> int:
        return 3 * self.cell_px

    @property
    def height(self) -> int:
        return 2 * self.cell_px + 4

    def pixels(self, coords: np.ndarray, cell: np.ndarray) -> np.ndarray:
        """(N, 2) cube coordinates in cells (N,) -> (N, 2) atlas pixel coordinates (x right, y down;
        integer values at texel centres)."""
        origin = np.stack([(cell % 3) * self.cell_px, (cell // 3) * self.cell_px], axis=1)
        return origin + (coords + self.half_extent) / (2 * self.half_extent) * self.cell_px - 0.5


def cube_map_charts(mesh: Mesh, centre: np.ndarray, *, max_extent: float = 1.5):
    """Each face's cube cell and its corners' cube coordinates: (cell (F,), coords (F, 3, 2), usable (F,)).

    A face's corners are taken in its centroid's cell; a face whose corners reach beyond ``max_extent``
    (a face spanning tens of degrees, bridging a region without points) is not usable (left grey)."""
    v = mesh.vertices - centre
    directions = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)
    centroid = v[mesh.faces].mean(axis=1)
    cell = _cube_cell(centroid)
    corners = directions[mesh.faces].reshape(-1, 3)
    coords = _cell_coordinates(corners, np.repeat(cell, 3)).reshape(-1, 3, 2)
    usable = np.all(np.isfinite(coords), axis=(1, 2)) & np.all(np.abs(coords) <= max_extent, axis=(1, 2))
    return cell, coords, usable


# --- rasterising faces into the atlas -------------------------------------------------------------------


def _barycentric(triangles_px: np.ndarray, face: np.ndarray, index: np.ndarray, width: int) -> np.ndarray:
    """Barycentric weights (N, 3) of texels ``index`` (N,) (atlas rows of ``width``) in the atlas triangles of
    ``face`` (N,) (triangles_px: (F, 3, 2) of every face; extrapolated outside)."""
    a = triangles_px[face, 0]
    e1, e2 = triangles_px[face, 1] - a, triangles_px[face, 2] - a
    den = e1[:, 0] * e2[:, 1] - e2[:, 0] * e1[:, 1]
    den = np.where(np.abs(den) < 1e-12, 1e-12, den)
    vx, vy = index % width - a[:, 0], index // width - a[:, 1]
    w1 = (vx * e2[:, 1] - e2[:, 0] * vy) / den
    w2 = (e1[:, 0] * vy - vx * e1[:, 1]) / den
    return np.stack([1.0 - w1 - w2, w1, w2], axis=1)


def face_neighbours(faces: np.ndarray) -> np.ndarray:
    """(F, 3) the face across the edge opposite each corner, -1 where none (a border)."""
    a, b = faces[:, [1, 2, 0]].ravel(), faces[:, [2, 0, 1]].ravel()
    key = np.minimum(a, b).astype(np.int64) * (int(faces.max()) + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    same = key[order[1:]] == key[order[:-1]]
    out = np.full(len(key), -1, np.int64)
    first, second = order[:-1][same], order[1:][same]
    out[first], out[second] = second // 3, first // 3
    return out.reshape(-1, 3)


def rasterise(triangles_px: np.ndarray, faces: np.ndarray, width: int, height: int, gutter_px: int) -> np.ndarray:
    """Which face covers each texel: (height * width,) int32, -1 for none. triangles_px : (F, 3, 2) atlas
    pixel coordinates of every face; faces : (K,) the faces drawn. Drawn as a renderer's ID buffer (OpenCV,
    to 1/16 texel): every face's outline widened by ``gutter_px`` first (the gutter), then every face's
    interior over them. OpenCV's fill also takes texels an edge only grazes (:func:`deepest_faces` gives
    them to the face they lie inside). (A rasteriser testing every texel of each face's box took 25 of the
    36-frame spiral's 80 s.)"""
    owner = np.full((height, width), -1, np.int32)
    fixed = np.round(np.asarray(triangles_px[faces]) * 16).astype(np.int32)
    if gutter_px > 0:
        for tri, f in zip(fixed, faces.tolist()):
            cv2.polylines(owner, [tri], True, f, thickness=2 * gutter_px + 1, lineType=cv2.LINE_8, shift=4)
    for tri, f in zip(fixed, faces.tolist()):
        cv2.fillConvexPoly(owner, tri, f, lineType=cv2.LINE_8, shift=4)
    return owner.ravel()


def deepest_faces(triangles_px: np.ndarray, face: np.ndarray, index: np.ndarray, width: int,
                  neighbours: np.ndarray, drawn: np.ndarray, *, steps: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Texels ``index`` covered by ``face`` (:func:`rasterise`) given to the face they lie deepest inside.
    From a texel whose centre is outside its face, a walk across the edge it is most outside of, face after
    face (``neighbours``, (F, 3) from :func:`face_neighbours`; faces ``drawn`` only), at most ``steps``
    faces: the point location of a triangulation. One step left 2 % of the texels of a random triangulation
    (thin faces) with a face that grazes them; the texels outside every face (the gutter) keep the face
    they are least outside of. Returns (faces, barycentric weights (N, 3) in them)."""
    bary = _barycentric(triangles_px, face, index, width)
    face = face.copy()
    here, here_bary = face.copy(), bary.copy()
    active = np.flatnonzero(bary.min(axis=1) < 0)
    for _ in range(steps):
        across = neighbours[here[active], here_bary[active].argmin(axis=1)]
        ok = across >= 0
        ok[ok] = drawn[across[ok]]
        active, across = active[ok], across[ok]
        if not len(active):
            break
        here[active] = across
        here_bary[active] = _barycentric(triangles_px, across, index[active], width)
        deeper = here_bary[active].min(axis=1) > bary[active].min(axis=1)
        face[active[deeper]] = across[deeper]
        bary[active[deeper]] = here_bary[active[deeper]]
        active = active[here_bary[active].min(axis=1) < 0]
    return face, bary


# --- which frames see which faces ----------------------------------------------------------------------


def face_visibility(mesh: Mesh, camera: Camera, poses: Sequence[Pose | None], *, min_cos: float) -> np.ndarray:
    """(F, n_frames) bool: the frame sees the face: a corner inside the image's (circular) field, the face
    turned towards the camera by ``min_cos`` at least, and the ray from the camera's centre to the face's
    centroid meeting no other part of the mesh first (Embree through trimesh; pure NumPy without it)."""
    import trimesh

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    tri = mesh.vertices[mesh.faces]
    centroid = tri.mean(axis=1)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    # a cone around the optical axis holding the whole image (its corners' rays), widened by the largest
    # face's angular size from the nearest camera: faces outside it cannot reach the image
    corner_rays = camera.unproject(np.array([[-0.5, -0.5], [camera.width - 0.5, -0.5], [-0.5, camera.height - 0.5],
                                             [camera.width - 0.5, camera.height - 0.5]]))
    half_angle = float(np.arccos(np.clip(corner_rays[:, 2] / np.linalg.norm(corner_rays, axis=1), -1, 1)).max())
    reach = np.linalg.norm(tri - centroid[:, None], axis=2).max(axis=1)
    visible = np.zeros((len(mesh.faces), len(poses)), bool)
    for k, pose in enumerate(poses):
        if pose is None:
            continue
        to_camera = pose.centre - centroid
        distance = np.linalg.norm(to_camera, axis=1)
        facing = np.einsum("ij,ij->i", normal, to_camera) >= min_cos * distance
        along = -(to_camera @ pose.optical_axis)
        spread = np.arcsin(np.clip(reach / np.maximum(distance, 1e-300), 0, 1))
        cone = np.arccos(np.clip(along / np.maximum(distance, 1e-300), -1, 1)) <= half_angle + spread
        candidates = np.flatnonzero(facing & cone)
        corners = camera.project_world(pose, tri[candidates].reshape(-1, 3)).reshape(-1, 3, 2)
        depth = ((tri[candidates].reshape(-1, 3) - pose.centre) @ pose.optical_axis).reshape(-1, 3)
        inside = (camera.in_image(corners.reshape(-1, 2)).reshape(-1, 3) & (depth > 0)).any(axis=1)
        candidates = candidates[inside]
        if not len(candidates):
            continue
        directions = -to_camera[candidates] / distance[candidates, None]
        origins = np.broadcast_to(pose.centre, directions.shape)
        hit, ray, first = tm.ray.intersects_location(origins, directions, multiple_hits=False)
        # float32 in Embree: a hit within 0.1 % of the distance is the face itself (or its neighbour)
        reached = np.ones(len(candidates), bool)
        blocked = np.linalg.norm(hit - pose.centre, axis=1) < (1 - 1e-3) * distance[candidates[ray]]
        reached[ray[blocked & (first != candidates[ray])]] = False
        visible[candidates[reached], k] = True
    return visible


def faces_towards(mesh: Mesh, centre: np.ndarray) -> Mesh:
    """The mesh with every face wound so that its normal points towards ``centre`` (the wall seen from
    inside; a phantom's true wall is wound outwards)."""
    tri = mesh.vertices[mesh.faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    away = np.einsum("ij,ij->i", normal, centre - tri.mean(axis=1)) < 0
    if not away.any():
        return mesh
    faces = mesh.faces.copy()
    faces[away] = faces[away][:, ::-1]
    return Mesh(mesh.vertices, faces, mesh.vertex_colors, mesh.vertex_normals)


# --- filling the texels -------------------------------------------------------------------------------


def sample_image(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, 3) float32 of an RGB image at pixel coordinates uv (N, 2)."""
    n = len(uv)
    if n == 0:  # a frame that sees a face but none of its texels (cv2.remap refuses an empty map)
        return np.zeros((0, image.shape[2]), np.float32)
    width = 1024
    rows = -(-n // width)
    maps = np.full((rows * width, 2), -10.0, np.float32)
    maps[:n] = uv
    maps = maps.reshape(rows, width, 2)
    out = cv2.remap(image, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, image.shape[2])[:n].astype(np.float32)


def field_margin(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """Pixels from uv (N, 2) to the edge of the field (the circular mask, else the image's border)."""
    border = np.minimum.reduce([uv[:, 0] + 0.5, uv[:, 1] + 0.5, camera.width - 0.5 - uv[:, 0],
                                camera.height - 0.5 - uv[:, 1]])
    if camera.mask_radius_px is None:
        return border
    centre = np.array([(camera.width - 1) / 2, (camera.height - 1) / 2])
    return np.minimum(border, camera.mask_radius_px - np.linalg.norm(uv - centre, axis=1))


class _Texels:
    """The atlas's texels that some seen face owns, grouped by face (``rows(faces)``: theirs, without a pass
    over every texel): their index in the atlas, face, 3-D point and unit normal (inward)."""

    def __init__(self, mesh: Mesh, owner: np.ndarray, width: int, triangles_px: np.ndarray, seen: np.ndarray,
                 vertex_normals: np.ndarray):
        ok = owner >= 0
        ok[ok] = seen[owner[ok]]
        index = np.flatnonzero(ok)
        face, bary = deepest_faces(triangles_px, owner[index], index, width, face_neighbours(mesh.faces), seen)
        order = np.argsort(face, kind="stable")
        self.index, self.face, bary = index[order], face[order], bary[order]
        self.count = np.bincount(self.face, minlength=len(mesh.faces))
        self.start = np.cumsum(self.count) - self.count
        # the gutter's texels extrapolate a little beyond the face: clamp to its edges
        bary = np.clip(bary, 0.0, None)
        bary /= bary.sum(axis=1, keepdims=True)

        def per_texel(x):  # per-face terms repeated over the face's texels (grouped by face): no gather
            return np.repeat(x, self.count, axis=0)

        self.points = np.einsum("ij,ijk->ik", bary, per_texel(mesh.vertices[mesh.faces]))
        n = np.einsum("ij,ijk->ik", bary, per_texel(vertex_normals[mesh.faces]))
        self.normals = n / np.sqrt(np.maximum(np.einsum("ij,ij->i", n, n), 1e-300))[:, None]

    def rows(self, faces: np.ndarray) -> np.ndarray:
        """The rows of the texels of ``faces`` (increasing faces: increasing rows)."""
        count = self.count[faces]
        shift = np.repeat(self.start[faces] - (np.cumsum(count) - count), count)
        return shift + np.arange(int(count.sum()))


def _vertex_normals(mesh: Mesh) -> np.ndarray:
    """Area-weighted vertex normals (V, 3), on the side the faces' winding gives (the cavity's inside)."""
    tri = mesh.vertices[mesh.faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(mesh.vertices)
    for k in range(3):
        np.add.at(vn, mesh.faces[:, k], cross)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def _view_terms(texels: _Texels, rows: np.ndarray, camera: Camera, pose: Pose, options: TextureOptions):
    """For texels ``rows`` seen from ``pose``: (kept rows, pixel uv, score, light factor cos i / d^2)."""
    p, n = texels.points[rows], texels.normals[rows]
    to_camera = pose.centre - p
    d = np.sqrt(np.einsum("ij,ij->i", to_camera, to_camera))
    cos = np.einsum("ij,ij->i", n, to_camera) / np.maximum(d, 1e-300)
    # the camera's coordinates by einsum, not Pose.transform's matmul: BLAS on (N, 3) x (3, 3) spent 1/6 of
    # the 36-frame spiral's texturing (its threads spinning on a loaded machine)
    in_camera = np.einsum("ij,kj->ik", -to_camera, pose.rotation)
    uv = camera.project(in_camera)
    # a bilinear read reaches one pixel out: within 1.5 px of the field's edge it would mix in the black mask
    margin = field_margin(camera, uv) - 1.5
    keep = (cos >= options.min_cos) & (margin > 0) & (in_camera[:, 2] > 0)
    feather = np.clip(margin / options.feather_px, 0.0, 1.0) if options.feather_px > 0 else np.ones(len(rows))
    score = cos * math.sqrt(camera.fx * camera.fy) / d * feather
    return rows[keep], uv[keep], score[keep], (cos / d**2)[keep]


def _face_scores(mesh: Mesh, faces: np.ndarray, camera: Camera, pose: Pose, options: TextureOptions) -> np.ndarray:
    """The view score (see :func:`_view_terms`) of ``pose`` at the centroids of ``faces``, 0 where not usable."""
    tri = mesh.vertices[mesh.faces[faces]]
    p = tri.mean(axis=1)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    to_camera = pose.centre - p
    d = np.linalg.norm(to_camera, axis=1)
    cos = np.einsum("ij,ij->i", n, to_camera) / np.maximum(d, 1e-300)
    margin = field_margin(camera, camera.project_world(pose, p)) - 1.5
    feather = np.clip(margin / options.feather_px, 0.0, 1.0) if options.feather_px > 0 else (margin > 0) * 1.0
    return np.where((cos >= options.min_cos) & (margin > 0), cos * math.sqrt(camera.fx * camera.fy) / d * feather, 0.0)


def texture_mesh(mesh: Mesh, centre: np.ndarray, camera: Camera, poses: Sequence[Pose | None],
                 frame: Callable[[int], np.ndarray], *, options: TextureOptions = TextureOptions()) -> TexturedMesh:
    """Texture a star-shaped cavity's wall ``mesh`` (mm; faces are turned towards ``centre`` in the result) from the frames:
    ``poses[k]`` is frame k's cam_from_world (None: not registered), ``frame(k)`` its (H, W, 3) uint8 RGB
    image (read once per frame that gives a texel, twice with ``level_gains``, so a long video need not be
    held in memory). See the module's text."""
    centre = np.asarray(centre, float)
    mesh = faces_towards(mesh, centre)
    visible = face_visibility(mesh, camera, poses, min_cos=options.min_cos)
    seen = visible.any(axis=1)
    cell, coords, usable = cube_map_charts(mesh, centre)
    seen &= usable

    # texel size: the frames' own resolution (the best frame's footprint per face), bounded by the atlas
    radius = float(np.median(np.linalg.norm(mesh.vertices - centre, axis=1)))
    texel_mm = options.texel_mm
    if texel_mm is None:
        centroid = mesh.vertices[mesh.faces].mean(axis=1)
        footprint = np.full(len(mesh.faces), np.inf)
        for k, pose in enumerate(poses):
            if pose is not None and visible[:, k].any():
                rows = np.flatnonzero(visible[:, k])
                footprint[rows] = np.minimum(footprint[rows], np.linalg.norm(centroid[rows] - pose.centre, axis=1))
        finite = footprint[np.isfinite(footprint)]
        texel_mm = float(np.median(finite)) / math.sqrt(camera.fx * camera.fy) if len(finite) else radius / 256
    extent = float(np.abs(coords[seen]).max()) if seen.any() else 1.0
    # mm per unit of cube coordinate at a cell's centre: the tangent adjustment's d(angle)/da = pi/4
    mm_per_unit = radius * math.pi / 4
    cell_px = int(math.ceil(2 * extent * mm_per_unit / texel_mm)) + 2 * options.gutter_px + 2
    cell_px = max(16, min(cell_px, options.max_atlas_px // 3))
    half_extent = extent + (options.gutter_px + 1) * 2 * extent / cell_px
    atlas = _Atlas(cell_px, half_extent)
    texel_mm = 2 * half_extent * mm_per_unit / cell_px

    triangles_px = atlas.pixels(coords.reshape(-1, 2), np.repeat(cell, 3)).reshape(-1, 3, 2)
    faces_seen = np.flatnonzero(seen)
    owner = rasterise(triangles_px, faces_seen, atlas.width, atlas.height, options.gutter_px)
    vertex_normals = _vertex_normals(mesh)
    texels = _Texels(mesh, owner, atlas.width, triangles_px, seen, vertex_normals)

    n_frames = len(poses)
    used = [k for k in range(n_frames) if poses[k] is not None and (visible[:, k] & seen).any()]

    gains = np.ones(n_frames)
    if options.level_gains:
        samples: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (texel rows, frame, log luminance)
        subsample = max(1, len(texels.index) // 200_000)
        for k in used:
            rows = texels.rows(np.flatnonzero(visible[:, k] & seen))
            rows, uv, _, light = _view_terms(texels, rows[rows % subsample == 0], camera, poses[k], options)
            value = sample_image(frame(k), uv).mean(axis=1)
            ok = value > 2.0  # black: outside the field or under-exposed
            scale = light if options.compensate_light else 1.0
            log = np.log(np.maximum(value, 1e-3) / scale)
            samples.append((rows[ok], np.full(int(ok.sum()), k), log[ok]))
        if samples:
            gains = _level_gains(samples, n_frames)

    # one pass: each texel's weights are (score / best so far) ** blend_power, and the sums are rescaled
    # when a better view comes, so that they end as the weights against the best view of all
    total = np.zeros((len(texels.index), 3), np.float32)
    weight = np.zeros(len(texels.index), np.float32)
    best = np.zeros(len(texels.index), np.float32)
    face_score = np.zeros((len(mesh.faces), n_frames), np.float32)
    for k in used:
        faces_k = np.flatnonzero(visible[:, k] & seen)
        # the face's best frame: the best score at its centroid
        face_score[faces_k, k] = _face_scores(mesh, faces_k, camera, poses[k], options)
        rows = texels.rows(faces_k)
        rows, uv, score, light = _view_terms(texels, rows, camera, poses[k], options)
        useful = score > 0  # min_cos 0: a grazing view adds nothing
        rows, uv, score, light = rows[useful], uv[useful], score[useful], light[useful]
        if not len(rows):
            continue
        top = np.maximum(best[rows], score)
        rescale = (best[rows] / top) ** options.blend_power
        w = (score / top) ** options.blend_power
        colour = sample_image(frame(k), uv) / gains[k]
        if options.compensate_light:
            colour /= light[:, None]
        total[rows] = total[rows] * rescale[:, None] + w[:, None] * colour
        weight[rows] = weight[rows] * rescale + w
        best[rows] = top
    filled = weight > 0
    albedo = np.zeros(total.shape)
    albedo[filled] = total[filled] / weight[filled, None]
    top = float(np.percentile(albedo[filled].max(axis=1), 99.5)) if filled.any() else 1.0
    image = np.full((atlas.height * atlas.width, 3), GREY, np.uint8)
    image[texels.index[filled]] = np.clip(albedo[filled] * (options.white_level / max(top, 1e-300)) + 0.5, 0, 255)
    image = image.reshape(atlas.height, atlas.width, 3)

    uv, face_uv = _corner_uv(triangles_px, seen, atlas)
    face_frame = np.where(face_score.max(axis=1) > 0, face_score.argmax(axis=1), -1)
    area = 0.5 * np.linalg.norm(np.cross(*(mesh.vertices[mesh.faces][:, 1:] - mesh.vertices[mesh.faces][:, :1])
                                         .transpose(1, 0, 2)), axis=1)
    textured = float(area[face_frame >= 0].sum() / max(area.sum(), 1e-300))
    return TexturedMesh(mesh, uv, face_uv, image, texel_mm, face_frame, textured, gains)


def _level_gains(samples, n_frames: int, *, rounds: int = 30) -> np.ndarray:
    """Per-frame gains from texels seen by several frames: log value_k(t) = log albedo(t) + log gain_k,
    solved by alternating means (texels given the gains, gains given the texels; the mean log gain is 0,
    the gauge). After a few rounds, samples more than 3 robust sigmas off (a specular glint, a pixel across
    a vessel's edge) are dropped."""
    rows = np.concatenate([s[0] for s in samples])
    frames = np.concatenate([s[1] for s in samples])
    values = np.concatenate([s[2] for s in samples])
    _, texel = np.unique(rows, return_inverse=True)
    shared = np.bincount(texel)[texel] >= 2
    if not shared.any():
        return np.ones(n_frames)
    texel, frames, values = texel[shared], frames[shared], values[shared]
    _, texel = np.unique(texel, return_inverse=True)
    n_texels = int(texel.max()) + 1
    keep = np.ones(len(values), bool)
    log_gain = np.zeros(n_frames)
    for r in range(rounds):
        w = keep.astype(float)
        per_texel = np.bincount(texel, w * (values - log_gain[frames]), n_texels) / \
            np.maximum(np.bincount(texel, w, n_texels), 1e-300)
        count = np.bincount(frames, w, n_frames)
        log_gain = np.bincount(frames, w * (values - per_texel[texel]), n_frames) / np.maximum(count, 1e-300)
        log_gain -= log_gain[count > 0].mean()
        log_gain[count == 0] = 0.0
        if r == rounds // 3:
            residual = values - per_texel[texel] - log_gain[frames]
            sigma = robust_sigma(residual, about=0.0) + 1e-12
            keep = np.abs(residual) <= 3 * sigma
    return np.exp(log_gain)


def _corner_uv(triangles_px: np.ndarray, seen: np.ndarray, atlas: _Atlas) -> tuple[np.ndarray, np.ndarray]:
    """OBJ texture coordinates: unique (T, 2) in [0, 1] (v up) and (F, 3) indices; unseen faces point at
    the grey strip below the cells."""
    px = triangles_px.copy()
    px[~seen] = [atlas.width / 2, atlas.height - 2.0]
    u = (px[..., 0] + 0.5) / atlas.width
    v = 1.0 - (px[..., 1] + 0.5) / atlas.height
    corners = np.stack([u, v], axis=-1).reshape(-1, 2)
    uv, inverse = np.unique(corners.round(9), axis=0, return_inverse=True)
    return uv, inverse.reshape(-1, 3)


def sample_texture(textured: TexturedMesh, faces: np.ndarray, barycentric: np.ndarray) -> np.ndarray:
    """The atlas's colour (N, 3) float (bilinear, as a renderer reads it) at the surface points given by
    their faces (N,) and barycentric weights (N, 3)."""
    uv = np.einsum("ij,ijk->ik", barycentric, textured.uv[textured.face_uv[faces]])
    h, w = textured.image.shape[:2]
    pixels = np.stack([uv[:, 0] * w - 0.5, (1.0 - uv[:, 1]) * h - 0.5], axis=1)
    return sample_image(textured.image, pixels)
