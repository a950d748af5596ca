"""Which frames look alike, from the images alone: a bag of visual words over the frames' own SIFT.

When a robot's poses are off by millimetres and degrees, the frusta they place on the scene no longer say
which frames overlap (at 15 mm from tissue a 3 mm error moves the footprint by a fifth of its width, and
2 deg of tilt by as much again). Image similarity does not depend on the poses: a vocabulary is learnt
from a sample of the frames' own descriptors (k-means), each frame becomes a tf-idf weighted histogram of
its words, and two frames are as similar as the cosine of their histograms (Sivic & Zisserman 2003; the
retrieval COLMAP's vocabulary-tree matcher performs). Overlapping frames share many words that are rare
elsewhere; the idf weight discounts texture that every frame has.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix

from scope3d.feature.detection import Features


@dataclass(frozen=True)
class RetrievalOptions:
    """How the vocabulary is learnt.

    n_words : int, vocabulary size (default 512). A few hundred words suffice for tens to hundreds of
        frames; the histogram must be sparse enough that unrelated frames share few words.
    sample_per_frame : int, descriptors per frame used to learn the vocabulary (default 300, the
        strongest; the rest are only assigned).
    iterations : int, k-means iterations (default 8: the words need not be optimal, only stable).
    seed : int, seed of the k-means initialisation.
    """

    n_words: int = 512
    sample_per_frame: int = 300
    iterations: int = 8
    seed: int = 0

    def __post_init__(self) -> None:
        if self.n_words < 2 or self.sample_per_frame < 1 or self.iterations < 1:
            raise ValueError("need n_words >= 2, sample_per_frame >= 1, iterations >= 1")


def image_similarity(features: list[Features], options: RetrievalOptions = RetrievalOptions()) -> np.ndarray:
    """Pairwise similarity of the frames, (n, n) float in [0, 1] (cosine of tf-idf word histograms).

    The diagonal is 0 so that a frame is never its own best partner. Frames without features have
    similarity 0 to every other.
    """
    n = len(features)
    sims = np.zeros((n, n))
    sample = [f.descriptors[: options.sample_per_frame] for f in features if len(f)]
    if n < 2 or not sample:
        return sims
    data = np.concatenate(sample).astype(np.float32)
    k = int(min(options.n_words, max(2, len(data) // 4)))
    words = _kmeans(data, k, options.iterations, np.random.default_rng(options.seed))
    counts = np.zeros((n, k))
    for f_id, f in enumerate(features):  # per-frame loop; each frame's assignment is one matrix product
        if len(f):
            counts[f_id] = np.bincount(_nearest(np.asarray(f.descriptors, np.float32), words), minlength=k)
    document_frequency = np.count_nonzero(counts, axis=0)
    idf = np.log(n / np.maximum(document_frequency, 1))
    tf = counts / np.maximum(counts.sum(axis=1, keepdims=True), 1)
    h = tf * idf
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
    sims = np.clip(h @ h.T, 0.0, 1.0)
    np.fill_diagonal(sims, 0.0)
    return sims


def _nearest(data: np.ndarray, words: np.ndarray) -> np.ndarray:
    """Index of the nearest word (k, D) of each row of ``data`` (N, D): |d - w|^2 = |d|^2 - 2 d.w + |w|^2,
    and |d|^2 is the same for every word, so one matrix product decides."""
    return np.argmin(np.einsum("ij,ij->i", words, words)[None, :] - 2.0 * data @ words.T, axis=1)


def _kmeans(data: np.ndarray, k: int, iterations: int, rng: np.random.Generator) -> np.ndarray:
    """Lloyd's k-means from k distinct random rows; (k, D) float32 centres. An empty cluster keeps its
    centre. (SciPy's kmeans2 took minutes here: its k-means++ start loops in Python.)"""
    words = data[rng.choice(len(data), k, replace=False)].copy()
    for _ in range(iterations):
        label = _nearest(data, words)
        count = np.bincount(label, minlength=k)
        sums = csr_matrix((np.ones(len(data), np.float32), (label, np.arange(len(data)))), shape=(k, len(data))) @ data
        filled = count > 0
        words[filled] = sums[filled] / count[filled, None]
    return words
