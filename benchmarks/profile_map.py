"""Where ``scope3d map`` spends its time, from process start (issue 17): CPU seconds per stage.

The machine is shared, so wall clock is noisy; CPU time (``time.process_time``: all threads of this process)
is what a quiet machine would show as wall time for single-threaded stages. The map runs in this process
exactly as ``scope3d map DATASET --out DIR --no-progress`` (through ``scope3d.cli.main.main``), under cProfile
with a process-CPU timer; each stage's cumulative CPU is read off its pipeline function. Writes
benchmarks/results/profile_map.json (and prints a Markdown table for docs/performance.md), or ``--result PATH``;
the peak resident memory is the kernel's high-water mark of this process image (``VmHWM`` of
/proc/self/status: exact, not sampled; unlike ``getrusage``'s ``ru_maxrss`` it does not inherit the peak of
a parent that forked this process). Each stage also gets its own peak (the mark restarted at the stage's start
by writing ``5`` to /proc/self/clear_refs; the process's peak is the largest of them and of what ran between
stages) and the resident size it starts from. Run:
    PYTHONPATH=src .venv/bin/python benchmarks/profile_map.py DATASET [--out DIR] [--result PATH]

DATASET: e.g. ``scope3d phantom dome --out /tmp/dome`` (the 30-frame dome, as bench_map_dome.py renders it).
"""
from __future__ import annotations

import time

CPU_AT_START = time.process_time()  # interpreter start-up, before any import of ours
WALL_AT_START = time.perf_counter()

import argparse  # noqa: E402
import cProfile  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import pstats  # noqa: E402
import resource  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "benchmarks" / "results"

# (stage, pipeline function of scope3d.pipelines.surgical_map) in the order run() calls them
STAGES = [
    ("features", "detect_features"),
    ("matching", "match_frames"),
    ("bundle (tracks, triangulation, BA)", "reconstruct"),
    ("surface", "build_surface"),
    ("fluorescence", "locate_targets"),
    ("evaluation", "evaluate_map"),
    ("outputs", "write_outputs"),
]


def _timed(function, cpu: dict, wall: dict, peak: dict, name: str):
    def wrapper(*args, **kwargs):
        c0, w0 = time.process_time(), time.perf_counter()
        peak["between stages"] = max(peak.get("between stages", 0.0), _peak_rss_kb())  # before the reset loses it
        peak.setdefault(f"{name} at start", _status_kb("VmRSS"))
        _reset_peak_rss()
        try:
            return function(*args, **kwargs)
        finally:
            cpu[name] = cpu.get(name, 0.0) + time.process_time() - c0
            wall[name] = wall.get(name, 0.0) + time.perf_counter() - w0
            peak[name] = max(peak.get(name, 0.0), _peak_rss_kb())
    return wrapper


