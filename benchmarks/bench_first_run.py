"""The first run after ``pip install`` vs a warm one: ``scope3d bundle-adjust`` on BAL ladybug-49-7776
(``--job bundle-adjust``, the default), or ``scope3d localize`` / ``scope3d map`` on a small dome phantom.

Two wheels are built from this checkout with pip (as ``pip install`` builds one): the normal one, whose
build compiles every numba kernel ahead of time (setup.py, scope3d.utils.aot), and one built with
SCOPE3D_AOT=0 (what a machine without a C compiler gets: numba compiles the kernels on first use).
Each is installed into a folder of its own (``pip install --no-deps --target``); every run is a fresh
process importing scope3d from that folder, with an empty numba cache of its own (NUMBA_CACHE_DIR):

* ``AOT, first run``: right after ``pip install``; ``AOT, second run``: the same again;
* ``JIT, first run``: every kernel compiles in the run; ``JIT, second run``: they load from numba's cache;
* ``Ceres, fresh process``: the peer (pycolmap, bench_bundle_bal.ceres_solve) on the same problem, its
  own import and set-up included in the process time (bundle-adjust only).

``--job localize``: the dome phantom at 320 x 320 (5 x 6 survey, its map by ``scope3d map``, an approach
to target 1 with a tool in view, the robot reporting +-1 mm), prepared once with this checkout's sources;
each run is ``scope3d localize MAP APPROACH`` (first frame's and median frame's time from its report.json).
``--job map``: each run is ``scope3d map`` of that survey. Results in first_run_<job>.json / .png.

Per run: wall and CPU time of the whole process (children's user + system, from process start: imports
included) and the solver's own time. Also the wheel builds' times (the compile moved to install).
Load averages are written with the results: the machine is shared.

Run: ``.venv/bin/python benchmarks/bench_first_run.py [--repeats 1] [--job localize|map]``. Needs pip and
the build dependencies of pyproject.toml (pip fetches them as for any install). Writes
benchmarks/results/first_run.json and first_run.png (bundle-adjust), first_run_<job>.json/.png otherwise.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "bal_ladybug_49_7776" / "problem-49-7776-pre.txt"
RESULTS = ROOT / "benchmarks" / "results"

CERES_RUN = """
import json, sys, time
sys.path.insert(0, sys.argv[2])
from bench_bundle_bal import ceres_solve
from scope3d.estimators.bundle import read_bal
out = ceres_solve(read_bal(sys.argv[1]), -1)
print(json.dumps(dict(solve_time_s=out["time_s"], final_cost=out["final_cost_reported"],
                      iterations=out["iterations"], kernels="Ceres")))
"""


def _timed(cmd: list[str], env: dict) -> tuple[subprocess.CompletedProcess, float, float]:
    """Run cmd; its wall time and CPU time (s, user + system of the child and its children)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr[-3000:]}")
    return done, wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def install(target: Path, *, aot: bool) -> dict:
    """Build a wheel of this checkout with pip and install it into ``target``; the build's times."""
    env = dict(os.environ, SCOPE3D_AOT="1" if aot else "0")
    env.pop("PYTHONPATH", None)
    with tempfile.TemporaryDirectory(prefix="scope3d-wheel-") as wheels:
        _, wall, cpu = _timed([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", str(ROOT), "-w", wheels],
                              env)
        wheel = next(Path(wheels).glob("scope3d-*.whl"))
        _timed([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target), str(wheel)],
               env)
    return {"wheel_build_wall_s": wall, "wheel_build_cpu_s": cpu,
            "aot_modules_installed": sorted(str(p.relative_to(target)) for p in (target / "scope3d").rglob("_*_aot.*"))}


def prepare_phantom(work: Path) -> dict[str, Path]:
    """The small dome survey, its map and one approach (this checkout's sources, numba warm): what the
    localize and map jobs read."""
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    cli = [sys.executable, "-m", "scope3d.cli.main"]
    paths = {"survey": work / "survey", "map": work / "map", "approach": work / "approach"}
    if not (paths["map"] / "map_points.npz").is_file():
        _timed(cli + ["phantom", "dome", "--size", "320x320", "--out", str(paths["survey"]), "--quiet"], env)
        _timed(cli + ["map", str(paths["survey"]), "--out", str(paths["map"]), "--quiet"], env)
        _timed(cli + ["phantom", "dome", "--size", "320x320", "--trajectory", "approach", "--target", "1",
                      "--pose-noise", "1", "--out", str(paths["approach"]), "--quiet"], env)
    return paths


