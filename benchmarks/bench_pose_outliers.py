"""Wrong reported poses (beyond their tolerance) against the per-frame test of the reports (issue 16 section 5).

A robot or tracker occasionally reports a pose that is not the camera's (a glitch, a stale sample). Bounded
adjustment trusts every box, so such a frame ends on its box's edge and drags the map. The map's pose check
(:mod:`scope3d.sfm.pose_checks`, its default: the linearised screen, then the exact test where it points) tests each report against the images and the other reports at a stated
false-alarm rate and releases the ones found wrong. This benchmark sweeps

  glitch size   -- the glitched frames' reported centres moved by G mm along x (``--glitches``; 0 = clean),
                   or turned by G degrees about x (``--turn-glitches``), the tolerance left as reported;
  glitched frames -- 1 or more frames (``--counts``), chosen from the middle of the frame order with a seed;
  seeds         -- phantom renderings and report noise (``--seeds``);
  survey        -- ``dome12``: dome, 12 frames of the 5x6 grid, 320 x 240, reports +-0.5 mm / +-0.25 deg
                   (docs/reliability.md section 5's case); ``dome30``: the whole 5x6 grid; ``dome56``: the
                   56-frame 7x8 survey, same camera;

and maps every dataset with the check on and off, in the same process. Recorded per run: mean surface
error direct and after ICP, the frames flagged, which glitched frames were found (hits) and which clean
frames were flagged (false alarms), the variance factor and CPU time. Results: results/pose_outliers.json
and pose_outliers.png (error with and without the check against the glitch size).

    PYTHONPATH=src python benchmarks/bench_pose_outliers.py [--quick]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from scope3d import phantoms  # noqa: E402
from scope3d.geometry.pose import Pose  # noqa: E402
from scope3d.geometry.rotation import rotvec_to_matrix  # noqa: E402
from scope3d.io.dataset import load_dataset  # noqa: E402
from scope3d.pipelines.surgical_map import MapOptions, run  # noqa: E402
from scope3d.sensor.pose_tolerance import MeasuredPose  # noqa: E402
from scope3d.sfm.pose_checks import PoseCheckOptions  # noqa: E402
from scope3d.utils.jsonio import write_json  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
SURVEYS = {"dome12": ("grid5x6", 12), "dome30": ("grid5x6", 30), "dome56": ("grid7x8", 56)}


def glitched(dataset, frames: list[int], shift_mm: float, turn_deg: float):
    poses = list(dataset.poses)
    for k in frames:
        m = poses[k]
        rotation = rotvec_to_matrix(np.deg2rad([turn_deg, 0.0, 0.0])) @ m.pose.rotation
        poses[k] = MeasuredPose(Pose.from_centre(rotation, m.pose.centre + [shift_mm, 0.0, 0.0]), m.tolerance)
    return replace(dataset, poses=poses)


def one_map(dataset, out: Path, check: bool) -> dict:
    options = replace(MapOptions(), figures=False, fluorescence=None, pose_check=PoseCheckOptions() if check else None)
    t0 = time.process_time()
    result = run(options, dataset, out)
    cpu = time.process_time() - t0
    r = result.report
    test = r["model_checks"].get("reported_pose_test")
    return {"direct_mm": r["surface_error_mm"]["direct"]["mean"], "after_icp_mm": r["surface_error_mm"]["after_icp"]["mean"],
            "flagged": [f["frame"] for f in test["flagged"]] if test else [],
            "statistics": [round(f["statistic"], 1) for f in test["flagged"]] if test else [],
            "variance_factor": test["variance_factor"] if test else None,
            "frames_tested": test["frames_tested"] if test else None,
            "frames_tested_exactly": test.get("frames_tested_exactly") if test else None,
            "cpu_s": round(cpu, 2), "pose_check_wall_s": r["timings_s"].get("pose check")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--surveys", default="dome12,dome56")
    ap.add_argument("--seeds", default="21,22,23")
    ap.add_argument("--glitches", default="0,1,2,5", help="centre shifts, mm (0: clean)")
    ap.add_argument("--turn-glitches", default="2", help="orientation glitches, deg (one frame)")
    ap.add_argument("--counts", default="1,2", help="glitched frames per dataset (shifts only)")
    ap.add_argument("--dome56-seeds", default="21", help="seeds for the 30- and 56-frame surveys (slow)")
    ap.add_argument("--quick", action="store_true", help="one seed, dome12, 0 and 2 mm")
    ap.add_argument("--out", default=str(RESULTS / "pose_outliers.json"))
    ap.add_argument("--merge", action="store_true",
                    help="keep the runs already in --out that this one does not repeat (run parts one at a time)")
    args = ap.parse_args(argv)
    if args.quick:
        args.surveys, args.seeds, args.glitches, args.turn_glitches, args.counts = "dome12", "21", "0,2", "", "1"
    runs = []
    tmp = Path(tempfile.mkdtemp(prefix="pose_outliers_"))
    for survey in args.surveys.split(","):
        trajectory, n_frames = SURVEYS[survey]
        seeds = args.seeds if survey == "dome12" else args.dome56_seeds
        for seed in [int(s) for s in seeds.split(",")]:
            seq = phantoms.generate("dome", trajectory, size=(320, 240), seed=seed, n_frames=n_frames, pose_noise_mm=0.5)
            dataset = load_dataset(phantoms.write(seq, tmp / f"{survey}_{seed}"))
            rng = np.random.default_rng(seed)
            middle = list(range(n_frames // 4, n_frames - n_frames // 4))
            cases = [("shift", float(g), c) for g in args.glitches.split(",") if g for c in
                     ([0] if float(g) == 0 else [int(c) for c in args.counts.split(",")])]
            cases += [("turn", float(g), 1) for g in args.turn_glitches.split(",") if g]
            if not runs:  # numba loads (or compiles) the kernels of the map and of the check on first use: not timed
                one_map(dataset, tmp / "warm-up", True)
            for kind, size, count in cases:
                frames = sorted(rng.choice(middle, size=count, replace=False).tolist()) if count else []
                ds = glitched(dataset, frames, size if kind == "shift" else 0.0, size if kind == "turn" else 0.0)
                row = {"survey": survey, "seed": seed, "kind": kind, "size": size, "glitched": [dataset.names[k] for k in frames]}
                # with and without the check in turn, first one then the other: neither order gets the warmer caches
                for check in ((True, False) if len(runs) % 2 == 0 else (False, True)):
                    row["check" if check else "no_check"] = one_map(ds, tmp / "map", check)
                found = set(row["check"]["flagged"])
                row["hits"] = len(found & set(row["glitched"]))
                row["false_alarms"] = sorted(found - set(row["glitched"]))
                runs.append(row)
                print(json.dumps(row), flush=True)
    out = Path(args.out)
    load = {args.surveys: list(os.getloadavg())}
    if args.merge and out.is_file():
        previous = json.loads(out.read_text())
        def key(r):
            return r["survey"], r["seed"], r["kind"], r["size"], len(r["glitched"])

        done = {key(r) for r in runs}
        runs = [r for r in previous["runs"] if key(r) not in done] + runs
        earlier = previous.get("load_average", {})
        load = {**(earlier if isinstance(earlier, dict) else {"earlier": earlier}), **load}
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json(out, {"load_average": load, "runs": runs})
    plot(runs, out.with_suffix(".png"))
    return 0


def plot(runs: list[dict], path: Path) -> None:
    from scope3d.utils.figures import new_figure, save_figure

    fig = new_figure(figsize=(10, 4))
    for a, key in enumerate(("direct_mm", "after_icp_mm")):
        ax = fig.add_subplot(1, 2, a + 1)
        for survey, marker in (("dome12", "o"), ("dome30", "^"), ("dome56", "s")):
            for check, colour in (("check", "tab:blue"), ("no_check", "tab:red")):
                rows = [r for r in runs if r["survey"] == survey and r["kind"] == "shift"]
                if not rows:
                    continue
                x = [r["size"] + 0.05 * len(r["glitched"]) for r in rows]
                ax.scatter(x, [r[check][key] for r in rows], marker=marker, color=colour, alpha=0.7,
                           label=f"{survey}, {'with' if check == 'check' else 'without'} the pose check")
        ax.set_yscale("log")
        ax.set_xlabel("glitch: reported centre moved by (mm)")
        ax.set_ylabel(f"mean surface error, {key.replace('_mm', '').replace('_', ' ')} (mm)")
        ax.grid(True, alpha=0.3)
    fig.axes[0].legend(fontsize=7)
    save_figure(fig, path)


if __name__ == "__main__":
    raise SystemExit(main())
