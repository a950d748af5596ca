"""Localization on real photographs against COLMAP on the same split (issue 34).

The Middlebury templeSparseRing (../shared/data beside the repo): the map from the 8 even views with their
calibrated poses, the 8 odd views localized from their images alone, each error against the odd view's
calibrated pose. COLMAP (pycolmap, a declared ``peers`` dependency) runs in the same process on the same
split: SIFT, exhaustive matching, ``triangulate_points`` with the even views' poses, each odd view's 2-D/3-D
correspondences through its verified matches, ``estimate_and_refine_absolute_pose``. Both are driven by the
functions of ``benchmarks/bench_localize_real.py`` themselves.

What is compared is the issue's target taken whole: the median position and orientation errors over *every*
odd view, a view given no pose counting as an infinite error (so a localizer cannot win the median by refusing
the hard views), must be no worse than COLMAP's; and no pose may be wrong, i.e. more than 10x COLMAP's median
position error (the issue's definition). Before issue 34 (a map point matched by one representative
descriptor only) scope3d gave 5 of the 8 views a pose on this split: its median over every view was 5.9 mm
against COLMAP's 3.8 mm.
"""
from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "benchmarks" / "bench_localize_real.py"
PAR = REPO.parent / "shared" / "data" / "middlebury_templeSparseRing" / "templeSR_par.txt"


@pytest.fixture(scope="module")
def temple_split(tmp_path_factory):
    if not PAR.is_file():
        pytest.fail(f"real data missing: {PAR} (see /work/shared/data/README.md)")
    sys.path.insert(0, str(BENCH.parent))
    bench = importlib.import_module(BENCH.stem)
    work = tmp_path_factory.mktemp("temple_split")
    return bench.scene_run(bench.temple(work), work, "temple_sparse_ring", diagnose=False)


def _median_over_every_view(rows: list[dict], key: str) -> float:
    return float(np.median([r.get(key, np.inf) for r in rows]))


def test_odd_temple_views_localized_no_worse_than_colmap(temple_split):
    ours, theirs = temple_split["scope3d"]["views"], temple_split["colmap"]["views"]
    assert [r["view"] for r in ours] == [r["view"] for r in theirs]
    for key in ("position_error_mm", "orientation_error_deg"):
        assert _median_over_every_view(ours, key) <= _median_over_every_view(theirs, key), key


def test_no_wrong_pose_on_the_temple_split(temple_split):
    wrong_mm = temple_split["wrong_if_position_error_above_mm"]
    assert np.isfinite(wrong_mm)
    errors = [r["position_error_mm"] for r in temple_split["scope3d"]["views"] if "position_error_mm" in r]
    assert errors and max(errors) <= wrong_mm
