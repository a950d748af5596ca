"""The localizer's global match (relocalization) on real photographs: exactly OpenCV's brute-force
ratio-test matches (issue 34: its two nearest neighbours now come from one BLAS product, a third of the time).

Two views of the Middlebury templeSparseRing (../shared/data beside the repo): the SIFT features of one stand
in for a map's points (their descriptors, positions irrelevant here), the other is the query. SIFT's
descriptors are integers, so the matrix-product distances are exact and the matches must be identical, not
close.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from scope3d.feature import matching
from scope3d.feature.detection import FEATURE_PRESETS, detect
from scope3d.io.map_points import MapPoints
from scope3d.sensor.camera import Camera
from scope3d.sfm.localization import Localizer, LocalizerOptions, _one_to_one

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "middlebury_templeSparseRing"


def _grey(name: str) -> np.ndarray:
    path = DATA / name
    if not path.is_file():
        pytest.fail(f"real data missing: {path} (see /work/shared/data/README.md)")
    return cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)


def test_global_match_equals_opencv_brute_force_on_real_views(monkeypatch):
    map_grey, query_grey = _grey("templeSR0001.png"), _grey("templeSR0002.png")
    h, w = map_grey.shape
    camera = Camera(w, h, 1520.0, 1520.0, w / 2 - 0.5, h / 2 - 0.5)
    options = LocalizerOptions(features=FEATURE_PRESETS["photograph"], tracking=False)
    mapped = detect(map_grey, camera, options=options.features)
    n = len(mapped.keypoints)
    points = MapPoints(np.zeros((n, 3)), mapped.descriptors, np.ones(n, np.int32), np.zeros((n, 3), np.uint8))
    query = detect(query_grey, camera, options=options.features).descriptors
    assert len(query) > 500 and n > 500
    monkeypatch.setattr(matching, "_NEAREST_BLOCK_ENTRIES", 256 * n)  # the product in blocks of 256 features

    ids, feat = Localizer(points, camera, options)._match_global(query)

    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(query, points.descriptors, k=2)
    rows = [(p[0].trainIdx, p[0].queryIdx, p[0].distance) for p in knn
            if p[0].distance < options.matching.ratio * p[1].distance]
    want_ids, want_feat, d = (np.array(v) for v in zip(*rows))
    want_ids, want_feat = _one_to_one(want_ids.astype(np.int64), want_feat.astype(np.int64), d**2)
    assert len(ids) > 50
    assert np.array_equal(ids, want_ids) and np.array_equal(feat, want_feat)
