"""The 3-D bladder panorama on hard bladders (issue 11 §2 and §4): ``scope3d panorama`` (images only and
planned poses) beside ``pycolmap.global_mapping`` on the same frames, swept over

* ``density``: the default spiral (36 frames, 608 px, ``--pose-noise 1``), dry, then with wet mucosa
  (``--wet``) and the vessels at 1, 0.5, 0.25 and 0.1 of the default density (``--vessel-density``);
* ``spirals``: the planned stand-off spirals of ``scope3d plan-scan`` (15 mm and 30 mm, 50 % overlap, 70 deg
  field) rendered by ``scope3d phantom bladder --plan`` on the default cavity and on an unseen one
  (``--shape-seed 5 --cavity-mm 40,35,30``).

Each row: frames registered, wall error after a 7-DoF similarity fitted to the tracks' true positions
(mean / median / p95, the metric of ``bench_panorama_3d.py``), the stars' scale error (ours; pycolmap has
no scale), CPU and wall time (features and matching included) and the load average around it. pycolmap
matches every pair, or with ``--sequential-above N`` each frame with its next 10 when a dataset has more
than N frames (exhaustive matching of 194 views is 18,721 pairs).

Each dataset is rendered once into ``--cache`` (default /tmp/scope3d_panorama_sweep) by the CLI, and read
from there afterwards. Results are merged per case into benchmarks/results/panorama_3d_<sweep>.json (a
case run again replaces its entry), with a picture of the error and registered frames per case.

Usage: PYTHONPATH=src python benchmarks/bench_panorama_3d_sweep.py {density,spirals} [--cases TAG ...]
    [--no-colmap] [--ours {both,images,planned,none}] [--incremental] [--cache DIR]
(``--no-colmap`` keeps pycolmap's rows of an earlier run of the same case: its result does not depend on our
code, and it is the slow half of the benchmark; ``--ours images`` likewise keeps the planned-pose rows, for a
change that only the image-only map goes through; ``--ours none`` runs pycolmap alone and keeps ours.)
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench_panorama_3d import colmap, load, ours
from scope3d.errors import InputError
from scope3d.io.dataset import load_dataset
from scope3d.scene.mesh import SampledSurface
from scope3d.utils.atomic import atomic_file
from scope3d.utils.figures import new_figure, save_figure

RESULTS = Path(__file__).parent / "results"
CLI = [sys.executable, "-m", "scope3d.cli.main"]
UNSEEN = ["--shape-seed", "5", "--cavity-mm", "40,35,30"]

#: sweep -> [(case tag, x value for the picture, plan: (stand-off mm, unseen shape) or None, phantom options)]
SWEEPS = {
    "density": [("dry_d1", 1.0, None, ["--pose-noise", "1"])]
               + [(f"wet_d{d:g}", d, None, ["--pose-noise", "1", "--wet", "--vessel-density", f"{d:g}"])
                  for d in (1.0, 0.5, 0.25, 0.1)]
               # an unseen wet cavity, smaller than the default (its image-only map was a wrong map, 26.5 mm)
               + [("wet_d0.5_unseen11", 0.5, None, ["--pose-noise", "1", "--seed", "3", "--wet", "--vessel-density",
                                                    "0.5", "--shape-seed", "11", "--cavity-mm", "38,34,29"])],
    "spirals": [(f"spiral{s}_{'unseen' if u else 'default'}", s, (s, u), ["--pose-noise", "1"] + (UNSEEN if u else []))
                for s in (30, 15) for u in (False, True)],
}


def dataset_for(cache: Path, tag: str, plan: tuple[int, bool] | None, phantom_args: list[str]) -> tuple[Path, dict]:
    """The case's dataset folder, rendered (and its plan made) unless already in the cache; and the
    commands that made it."""
    commands = {}
    args = list(phantom_args)
    if plan is not None:
        standoff, unseen = plan
        plan_dir = cache / f"plan{standoff}_{'unseen' if unseen else 'default'}"
        # the unseen cavity's plan is made on its own wall: the mesh of any rendering of it
        surface = str(cache / "unseen_wall" / "ground_truth" / "surface.ply") if unseen else "bladder"
        if unseen and not (cache / "unseen_wall" / "report.json").exists():
            cmd = CLI + ["phantom", "bladder", *UNSEEN, "--frames", "1", "--size", "64x64", "--quiet",
                         "--out", str(cache / "unseen_wall")]
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        cmd = CLI + ["plan-scan", surface, "--standoff", str(standoff), "--quiet", "--out", str(plan_dir)]
        commands["plan"] = " ".join(cmd[2:])
        if not (plan_dir / "plan.json").exists():
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        args += ["--plan", str(plan_dir / "plan.json")]
    out = cache / tag
    cmd = CLI + ["phantom", "bladder", *args, "--quiet", "--out", str(out)]
    commands["render"] = " ".join(cmd[2:])
    if not (out / "report.json").exists():
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return out, commands


def run_case(path: Path, args) -> dict:
    ds = load_dataset(path)
    truth = SampledSurface(ds.ground_truth.surface(), 0.25)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for use_planned in {"both": (False, True), "images": (False,), "planned": (True,), "none": ()}[args.ours]:
            before = load()
            try:
                row = ours(ds, work, use_planned, stars=True)
            except InputError as exc:  # our refusal (frames not tied together) is a result too
                row = {"method": "scope3d panorama" + (" (planned poses)" if use_planned else " (images only)"),
                       "n_registered": 0, "surface_error_mm": None, "error": str(exc)}
            rows.append({**row, "load_before": before, "load_after": load()})
        if not args.no_colmap:
            overlap = 10 if len(ds) > args.sequential_above else 0
            for mapper in ("global", "incremental") if args.incremental else ("global",):
                before = load()
                try:
                    row = colmap(ds, work, mapper, truth, sequential_overlap=overlap)
                except Exception as exc:  # a peer's failure is a result, not a crash of the benchmark
                    row = {"method": f"pycolmap.{mapper}_mapping", "error": repr(exc)}
                rows.append({**row, "load_before": before, "load_after": load()})
    return {"dataset": str(path), "n_frames": len(ds), "image_size": [ds.camera.width, ds.camera.height],
            "rows": rows}


def save_picture(sweep: str, cases: dict, path: Path) -> None:
    """Mean wall error (log) and registered frames per case, one line per method."""
    tags = [t for t, *_ in SWEEPS[sweep] if t in cases]
    methods = sorted({r["method"] for t in tags for r in cases[t]["rows"]})
    fig = new_figure(figsize=(11, 4.2))
    ax_err, ax_reg = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    x = np.arange(len(tags))
    for m in methods:
        err, reg = [], []
        for t in tags:
            row = next((r for r in cases[t]["rows"] if r["method"] == m), {})
            err.append((row.get("surface_error_mm") or {}).get("mean", np.nan))
            # a method not run on a case is no point (not 0 frames registered)
            reg.append(row.get("n_registered", 0) / cases[t]["n_frames"] if row else np.nan)
        ax_err.plot(x, err, "o-", label=m)
        ax_reg.plot(x, reg, "o-", label=m)
    ax_err.axhline(0.2, color="grey", ls=":", lw=1, label="issue's 0.2 mm")
    ax_err.set_yscale("log")
    ax_err.set_ylabel("mean wall error after similarity, mm")
    ax_reg.set_ylabel("frames registered (fraction)")
    ax_reg.set_ylim(0, 1.05)
    for ax in (ax_err, ax_reg):
        ax.set_xticks(x, [f"{t}\n{cases[t]['n_frames']} fr" for t in tags], fontsize=8)
    ax_err.legend(fontsize=7)
    fig.suptitle(f"3-D panorama sweep: {sweep}")
    save_figure(fig, path)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("sweep", choices=sorted(SWEEPS))
    ap.add_argument("--cases", nargs="*", help="case tags to run (default all of the sweep)")
    ap.add_argument("--no-colmap", action="store_true",
                    help="ours only; pycolmap's rows of an earlier run of the case are kept (same frames)")
    ap.add_argument("--ours", choices=("both", "images", "planned", "none"), default="both",
                    help="which of our maps to run (default both; none: pycolmap only); the rows not run of an "
                         "earlier run of the case are kept")
    ap.add_argument("--incremental", action="store_true", help="also pycolmap.incremental_mapping (slow)")
    ap.add_argument("--sequential-above", type=int, default=100,
                    help="pycolmap matches each frame with its next 10 above this many frames (default 100)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/scope3d_panorama_sweep"))
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    out = RESULTS / f"panorama_3d_{args.sweep}.json"
    result = json.loads(out.read_text()) if out.exists() else {"sweep": args.sweep, "cases": {}}
    result.update(cpu_count=os.cpu_count(),
                  metric="distance of each point to the true wall after a 7-DoF similarity fitted to the points' "
                         "true positions (true depth maps + true poses); same for every method")
    for tag, value, plan, phantom_args in SWEEPS[args.sweep]:
        if args.cases and tag not in args.cases:
            continue
        path, commands = dataset_for(args.cache, tag, plan, phantom_args)
        case = {"x": value, "commands": commands, **run_case(path, args)}
        # read again: another run of the sweep (pycolmap alone, say) may have merged its rows meanwhile
        if out.exists():
            result["cases"] = json.loads(out.read_text())["cases"]
        if tag in result["cases"]:  # rows not run again: those of an earlier run on the same frames
            ran = {r["method"] for r in case["rows"]}
            kept = [r for r in result["cases"][tag]["rows"] if r["method"] not in ran
                    and (args.no_colmap or not r["method"].startswith("pycolmap"))]
            case["rows"] = sorted(case["rows"] + kept, key=lambda r: (r["method"].startswith("pycolmap"), r["method"]))
        result["cases"][tag] = case
        RESULTS.mkdir(exist_ok=True)
        with atomic_file(out) as f:
            f.write(json.dumps(result, indent=2, default=float))
        save_picture(args.sweep, result["cases"], RESULTS / f"panorama_3d_{args.sweep}.png")
        print(json.dumps({tag: case}, indent=1, default=float), flush=True)


if __name__ == "__main__":
    main()
