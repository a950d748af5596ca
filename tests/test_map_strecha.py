"""Guided matching on real high-resolution photographs with calibrated poses (issue 34, "Full resolution").

The Strecha Herz-Jesu-P8 scene (../shared/data beside the repo; 3072 x 2048, metric calibrated cameras),
at half resolution to stay small: views 0000 and 0003, about 3 m apart around the facade. Their depth prior
(the map's, 6.8-20 m) sweeps each feature's ray into an epipolar segment longer than the sampled search
allows (2 ``max_radius_px``) for every feature; before issue 34 such segments were dropped, the pair was
left without a single match and ``scope3d map`` stopped with "no feature could be matched between frames".
A segment that long is still a strip a few pixels wide: it must be searched, and (the guided matcher's
point) find at least the matches that the exhaustive search finds, with every match inside its strip.
The scene is read by the loader of ``benchmarks/bench_localize_real.py`` itself (one copy of the reader).
"""
from __future__ import annotations

import importlib
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from scope3d.feature.detection import detect
from scope3d.feature.matching import match_exhaustive, match_guided
from scope3d.pipelines.surgical_map import MAP_PRESETS, run

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "benchmarks" / "bench_localize_real.py"
SCENE = REPO.parent / "shared" / "data" / "strecha_herz_jesus_p8"
VIEWS = [0, 3]
SCALE = 0.5


@pytest.fixture(scope="module")
def mapped(tmp_path_factory):
    """The two views (calibrated poses) and their map with preset ``photograph``."""
    if not (SCENE / "gt_dense_cameras").is_dir():
        pytest.fail(f"real data missing: {SCENE} (see /work/shared/data/README.md)")
    sys.path.insert(0, str(BENCH.parent))
    bench = importlib.import_module(BENCH.stem)
    work = tmp_path_factory.mktemp("strecha")
    ds = bench.subset(bench.strecha(work, SCENE.name, SCALE), VIEWS)
    return ds, run(replace(MAP_PRESETS["photograph"], figures=False), ds, work / "map")


def test_strecha_pair_maps_with_guided_matching(mapped):
    _, res = mapped
    assert [m.method for m in res.matching.matches] == ["guided"]
    assert len(res.matching.matches[0]) >= MAP_PRESETS["photograph"].matching.min_matches
    assert sorted(np.unique(res.sparse.tracks.frame).tolist()) == [0, 1]  # both views hold points


def test_long_segments_find_what_exhaustive_search_finds(mapped):
    ds, res = mapped
    options = MAP_PRESETS["photograph"]
    prior = res.matching.depth_prior
    fi, fj = (detect(ds.frame(k), ds.camera, options=options.features) for k in range(2))
    guided = match_guided(ds.camera, fi, fj, ds.poses[0], ds.poses[1], prior, options=options.matching)
    exhaustive = match_exhaustive(ds.camera, fi, fj, options.matching)
    assert guided.method == "guided" and len(exhaustive) >= options.matching.min_matches
    assert len(guided) >= len(exhaustive)
    # every guided match lies within the exact-pose window (base radius) of its feature's segment
    pose_i, pose_j = ds.poses[0].pose, ds.poses[1].pose
    p0, p1 = (ds.camera.project_world(pose_j, pose_i.inverse().transform(ds.camera.unproject(fi.keypoints[guided.idx_i], z)))
              for z in (prior.near_mm, prior.far_mm))
    q = fj.keypoints[guided.idx_j]
    d = p1 - p0
    t = np.clip(np.einsum("ij,ij->i", q - p0, d) / np.einsum("ij,ij->i", d, d), 0.0, 1.0)
    gap = np.linalg.norm(q - p0 - t[:, None] * d, axis=1)
    assert gap.max() <= options.matching.base_radius_px
