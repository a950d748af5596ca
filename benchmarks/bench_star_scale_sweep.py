"""The stars' scale (issue 11: "scale within 1 % from the stars") and its stated uncertainty over cavities
not designed on, against the truth.

Cases: bladder phantoms of 36 frames of 608 px (``scope3d phantom bladder``, the default spiral adapted to
the cavity, ``--pose-noise 1``), shape seeds 100-109 with semi-axes drawn once from a seeded generator
(uniform 36-46 mm, sorted), two of them wet with half the vessels, one at 256 px, one blurred by 1 px (the
phantom's frames are otherwise sharp); and seed 23 (42,37,30),
the cavity on which the stars were +1.16 % (diagnosed on, so not counted as unseen). Each case's map is
made by ``scope3d.pipelines.panorama.run`` without the stars (planned poses, and images only with
``--images``), cached, and the stars' scale is measured on it by ``metrology.star_scale`` exactly as the
pipeline does (the same poses and tracks).

Per case: the stars' scale error as ``report.json`` states it (``scale_error_fraction``: the scaled map's
similarity scale against the truth minus 1; positive = the stars' scale too small), the stated sigma
(``scale_uncertainty_fraction``), z = error / sigma, and the map's own similarity scale (true mm per map
unit, fitted to all tracks' true positions). Per star view, each over the map's similarity scale so the
stars' error is separated from the map's (the view's scale over the truth's minus 1):

* ``truth_pixels``: the view's weighted pixels lifted by the true per-pixel depth (the segmentation alone);
* ``truth_wall``: the wall model fitted to the *true* positions of the same tracks with the true pose;
* ``map``: the view's scale from the map (what the pipeline uses);
* ``map_local``: the similarity scale of the map's points about the star against their true positions
  (the map's own local scale there; a rough sign only: fitted to a 7 mm patch of noisy points it comes
  out low, -0.8 % on average over the sweep's views);
and the star's depth, its incidence (the angle between the ray and the true wall's normal), its distance
from the field's edge, its pixels and the wall's points.

Usage: PYTHONPATH=src python benchmarks/bench_star_scale_sweep.py [--cases TAG ...] [--images TAG ...]
    [--cache DIR]  ->  benchmarks/results/star_scale_sweep.json and .png (cases merged into earlier results)
"""
from __future__ import annotations

import argparse
import json
import os
import pickle
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import map_coordinates

from bench_panorama_3d import load
from scope3d.errors import InputError
from scope3d.geometry.similarity import fit_similarity
from scope3d.io.dataset import load_dataset
from scope3d.metrology.evaluation import true_track_points
from scope3d.metrology.fluorescence import auto_threshold
from scope3d.metrology.star_scale import (StarScaleOptions, covered_area, field_inside, fit_local_wall,
                                          pentagram_area_mm2, star_blobs, star_scale)
from scope3d.pipelines.panorama import Panorama3dOptions, evaluate, run
from scope3d.utils.atomic import atomic_file
from scope3d.utils.figures import new_figure, save_figure

RESULTS = Path(__file__).parent / "results"
CLI = [sys.executable, "-m", "scope3d.cli.main"]
# semi-axes of shape seeds 100-109: np.sort(np.random.default_rng(1124).uniform(36, 46, 3))[::-1], rounded
AXES = ["40,38,36", "41,41,38", "42,42,39", "46,45,42", "41,41,36", "45,44,43", "46,43,41", "44,42,37",
        "42,39,38", "46,45,45"]
WET = ["--wet", "--vessel-density", "0.5"]
#: (tag, phantom options, unseen: not designed on)
CASES = ([("s23", ["--shape-seed", "23", "--cavity-mm", "42,37,30", "--seed", "9"], False)]
         + [(f"s{100 + i}" + ("_wet" if i >= 8 else ""),
             ["--shape-seed", str(100 + i), "--cavity-mm", AXES[i], "--seed", str(100 + i)] + (WET if i >= 8 else []),
             True) for i in range(10)]
         + [("s100_256px", ["--shape-seed", "100", "--cavity-mm", AXES[0], "--seed", "100", "--size", "256x256"],
             True),
            # a scope's optics blur: the phantom's default frames are sharp (blur 0, one ray per pixel)
            ("s104_blur1", ["--shape-seed", "104", "--cavity-mm", AXES[4], "--seed", "104", "--blur", "1"], True)])


