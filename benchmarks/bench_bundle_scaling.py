"""Time per iteration and peak memory of scope3d's bundle adjuster on BAL-like synthetic problems.

Problems of about 10k, 100k and 1M observations: a row of cameras, each point seen by 4 consecutive
ones, per-camera intrinsics (f, k1, k2; square pixels; principal point fixed), poses as (w, t), no gauge
fixed — the structure of the BAL files. 0.5 px noise, perturbed start. Each size runs in its own process
(peak RSS from /usr/bin/time -v covers the scene generation too) for a few LM iterations with the
convergence tests disabled. Time per iteration excludes the one-off setup (structure of the reduced
system, first linearisation), which is reported separately.

Run: ``.venv/bin/python benchmarks/bench_bundle_scaling.py`` (about 1-2 minutes).
Writes benchmarks/results/bundle_scaling.json and bundle_scaling.png.
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "src"))

# (cameras, points) for ~10k, 100k, 1M observations at 4 observations per point
SIZES = {"10k": (50, 2_500), "100k": (250, 25_000), "1M": (1_000, 250_000)}
ITERATIONS = 5


def run_single(name: str) -> dict:
    from scope3d.estimators.bundle import BundleProblem, SolverOptions, solve, warm_up
    from scope3d.phantoms.bundle_scene import make_scene

    warm_up()
    m, n = SIZES[name]
    scene = make_scene(m, n, observations_per_point=4, pixel_noise_px=0.5, seed=1)
    rng = np.random.default_rng(2)
    intr = np.tile(scene.intrinsics, (m, 1))
    intr[:, 1] = intr[:, 0]
    problem = BundleProblem(
        scene.observations_px, scene.camera_index, scene.point_index,
        scene.rotations, scene.translations + rng.normal(0, 0.01, (m, 3)),
        scene.points + rng.normal(0, 0.05, (n, 3)), intr * (1 + rng.normal(0, 0.002, (m, 6))),
        position_parameter="translation", square_pixels=True,
    )
    problem.fix("intrinsics", components=["cx", "cy"])
    options = SolverOptions(max_iterations=ITERATIONS, function_tolerance=0.0, gradient_tolerance=0.0,
                            parameter_tolerance=0.0)
    start = time.perf_counter()
    result = solve(problem, options)
    total = time.perf_counter() - start
    setup = result.log[0].time_s
    return {
        "name": name,
        "num_cameras": m,
        "num_points": n,
        "num_observations": problem.num_observations,
        "camera_side_parameters": 6 * (problem.num_cameras + problem.num_groups),
        "linear_solver": result.linear_solver,
        "iterations": result.iterations,
        "setup_s": setup,
        "solve_time_s": total,
        "time_per_iteration_s": (result.log[-1].time_s - setup) / max(result.iterations, 1),
        "initial_cost": result.initial_cost,
        "final_cost": result.final_cost,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--single", choices=list(SIZES), help=argparse.SUPPRESS)
    parser.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    args = parser.parse_args()
    if args.single:
        print("RESULT " + json.dumps(run_single(args.single)))
        return 0

    rows = []
    for name in args.sizes:
        cmd = ["/usr/bin/time", "-v", sys.executable, __file__, "--single", name]
        out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
        if out.returncode != 0:
            raise RuntimeError(out.stderr[-3000:])
        row = json.loads(next(line for line in out.stdout.splitlines() if line.startswith("RESULT "))[7:])
        row["peak_rss_mb"] = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", out.stderr).group(1)) / 1024
        rows.append(row)
        print(f"{name:5s} {row['num_observations']:9d} obs  {row['linear_solver']:6s}  setup {row['setup_s']:7.2f} s  "
              f"{row['time_per_iteration_s']:7.3f} s/iteration  peak {row['peak_rss_mb']:7.0f} MB", flush=True)

    per_obs = [r["time_per_iteration_s"] / r["num_observations"] * 1e6 for r in rows]
    summary = {"iterations_each": ITERATIONS, "rows": rows,
               "microseconds_per_observation_per_iteration": per_obs}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "bundle_scaling.json").write_text(json.dumps(summary, indent=2))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = np.array([r["num_observations"] for r in rows], dtype=float)
    t = np.array([r["time_per_iteration_s"] for r in rows])
    mem = np.array([r["peak_rss_mb"] for r in rows])
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.5))
    ax1.loglog(k, t, "o-", label="scope3d")
    ax1.loglog(k, t[0] * k / k[0], "k--", lw=0.8, label="linear")
    ax1.set_xlabel("observations")
    ax1.set_ylabel("time per LM iteration [s]")
    ax1.legend()
    ax1.grid(True, which="both", alpha=0.3)
    ax2.loglog(k, mem, "o-")
    ax2.set_xlabel("observations")
    ax2.set_ylabel("peak RSS [MB]")
    ax2.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(RESULTS / "bundle_scaling.png", dpi=110)
    plt.close(fig)
    print("µs per observation per iteration: " + ", ".join(f"{v:.2f}" for v in per_obs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
