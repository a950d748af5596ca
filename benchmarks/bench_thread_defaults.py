"""Thread metrology with the defaults (issue 38): ``scope3d phantom thread --trajectory quadrants`` with no
scan options (the scan plan's step, frames per quadrant and frame gap for the thread size, lens and side
view), then ``scope3d thread-scan DIR`` with no options, for every size the gauge knows at 45° and 90°.

Each (size, side view, seed) renders one hole made mid-class 6H (minor and pitch diameters half their
tolerance above the basic sizes, the major 0.05 mm over): with seed 23 it also carries a chipped crest
(``--defect 200:20:0.3``, the phantom's default turn, the thread's middle) and must ``fail`` with the chip
found within 10° of 200°; with seed 31 it is sound and must ``pass``. The issue's two literal cases (the
default hole, made at the basic sizes, i.e. on the 6H lower limits) run too: ``--side-view 90 --defect
200:20:0.3 --seed 23`` (must fail, the chip found) and ``--thread M10x1.5 --seed 31`` at 45° (a hole on its
limits: the right verdict is ``indeterminate`` unless the measurement is off by more than its U).
Seeds 23 and 31 were not used while developing (that used 1-3); seed 47 (``*_chip_s47``, run by name with
``--cases``) checks what was fixed after the two seeds' first run on a seed that run never saw, and seed 41
(``*_chip_s41``, ``*_sound_s41``, by name too) what was fixed after that (issue 38's third pass). The only
option given besides the hole is ``--size 400x320`` (the borescope's 1280x1024 frames take ~10x the CPU to
render and map; the plan's step, frames and gap do not depend on the pixel count, only on the field of view).

Errors against the as-made sizes and the true registration come from ``report.json``; the wall and CPU
(user + system of the child process) times of the render and the scan are measured per hole.

    PYTHONPATH=src .venv/bin/python benchmarks/bench_thread_defaults.py --data DIR [--cases a,b] [--rows F] [--reuse]
    PYTHONPATH=src .venv/bin/python benchmarks/bench_thread_defaults.py --merge F1,F2,...

writes the rows to ``--rows`` (default benchmarks/results/thread_defaults.json) after every hole;
``--merge`` combines row files into benchmarks/results/thread_defaults.json and draws thread_defaults.png.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
SIZES = ("M5x0.8", "M6x1", "M8x1.25", "M10x1.5", "M12x1.75")
VIEWS = (45, 90)
CHIP = (200.0, 20.0, 0.3)
CHECK_SEED = 47
# a fourth seed, never used while fixing anything: chipped and sound holes of every size and view
UNSEEN_SEED = 41
# targets of issue 13
DIAMETER_MM, PITCH_MM, ROTATION_DEG, OFFSET_MM, TIME_S, CHIP_DEG = 0.02, 0.005, 0.5, 0.02, 60.0, 10.0


def mid_class(designation: str) -> tuple[float, float, float]:
    """(minor, pitch, major) diameter offsets of a hole made in the middle of its 6H tolerances."""
    from scope3d.metrology.thread_tolerances import thread_limits

    lim = thread_limits(designation)
    return round((lim.d1_max_mm - lim.d1_min_mm) / 2, 4), round((lim.d2_max_mm - lim.d2_min_mm) / 2, 4), 0.05


def cases() -> dict:
    out = {}
    for size in SIZES:
        for view in VIEWS:
            minor, pitch, major = mid_class(size)
            hole = ["--thread", size, "--side-view", str(view), "--minor-diameter-offset", str(minor),
                    "--pitch-diameter-offset", str(pitch), "--major-diameter-offset", str(major)]
            tag = f"{size.split('x')[0].lower()}_{view}"
            out[f"{tag}_chip_s23"] = (hole + ["--defect", ":".join(map(str, CHIP)), "--seed", "23"], "fail", True)
            out[f"{tag}_sound_s31"] = (hole + ["--seed", "31"], "pass", False)
            # a third seed, never used while fixing what the first two showed: run by name (--cases)
            out[f"{tag}_chip_s{CHECK_SEED}"] = (hole + ["--defect", ":".join(map(str, CHIP)), "--seed", str(CHECK_SEED)],
                                               "fail", True)
            out[f"{tag}_chip_s{UNSEEN_SEED}"] = (hole + ["--defect", ":".join(map(str, CHIP)), "--seed",
                                                        str(UNSEEN_SEED)], "fail", True)
            out[f"{tag}_sound_s{UNSEEN_SEED}"] = (hole + ["--seed", str(UNSEEN_SEED)], "pass", False)
    out["issue_m8_90_chip_s23"] = (["--side-view", "90", "--defect", "200:20:0.3", "--seed", "23"], "fail", True)
    out["issue_m10_45_s31"] = (["--thread", "M10x1.5", "--seed", "31"], "indeterminate", False)
    return out


def timed(argv: list[str]) -> tuple[float, float, subprocess.CompletedProcess]:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "scope3d.cli.main", *argv], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT / "src")})
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, done


def run_case(name: str, data: Path, reuse: bool = False) -> dict:
    args, expected, chip = cases()[name]
    hole, scan = data / name, data / f"{name}_scan"
    row = {"case": name, "phantom_args": args + ["--size", "400x320"], "expected": expected,
           "load_before": os.getloadavg()}
    if reuse and (hole / "report.json").exists():  # the same render (same arguments), scanned again
        row.update(render_wall_s=None, render_cpu_s=None, render_reused=True)
    else:
        wall, cpu, done = timed(["phantom", "thread", "--trajectory", "quadrants", *row["phantom_args"], "--out",
                                 str(hole), "--no-progress"])
        row.update(render_wall_s=wall, render_cpu_s=cpu)
        if done.returncode != 0:
            row["error"] = (done.stderr.strip().splitlines() or ["?"])[-1]
            return row
    if scan.exists():
        shutil.rmtree(scan)
    row["scan_plan"] = json.loads((hole / "report.json").read_text()).get("scan_plan")
    wall, cpu, done = timed(["thread-scan", str(hole), "--out", str(scan), "--no-progress"])
    row.update(scan_wall_s=wall, scan_cpu_s=cpu, load_after=os.getloadavg())
    if done.returncode != 0:
        row["error"] = (done.stderr.strip().splitlines() or ["?"])[-1]
        return row
    report = json.loads((scan / "report.json").read_text())
    g, reg = report["gauge"], report["registration"]
    row["verdict"] = g["verdict"]
    row["verdict_right"] = g["verdict"] == expected
    row["message"] = g.get("message")
    row["defects"] = g.get("defects", [])
    if chip:
        found = [d for d in row["defects"] if abs((d["angle_deg"] - CHIP[0] + 180) % 360 - 180) <= CHIP_DEG]
        row["chip_found"] = bool(found)
    else:
        row["false_defects"] = len(row["defects"])
    row["gauge_errors_mm"] = reg.get("gauge_errors_mm")
    row["uncertainty_mm"] = {k: g[k]["uncertainty"] for k in ("minor_diameter_mm", "pitch_diameter_mm",
                                                            "major_diameter_mm", "pitch_mm") if k in g}
    row["rotation_error_deg"], row["offset_error_mm"] = reg.get("rotation_error_deg"), reg.get("offset_error_mm")
    row["timings_s"] = report["timings_s"]
    row["scan"] = report["scan"]
    e = row["gauge_errors_mm"]
    # a size the scan did not measure (its profile part unseen: a fitted guess, or a basic size held) meets
    # no target, whatever its error
    row["not_measured"] = [k.removesuffix("_mm") for k in ("minor_diameter_mm", "pitch_diameter_mm",
                                                           "major_diameter_mm") if g.get(k, {}).get("measured") is False]
    measured = [k for k in ("minor_diameter", "major_diameter", "pitch_diameter") if k not in row["not_measured"]]
    row["measured_within_targets"] = bool(e) and all(abs(e[k]) <= DIAMETER_MM for k in measured) \
        and abs(e["pitch"]) <= PITCH_MM and row["rotation_error_deg"] <= ROTATION_DEG \
        and row["offset_error_mm"] <= OFFSET_MM
    row["targets_met"] = row["measured_within_targets"] and not row["not_measured"]
    return row


def figure(rows: list[dict], path: Path) -> None:
    from scope3d.utils.figures import new_figure, save_figure

    fig = new_figure((11, 4.5))
    ax = fig.add_subplot(1, 2, 1)
    names = [r["case"] for r in rows if r.get("gauge_errors_mm")]
    for k, (key, marker) in enumerate((("minor_diameter", "o"), ("pitch_diameter", "s"), ("major_diameter", "^"))):
        ax.scatter(range(len(names)), [r["gauge_errors_mm"][key] for r in rows if r.get("gauge_errors_mm")],
                   marker=marker, label=key.replace("_", " "))
    ax.axhspan(-DIAMETER_MM, DIAMETER_MM, color="0.9", zorder=-1)
    ax.set_xticks(range(len(names)), names, rotation=70, fontsize=7)
    ax.set_ylabel("error against the as-made size (mm)")
    ax.set_title("diameters (grey: the ±0.02 mm target)")
    ax.legend(fontsize=7)
    ax = fig.add_subplot(1, 2, 2)
    done = [r for r in rows if "scan_wall_s" in r]
    ax.bar(range(len(done)), [r["scan_wall_s"] for r in done], label="thread-scan wall")
    ax.bar(range(len(done)), [r["scan_cpu_s"] for r in done], width=0.4, label="thread-scan CPU")
    ax.axhline(TIME_S, color="red", lw=1)
    ax.set_xticks(range(len(done)), [r["case"] for r in done], rotation=70, fontsize=7)
    ax.set_ylabel("s per hole (shared, loaded 2-core machine)")
    ax.legend(fontsize=7)
    save_figure(fig, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, help="folder for the rendered holes and scans")
    ap.add_argument("--cases", help="comma-separated case names (default: all)")
    ap.add_argument("--rows", type=Path, default=OUT / "thread_defaults.json")
    ap.add_argument("--merge", help="comma-separated row files to combine into results/thread_defaults.json")
    ap.add_argument("--reuse", action="store_true", help="scan a hole already rendered in --data again, not re-render it")
    a = ap.parse_args()
    if a.merge:
        rows = [r for f in a.merge.split(",") for r in json.loads(Path(f).read_text())["rows"]]
        order = list(cases())
        rows.sort(key=lambda r: order.index(r["case"]))
        def tally(sel):
            return {"cases": len(sel), "verdicts_right": sum(bool(r.get("verdict_right")) for r in sel),
                    "chips_found": f"{sum(bool(r.get('chip_found')) for r in sel)} of "
                                   f"{sum('chip_found' in r for r in sel)}",
                    "targets_met": sum(bool(r.get("targets_met")) for r in sel),
                    "measured_sizes_within_targets": sum(bool(r.get("measured_within_targets")) for r in sel),
                    "scan_under_60s_wall": sum(r.get("scan_wall_s", 1e9) < TIME_S for r in sel),
                    "scan_under_60s_cpu": sum(r.get("scan_cpu_s", 1e9) < TIME_S for r in sel)}

        def view(r):  # the phantom's default side view is 45°
            args = r["phantom_args"]
            return int(args[args.index("--side-view") + 1]) if "--side-view" in args else 45

        def seed(r):  # the two cases apart: their holes sit on the 6H lower limits
            return "issue" if r["case"].startswith("issue") else "s" + r["case"].rsplit("_s", 1)[1]

        summary = {**tally(rows), "by_side_view": {str(v): tally([r for r in rows if view(r) == v]) for v in VIEWS},
                   "by_side_view_and_seed": {f"{v} {k}": tally(sel) for v in VIEWS for k in sorted({seed(r) for r in rows})
                                             if (sel := [r for r in rows if view(r) == v and seed(r) == k])}}
        (OUT / "thread_defaults.json").write_text(json.dumps({"summary": summary, "rows": rows}, indent=1))
        figure(rows, OUT / "thread_defaults.png")
        print(json.dumps(summary, indent=1))
        return
    names = a.cases.split(",") if a.cases else [n for n in cases()
                                                if not n.endswith((f"_s{CHECK_SEED}", f"_s{UNSEEN_SEED}"))]
    a.data.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in names:
        rows.append(run_case(name, a.data, a.reuse))
        r = rows[-1]
        print(name, r.get("verdict"), r.get("chip_found"), r.get("gauge_errors_mm"), r.get("rotation_error_deg"),
              r.get("offset_error_mm"), r.get("scan_wall_s"), r.get("scan_cpu_s"), r.get("error"), flush=True)
        a.rows.write_text(json.dumps({"rows": rows}, indent=1))


if __name__ == "__main__":
    main()