def dataset_for(cache: Path, tag: str, phantom_args: list[str]) -> tuple[Path, str]:
    """The case's dataset (rendered by the CLI unless in the cache) and the command that makes it."""
    path = cache / tag
    cmd = CLI + ["phantom", "bladder", "--pose-noise", "1", *phantom_args, "--quiet", "--out", str(path)]
    if not (path / "report.json").exists():
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return path, "scope3d " + " ".join(cmd[3:-2]) + " --out DATASET"


def map_for(cache: Path, tag: str, ds, planned: bool) -> dict:
    """The map of ``run`` without the stars (cached): poses, tracks, wall error, similarity scale, CPU."""
    path = cache / f"{tag}_map_{'planned' if planned else 'images'}.pkl"
    if path.exists():
        return pickle.loads(path.read_bytes())
    c0 = time.process_time()
    options = Panorama3dOptions(use_planned_poses=planned, stars=None, figures=False, texture=None)
    with tempfile.TemporaryDirectory() as tmp:
        try:
            result = run(options, ds, Path(tmp) / "out")
            report, cavity = result.report, result.cavity
        except InputError as exc:  # a refused map (self-check) has no stars to measure
            entry = {"refused": str(exc)}
            path.write_bytes(pickle.dumps(entry))
            return entry
    summary = evaluate(ds, cavity, options.evaluation_step_mm)["surface_error_mm"]["after_similarity"]
    entry = {"poses": cavity.poses, "tracks": cavity.tracks, "n_registered": int(cavity.registered.sum()),
             "wall_error_mm": {k: summary[k] for k in ("mean", "median", "p95")}, "map_scale": summary["scale"],
             "cpu_s": time.process_time() - c0}
    path.write_bytes(pickle.dumps(entry))
    return entry


def _lifted_area(camera, depth: np.ndarray, pixels: np.ndarray, weights: np.ndarray) -> float:
    """Area (mm^2) of the weighted pixels with their corners lifted by the true z-depth (bilinear)."""
    def cast(p):
        z = map_coordinates(depth, [p[:, 1], p[:, 0]], order=1, mode="nearest")
        return np.c_[camera.pixel_to_normalised(p), np.ones(len(p))] * z[:, None]
    a, b, c = cast(pixels - 0.5), cast(pixels + [0.5, -0.5]), cast(pixels + [-0.5, 0.5])
    return float(np.sum(weights * np.linalg.norm(np.cross(b - a, c - a), axis=1)))