def _reset_peak_rss() -> None:
    """Restart the kernel's high-water mark at the current resident size (Linux >= 4.0: ``5`` to
    /proc/self/clear_refs), so that each stage's own peak can be read; a no-op elsewhere."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _peak_rss_kb() -> float:
    """High-water mark of this process's resident memory since exec or the last reset, kB (Linux: VmHWM;
    elsewhere ru_maxrss)."""
    return _status_kb("VmHWM")


def _status_kb(field: str) -> float:
    """A memory field of /proc/self/status, kB (``ru_maxrss`` where there is no such file)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return float(line.split()[1])
    except OSError:
        pass
    return float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--out", default=None)
    parser.add_argument("--cprofile", type=int, default=0, metavar="N",
                        help="also run under cProfile (process-CPU timer; it slows Python-heavy code) and list "
                             "the N functions with the most own CPU")
    parser.add_argument("--result", default=str(OUT / "profile_map.json"), metavar="PATH",
                        help="where to write the JSON (default benchmarks/results/profile_map.json)")
    args = parser.parse_args()
    out = args.out or tempfile.mkdtemp(prefix="profile_map_")

    cpu0, wall0 = time.process_time(), time.perf_counter()
    import scope3d.cli.main as cli  # the CLI's own imports are part of what a user waits for
    import scope3d.pipelines.surgical_map as pipeline  # what `scope3d map` imports before it starts

    cpu_imports, wall_imports = time.process_time() - cpu0, time.perf_counter() - wall0
    cpu: dict = {}
    wall: dict = {}
    peak: dict = {}
    for _, name in STAGES:  # run() looks its stages up as module globals at call time
        setattr(pipeline, name, _timed(getattr(pipeline, name), cpu, wall, peak, name))
    profiler = cProfile.Profile(time.process_time) if args.cprofile else None
    c0, w0 = time.process_time(), time.perf_counter()
    if profiler:
        profiler.enable()
    cli.main(["map", args.dataset, "--out", out, "--no-progress"])
    if profiler:
        profiler.disable()
    cpu_run, wall_run = time.process_time() - c0, time.perf_counter() - w0
    rows = [{"stage": "interpreter start-up", "cpu_s": CPU_AT_START, "wall_s": None},
            {"stage": "imports (CLI, pipeline and what it imports)", "cpu_s": cpu0 - CPU_AT_START + cpu_imports,
             "wall_s": wall0 - WALL_AT_START + wall_imports}]
    staged_cpu = sum(cpu.values())
    staged_wall = sum(wall.values())
    rows.append({"stage": "load dataset and frames, other", "cpu_s": cpu_run - staged_cpu, "wall_s": wall_run - staged_wall})
    rows += [{"stage": stage, "cpu_s": cpu.get(name, 0.0), "wall_s": wall.get(name, 0.0),
              "peak_rss_mb": round(peak[name] / 1024.0, 1) if name in peak else None,
              "rss_at_start_mb": round(peak[f"{name} at start"] / 1024.0, 1) if name in peak else None}
             for stage, name in STAGES]
    # the figures are drawn in a child process (scope3d.utils.background) while the evaluation runs: its CPU
    # is not this process's, and its wall time overlaps the stages'
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    rows.append({"stage": "figures (child process, concurrent)", "cpu_s": children.ru_utime + children.ru_stime,
                 "wall_s": None})
    rows.append({"stage": "total from process start", "cpu_s": time.process_time() + children.ru_utime + children.ru_stime,
                 "wall_s": time.perf_counter() - WALL_AT_START})
    for r in rows:
        r["cpu_s"] = round(r["cpu_s"], 3)
        r["wall_s"] = None if r["wall_s"] is None else round(r["wall_s"], 3)
    report = json.loads((Path(out) / "report.json").read_text())
    result = {"dataset": args.dataset, "load_average_1_5_15min": [round(v, 2) for v in os.getloadavg()],
              "cprofile": bool(profiler), "stages": rows, "n_frames": report["n_frames"],
              "n_features": report["n_features"], "n_pairs": report["n_pairs"], "n_matches": report["n_matches"],
              "n_points": report["n_points"], "n_observations": report["n_observations"],
              "peak_rss_mb": round(max([_peak_rss_kb(), *peak.values()]) / 1024.0, 1),
              "surface_error_mm": {k: report["surface_error_mm"][k] for k in ("direct", "after_icp")}
              if "surface_error_mm" in report else None}
    if profiler:
        stats = pstats.Stats(profiler)
        top = sorted(stats.stats.items(), key=lambda kv: kv[1][2], reverse=True)[: args.cprofile]
        result["top_functions_by_own_cpu_s"] = [
            {"function": f"{Path(f).name}:{line}:{n}", "own_cpu_s": round(v[2], 3), "cumulative_cpu_s": round(v[3], 3),
             "calls": v[1]} for (f, line, n), v in top]
    Path(args.result).parent.mkdir(parents=True, exist_ok=True)
    Path(args.result).write_text(json.dumps(result, indent=2) + "\n")
    print(f"load average {result['load_average_1_5_15min']}" + (" (under cProfile)" if profiler else ""))
    print("| stage | CPU s | wall s | resident at start MB | peak MB |\n| --- | ---: | ---: | ---: | ---: |")
    for r in rows:
        wall_text = "" if r["wall_s"] is None else f"{r['wall_s']:.2f}"
        mb = "".join(f" {r[k]:.0f} |" if r.get(k) is not None else " |" for k in ("rss_at_start_mb", "peak_rss_mb"))
        print(f"| {r['stage']} | {r['cpu_s']:.2f} | {wall_text} |{mb}")
    print(f"peak resident memory {result['peak_rss_mb']:.0f} MB")
    for t in result.get("top_functions_by_own_cpu_s", []):
        print(f"{t['own_cpu_s']:8.3f} {t['cumulative_cpu_s']:8.3f} {t['calls']:8d}  {t['function']}")


if __name__ == "__main__":
    main()
