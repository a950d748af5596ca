"""Which image-only cavity map to keep (issue 11 §4): without planned poses ``map_cavity`` adjusts two maps of
the same frames, the all-pair map (every verified pair's tracks, centres from their rays) and the chain's map
(the shape-tested pairs alone, from the depth-scaled start), and keeps one by figures that need no truth
(``scope3d.sfm.cavity_map_choice.choose_map``). This benchmark records, per case, both candidates' figures
(observations of every verified track explained within the gate, wall spread, cameras off centre, frames
registered), the figure of their disagreement (``map_disagreement``), which one the code keeps and why, and
each candidate's true mean wall error after similarity (the metric of ``bench_panorama_3d.py``), so that the
rule can be judged against the truth on every case.

Cases: the density sweep and the 30 mm (and with ``--cases``, 15 mm) stand-off spirals of
``bench_panorama_3d_sweep.py``, the 256 px spiral, and unseen cavities (shape seeds 5 at 608 and 224 px, 23,
11; and 31, 37, a wet 31, 43 and a wet 47, which the rule was not designed on). Each dataset is rendered once into
``--cache``. Results are merged per case into benchmarks/results/panorama_3d_map_choice.json.

Usage: PYTHONPATH=src python benchmarks/bench_panorama_3d_map_choice.py [--cases TAG ...] [--cache DIR]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import time
from dataclasses import replace
from pathlib import Path

from bench_panorama_3d import load
from bench_panorama_3d_sweep import CLI, SWEEPS, dataset_for
from scope3d.errors import InputError
from scope3d.io.dataset import load_dataset
from scope3d.pipelines.panorama import Panorama3dOptions, evaluate, panorama_features
from scope3d.sfm.cavity_mapping import map_cavity
from scope3d.utils.atomic import atomic_file

RESULTS = Path(__file__).parent / "results"

#: cases beyond the sweeps: tag -> (phantom options, designed on: the rule was chosen looking at it)
EXTRA = {
    "spiral36_256": (["--pose-noise", "1", "--size", "256x256"], True),
    "unseen5": (["--shape-seed", "5", "--cavity-mm", "40,35,30", "--pose-noise", "1", "--seed", "7"], True),
    "unseen5_224": (["--shape-seed", "5", "--cavity-mm", "40,35,30", "--pose-noise", "1", "--seed", "7",
                     "--size", "224x224"], True),
    "unseen23": (["--shape-seed", "23", "--cavity-mm", "42,37,30", "--pose-noise", "1", "--seed", "9"], True),
    "unseen11_dry": (["--shape-seed", "11", "--cavity-mm", "38,34,29", "--pose-noise", "1", "--seed", "3"], True),
    "unseen31": (["--shape-seed", "31", "--cavity-mm", "44,36,31", "--pose-noise", "1", "--seed", "4"], False),
    "unseen37": (["--shape-seed", "37", "--cavity-mm", "39,35,33", "--pose-noise", "1", "--seed", "6"], False),
    "unseen31_wet_d0.5": (["--shape-seed", "31", "--cavity-mm", "44,36,31", "--pose-noise", "1", "--seed", "4",
                           "--wet", "--vessel-density", "0.5"], False),
    # rendered after the last change of the rule (the significance of the explained difference), unseen by it
    "unseen43": (["--shape-seed", "43", "--cavity-mm", "41,37,32", "--pose-noise", "1", "--seed", "5"], False),
    "unseen47_wet_d0.5": (["--shape-seed", "47", "--cavity-mm", "43,35,30", "--pose-noise", "1", "--seed", "8",
                           "--wet", "--vessel-density", "0.5"], False),
}
#: the sweeps' cases run by default (the 15 mm spirals, 165-194 views, only when named)
SWEEP_CASES = ["dry_d1", "wet_d1", "wet_d0.5", "wet_d0.25", "wet_d0.1", "wet_d0.5_unseen11",
               "spiral30_default", "spiral30_unseen"]


def dataset(cache: Path, tag: str) -> tuple[Path, dict]:
    """The case's dataset folder (rendered unless in the cache) and the commands that made it."""
    for sweep in SWEEPS.values():
        for t, _, plan, args in sweep:
            if t == tag:
                return dataset_for(cache, t, plan, args)
    out = cache / tag
    cmd = CLI + ["phantom", "bladder", *EXTRA[tag][0], "--quiet", "--out", str(out)]
    if not (out / "report.json").exists():
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return out, {"render": " ".join(cmd[2:])}


def wall_error(ds, cavity, tracks) -> float | None:
    """Mean distance of ``tracks``' points to the true wall after similarity (mm)."""
    found = evaluate(ds, replace(cavity, tracks=tracks), Panorama3dOptions().evaluation_step_mm)
    return (found.get("surface_error_mm") or {}).get("after_similarity", {}).get("mean")


def run_case(path: Path) -> dict:
    """Both candidate maps of the images-only panorama of the dataset at ``path``: figures, choice, truth."""
    ds = load_dataset(path)
    c0, t0 = time.process_time(), time.perf_counter()
    options = Panorama3dOptions(use_planned_poses=False)
    features = panorama_features(options, ds)
    try:
        cavity = map_cavity(ds.camera, features, None, options.cavity, options.matching, where=str(path))
    except InputError as exc:  # frames not tied together: no candidate at all
        return {"error": str(exc), "cpu_s": time.process_time() - c0}
    choice = dict(cavity.choice)
    kept = "all_pairs" if choice["kept"] == "all pairs" else "chain"
    other = "chain" if kept == "all_pairs" else "all_pairs"
    choice[kept] = {**choice[kept], "true_mean_wall_error_mm": wall_error(ds, cavity, cavity.tracks)}
    choice[other] = {**choice[other], "true_mean_wall_error_mm": wall_error(ds, cavity, cavity.alternative[0])}
    errors = [choice[k]["true_mean_wall_error_mm"] for k in ("all_pairs", "chain")]
    better = "all_pairs" if errors[0] <= errors[1] else "chain"
    return {**choice, "better_by_truth": better, "kept_the_better": kept == better,
            "n_frames": len(ds), "image_size": [ds.camera.width, ds.camera.height],
            "cpu_s": time.process_time() - c0, "wall_s": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", nargs="*", help="case tags (default: the sweeps' density and 30 mm cases and EXTRA)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/scope3d_panorama_sweep"))
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    out = RESULTS / "panorama_3d_map_choice.json"
    for tag in args.cases or SWEEP_CASES + list(EXTRA):
        path, commands = dataset(args.cache, tag)
        before = load()
        case = {"commands": commands, "designed_on": EXTRA.get(tag, (None, True))[1], **run_case(path),
                "load_before": before, "load_after": load()}
        result = json.loads(out.read_text()) if out.exists() else {
            "what": "image-only panorama: both candidate maps per case (scope3d.sfm.cavity_mapping.map_cavity)",
            "cases": {}}
        result["cases"][tag] = case
        RESULTS.mkdir(exist_ok=True)
        with atomic_file(out) as f:
            f.write(json.dumps(result, indent=2, default=float))
        print(json.dumps({tag: case}, default=float), flush=True)


if __name__ == "__main__":
    main()
