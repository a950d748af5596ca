"""Pictures of feature matches (reference Fig. 3.4 / 4.5: matches with and without prediction)."""
from __future__ import annotations

import cv2
import numpy as np

from scope3d.io.images import write_image


def save_matches_png(path, img_i, img_j, feat_i, feat_j, match_sets, titles, *, max_lines: int = 80) -> None:
    """Side-by-side pairs with lines for (a random subset of) matches, one row per match set.

    img_i, img_j : (H, W, 3) or (H, W) uint8 frames; feat_i, feat_j : their :class:`~scope3d.feature.detection.Features`;
    match_sets : :class:`~scope3d.feature.matching.PairMatches` per row; titles : one per row. At most
    ``max_lines`` matches per row are drawn (a seeded subset). Writes a PNG at ``path``.
    """
    rows = []
    rng = np.random.default_rng(0)
    for m, title in zip(match_sets, titles):
        canvas = np.concatenate([img_i, img_j], axis=1).copy()
        if canvas.ndim == 2:
            canvas = np.repeat(canvas[..., None], 3, axis=2)
        w = img_i.shape[1]
        idx = np.arange(len(m))
        if len(idx) > max_lines:
            idx = rng.choice(idx, max_lines, replace=False)
        for k in idx:
            p = tuple(int(v) for v in np.rint(feat_i.keypoints[m.idx_i[k]]))
            q = tuple(int(v) for v in np.rint(feat_j.keypoints[m.idx_j[k]] + [w, 0]))
            color = tuple(int(c) for c in rng.integers(60, 255, 3))
            cv2.line(canvas, p, q, color, 1, cv2.LINE_AA)
            cv2.circle(canvas, p, 3, color, 1)
            cv2.circle(canvas, q, 3, color, 1)
        cv2.putText(canvas, title, (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 0), 2, cv2.LINE_AA)
        rows.append(canvas)
    write_image(path, np.concatenate(rows, axis=0))
