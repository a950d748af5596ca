"""Which frames overlap: pair selection from poses and a depth prior.

:func:`frame_overlap` / :func:`select_pairs` — the reference's first use of known poses: "by knowing each
position of cameras, the frame pairs with overlap can be easily discovered". A frame's field of view is
placed on the scene at a depth prior; the fraction of it that lands inside the other frame's field of
view is the pair's overlap.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import minimum_spanning_tree

from scope3d.feature.depth_prior import DepthPrior
from scope3d.geometry.pose import Pose
from scope3d.sensor.camera import Camera


@dataclass(frozen=True)
class PairOptions:
    """Which frame pairs to match.

    min_overlap : float, minimum fraction of one frame's field of view (placed at the depth prior)
        seen by the other (default 0.25; the reference planned >= 50 % between grid neighbours, so
        0.25 keeps diagonal and second neighbours, which tie the tracks together).
    max_pairs_per_frame : int, keep at most this many best-overlapping partners per frame
        (default 10; bounds the cost on dense trajectories). 0 = no limit.
    max_pairs_per_direction : int, keep at most this many best-scored partners in each direction of
        camera motion (default 0 = no such limit). The baseline to a partner, in the frame's camera
        coordinates, is classed by its dominant axis (+-x, +-y, +-z); partners whose baseline subtends
        less than 1 deg at the prior depth (the same place, no triangulation) form a seventh class.
        With 1, a ring links each view to its nearest neighbour on either side, a raster to its four
        neighbours, whatever the spacing. Why not more partners: tracks are joined as connected components of the match graph, and
        every extra pair adds a few wrong matches that glue two tracks into one holding two features
        of a frame, which is dropped whole (:func:`~scope3d.feature.tracks.build_tracks`). A point's views are
        already connected by the chain of nearest neighbours, and the glue grows with pairs per frame
        x track length, i.e. with the density of views: on a 48-view ring rendered around the dome
        phantom, 24 % of the matched features were lost so with the 4 best partners and 64 % with all
        partners within 35 deg, none with 1 per direction (benchmarks/bench_map_views.py).
    samples_per_side : int, the field of view is sampled on this many pixels per side (default 16).
    max_view_angle_deg : float, pairs whose optical axes differ by more are skipped (default 60 deg:
        SIFT descriptors stop matching beyond ~50-60 deg of viewpoint change). Partners are ranked by
        overlap x cos(axis angle), so around an object (where every frustum "overlaps" at the depth
        prior) the nearest viewpoints come first. With ``max_pairs_per_direction``, a frame the limit would
        leave without any partner keeps its nearest viewpoint and the nearest in the opposite direction
        (the temple's 8 even views, 45 deg apart: 8 pairs and 549 points instead of 2 pairs and 216 at 35 deg).
    """

    min_overlap: float = 0.25
    max_pairs_per_frame: int = 10
    samples_per_side: int = 16
    max_view_angle_deg: float = 60.0
    max_pairs_per_direction: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.min_overlap <= 1:
            raise ValueError(f"min_overlap must be in [0, 1], got {self.min_overlap}")
        if self.max_pairs_per_frame < 0 or self.max_pairs_per_direction < 0 or self.samples_per_side < 2:
            raise ValueError("max_pairs_per_frame and max_pairs_per_direction must be >= 0 and samples_per_side >= 2")
        if not 0 < self.max_view_angle_deg <= 180:
            raise ValueError(f"max_view_angle_deg must be in (0, 180], got {self.max_view_angle_deg}")


def fov_samples(camera: Camera, n: int) -> np.ndarray:
    """(K, 2) pixels on an n x n grid inside the valid image (circular mask respected)."""
    u = np.linspace(0, camera.width - 1, n)
    v = np.linspace(0, camera.height - 1, n)
    grid = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    return grid[camera.in_image(grid)]


def frame_overlap(camera: Camera, poses: list[Pose], depth_prior: DepthPrior, *, samples_per_side: int = 16) -> np.ndarray:
    """Pairwise overlap of the frames' fields of view placed at the depth prior.

    poses : n ``cam_from_world`` poses (mm). Returns (n, n) float in [0, 1]: entry [a, b] is the fraction
    of frame a's field of view, back-projected to depth ``depth_prior.mid_mm`` in frame a, that projects
    inside frame b. The matrix is symmetrised with the minimum (both must see each other).
    """
    if not poses:
        raise ValueError("no poses given")
    pix = fov_samples(camera, samples_per_side)
    pts_cam = camera.unproject(pix, np.full(len(pix), depth_prior.mid_mm))
    n = len(poses)
    rot = np.stack([p.rotation for p in poses])
    trans = np.stack([p.translation for p in poses])
    # world points of every frame's footprint: (n, K, 3)
    world = np.einsum("nji,nkj->nki", rot, pts_cam[None] - trans[:, None, :])
    overlap = np.zeros((n, n))
    for b in range(n):  # per-frame loop; all samples of all frames at once
        uv = camera.project(world.reshape(-1, 3) @ rot[b].T + trans[b]).reshape(n, -1, 2)
        overlap[:, b] = camera.in_image(uv.reshape(-1, 2)).reshape(n, -1).mean(axis=1)
    np.fill_diagonal(overlap, 1.0)
    return np.minimum(overlap, overlap.T)


def select_pairs(
    camera: Camera, poses: list[Pose], depth_prior: DepthPrior, *, options: PairOptions = PairOptions()
) -> list[tuple[int, int, float]]:
    """Frame pairs worth matching, as (i, j, overlap) with i < j, best overlap first.

    Each frame keeps its best-scored partners (overlap x cos(axis angle)) within the limits of
    ``options``: per direction of camera motion first (``max_pairs_per_direction``), then per frame
    (``max_pairs_per_frame``); a pair is matched when either frame keeps it.
    """
    ov = frame_overlap(camera, poses, depth_prior, samples_per_side=options.samples_per_side)
    n = len(poses)
    axes = np.stack([p.optical_axis for p in poses])
    cos_axes = np.clip(axes @ axes.T, -1.0, 1.0)
    score = ov * np.maximum(cos_axes, 0.0)
    keep = np.zeros((n, n), dtype=bool)
    cand = (ov >= options.min_overlap) & (cos_axes >= np.cos(np.deg2rad(options.max_view_angle_deg)))
    np.fill_diagonal(cand, False)
    centres = np.stack([p.centre for p in poses])
    # the view-angle limit never isolates a frame: one with no partner within it (a sparse ring, views 45 deg
    # apart) keeps its nearest viewpoint (axes within 90 deg) and the nearest in the opposite direction of
    # motion (a ring's neighbours on either side; _motion_direction's classes 2c and 2c + 1 are opposite)
    isolated = ~cand.any(axis=1)
    reach = (ov >= options.min_overlap) & (cos_axes > 0.0)
    np.fill_diagonal(reach, False)
    for a in range(n):
        if isolated[a] and options.max_pairs_per_direction:
            partners = np.flatnonzero(reach[a])
            partners = partners[np.argsort(-cos_axes[a, partners], kind="stable")]
            cls = _motion_direction(poses[a], centres[partners], depth_prior.mid_mm)
            if len(partners):
                sides = (cls == cls[0]) | ((cls == (cls[0] ^ 1)) & (cls[0] < 6))
                _, first = np.unique(cls[sides], return_index=True)
                keep[a, partners[sides][first]] = True
            continue
        partners = np.flatnonzero(cand[a])
        partners = partners[np.argsort(-score[a, partners], kind="stable")]
        if options.max_pairs_per_direction:
            cls = _motion_direction(poses[a], centres[partners], depth_prior.mid_mm)
            rank = np.zeros(len(partners), int)  # rank within its class, best first
            for c in np.unique(cls):
                rank[cls == c] = np.arange(np.count_nonzero(cls == c))
            partners = partners[rank < options.max_pairs_per_direction]
        if options.max_pairs_per_frame:
            partners = partners[: options.max_pairs_per_frame]
        keep[a, partners] = True
    keep = keep | keep.T
    ii, jj = np.nonzero(np.triu(keep, 1))
    order = np.argsort(-score[ii, jj], kind="stable")
    return [(int(ii[k]), int(jj[k]), float(ov[ii[k], jj[k]])) for k in order]


def _motion_direction(pose: Pose, centres: np.ndarray, depth_mm: float) -> np.ndarray:
    """Direction class (M,) int of the baselines from ``pose``'s centre to ``centres`` (M, 3) mm:
    0..5 for the dominant axis of the baseline in camera coordinates (+x, -x, +y, -y, +z, -z), 6 when
    the baseline subtends less than 1 deg at ``depth_mm`` (the same place: no triangulation angle)."""
    b = (np.asarray(centres, float).reshape(-1, 3) - pose.centre) @ pose.rotation.T
    axis = np.argmax(np.abs(b), axis=1)
    cls = 2 * axis + (b[np.arange(len(b)), axis] < 0)
    cls[np.linalg.norm(b, axis=1) < np.tan(np.deg2rad(1.0)) * depth_mm] = 6
    return cls


def best_partner_pairs(pairs: list[tuple[int, int, float]], n_frames: int, per_frame: int = 1) -> list[int]:
    """Indices of each frame's ``per_frame`` best-scored pairs (``pairs`` sorted best first, as
    :func:`select_pairs` returns them)."""
    count = np.zeros(n_frames, int)
    chosen = []
    for k, (i, j, _) in enumerate(pairs):
        if count[i] < per_frame or count[j] < per_frame:
            chosen.append(k)
            count[i] += 1
            count[j] += 1
    return chosen


def spanning_pairs(pairs: list[tuple[int, int, float]], n_frames: int) -> list[int]:
    """Indices (sorted) of each frame's best partner, plus the best-scored pairs that join what those
    leave apart: a maximum spanning forest grown from the best partners (Kruskal, through
    :func:`scipy.sparse.csgraph.minimum_spanning_tree` on the pairs' ranks), so that one adjustment of
    these pairs' tracks ties every frame to every other it can reach. ``pairs`` sorted best first."""
    chosen = set(best_partner_pairs(pairs, n_frames, per_frame=1))
    if not pairs:
        return []
    ii = np.array([p[0] for p in pairs])
    jj = np.array([p[1] for p in pairs])
    # ranks as weights, best partners below every other pair: Kruskal takes them first, then joins the
    # groups they leave with the best-ranked pairs between them
    weight = np.arange(len(pairs), dtype=float) + 2.0
    weight[sorted(chosen)] = 1.0
    tree = minimum_spanning_tree(coo_matrix((weight, (ii, jj)), shape=(n_frames, n_frames)).tocsr()).tocoo()
    index = {(int(i), int(j)): k for k, (i, j) in enumerate(zip(ii, jj))}
    for a, b in zip(tree.row, tree.col):
        chosen.add(index.get((int(a), int(b)), index.get((int(b), int(a)))))
    return sorted(chosen)
