"""Is the coarse pass's relative-rotation sigma honest, and would an honest one improve the averaging?

On one phantom dataset (``scope3d phantom dome --seed S --pose-noise N``): the coarse pass
(sfm.coarse_poses) on the map's default features; per verified pair its relative-rotation error against
the truth, its stated sigma (worst axis) and the baseline; then rotation averaging
(estimators.averaging.average_rotations) with the stated sigmas, with short pairs' sigmas doubled (a
parallax floor), with truth-informed sigmas max(sigma, true error) (no sigma rule can weigh the pairs
better than the truth does) and with equal sigmas. Rotation error of the averaged rotations against the
truth: absolute, and after removing the best common rotation (the gauge). Prints; no files. Run:
    PYTHONPATH=src .venv/bin/python benchmarks/diag_rotation_sigma.py DATASET
"""
from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from scope3d.estimators.averaging import average_rotations
from scope3d.geometry.rotation import rotation_angle_between
from scope3d.io.dataset import load_dataset
from scope3d.pipelines.surgical_map import MAP_PRESETS, detect_features
from scope3d.sfm.coarse_poses import coarse_poses


def rotation_errors_deg(rotations, true) -> tuple[float, float]:
    """Mean error (deg) of rotations (n, 3, 3) against the true poses: absolute, and after the best
    common rotation is removed."""
    absolute = [rotation_angle_between(r, t.rotation) for r, t in zip(rotations, true)]
    common = Rotation.from_matrix(np.stack([t.rotation.T @ r for r, t in zip(rotations, true)])).mean().as_matrix()
    relative = [rotation_angle_between(r @ common.T, t.rotation) for r, t in zip(rotations, true)]
    return float(np.degrees(np.mean(absolute))), float(np.degrees(np.mean(relative)))


def main(path: str) -> None:
    ds = load_dataset(path)
    options = MAP_PRESETS["default"]
    features = detect_features(options, ds, [ds.frame(k) for k in range(len(ds))])
    coarse = coarse_poses(ds.camera, features, ds.poses, match_options=options.matching, options=options.coarse)
    true = ds.ground_truth.poses
    rel = coarse.relative
    err = np.array([rotation_angle_between(r.rotation, true[r.j].rotation @ true[r.i].rotation.T) for r in rel])
    sigma = np.array([r.rotation_sigma_rad for r in rel])
    base = np.array([np.linalg.norm(true[r.i].centre - true[r.j].centre) for r in rel])
    print(f"{path}: {len(rel)} verified pairs")
    for b in np.unique(np.round(base, 2)):
        sel = np.round(base, 2) == b
        z = err[sel] / sigma[sel]
        print(f"  baseline {b:6.2f} mm: {sel.sum():3d} pairs, error/sigma median {np.median(z):.2f} p90 "
              f"{np.percentile(z, 90):.2f} max {z.max():.2f}; error median {np.degrees(np.median(err[sel])):.3f} deg, "
              f"sigma median {np.degrees(np.median(sigma[sel])):.3f} deg")
    short = base <= base.min() * 1.001
    for name, s in (("stated", sigma), ("short pairs x2", np.where(short, 2 * sigma, sigma)),
                    ("truth-informed", np.maximum(sigma, err)), ("equal", np.full(len(rel), np.median(sigma)))):
        rotations, _ = average_rotations(ds.poses, [replace(r, rotation_sigma_rad=float(v)) for r, v in zip(rel, s)])
        a, c = rotation_errors_deg(rotations, true)
        print(f"  averaged with {name:15s} sigmas: {a:.4f} deg absolute, {c:.4f} deg after a common rotation")
    a, c = rotation_errors_deg([m.pose.rotation for m in ds.poses], true)
    print(f"  reported: {a:.4f} deg absolute, {c:.4f} deg after a common rotation")


if __name__ == "__main__":
    main(sys.argv[1])
