"""Tracks from pairwise feature matches.

:func:`build_tracks` joins pairwise matches into tracks as connected components of the graph whose nodes
are (frame, feature) and whose edges are matches. A component that holds two different features of the
same frame is inconsistent (a wrong match somewhere along it) and is dropped whole, as COLMAP does, or
split into consistent tracks (:func:`split_components`, what the map does: ``TrackOptions.split_inconsistent``).
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from scope3d.feature.detection import Features
from scope3d.feature.matching import PairMatches
from scope3d.scene.tracks import Tracks


def match_components(features: list[Features], matches: list[PairMatches]) -> tuple[np.ndarray, ...]:
    """The match graph's connected components (scipy.sparse.csgraph). Returns, for every matched feature,
    its node (M,) (offset of its frame's first feature + its index), frame (M,), component label (M,) and
    whether its component is inconsistent (M,) bool: holds two features of one frame."""
    offsets = np.concatenate([[0], np.cumsum([len(f) for f in features])])
    n_nodes = int(offsets[-1])
    src = [offsets[m.i] + m.idx_i for m in matches if len(m)]
    dst = [offsets[m.j] + m.idx_j for m in matches if len(m)]
    if not src:
        e = np.zeros(0, np.int64)
        return e, e, e, np.zeros(0, bool)
    src, dst = np.concatenate(src), np.concatenate(dst)
    graph = coo_matrix((np.ones(len(src), np.int8), (src, dst)), shape=(n_nodes, n_nodes))
    _, label = connected_components(graph, directed=False)
    node = np.unique(np.concatenate([src, dst]))
    frame = np.searchsorted(offsets, node, side="right") - 1
    lab = label[node]
    # inconsistent components: a (label, frame) key seen twice
    key = lab.astype(np.int64) * len(features) + frame
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    return node, frame, lab, np.isin(lab, np.unique(lab[cnt[inv] > 1]))


def build_tracks(features: list[Features], matches: list[PairMatches], *, min_track_length: int = 2,
                 split_inconsistent: bool = False) -> Tracks:
    """Tracks = connected components of the match graph (:func:`match_components`); components with two
    features in one frame are dropped (or, with ``split_inconsistent``, split: :func:`split_components`), and
    so are those shorter than ``min_track_length``."""
    offsets = np.concatenate([[0], np.cumsum([len(f) for f in features])])
    node, frame, lab, conflicted = match_components(features, matches)
    if len(node) == 0:
        e = np.zeros(0, np.int64)
        return Tracks(e, e, e, np.zeros((0, 2)), np.zeros((0, 3), np.uint8), np.zeros((0, 3)))
    if split_inconsistent and conflicted.any():
        lab = lab.copy()
        lab[conflicted] = int(lab.max()) + 1 + split_components(features, matches, node[conflicted])
        conflicted = np.zeros_like(conflicted)
    size = np.bincount(lab)
    ok = ~conflicted & (size[lab] >= min_track_length)
    node, frame, lab = node[ok], frame[ok], lab[ok]
    order = np.lexsort((frame, lab))
    node, frame, lab = node[order], frame[order], lab[order]
    _, track = np.unique(lab, return_inverse=True)
    feature = node - offsets[frame]
    pixels = np.empty((len(node), 2))
    col = np.empty((len(node), 3))
    for f in np.unique(frame):  # per-frame loop
        sel = frame == f
        pixels[sel] = features[f].keypoints[feature[sel]]
        col[sel] = features[f].colors[feature[sel]]
    n_tracks = int(track.max()) + 1 if len(track) else 0
    counts = np.bincount(track, minlength=n_tracks)[:, None]
    colors = np.stack([np.bincount(track, col[:, c], n_tracks) for c in range(3)], axis=1) / np.maximum(counts, 1)
    return Tracks(track.astype(np.int64), frame.astype(np.int64), feature.astype(np.int64), pixels,
                  np.clip(np.rint(colors), 0, 255).astype(np.uint8))


def split_components(features: list[Features], matches: list[PairMatches], nodes: np.ndarray) -> np.ndarray:
    """Consistent tracks out of inconsistent components: the matches among ``nodes`` (M,) (sorted, as
    :func:`match_components` numbers them) joined greedily, most similar descriptors first, each join refused
    when it would put two features of one frame into one track. Returns a label (M,) per node, 0-based.

    Why: a component is inconsistent when a wrong match glues two tracks, and the longer the tracks the more
    likely that is. Dropping it whole loses the best-observed points: through a wide lens, where every frame
    sees most of the scene, 39 % of the matched features of the 30-frame dome (seed 5, 140 deg fisheye) sat
    in such components, holding its longest tracks (up to 89 features). A wrong match is the least similar
    link between two right tracks, so it comes last and is refused."""
    offsets = np.concatenate([[0], np.cumsum([len(f) for f in features])])
    frame_of = np.searchsorted(offsets, nodes, side="right") - 1
    src, dst, dist = [], [], []
    for m in matches:
        if not len(m):
            continue
        a, b = offsets[m.i] + m.idx_i, offsets[m.j] + m.idx_j
        keep = np.isin(a, nodes)  # both ends lie in one component: one end in ``nodes`` is enough
        if keep.any():
            src.append(a[keep])
            dst.append(b[keep])
            diff = features[m.i].descriptors[m.idx_i[keep]] - features[m.j].descriptors[m.idx_j[keep]]
            dist.append(np.einsum("ij,ij->i", diff, diff))
    parent = np.arange(len(nodes))
    frames: list[set] = [{int(f)} for f in frame_of]

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    if src:
        src_i = np.searchsorted(nodes, np.concatenate(src))
        dst_i = np.searchsorted(nodes, np.concatenate(dst))
        for e in np.argsort(np.concatenate(dist), kind="stable"):  # per-match loop, most similar first
            ra, rb = root(int(src_i[e])), root(int(dst_i[e]))
            if ra == rb or not frames[ra].isdisjoint(frames[rb]):
                continue
            if len(frames[ra]) < len(frames[rb]):
                ra, rb = rb, ra
            parent[rb] = ra
            frames[ra] |= frames[rb]
    roots = np.array([root(k) for k in range(len(nodes))])
    return np.unique(roots, return_inverse=True)[1]


#: Observations whose descriptors are gathered at once by :func:`track_descriptors` (8 MB of float32).
_BLOCK_ROWS = 16384


def track_descriptors(features: list[Features], tracks: Tracks) -> np.ndarray:
    """One representative SIFT descriptor per track: the observation's descriptor nearest the track's mean
    (a medoid-like choice, as COLMAP keeps one real descriptor rather than an average that no image shows).

    Returns (n_tracks, 128) float32, in the scale of :class:`~scope3d.feature.detection.Features`.

    The observations' descriptors are gathered in blocks, twice (for the means, then for the distances),
    instead of all at once: at a 1,000-frame map's 7e5 observations the whole array, its difference to the
    means and that difference squared took 1.1 GB. The means are accumulated in the observations' order
    and each distance is the same expression per row, so the result is the same to the bit.
    """
    n = tracks.n_tracks
    if n == 0:
        return np.zeros((0, 128), np.float32)
    blocks = [np.arange(lo, min(lo + _BLOCK_ROWS, tracks.n_observations))
              for lo in range(0, tracks.n_observations, _BLOCK_ROWS)]
    counts = np.bincount(tracks.track, minlength=n).astype(np.float32)
    mean = np.zeros((n, 128), np.float32)
    for rows in blocks:
        np.add.at(mean, tracks.track[rows], _observation_descriptors(features, tracks, rows))
    mean /= counts[:, None]
    dist = np.empty(tracks.n_observations, np.float32)
    for rows in blocks:
        dist[rows] = np.sum((_observation_descriptors(features, tracks, rows) - mean[tracks.track[rows]]) ** 2, axis=1)
    # the observation with the least distance per track: sort by (track, distance), take each track's first
    order = np.lexsort((dist, tracks.track))
    first = order[np.r_[True, tracks.track[order][1:] != tracks.track[order][:-1]]]
    return _observation_descriptors(features, tracks, first)


def observation_descriptors(features: list[Features], tracks: Tracks) -> np.ndarray:
    """(n_observations, 128) float32: every observation's own descriptor, in the tracks' order (the point
    of row k is ``tracks.track[k]``). Localization matches a new frame against all of them
    (:class:`~scope3d.io.map_points.MapPoints`)."""
    return _observation_descriptors(features, tracks, np.arange(tracks.n_observations))


def _observation_descriptors(features: list[Features], tracks: Tracks, rows: np.ndarray) -> np.ndarray:
    """(len(rows), 128) float32 descriptors of the observations ``rows`` (indices into ``tracks``)."""
    frame = tracks.frame[rows]
    feature = tracks.feature[rows]
    out = np.empty((len(rows), 128), np.float32)
    if len(rows) == 0:
        return out
    order = np.argsort(frame, kind="stable")
    bounds = np.flatnonzero(np.r_[True, frame[order][1:] != frame[order][:-1], True])
    for lo, hi in zip(bounds[:-1], bounds[1:]):  # per-frame loop
        sel = order[lo:hi]
        out[sel] = features[frame[sel[0]]].descriptors[feature[sel]]
    return out
