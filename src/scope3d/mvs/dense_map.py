"""The dense surgical-field map (issue 35; the reference's ch. 9.3.1 asks for it): a depth map per frame from
its best neighbours, the depth maps fused where the views agree, and a mesh of them that follows overhangs.

1. :func:`select_neighbours` — per frame, the frames that see most of what it sees (the sparse map's points
   projected with the adjusted poses) at a useful triangulation angle (COLMAP's view selection in spirit:
   overlap, weighed down below ``good_angle_deg``, none under ``angle_range_deg[0]`` or over its end).
2. :func:`frame_depths` — the plane sweep of :mod:`scope3d.mvs.plane_sweep` over the depth range of the
   points the frame sees, widened by ``depth_margin``: ZNCC over a window (an affine change of brightness
   between views, as the scope's light moves with it, does not change the score), each pixel scored by its
   best two of the eight sources (those that do not see it there, occluded or glinting, are left out); its
   gates give a confidence per pixel (the score, the sources that agree, the peak's margin) and a depth
   standard deviation from the match's ``match_sigma_px`` and the parallax.
3. :func:`fuse_depths` — geometric consistency: a frame's pixel becomes a point where at least
   ``min_consistent_views`` other frames' depth maps, read where the point projects, agree with its depth
   within ``consistency_sigmas`` of the two depths' standard deviations combined; its position is the
   inverse-variance mean of the agreeing depths' points, its normal the depth map's (towards the camera), its
   colour the reflectance frame's. Points closer than ``merge_mm`` are merged.
4. :func:`poisson_mesh` — a screened Poisson surface of the fused points and normals (Open3D), trimmed to
   where there are points: a surface in 3-D, not a height field, so an overhanging lip and the recess under
   it are both kept. (Open3D's TSDF volumes, the other usual way, gave no surface at all in the installed
   0.20: ``ScalableTSDFVolume`` and ``VoxelBlockGrid`` meshed nothing even from one exact plane, and a
   ``UniformTSDFVolume`` over the 40 mm field at 0.08 mm would need 125 M voxels.)

Units: mm; poses are ``cam_from_world``.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.mvs.plane_sweep import PlaneSweepOptions, sweep
from scope3d.scene.mesh import Mesh, PointCloud
from scope3d.sensor.camera import Camera
from scope3d.utils.progress import Progress, advance, stage
from scope3d.utils.sample_image import sample_image
from scope3d.utils.threads import check_threads, resolve_threads


@dataclass(frozen=True)
class DenseOptions:
    """sweep : the plane sweep (default: 7 px ZNCC windows, steps of 1 px of parallax refined by a parabola,
        each pixel scored by its best 2 sources, ZNCC >= 0.5 in at least 2 sources, every pixel).
    neighbours : source frames per frame (default 8: with each pixel scored by its best two, a pixel that
        some sources cannot see, behind the cavity's lip or under the moving light's glint, still has two
        that can).
    angle_range_deg : triangulation angles a source may have with the frame, at the median point they share
        (default 2-35°: below, a depth step moves a pixel too little; above, the views differ too much for a
        window to match). good_angle_deg : below it a source's score is scaled down by angle / good (default 8°).
    min_overlap : fraction of the frame's sparse points a source must see (default 0.3).
    depth_margin : the sweep's range is the frame's sparse points' 1st-99th percentile depth widened by this
        fraction of their median depth on each side (default 0.15: the sparse map misses the deepest, darkest
        corners of a cavity).
    consistency_sigmas : two depths agree within this many standard deviations of their difference (default 3).
    min_consistent_views : other frames that must agree (default 2).
    min_sigma_mm : floor of a depth's standard deviation (default 0.01 mm: reading a depth map at a
        projected point interpolates between pixels, off by the surface's curvature there).
    merge_mm : fused points closer than this are merged (default 0.03 mm, about a pixel's footprint at 608 px).
    threads : frames swept at once (default 0: every available core, :mod:`scope3d.utils.threads`; OpenCV
        and NumPy's large array operations release the interpreter; the results do not depend on it).
    poisson_depth : octree depth of the Poisson surface (default 9: 512 cells across the cloud's extent,
        0.08 mm over the dome's 40 mm plate). trim_mm : mesh vertices farther than this from every fused
        point are dropped (default 0.2 mm: a few fused points' spacing).
    """

    sweep: PlaneSweepOptions = PlaneSweepOptions(window_px=7, step_px=1.0, min_ncc=0.5, min_sources=2,
                                                 stride_px=1, min_peak_margin=0.02, best_sources=2)
    neighbours: int = 8
    angle_range_deg: tuple[float, float] = (2.0, 35.0)
    good_angle_deg: float = 8.0
    min_overlap: float = 0.3
    depth_margin: float = 0.15
    consistency_sigmas: float = 3.0
    min_consistent_views: int = 2
    min_sigma_mm: float = 0.01
    merge_mm: float = 0.03
    poisson_depth: int = 9
    trim_mm: float = 0.2
    threads: int = 0

    def __post_init__(self) -> None:
        lo, hi = self.angle_range_deg
        if not (self.neighbours >= self.sweep.min_sources and 0 <= lo < hi < 90 and self.good_angle_deg > 0):
            raise ValueError("need neighbours >= the sweep's min_sources and 0 <= min angle < max angle < 90")
        if not (0 <= self.min_overlap <= 1 and 0 < self.depth_margin < 0.9 and self.consistency_sigmas > 0):
            raise ValueError("need min_overlap in [0, 1], depth_margin in (0, 0.9), consistency_sigmas > 0")
        if self.min_consistent_views < 1 or self.min_sigma_mm <= 0 or self.merge_mm < 0:
            raise ValueError("need min_consistent_views >= 1, min_sigma_mm > 0 and merge_mm >= 0")
        check_threads(self.threads)
        if not 5 <= self.poisson_depth <= 12 or self.trim_mm <= 0:
            raise ValueError("need poisson_depth in 5-12 and trim_mm > 0")


@dataclass
class FrameDepth:
    """One frame's dense depth: depth_mm (H, W) z-depth in its camera, NaN where the sweep kept nothing;
    sigma_mm (H, W) its standard deviation; score (H, W) the mean ZNCC (the confidence); sources : the frames
    it was swept against; depth_range_mm : (near, far) swept."""

    depth_mm: np.ndarray
    sigma_mm: np.ndarray
    score: np.ndarray
    sources: list[int]
    depth_range_mm: tuple[float, float]


@dataclass
class FusedDepths:
    """cloud : the fused points (mm world) with normals and colours; support : (N,) how many frames' depths
    each point rests on (its own and the agreeing ones); sigma_mm : (N,) the standard deviation of each
    point's inverse-variance mean (before merging: of the merged ones' mean); consistent : per frame (H, W) bool, the pixels that
    passed; rejected : pixels with a depth that no two others confirmed."""

    cloud: PointCloud
    support: np.ndarray
    sigma_mm: np.ndarray
    consistent: list[np.ndarray]
    rejected: int = 0
    candidates: int = 0
    counts: dict = field(default_factory=dict)


def _visible(camera: Camera, pose: Pose, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) bool: the points fall inside the camera's image; and the z-depths (M,) of those that do."""
    idx, _, z = camera.nearest_pixels(pose, points)
    seen = np.zeros(len(points), bool)
    seen[idx] = True
    return seen, z


def select_neighbours(camera: Camera, poses: list[Pose], points: np.ndarray, *,
                      options: DenseOptions = DenseOptions()) -> list[list[int]]:
    """Per frame, up to ``options.neighbours`` source frames, best first (see the module docstring).
    points : (N, 3) mm world, the sparse map."""
    seen = [_visible(camera, p, points)[0] for p in poses]
    centres = np.stack([p.centre for p in poses])
    lo, hi = np.deg2rad(options.angle_range_deg)
    good = np.deg2rad(options.good_angle_deg)
    out = []
    for i in range(len(poses)):
        mine = np.flatnonzero(seen[i])
        scores = np.zeros(len(poses))
        for j in range(len(poses)):
            if j == i or len(mine) == 0:
                continue
            shared = mine[seen[j][mine]]
            overlap = len(shared) / len(mine)
            if overlap < options.min_overlap:
                continue
            a = points[shared] - centres[i]
            b = points[shared] - centres[j]
            cos = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
            angle = float(np.median(np.arccos(np.clip(cos, -1.0, 1.0))))
            if lo <= angle <= hi:
                scores[j] = overlap * min(1.0, angle / good)
        order = [int(j) for j in np.argsort(-scores, kind="stable") if scores[j] > 0]
        out.append(order[:options.neighbours])
    return out


def frame_depths(camera: Camera, images: list[np.ndarray], poses: list[Pose], points: np.ndarray, *,
                 options: DenseOptions = DenseOptions(), progress: Progress | None = None) -> list[FrameDepth | None]:
    """A :class:`FrameDepth` per frame (None where too few sources or sparse points), see the module docstring.
    images : reflectance frames; poses : adjusted ``cam_from_world``; points : (N, 3) mm world, the sparse map."""
    neighbours = select_neighbours(camera, poses, points, options=options)
    stage(progress, "dense depth", len(images))

    def one(i: int) -> FrameDepth | None:
        sources = neighbours[i]
        _, z = _visible(camera, poses[i], points)
        if len(sources) < options.sweep.min_sources or len(z) < 10:
            return None
        lo, mid, hi = np.percentile(z, [1, 50, 99])
        near, far = max(lo - options.depth_margin * mid, 0.1 * mid), hi + options.depth_margin * mid
        d = sweep(camera, images[i], poses[i], [images[k] for k in sources], [poses[k] for k in sources],
                  (near, far), options=options.sweep)
        depth = np.where(camera.mask(), d.depth_mm, np.nan)
        return FrameDepth(depth, np.maximum(d.sigma_mm, options.min_sigma_mm), d.score, sources,
                          (float(near), float(far)))

    out: list[FrameDepth | None] = [None] * len(images)
    with ThreadPoolExecutor(max_workers=resolve_threads(options.threads, len(images))) as pool:
        for i, depth in zip(range(len(images)), pool.map(one, range(len(images)))):
            out[i] = depth
            advance(progress)
    return out


def _read(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear read of a float image at (N, 2) pixels; NaN outside or next to a NaN (a depth edge); any N."""
    return sample_image(image.astype(np.float32), uv, border=cv2.BORDER_CONSTANT, border_value=np.nan).astype(float)


def depth_normals(camera: Camera, depth_mm: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals in the camera frame from a depth map's central differences, facing the camera;
    NaN where a neighbour has no depth."""
    h, w = depth_mm.shape
    p = camera.unproject(camera.pixel_grid().reshape(-1, 2), depth_mm.reshape(-1)).reshape(h, w, 3)
    du = np.full_like(p, np.nan)
    dv = np.full_like(p, np.nan)
    du[:, 1:-1] = p[:, 2:] - p[:, :-2]
    dv[1:-1] = p[2:] - p[:-2]
    n = np.cross(du, dv)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    flip = np.sum(n * p, axis=-1) > 0
    n[flip] *= -1
    return n


def fuse_depths(camera: Camera, images: list[np.ndarray], poses: list[Pose], depths: list[FrameDepth | None], *,
                options: DenseOptions = DenseOptions(), progress: Progress | None = None) -> FusedDepths:
    """Fuse the frames' depth maps by geometric consistency (see the module docstring)."""
    h, w = camera.height, camera.width
    pixels = camera.pixel_grid().reshape(-1, 2)
    k_sig = options.consistency_sigmas
    pts, nrm, col, sup, sig, consistent = [], [], [], [], [], []
    candidates = 0
    stage(progress, "fusion", len(depths))
    for i, d in enumerate(depths):
        keep = np.zeros((h, w), bool)
        consistent.append(keep)
        if d is None:
            advance(progress)
            continue
        flat = np.flatnonzero(np.isfinite(d.depth_mm.reshape(-1)))
        candidates += len(flat)
        z_i = d.depth_mm.reshape(-1)[flat]
        s_i = d.sigma_mm.reshape(-1)[flat]
        world = poses[i].inverse().transform(camera.unproject(pixels[flat], z_i))
        weight = 1.0 / s_i**2
        total = world * weight[:, None]
        wsum = weight.copy()
        agree = np.zeros(len(flat), int)
        for k, other in enumerate(depths):
            if k == i or other is None:
                continue
            p = poses[k].transform(world)
            front = p[:, 2] > 1e-6
            uv = np.full((len(p), 2), -1.0)
            uv[front] = camera.project(p[front])
            inside = front & camera.in_image(uv) & camera.sees_pixels(uv)
            idx = np.flatnonzero(inside)
            if len(idx) == 0:
                continue
            z_k = _read(other.depth_mm, uv[idx])
            s_k = _read(other.sigma_mm, uv[idx])
            ok = np.isfinite(z_k) & (np.abs(p[idx, 2] - z_k) <= k_sig * np.sqrt(s_i[idx] ** 2 + s_k**2))
            idx, z_k, s_k = idx[ok], z_k[ok], s_k[ok]
            agree[idx] += 1
            # the agreeing depth's point: on frame k's ray through the projection
            x_k = poses[k].inverse().transform(camera.unproject(uv[idx], z_k))
            total[idx] += x_k / s_k[:, None] ** 2
            wsum[idx] += 1.0 / s_k**2
        good = agree >= options.min_consistent_views
        keep.reshape(-1)[flat[good]] = True
        normals_cam = depth_normals(camera, d.depth_mm).reshape(-1, 3)[flat[good]]
        finite = np.all(np.isfinite(normals_cam), axis=1)
        pts.append((total[good] / wsum[good, None])[finite])
        nrm.append((normals_cam @ poses[i].rotation)[finite])  # camera to world: R^T n, as rows n R
        img = images[i] if images[i].ndim == 3 else np.repeat(images[i][..., None], 3, axis=2)
        col.append(img.reshape(-1, 3)[flat[good]][finite])
        sup.append(agree[good][finite] + 1)
        sig.append(1.0 / np.sqrt(wsum[good][finite]))
        advance(progress)
    points = np.concatenate(pts) if pts else np.zeros((0, 3))
    normals = np.concatenate(nrm) if nrm else np.zeros((0, 3))
    colors = np.concatenate(col) if col else np.zeros((0, 3), np.uint8)
    support = np.concatenate(sup) if sup else np.zeros(0, int)
    sigma = np.concatenate(sig) if sig else np.zeros(0)
    kept = len(points)
    if options.merge_mm > 0 and len(points):
        points, normals, colors, support, sigma = _merge(points, normals, colors, support, sigma, options.merge_mm)
    return FusedDepths(PointCloud(points, colors, normals), support, sigma, consistent, candidates - kept, candidates,
                       {"candidates": int(candidates), "consistent": int(kept), "merged": int(len(points))})


def _merge(points, normals, colors, support, sigma, cell_mm):
    """Average the points (and normals, colours) that fall in one ``cell_mm`` voxel; support adds up, and
    sigma is the plain mean's: sqrt(sum sigma²) / n."""
    keys = np.floor(points / cell_mm).astype(np.int64)
    _, inv, count = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)

    def mean(values):
        out = np.zeros((len(count), values.shape[1]))
        np.add.at(out, inv, values)
        return out / count[:, None]

    n = mean(normals)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    s = np.zeros(len(count), int)
    np.add.at(s, inv, support)
    var = np.zeros(len(count))
    np.add.at(var, inv, sigma**2)
    return (mean(points), n, np.clip(np.rint(mean(colors.astype(float))), 0, 255).astype(np.uint8), s,
            np.sqrt(var) / count)


def poisson_mesh(cloud: PointCloud, *, options: DenseOptions = DenseOptions()) -> Mesh:
    """Open3D's screened Poisson surface (Kazhdan & Hoppe 2013) of the fused points and their normals, at
    octree depth ``poisson_depth``, trimmed: a vertex farther than ``trim_mm`` from every fused point is
    interpolation over a hole (or the closed surface Poisson makes around the data) and is dropped with its
    faces. Colours: the nearest fused point's."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    if len(cloud) < 100:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.points))
    pc.normals = o3d.utility.Vector3dVector(cloud.normals)
    mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=options.poisson_depth)
    v = np.asarray(mesh.vertices, dtype=float)
    f = np.asarray(mesh.triangles, dtype=np.int64)
    dist, nearest = cKDTree(cloud.points).query(v)
    keep = dist <= options.trim_mm
    f = f[np.all(keep[f], axis=1)]
    used = np.unique(f)
    index = np.full(len(v), -1, np.int64)
    index[used] = np.arange(len(used))
    mesh.compute_vertex_normals()
    normals = np.asarray(mesh.vertex_normals, dtype=float)[used]
    colors = cloud.colors[nearest[used]] if cloud.colors is not None else None
    return Mesh(v[used], index[f], vertex_colors=colors, vertex_normals=normals)


@dataclass
class DenseMap:
    """The dense stage's result: fused (the consistent points), mesh (the trimmed Poisson surface), depths
    (per frame, None where none), seconds (per step: depth, fusion, mesh)."""

    fused: FusedDepths
    mesh: Mesh
    depths: list[FrameDepth | None]
    seconds: dict

    def summary(self) -> dict:
        made = [d for d in self.depths if d is not None]
        return {"frames_with_depth": len(made), "points": len(self.fused.cloud), **self.fused.counts,
                "mesh_vertices": len(self.mesh.vertices), "mesh_faces": len(self.mesh.faces),
                "seconds": self.seconds}


def build_dense_map(camera: Camera, images: list[np.ndarray], poses: list[Pose], points: np.ndarray, *,
                    options: DenseOptions = DenseOptions(), progress: Progress | None = None) -> DenseMap:
    """Depth per frame, fusion and the mesh (module docstring), one after the other. images : reflectance
    frames; poses : the adjusted ``cam_from_world``; points : (N, 3) mm, the sparse map."""

    t0 = time.perf_counter()
    depths = frame_depths(camera, images, poses, points, options=options, progress=progress)
    t1 = time.perf_counter()
    fused = fuse_depths(camera, images, poses, depths, options=options, progress=progress)
    t2 = time.perf_counter()
    mesh = poisson_mesh(fused.cloud, options=options)
    t3 = time.perf_counter()
    return DenseMap(fused, mesh, depths, {"depth": t1 - t0, "fusion": t2 - t1, "mesh": t3 - t2})
