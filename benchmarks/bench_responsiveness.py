"""How fast the things the unit tests check as properties happen, in seconds (issue 31: timing targets live
here, not in tests/, where they failed on a loaded machine):

* ``lying_ply``: ``read_ply`` refusing a 64-byte PLY whose header claims 10^9 vertices (binary and ASCII):
  wall seconds per refusal (tests/test_mesh.py checks that nothing is parsed and the work does not grow
  with the claim);
* ``ctrl_c``: ``scope3d map`` and ``scope3d bundle-adjust`` (tests/kill_harness.py's small inputs) sent
  SIGINT the moment their first temporary output appears: wall seconds from the signal to the exit, and
  the CPU seconds the job spent after it against an uninterrupted run's from the same moment
  (tests/test_kill_and_interrupt.py checks the CPU ratio);
* ``map_laps``: the default map of the 400 x 400 dome phantom: the wall time around ``run``, the report's
  laps and the gap between them (tests/test_map.py checks on a jumping clock that every stage call lies in
  a lap).

Load averages are written with the results: the machine is shared. Run:
``PYTHONPATH=src python benchmarks/bench_responsiveness.py [--repeats 3]``; writes
benchmarks/results/responsiveness.json.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "src"))

from kill_harness import environment, jobs, litter, make_inputs, put_previous  # noqa: E402

RESULTS = REPO / "benchmarks" / "results" / "responsiveness.json"


def lying_ply(folder: Path, repeats: int) -> dict:
    from scope3d.errors import InputError
    from scope3d.io.ply import read_ply

    out = {}
    for fmt in ("binary_little_endian", "ascii"):
        path = folder / f"lie_{fmt}.ply"
        path.write_bytes(f"ply\nformat {fmt} 1.0\nelement vertex 1000000000\nproperty double x\nproperty double y\n"
                         f"property double z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                         .encode() + b"\0" * 64)
        seconds = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            try:
                read_ply(path)
            except InputError:
                pass
            seconds.append(time.perf_counter() - t0)
        out[fmt] = {"wall_s": [round(s, 6) for s in seconds]}
    return out


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _run(job, interrupt: bool) -> dict:
    """One run; at the first temporary output: CPU seconds so far (and SIGINT if ``interrupt``)."""
    before = set(litter(job))
    t0 = time.perf_counter()
    proc = subprocess.Popen(job.argv, env=environment(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            cwd=REPO)
    at_cpu = at_wall = None
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        if at_cpu is None and set(litter(job)) - before:
            at_cpu, at_wall = _cpu_s(proc.pid), time.perf_counter()
            if interrupt:
                proc.send_signal(signal.SIGINT)
        time.sleep(0.001)
    end_wall = time.perf_counter()
    proc.returncode = os.waitstatus_to_exitcode(status)
    return {"status": proc.returncode, "wall_s": round(end_wall - t0, 3),
            "after_first_temporary_wall_s": None if at_wall is None else round(end_wall - at_wall, 3),
            "after_first_temporary_cpu_s": None if at_cpu is None
            else round(usage.ru_utime + usage.ru_stime - at_cpu, 3)}


def ctrl_c(folder: Path, repeats: int) -> dict:
    inputs = make_inputs(folder / "in")
    chosen = {job.name: job for job in jobs(inputs, folder / "out")}
    out = {}
    for name in ("map", "bundle-adjust"):
        job = chosen[name]
        rows = []
        for _ in range(repeats):
            put_previous(job)
            uninterrupted = _run(job, interrupt=False)
            put_previous(job)
            interrupted = _run(job, interrupt=True)
            rows.append({"uninterrupted": uninterrupted, "interrupted": interrupted})
        out[name] = rows
    return out


def map_laps(folder: Path) -> dict:
    from scope3d import phantoms
    from scope3d.io.dataset import load_dataset
    from scope3d.pipelines.surgical_map import MapOptions, run

    seq = phantoms.generate("dome", "grid5x6", size=(400, 400), seed=0)
    dataset = load_dataset(phantoms.write(seq, folder / "dome"))
    t0 = time.perf_counter()
    result = run(MapOptions(), dataset, folder / "map")
    wall = time.perf_counter() - t0
    laps = result.report["timings_s"]
    return {"wall_s": round(wall, 3), "laps_s": laps, "gap_s": round(wall - sum(laps.values()), 4),
            "shortest_heavy_lap_s": min(laps[k] for k in ("features", "matching", "bundle", "surface",
                                                          "fluorescence", "evaluation"))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    report = {"load_average_at_start": os.getloadavg(), "cpus": os.cpu_count(), "repeats": args.repeats}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        report["lying_ply"] = lying_ply(tmp, args.repeats)
        report["ctrl_c"] = ctrl_c(tmp / "jobs", args.repeats)
        report["map_laps"] = map_laps(tmp)
    report["load_average_at_end"] = os.getloadavg()
    args.results.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
