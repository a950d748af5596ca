"""The first run after ``pip install`` vs a warm one: ``scope3d bundle-adjust`` on BAL ladybug-49-7776.

Each run is a fresh process (what a user starts), with the numba kernels' on-disk cache in a folder of
its own (NUMBA_CACHE_DIR, so the cache the Makefile built beside the sources is not used):

* ``cold, API``: an empty cache, as right after ``pip install``; the Python API's ``solve`` with default
  threads (what ``scope3d bundle-adjust`` did before): every kernel it calls compiles in the run,
  the parallel Schur assembly included;
* ``warm, API``: the same cache again: kernels load from disk;
* ``cold, command``: ``scope3d bundle-adjust`` on an empty cache: it sees the parallel kernel missing,
  starts the background warm-up (:mod:`scope3d.estimators.bundle.jit`) and assembles on one thread;
* ``warm, command``: the command again once that warm-up has finished.

Wall time and CPU time (children's user + system; the detached warm-up's CPU is not counted) per run,
and the solver's own time. Load averages are written with the results: the machine is shared.

Run: ``.venv/bin/python benchmarks/bench_first_run.py [--iterations 5] [--repeats 2]``. Writes
benchmarks/results/first_run.json and first_run.png.
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


API_RUN = """
import json, sys, time
from scope3d.estimators.bundle import SolverOptions, bal_to_problem, read_bal, solve
result = solve(bal_to_problem(read_bal(sys.argv[1])), SolverOptions(max_iterations=int(sys.argv[2])))
print(json.dumps(dict(solve_time_s=result.solve_time_s, final_cost=result.final_cost, iterations=result.iterations)))
"""


def _timed(cmd: list[str], env: dict) -> tuple[dict, float, float]:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return json.loads(done.stdout), wall, cpu


def run_once(cache_dir: Path, iterations: int, *, api: bool = False) -> dict:
    """One process solving ladybug: ``scope3d bundle-adjust`` (api=False) or the Python API's ``solve``
    with its default threads (api=True: what the command did before it checked the cache). Its wall
    and CPU times (s; a detached background warm-up's CPU is not counted: it runs on the other core)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir), PYTHONPATH=str(ROOT / "src"))
    with tempfile.TemporaryDirectory() as tmp:
        if api:
            cmd = [sys.executable, "-c", API_RUN, str(DATA), str(iterations)]
        else:
            cmd = [sys.executable, "-m", "scope3d.cli.main", "bundle-adjust", str(DATA), "--report",
                   str(Path(tmp) / "report.json"), "--max-iterations", str(iterations), "--quiet", "--json"]
        report, wall, cpu = _timed(cmd, env)
    return {"wall_s": wall, "cpu_s": cpu, "solve_time_s": report.get("solve_time_s"),
            "final_cost": report["final_cost"], "iterations": report["iterations"],
            "assembly_threads": report.get("assembly_threads")}


def wait_for_background_warm_up(cache_dir: Path, timeout_s: float = 1800.0) -> float:
    """Seconds waited until the background warm-up's lock (one per cache folder) is gone."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir), PYTHONPATH=str(ROOT / "src"))
    lock = subprocess.run([sys.executable, "-c", "from scope3d.estimators.bundle.jit import _lock_path; "
                           "print(_lock_path())"], env=env, capture_output=True, text=True, check=True).stdout.strip()
    start = time.perf_counter()
    while Path(lock).exists() and time.perf_counter() - start < timeout_s:
        time.sleep(1.0)
    return time.perf_counter() - start


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=5, help="solver iterations per run (5)")
    parser.add_argument("--repeats", type=int, default=1, help="times each scenario runs, fresh caches (1)")
    args = parser.parse_args()
    if not DATA.is_file():
        print(f"missing {DATA}", file=sys.stderr)
        return 1
    load_before = os.getloadavg()
    runs: dict[str, list[dict]] = {name: [] for name in SCENARIOS}
    waits = []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
            runs["cold, API (every kernel compiles)"].append(run_once(Path(cache), args.iterations, api=True))
            runs["warm, API"].append(run_once(Path(cache), args.iterations, api=True))
        with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
            runs["cold, command (parallel kernel in the background)"].append(run_once(Path(cache), args.iterations))
            waits.append(wait_for_background_warm_up(Path(cache)))
            runs["warm, command"].append(run_once(Path(cache), args.iterations))
    summary = {name: {key: min(r[key] for r in rs) for key in ("wall_s", "cpu_s", "solve_time_s")}
               for name, rs in runs.items()}
    warm = summary["warm, API"]
    result = {
        "problem": DATA.name, "iterations": args.iterations, "repeats": args.repeats, "runs": runs, "best": summary,
        "first_run_penalty_before": {k: summary["cold, API (every kernel compiles)"][k] - warm[k] for k in ("wall_s", "cpu_s")},
        "first_run_penalty_now": {k: summary["cold, command (parallel kernel in the background)"][k]
                                  - summary["warm, command"][k] for k in ("wall_s", "cpu_s")},
        "background_warm_up_still_running_after_first_run_s": waits,
        "load_average_before": load_before, "load_average_after": os.getloadavg(),
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "first_run.json").write_text(json.dumps(result, indent=2) + "\n")
    _plot(summary, RESULTS / "first_run.png", args.iterations)
    print(json.dumps({k: result[k] for k in ("best", "first_run_penalty_before", "first_run_penalty_now")}, indent=2))
    print(f"load average before {load_before[0]:.1f}, after {result['load_average_after'][0]:.1f}")
    return 0


SCENARIOS = ("cold, API (every kernel compiles)", "warm, API", "cold, command (parallel kernel in the background)",
             "warm, command")


def _plot(summary: dict, path: Path, iterations: int) -> None:
    sys.path.insert(0, str(ROOT / "src"))
    from scope3d.utils.figures import new_figure, save_figure

    fig = new_figure((7.0, 3.6), dpi=110)
    ax = fig.add_subplot()
    names = list(summary)
    x = range(len(names))
    ax.bar([i - 0.2 for i in x], [summary[n]["wall_s"] for n in names], width=0.4, label="wall")
    ax.bar([i + 0.2 for i in x], [summary[n]["cpu_s"] for n in names], width=0.4, label="CPU")
    ax.set_xticks(list(x), [n.split(" (")[0] for n in names], fontsize=8)
    ax.set_ylabel("seconds (best of the repeats)")
    ax.set_title(f"scope3d bundle-adjust ladybug-49, {iterations} iterations: first run vs warm")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
