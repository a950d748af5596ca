"""The whole-organ 2-D map (issue 37): ``scope3d panorama``'s organ_map against the bladder phantom's truth.

Per case (the default 36-frame spiral at 30 mm stand-off, rendered at SIZE px): the panorama is run (planned
poses, or images only), and its organ map is measured against the truth:

- alignment (atlas px, p95 target 1 px): every 4th pixel of every registered frame, the atlas position the
  map gives it (ray from the map's pose onto the fitted surface) against the atlas position of its true wall
  point (true pose and depth), carried into the map's frame by the similarity fitted to the tracks' true
  positions (the wall error's gauge, not fitted on the atlas);
- coverage against the true covered fraction (true poses on the true mesh, ray casting; target 1 %).

Variants on the same map: the bare ellipsoid (radial_degree 0) beside the ellipsoid with its radial
correction (the default, degree 4), and the true poses on the true wall's fitted surface (what remains is the
surface model and the atlas's sampling).

--multi: two scans of the same bladder with the reference's ~125° bending limit, at 15 mm and 30 mm stand-off
(planned poses: both maps in the plan's frame), each alone and combined on one atlas; coverage of each.

Usage: PYTHONPATH=src python benchmarks/bench_organ_map.py [--size 200] [--images-only-size 608] [--multi]
writes benchmarks/results/organ_map.json and organ_map_*.png.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from scope3d.geometry.similarity import Similarity
from scope3d.io.dataset import load_dataset
from scope3d.mvs.organ_map import OrganMapOptions, alignment_error, fit_cavity_surface, organ_map
from scope3d.phantoms import generate, write
from scope3d.pipelines.panorama import Panorama3dOptions, build_organ_map, evaluate, evaluate_organ_map, run
from scope3d.sfm.scan_planning import coverage

RESULTS = Path(__file__).parent / "results"


def save_picture(src: Path, name: str) -> None:
    """The organ map's picture into results/, at most 1536 px wide (the repository keeps the figures small)."""
    image = cv2.imread(str(src))
    if image.shape[1] > 1536:
        image = cv2.resize(image, (1536, round(image.shape[0] * 1536 / image.shape[1])), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(RESULTS / name), image)


def load() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def organ_figures(organ, evaluation: dict) -> dict:
    al = dict(evaluation.get("alignment") or {})
    al.pop("per_frame_p95_px", None)
    return {"surface": organ.surface.kind, "surface_reason": organ.surface.reason,
            "semi_axes": organ.surface.semi_axes.tolist(), "radial_rms_fraction": organ.surface.radial_rms,
            "atlas_px": [organ.width, organ.height], "texel_mm": organ.texel_mm,
            "coverage_fraction": organ.coverage_fraction,
            "true_coverage_fraction": evaluation.get("true_coverage_fraction"),
            "coverage_error_fraction": evaluation.get("coverage_error_fraction"),
            "n_uncovered_regions": len(organ.regions),
            "uncovered_regions_mm2": [r["area_mm2"] for r in organ.regions], "alignment": al,
            "meets_targets": bool(al and al["p95_px"] <= 1.0 and abs(evaluation["coverage_error_fraction"]) <= 0.01)}


def case(name: str, dataset_dir: Path, planned: bool, work: Path) -> dict:
    ds = load_dataset(dataset_dir)
    t0, c0 = time.perf_counter(), time.process_time()
    result = run(Panorama3dOptions(use_planned_poses=planned, refuse_implausible=False), ds, work / name)
    row = {"case": name, "poses": "planned (bounded)" if planned else "images only",
           "n_frames": result.report["n_frames"], "n_registered": result.report["n_registered"],
           "wall_error_mm": result.report.get("surface_error_mm", {}).get("after_similarity"),
           "self_check_warnings": result.report["self_check"]["warnings"],
           "self_check_problems": result.report["self_check"]["problems"],
           "panorama_wall_s": time.perf_counter() - t0, "panorama_cpu_s": time.process_time() - c0,
           "organ_map_cpu_s": result.report["cpu_by_stage_s"].get("organ_map_s")}
    save_picture(work / name / "organ_map.png", f"organ_map_{name}.png")
    sim = evaluate(ds, result.cavity, 0.25).get("_similarity")
    for degree in (4, 0):
        c1 = time.process_time()
        options = OrganMapOptions(radial_degree=degree)
        organ = build_organ_map(options, [(ds, result.cavity)])
        row[f"radial_degree_{degree}"] = {**organ_figures(organ, evaluate_organ_map([(ds, result.cavity, sim)], organ)),
                                          "cpu_s": time.process_time() - c1}
    print(name, json.dumps(row, indent=1, default=str), flush=True)
    return row


