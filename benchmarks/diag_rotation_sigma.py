"""Is the coarse pass's relative-rotation sigma honest, and would an honest one improve the averaging?

On one phantom dataset (``scope3d phantom dome --seed S --pose-noise N``): the coarse pass
(sfm.coarse_poses) on the map's default features; per verified pair its relative-rotation error against
the truth, its stated sigma (worst axis) and the baseline; then rotation averaging
(estimators.averaging.average_rotations) with the stated sigmas, with short pairs' sigmas doubled (a
parallax floor), with truth-informed sigmas max(sigma, true error) (no sigma rule can weigh the pairs
better than the truth does) and with equal sigmas. Rotation error of the averaged rotations against the
truth: absolute, and after removing the best common rotation (the gauge). Prints each dataset's rows and
writes them all to benchmarks/results/rotation_sigma.json (docs/surgical_map.md's table). Run (each dataset
about a minute; the table's five: seed 0 and 53 at 1 mm, 41 and 53 at 3 mm, 67 at 5 mm):
    for sn in "0 1" "53 1" "41 3" "53 3" "67 5"; do set -- $sn
        scope3d phantom dome --seed $1 --pose-noise $2 --out /tmp/dome_s$1_n$2; done
    PYTHONPATH=src .venv/bin/python benchmarks/diag_rotation_sigma.py /tmp/dome_s*_n*
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from scope3d.estimators.averaging import average_rotations
from scope3d.geometry.rotation import rotation_angle_between
from scope3d.io.dataset import load_dataset
from scope3d.pipelines.surgical_map import MAP_PRESETS, detect_features
from scope3d.sfm.coarse_poses import coarse_poses
from scope3d.utils.jsonio import write_json

OUT = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "rotation_sigma.json"


def rotation_errors_deg(rotations, true) -> tuple[float, float]:
    """Mean error (deg) of rotations (n, 3, 3) against the true poses: absolute, and after the best
    common rotation is removed."""
    absolute = [rotation_angle_between(r, t.rotation) for r, t in zip(rotations, true)]
    common = Rotation.from_matrix(np.stack([t.rotation.T @ r for r, t in zip(rotations, true)])).mean().as_matrix()
    relative = [rotation_angle_between(r @ common.T, t.rotation) for r, t in zip(rotations, true)]
    return float(np.degrees(np.mean(absolute))), float(np.degrees(np.mean(relative)))


def measure(path: str) -> dict:
    """One dataset's rows: per baseline the pairs' error over their stated sigma, and the averaged rotations'
    mean error (deg) with each sigma rule."""
    ds = load_dataset(path)
    options = MAP_PRESETS["default"]
    features = detect_features(options, ds, [ds.frame(k) for k in range(len(ds))])
    coarse = coarse_poses(ds.camera, features, ds.poses, match_options=options.matching, options=options.coarse)
    true = ds.ground_truth.poses
    rel = coarse.relative
    err = np.array([rotation_angle_between(r.rotation, true[r.j].rotation @ true[r.i].rotation.T) for r in rel])
    sigma = np.array([r.rotation_sigma_rad for r in rel])
    base = np.array([np.linalg.norm(true[r.i].centre - true[r.j].centre) for r in rel])
    row = {"dataset": str(path), "pairs": len(rel), "baselines": [], "averaged_deg": {}}
    for b in np.unique(np.round(base, 2)):
        sel = np.round(base, 2) == b
        z = err[sel] / sigma[sel]
        row["baselines"].append({"baseline_mm": float(b), "pairs": int(sel.sum()),
                                 "error_over_sigma": {"median": float(np.median(z)),
                                                      "p90": float(np.percentile(z, 90)), "max": float(z.max())},
                                 "error_median_deg": float(np.degrees(np.median(err[sel]))),
                                 "sigma_median_deg": float(np.degrees(np.median(sigma[sel])))})
    short = base <= base.min() * 1.001
    for name, s in (("stated", sigma), ("short pairs x2", np.where(short, 2 * sigma, sigma)),
                    ("truth-informed", np.maximum(sigma, err)), ("equal", np.full(len(rel), np.median(sigma)))):
        rotations, _ = average_rotations(ds.poses, [replace(r, rotation_sigma_rad=float(v)) for r, v in zip(rel, s)])
        a, c = rotation_errors_deg(rotations, true)
        row["averaged_deg"][name] = {"absolute": a, "after_common_rotation": c}
    a, c = rotation_errors_deg([m.pose.rotation for m in ds.poses], true)
    row["averaged_deg"]["reported"] = {"absolute": a, "after_common_rotation": c}
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+", help="phantom dome datasets (scope3d phantom dome --pose-noise N)")
    parser.add_argument("--out", default=str(OUT), help="JSON written (default benchmarks/results/rotation_sigma.json)")
    args = parser.parse_args()
    load_before = os.getloadavg()
    rows = []
    t0 = time.perf_counter()
    for path in args.datasets:
        row = measure(path)
        rows.append(row)
        print(json.dumps(row, indent=1), flush=True)
    write_json(args.out, {"benchmark": "coarse pass's relative-rotation sigma against the truth, and rotation "
                                       "averaging with other sigma rules (mean error, deg)",
                          "machine": platform.machine(), "load_average_before_after": [load_before[0],
                                                                                        os.getloadavg()[0]],
                          "wall_s": time.perf_counter() - t0, "datasets": rows})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