def run_once(site: Path, cache_dir: Path, *, ceres: bool = False, job: str = "bundle-adjust",
             phantom: dict[str, Path] | None = None) -> dict:
    """One fresh process running ``job`` from the installed ``site`` (or Ceres on ladybug)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir), PYTHONPATH=str(site))
    with tempfile.TemporaryDirectory() as tmp:
        if ceres:
            cmd = [sys.executable, "-c", CERES_RUN, str(DATA), str(ROOT / "benchmarks")]
        elif job == "localize":
            cmd = [sys.executable, "-m", "scope3d.cli.main", "localize", str(phantom["map"]), str(phantom["approach"]),
                   "--out", str(Path(tmp) / "loc"), "--quiet"]
        elif job == "map":
            cmd = [sys.executable, "-m", "scope3d.cli.main", "map", str(phantom["survey"]), "--out",
                   str(Path(tmp) / "map"), "--quiet"]
        else:
            cmd = [sys.executable, "-m", "scope3d.cli.main", "bundle-adjust", str(DATA), "--report",
                   str(Path(tmp) / "report.json"), "--quiet", "--json"]
        done, wall, cpu = _timed(cmd, env)
        if job == "localize" and not ceres:
            frames = json.loads((Path(tmp) / "loc" / "report.json").read_text())["frames"]
            times = [f["time_ms"] for f in frames]
            return {"wall_s": wall, "cpu_s": cpu, "first_frame_ms": times[0], "median_frame_ms": float(sorted(times)[len(times) // 2]),
                    "localized": sum(f["status"] == "ok" for f in frames), "frames": len(frames)}
        if job == "map":
            return {"wall_s": wall, "cpu_s": cpu}
    report = json.loads(done.stdout)
    return {"wall_s": wall, "cpu_s": cpu, "solve_time_s": report["solve_time_s"], "final_cost": report["final_cost"],
            "iterations": report["iterations"], "kernels": report.get("kernels"),
            "assembly_threads": report.get("assembly_threads")}


SCENARIOS = ("AOT, first run", "AOT, second run", "JIT, first run", "JIT, second run", "Ceres, fresh process")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=1, help="times each scenario runs, fresh caches (1)")
    parser.add_argument("--job", choices=("bundle-adjust", "localize", "map"), default="bundle-adjust",
                        help="the command each run times (default bundle-adjust on ladybug)")
    args = parser.parse_args()
    if args.job == "bundle-adjust" and not DATA.is_file():
        print(f"missing {DATA}", file=sys.stderr)
        return 1
    load_before = os.getloadavg()
    scenarios = SCENARIOS if args.job == "bundle-adjust" else SCENARIOS[:4]
    runs: dict[str, list[dict]] = {name: [] for name in scenarios}
    with tempfile.TemporaryDirectory(prefix="scope3d-first-run-") as tmp:
        phantom = prepare_phantom(Path(tmp) / "phantom") if args.job != "bundle-adjust" else None
        sites = {"AOT": Path(tmp) / "aot", "JIT": Path(tmp) / "jit"}
        installs = {name: install(site, aot=name == "AOT") for name, site in sites.items()}
        for _ in range(args.repeats):
            for name, site in sites.items():
                with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
                    runs[f"{name}, first run"].append(run_once(site, Path(cache), job=args.job, phantom=phantom))
                    runs[f"{name}, second run"].append(run_once(site, Path(cache), job=args.job, phantom=phantom))
            if args.job == "bundle-adjust":
                with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
                    runs["Ceres, fresh process"].append(run_once(sites["AOT"], Path(cache), ceres=True))
    keys = [k for k in runs["AOT, first run"][0] if k.endswith(("_s", "_ms"))]
    best = {name: {key: min(r[key] for r in rs) for key in keys} for name, rs in runs.items()}
    result = {
        "job": args.job, "problem": DATA.name if args.job == "bundle-adjust" else "dome phantom 320x320",
        "repeats": args.repeats, "installs": installs, "runs": runs, "best": best,
        "first_run_penalty_aot": {k: best["AOT, first run"][k] - best["AOT, second run"][k] for k in keys},
        "first_run_penalty_jit": {k: best["JIT, first run"][k] - best["JIT, second run"][k] for k in keys},
        "load_average_before": load_before,
    }
    if args.job == "bundle-adjust":
        result["solve_time_ratio_aot_first_run_over_ceres"] = (
            best["AOT, first run"]["solve_time_s"] / best["Ceres, fresh process"]["solve_time_s"])
        result["process_wall_ratio_aot_first_run_over_ceres"] = (
            best["AOT, first run"]["wall_s"] / best["Ceres, fresh process"]["wall_s"])
    result["load_average_after"] = os.getloadavg()
    stem = "first_run" if args.job == "bundle-adjust" else f"first_run_{args.job}"
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=2) + "\n")
    _plot(best, RESULTS / f"{stem}.png", args.job)
    print(json.dumps({k: result[k] for k in ("installs", "best", "first_run_penalty_aot", "first_run_penalty_jit")},
                     indent=2))
    print(f"load average before {load_before[0]:.1f}, after {result['load_average_after'][0]:.1f}")
    return 0


def _plot(best: dict, path: Path, job: str) -> None:
    sys.path.insert(0, str(ROOT / "src"))
    from scope3d.utils.figures import new_figure, save_figure

    fig = new_figure((8.0, 3.6), dpi=110)
    ax = fig.add_subplot()
    names = list(best)
    x = range(len(names))
    ax.bar([i - 0.27 for i in x], [best[n]["wall_s"] for n in names], width=0.27, label="process wall")
    ax.bar(list(x), [best[n]["cpu_s"] for n in names], width=0.27, label="process CPU")
    third = "solve_time_s" if job == "bundle-adjust" else "first_frame_ms" if job == "localize" else None
    if third:
        scale = 1e-3 if third.endswith("_ms") else 1.0
        ax.bar([i + 0.27 for i in x], [scale * best[n][third] for n in names], width=0.27,
               label="solve (wall)" if job == "bundle-adjust" else "first frame (wall)")
    ax.set_xticks(list(x), names, fontsize=7)
    ax.set_ylabel("seconds (best of the repeats)")
    what = "bundle-adjust ladybug-49" if job == "bundle-adjust" else f"{job}, dome phantom 320 px"
    ax.set_title(f"scope3d {what} after pip install: compiled at install (AOT) vs JIT", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
