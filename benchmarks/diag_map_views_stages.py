"""Where the points go as views grow: counts after every stage of the known-pose map on rings of views.

For each ring (the Middlebury templeSparseRing sub-sampled to 8, 12, 16 views; the dome phantom's rendered
ring of 8 to 64 views, as in bench_map_views.py) and the ``photograph`` preset with each SIFT contrast
threshold and pair rule of RULES (or those named on the command line): features, pairs, matches, matched features, match-graph components, features lost in
components holding two features of one frame (dropped whole by build_tracks), tracks >= 2 views, tracks
kept by triangulation and adjustment (reprojection gate, angle), and the final points with their mean
reprojection error. Prints a table and writes benchmarks/results/map_views_stages.json.
    PYTHONPATH=src .venv/bin/python benchmarks/diag_map_views_stages.py
"""
from __future__ import annotations

import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_map_views import PAR, PHOTOGRAPH, dome_rings, ring_subset

from scope3d.cli.main import main as cli
from scope3d.feature.pairs import PairOptions
from scope3d.feature.tracks import build_tracks, match_components
from scope3d.io.dataset import load_dataset
from scope3d.pipelines.surgical_map import detect_features, match_frames, reconstruct

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
# the photograph preset (contrast 0.02, one partner per direction) is contrast_0.02_per_direction_1; before
# this study its contrast threshold was OpenCV's 0.04
PAIR_RULES = {
    "per_direction_1": PHOTOGRAPH.pairs,
    "per_direction_2": replace(PHOTOGRAPH.pairs, max_pairs_per_direction=2),
    "all_within_35deg": PairOptions(min_overlap=0.2, max_pairs_per_frame=0, max_view_angle_deg=35.0),
}
RULES = {f"contrast_{ct}_{name}": replace(PHOTOGRAPH, pairs=pairs, features=replace(PHOTOGRAPH.features, contrast_threshold=ct))
         for ct in (0.04, 0.02, 0.01) for name, pairs in PAIR_RULES.items()}


def stage_counts(ds, options) -> dict:
    frames = [ds.frame(k) for k in range(len(ds))]
    features = detect_features(options, ds, frames)
    matching = match_frames(options, ds, features)
    node, _, lab, bad = match_components(features, matching.matches)
    tracks = build_tracks(features, matching.matches, min_track_length=options.tracks.min_track_length)
    sparse = reconstruct(options, ds, features, matching)
    return {"n_views": len(ds), "features": int(sum(len(f) for f in features)), "pairs": len(matching.pairs),
            "matches": matching.n_matches, "matched_features": int(len(node)),
            "components": int(len(np.unique(lab))), "conflicted_components": int(len(np.unique(lab[bad]))),
            "features_in_conflicted_components": int(bad.sum()), "tracks": tracks.n_tracks,
            "track_observations": tracks.n_observations, "points": sparse.tracks.n_tracks,
            "observations": sparse.tracks.n_observations,
            "mean_reprojection_error_px": round(sparse.mean_reprojection_error_px, 4)}


def main(rules: list[str]) -> None:
    rows = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        assert cli(["import", "middlebury", str(PAR), "--out", str(tmp / "temple"), "--quiet"]) == 0
        temple = load_dataset(tmp / "temple")
        temples = (ring_subset(temple, n, tmp / f"temple{n}") for n in (8, 12, 16))
        for family, datasets in (("temple", temples), ("dome_ring", dome_rings(tmp))):
            for ds in datasets:
                for rule in rules:
                    row = {"family": family, "rule": rule, **stage_counts(ds, RULES[rule])}
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "map_views_stages.json").write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:] or list(RULES))
