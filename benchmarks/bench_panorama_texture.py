"""The textured wall of the 3-D panorama (issue 11 §4) against the phantom's truth.

On a bladder phantom dataset: ``scope3d panorama``'s map (planned poses and the stars, as the command runs by
default; ``--ignore-poses`` for images only), then its wall textured (``scope3d.mvs.texturing``, timed on its
own), then, at the same true-wall points read along lines of sight from the true centre
(``scope3d.metrology.texture_evaluation``): the colour error against the true albedo (after one gain per
channel) and the misregistration in mm of sharp features (vessel edges: phase correlation of true-albedo and
texture patches). Beside it, the same measures for what the panorama wrote before (mesh.ply coloured per
vertex by the sparse points' colours) and, with ``--floor``, for the same texturing with the true poses on
the true wall (what the map's errors cost).

Usage: PYTHONPATH=src python benchmarks/bench_panorama_texture.py DATASET [--tag NAME] [--ignore-poses] [--floor]
writes benchmarks/results/panorama_texture[_TAG].json and .png (the atlas, a crop, and truth beside).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from scope3d.geometry.similarity import Similarity
from scope3d.io.dataset import load_dataset
from scope3d.io.obj import read_textured_obj, write_textured_obj
from scope3d.metrology.evaluation import errors_after_similarity, true_track_points
from scope3d.metrology.texture_evaluation import textured_errors, vertex_colour_errors
from scope3d.mvs.texturing import TextureOptions, texture_mesh
from scope3d.phantoms.scenes import build_scene
from scope3d.pipelines.panorama import Panorama3dOptions, cavity_mesh, run
from scope3d.scene.mesh import SampledSurface
from scope3d.utils.figures import new_figure, save_figure

RESULTS = Path(__file__).parent / "results"


def load() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def true_scene(ds):
    info = json.loads((ds.root / "ground_truth" / "scene.json").read_text())
    b = info["bladder"]
    bladder = {"semi_axes_mm": tuple(b["semi_axes_mm"]), "shape_seed": b["shape_seed"],
               "vessel_density": b["vessel_density"], "wet": b["material"]["kind"] == "wet mucosa"}
    return build_scene("bladder", texture_seed=info["texture"]["seed"],
                       bladder=tuple(sorted((k, v) for k, v in bladder.items())))


def timed_texture(mesh, centre, ds, poses, options):
    c0, t0 = time.process_time(), time.perf_counter()
    textured = texture_mesh(mesh, centre, ds.camera, poses, ds.frame, options=options)
    return textured, {"cpu_s": time.process_time() - c0, "wall_s": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--tag", default="")
    ap.add_argument("--ignore-poses", action="store_true")
    ap.add_argument("--floor", action="store_true", help="also texture the true wall from the true poses")
    args = ap.parse_args()
    ds = load_dataset(args.dataset)
    scene = true_scene(ds)
    true_wall = ds.ground_truth.surface()
    out = {"dataset": str(ds.root), "frames": len(ds), "size_px": [ds.camera.width, ds.camera.height],
           "load_before": load()}

    with tempfile.TemporaryDirectory() as tmp:
        c0, t0 = time.process_time(), time.perf_counter()
        result = run(Panorama3dOptions(use_planned_poses=not args.ignore_poses, figures=False, texture=None),
                     ds, Path(tmp) / "run")
        report, cavity = result.report, result.cavity
        out["map"] = {"poses": report["poses"], "n_registered": report["n_registered"], "n_points": report["n_points"],
                      "surface_error_mm": report.get("surface_error_mm"), "cpu_s": time.process_time() - c0,
                      "wall_s": time.perf_counter() - t0}
    tr = cavity.tracks
    true_points = true_track_points(ds.camera, ds.ground_truth.poses, ds.ground_truth.depth, tr.frame, tr.track,
                                    tr.pixels, tr.n_tracks)
    _, _, sim = errors_after_similarity(tr.points, true_points, SampledSurface(true_wall, 0.25))
    wall = cavity_mesh(tr.points, cavity.centre_mm, tr.colors)
    poses = [p if ok else None for p, ok in zip(cavity.poses, cavity.registered)]
    out["wall_mesh"] = {"vertices": int(len(wall.vertices)), "faces": int(len(wall.faces))}

    textured, timing = timed_texture(wall, cavity.centre_mm, ds, poses, TextureOptions())
    out["texture"] = {"timing": timing, "load_after": load(), "atlas_px": list(textured.image.shape[:2]),
                      "texel_mm": textured.texel_mm, "textured_fraction": textured.textured_fraction}
    with tempfile.TemporaryDirectory() as tmp:  # the files round-trip (what a user's tool reads)
        paths = write_textured_obj(Path(tmp) / "wall.obj", textured.mesh.vertices, textured.mesh.faces, textured.uv,
                                   textured.face_uv, textured.image)
        out["texture"]["files_mb"] = {p.name: p.stat().st_size / 1e6 for p in paths}
        v, f, uv, fuv, image = read_textured_obj(paths[0])
        assert np.array_equal(f, textured.mesh.faces) and np.array_equal(image, textured.image)
    out["texture"]["vs_truth"] = textured_errors(textured, sim, true_wall, np.zeros(3), scene.albedo)
    out["texture_levelled_gains"] = textured_errors(
        texture_mesh(wall, cavity.centre_mm, ds.camera, poses, ds.frame, options=TextureOptions(level_gains=True)),
        sim, true_wall, np.zeros(3), scene.albedo)
    out["vertex_colours"] = vertex_colour_errors(wall, textured.texel_mm, sim, true_wall, np.zeros(3), scene.albedo)
    if args.floor:
        identity = Similarity(1.0, np.eye(3), np.zeros(3), np.zeros(3))
        floor, floor_timing = timed_texture(true_wall, np.zeros(3), ds, ds.ground_truth.poses,
                                            TextureOptions(texel_mm=textured.texel_mm * sim.scale))
        out["floor_true_poses_and_wall"] = {"timing": floor_timing, "faces": int(len(true_wall.faces)),
                                            **textured_errors(floor, identity, true_wall, np.zeros(3), scene.albedo)}
    out["load_after"] = load()

    tag = f"_{args.tag}" if args.tag else ""
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"panorama_texture{tag}.json").write_text(json.dumps(out, indent=2))
    fig = new_figure(figsize=(12, 8.4))
    ax = fig.add_subplot(1, 1, 1)
    ax.imshow(textured.image)
    c = out["texture"]["vs_truth"]
    ax.set_title(f"textured wall atlas (cube map of directions), texel {textured.texel_mm * sim.scale:.3f} mm; colour "
                 f"error {c['colour_error']['mean_grey']:.1f} grey levels, misregistration "
                 f"{c['misregistration_mm'].get('median', float('nan')):.3f} mm median", fontsize=9)
    ax.axis("off")
    save_figure(fig, RESULTS / f"panorama_texture{tag}.png")
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