def view_truth(ds, entry: dict, true_points: np.ndarray, view: dict, options: StarScaleOptions,
               threshold: int, inside: np.ndarray) -> dict:
    """One star view measured against the truth (module docstring); scales as the view's over the truth's
    minus 1."""
    camera, gt, k = ds.camera, ds.ground_truth, view["frame"]
    blob = min(star_blobs(ds.fluorescence_frame(k), threshold, inside, options=options),
               key=lambda b: np.linalg.norm(b.centre_px - view["pixel"]))
    true_area = pentagram_area_mm2(options.outer_diameter_mm)
    depth = gt.depth(k).astype(float)
    tr = entry["tracks"]
    sel = tr.frame == k
    near = np.linalg.norm(tr.pixels[sel] - blob.centre_px, axis=1) <= options.neighbourhood * blob.radius_px
    ids = tr.track[sel][near]
    ok = np.all(np.isfinite(true_points[ids]), axis=1)
    wall = fit_local_wall(camera, gt.poses[k], true_points[ids][ok], blob.centre_px, options.curved_wall)
    truth_wall = np.sqrt(true_area / covered_area(camera, wall, blob.pixels, blob.weights)) - 1.0 if wall else None
    local = fit_similarity(tr.points[ids][ok], true_points[ids][ok]).scale if ok.sum() >= 4 else np.nan
    # the true wall's normal at the star: a plane through the star's pixels lifted by the true depth
    lifted = np.c_[camera.pixel_to_normalised(blob.pixels), np.ones(len(blob.pixels))] \
        * map_coordinates(depth, [blob.pixels[:, 1], blob.pixels[:, 0]], order=1, mode="nearest")[:, None]
    centred = lifted - lifted.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][2]
    ray = lifted.mean(axis=0) / np.linalg.norm(lifted.mean(axis=0))
    edge = (camera.mask_radius_px or np.inf) - np.max(np.hypot(blob.pixels[:, 0] - camera.cx,
                                                               blob.pixels[:, 1] - camera.cy))
    return {"frame": k, "area_px": view["area_px"], "n_points": view["n_points"], "sigma": view["sigma"],
            "sigma_parts": view["sigma_parts"],
            "depth_mm": float(lifted[:, 2].mean()), "incidence_deg": float(np.degrees(np.arccos(abs(normal @ ray)))),
            "edge_px": float(edge),
            "truth_pixels": float(np.sqrt(true_area / _lifted_area(camera, depth, blob.pixels, blob.weights)) - 1.0),
            "truth_wall": truth_wall, "map": view["scale"] / entry["map_scale"] - 1.0,
            "map_local": float(local / entry["map_scale"] - 1.0)}


def stars_on(ds, entry: dict, options: StarScaleOptions) -> dict:
    """The stars' scale on a cached map, as the pipeline measures it, and each view against the truth."""
    fluorescence = [ds.fluorescence_frame(k) for k in range(len(ds))]
    c0 = time.process_time()
    try:
        stars = star_scale(ds.camera, entry["poses"], entry["tracks"], fluorescence, options=options)
    except InputError as exc:
        return {"stars_error": str(exc)}
    cpu = time.process_time() - c0
    tr = entry["tracks"]
    true_points = true_track_points(ds.camera, ds.ground_truth.poses, ds.ground_truth.depth, tr.frame, tr.track,
                                    tr.pixels, tr.n_tracks)
    threshold = auto_threshold(fluorescence, options=options.fluorescence)
    inside = field_inside(ds.camera, options.border_px)
    error = entry["map_scale"] / stars.scale - 1.0  # report.json's scale_error_fraction
    return {"scale_error_fraction": error, "sigma": stars.uncertainty, "z": error / stars.uncertainty,
            "n_views": len(stars.views), "stars_cpu_s": cpu,
            "views": [view_truth(ds, entry, true_points, v, options, threshold, inside) for v in stars.views]}


def save_picture(cases: dict, path: Path, limit: float = 2.5) -> None:
    """Error per case with +-2 stated sigmas; a map that is not good (wall error >= 0.5 mm) hollow, and
    a point beyond +-limit % written at the edge."""
    fig = new_figure(figsize=(11, 4.8))
    ax = fig.add_subplot(1, 1, 1)
    labels, shown = [], set()
    for i, (tag, case) in enumerate(cases.items()):
        labels.append(tag + ("" if case["unseen"] else "*"))
        for dx, (mode, colour) in zip((-0.12, 0.12), (("planned", "C0"), ("images", "C1"))):
            row = case["modes"].get(mode) or {}
            if "scale_error_fraction" not in row:
                continue
            e, good = 100 * row["scale_error_fraction"], row["wall_error_mm"]["mean"] < 0.5
            if abs(e) > limit:
                ax.annotate(f"{e:+.1f} ± {200 * row['sigma']:.1f} %", (i + dx, np.sign(e) * (limit - 0.15)), fontsize=7,
                            color=colour, ha="center", va="center")
                continue
            ax.errorbar(i + dx, e, yerr=200 * row["sigma"], fmt="o", color=colour, mfc=colour if good else "white",
                        capsize=3, label=None if mode in shown else mode)
            shown.add(mode)
    ax.axhline(0, color="k", lw=0.6)
    for y in (-1, 1):
        ax.axhline(y, color="grey", ls=":", lw=1)
    ax.set_ylim(-limit, limit)
    ax.set_xticks(range(len(labels)), labels, fontsize=7, rotation=30)
    ax.set_ylabel("stars' scale error, % (bars: ±2 stated sigma)")
    ax.legend(fontsize=8, title="poses")
    ax.set_title("the stars' scale against the truth (dotted: the issue's 1 %; hollow: map >= 0.5 mm; "
                 "*: designed on)", fontsize=9)
    save_figure(fig, path)