def true_pose_case(dataset_dir: Path) -> dict:
    """The map from the true poses on the surface fitted to the true wall's vertices: the ceiling."""
    ds = load_dataset(dataset_dir)
    gt = ds.ground_truth
    wall = gt.surface()
    centres = np.stack([p.centre for p in gt.poses])
    options = OrganMapOptions()
    surface = fit_cavity_surface(wall.vertices, centres, gt.poses[0].centre + 30 * gt.poses[0].optical_axis,
                                 options=options)
    organ = organ_map(surface, ds.camera, gt.poses, ds.frame, options=options)
    identity = Similarity(1.0, np.eye(3), np.zeros(3), np.zeros(3))
    al = alignment_error(surface, ds.camera, gt.poses, gt.poses, gt.depth, identity, organ.width, organ.height)
    truth = coverage(wall, ds.camera, gt.poses).fraction
    return organ_figures(organ, {"alignment": al, "true_coverage_fraction": truth,
                                 "coverage_error_fraction": organ.coverage_fraction - truth})


def multi(size: int, work: Path) -> dict:
    """15 mm and 30 mm spirals with the 125° bending limit, each alone and combined on one atlas
    (``scope3d panorama D15 D30``: planned poses, both maps in the plan's frame)."""
    from scope3d.cli.main import main as cli
    data = {}
    for standoff in (15, 30):
        plan = work / f"plan{standoff}"
        assert cli(["plan-scan", "bladder", "--standoff", str(standoff), "--bend-limit", "125", "--out", str(plan),
                    "--quiet"]) == 0
        data[standoff] = work / f"scan{standoff}"
        assert cli(["phantom", "bladder", "--plan", str(plan / "plan.json"), "--size", f"{size}x{size}",
                    "--out", str(data[standoff]), "--quiet"]) == 0
    rows = {}
    for label, parts in (("15mm", [15]), ("30mm", [30]), ("15mm+30mm", [15, 30])):
        out = work / f"pano_{label}"
        c0 = time.process_time()
        assert cli(["panorama", *[str(data[s]) for s in parts], "--no-scale", "--out", str(out), "--quiet"]) == 0
        report = json.loads((out / "report.json").read_text())
        organ = report["organ_map"]
        al = dict(organ.get("alignment") or {})
        al.pop("per_frame_p95_px", None)
        al.pop("videos", None)
        rows[label] = {"n_frames": sum(len(list((data[s] / "frames").iterdir())) for s in parts),
                       "coverage_fraction": organ["coverage_fraction"],
                       "true_coverage_fraction": organ["true_coverage_fraction"],
                       "videos_alone": [v["coverage_fraction"] for v in organ.get("videos", [])],
                       "n_uncovered_regions": len(organ["uncovered_regions"]), "alignment": al,
                       "cpu_s": time.process_time() - c0}
        if len(parts) > 1:
            save_picture(out / "organ_map.png", f"organ_map_multi_{label.replace('+', '_')}.png")
        print(label, rows[label], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--size", type=int, default=200)
    parser.add_argument("--images-only-size", type=int, default=608)
    parser.add_argument("--multi", action="store_true")
    parser.add_argument("--multi-only", action="store_true", help="only the two scans; kept beside the cases "
                        "already in organ_map.json")
    args = parser.parse_args()
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / "organ_map.json"
    if args.multi_only:
        out = json.loads(path.read_text()) if path.is_file() else {}
        with tempfile.TemporaryDirectory() as tmp:
            out["multi_video"] = {"load_before": load(), **multi(args.size, Path(tmp)), "load_after": load()}
        path.write_text(json.dumps(out, indent=1, default=str))
        return
    out = {"machine": "2 cores shared with other jobs", "load_before": load(), "cases": [], "targets":
           {"alignment_p95_px": 1.0, "coverage_error": 0.01}}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for size in sorted({args.size, args.images_only_size}):
            write(generate("bladder", size=(size, size)), work / f"bladder{size}")
        out["true_poses"] = true_pose_case(work / f"bladder{args.size}")
        print("true poses", out["true_poses"], flush=True)
        out["cases"].append(case(f"planned_{args.size}px", work / f"bladder{args.size}", True, work))
        out["cases"].append(case(f"images_only_{args.size}px", work / f"bladder{args.size}", False, work))
        if args.images_only_size != args.size:
            out["cases"].append(case(f"images_only_{args.images_only_size}px",
                                     work / f"bladder{args.images_only_size}", False, work))
        if args.multi:
            out["multi_video"] = multi(args.size, work)
    out["load_after"] = load()
    if "multi_video" not in out and path.is_file():  # the two scans' run (--multi-only) kept beside
        out["multi_video"] = json.loads(path.read_text()).get("multi_video")
    path.write_text(json.dumps(out, indent=1, default=str))


if __name__ == "__main__":
    main()
