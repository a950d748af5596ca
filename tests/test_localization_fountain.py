"""Relocalization at 1 Mpx with SIFT on the half-size frame (``LocalizerOptions.sift_image_scale``), on real
photographs (issue 34).

The Strecha fountain-P11 (../shared/data beside the repo) resized to 1229 x 819 (1.0 Mpx) as
``benchmarks/bench_localize_speed.py`` does: the map from the 6 even views with their calibrated poses, each
of the 5 odd views relocalized (no prior) at full and at half SIFT resolution. Half-size SIFT must localize
every view the full-size one does, and no pose may be wrong in the issue's sense: more than 10x the
full-resolution median position error (the same definition as against COLMAP's).
"""
from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

from scope3d.sfm.localization import Localizer, LocalizerOptions

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "benchmarks" / "bench_localize_real.py"
SCENE = REPO.parent / "shared" / "data" / "strecha_fountain_p11"
WRONG_FACTOR = 10.0


@pytest.fixture(scope="module")
def fountain_split(tmp_path_factory):
    if not (SCENE / "gt_dense_cameras").is_dir():
        pytest.fail(f"real data missing: {SCENE} (see /work/shared/data/README.md)")
    sys.path.insert(0, str(BENCH.parent))
    bench = importlib.import_module(BENCH.stem)
    work = tmp_path_factory.mktemp("fountain")
    ds = bench.strecha(work, "strecha_fountain_p11", 0.4)
    label = "strecha_fountain_p11_x0.4"
    even, odd = list(range(0, len(ds), 2)), list(range(1, len(ds), 2))
    points, _ = bench.scope3d_map(ds, even, work / "map", bench.map_options(label))
    return ds, points, odd


def _errors(ds, points, odd, options) -> list[float]:
    out = []
    with Localizer(points, ds.camera, options) as loc:
        for i in odd:
            loc.reset()
            r = loc.localize(ds.frame(i))
            out.append(r.pose.distance_to(ds.poses[i].pose)[0] if r.ok else np.inf)
    return out


def test_half_size_sift_relocalizes_every_view_at_1_mpx(fountain_split):
    ds, points, odd = fountain_split
    assert ds.camera.width * ds.camera.height > 0.9e6
    full = _errors(ds, points, odd, LocalizerOptions(tracking=False))
    half = _errors(ds, points, odd, LocalizerOptions(tracking=False, sift_image_scale=0.5))
    assert np.all(np.isfinite(full))
    assert np.all(np.isfinite(half)), half
    assert max(half) <= WRONG_FACTOR * float(np.median(full)), (half, full)