def summary(cases: dict) -> dict:
    """z-scores and coverage over the unseen cases' maps that are good (wall error < 0.5 mm)."""
    rows = [row for case in cases.values() if case["unseen"] for row in case["modes"].values()
            if "z" in row and row["wall_error_mm"]["mean"] < 0.5]
    z = np.array([r["z"] for r in rows])
    e = np.array([r["scale_error_fraction"] for r in rows])
    if not len(z):
        return {}
    return {"n_maps": len(z), "abs_error_max": float(np.abs(e).max()), "error_rms": float(np.sqrt(np.mean(e ** 2))),
            "within_1_percent": int(np.sum(np.abs(e) < 0.01)),
            "z_mean": float(z.mean()), "z_rms": float(np.sqrt(np.mean(z ** 2))),
            "coverage_2_sigma": float(np.mean(np.abs(z) < 2)), "coverage_1_sigma": float(np.mean(np.abs(z) < 1))}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", nargs="*", help="case tags (default all)")
    ap.add_argument("--images", nargs="*", default=[], help="cases also mapped from images alone (--ignore-poses)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/scope3d_star_scale_sweep"))
    ap.add_argument("--picture", action="store_true", help="only redraw the picture from the results")
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    out = RESULTS / "star_scale_sweep.json"
    result = json.loads(out.read_text()) if out.exists() else {"cases": {}}
    if args.picture:
        save_picture(result["cases"], RESULTS / "star_scale_sweep.png")
        return
    result.update(cpu_count=os.cpu_count(), options=repr(StarScaleOptions()))
    for tag, phantom_args, unseen in CASES:
        if args.cases and tag not in args.cases:
            continue
        path, command = dataset_for(args.cache, tag, phantom_args)
        ds = load_dataset(path)
        case = {"command": command, "unseen": unseen, "load": load(), "modes": {}}
        for mode in ("planned", "images") if tag in args.images else ("planned",):
            entry = map_for(args.cache, tag, ds, mode == "planned")
            if "refused" in entry:
                case["modes"][mode] = {"refused": entry["refused"]}
                continue
            case["modes"][mode] = {"n_registered": entry["n_registered"], "wall_error_mm": entry["wall_error_mm"],
                                   "map_scale": entry["map_scale"], "map_cpu_s": entry["cpu_s"],
                                   **stars_on(ds, entry, StarScaleOptions())}
        old = result["cases"].get(tag, {}).get("modes", {})
        case["modes"] = {**{m: r for m, r in old.items() if m not in case["modes"]}, **case["modes"]}
        result["cases"][tag] = case
        result["cases"] = dict(sorted(result["cases"].items()))
        result["summary"] = summary(result["cases"])
        with atomic_file(out) as f:
            f.write(json.dumps(result, indent=1, default=float))
        save_picture(result["cases"], RESULTS / "star_scale_sweep.png")
        print(tag, json.dumps({m: {k: v for k, v in r.items() if k != "views"} for m, r in case["modes"].items()},
                              default=float), flush=True)
    print(json.dumps(result.get("summary"), indent=1))


if __name__ == "__main__":
    main()
