"""A production line of thread scans on a Dask cluster: one job per hole, one result folder per hole.

    done       <- holes whose folder already holds report.json (skipped: a rerun resumes)
    jobs       <- one task per remaining hole on the cluster (a LocalCluster, or a scheduler's address)
    results    <- each task writes its hole's folder atomically (complete or absent), and returns a line
    summary    <- summary.csv and summary.json over every hole, done before or now

A worker killed mid-hole loses nothing finished: finished holes are on disk, and the scheduler runs the
killed worker's hole again on another worker (Dask reschedules the tasks of a lost worker, up to its
``allowed-failures``). A hole that fails on bad input is recorded as ``error`` and not retried.
"""
from __future__ import annotations

import csv
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from scope3d.errors import InputError
from scope3d.io.json_object import read_json_object
from scope3d.pipelines.thread_scan import ThreadScanOptions
from scope3d.utils.atomic import atomic_directory, atomic_file
from scope3d.utils.jsonio import write_json
from scope3d.utils.progress import Progress, advance, stage

SUMMARY_FIELDS = ("hole", "status", "verdict", "minor_diameter_mm", "major_diameter_mm", "pitch_diameter_mm",
                  "pitch_mm", "defects", "time_s", "message")


@dataclass
class ThreadBatchResult:
    """rows : one dict per hole (SUMMARY_FIELDS); skipped : holes already done; time_s : wall time."""

    rows: list[dict]
    skipped: list[str]
    time_s: float
    workers: int
    log: list[str] = field(default_factory=list)

    def report(self) -> dict:
        """The batch's report.json: counts, wall time (s) and one row per hole (as in summary.csv)."""
        n_errors = sum(r["status"] == "error" for r in self.rows)
        return {"job": "batch thread-scan", "n_holes": len(self.rows), "n_measured": len(self.rows) - n_errors,
                "n_skipped": len(self.skipped), "n_errors": n_errors, "workers": self.workers,
                "time_s": self.time_s, "holes": self.rows}

    def summary(self) -> str:
        lines = [f"{'hole':24s} {'status':7s} {'verdict':13s} {'D1':>8s} {'D':>8s} {'D2':>8s} {'P':>7s} defects"]
        for r in self.rows:
            if r["status"] == "error":
                lines.append(f"{r['hole']:24s} error   {r['message']}")
                continue
            lines.append(f"{r['hole']:24s} {r['status']:7s} {r['verdict']:13s} {r['minor_diameter_mm']:8.4f} "
                         f"{r['major_diameter_mm']:8.4f} {r['pitch_diameter_mm']:8.4f} {r['pitch_mm']:7.4f} {r['defects']}")
        n_done = sum(r["status"] != "error" for r in self.rows)
        lines.append(f"{n_done} of {len(self.rows)} holes measured ({len(self.skipped)} done before) in "
                     f"{self.time_s:.1f} s on {self.workers} worker(s)")
        return "\n".join(lines)


def hole_names(datasets: list[Path]) -> list[str]:
    """A result folder name per dataset: its folder name, made unique with its position if repeated."""
    names = [Path(d).resolve().name for d in datasets]
    return [n if names.count(n) == 1 else f"{n}-{k}" for k, n in enumerate(names)]


def _row_from_report(hole: str, report: dict, status: str) -> dict:
    g = report["gauge"]

    def value(key):  # a size the scan did not measure (its part of the profile unseen) is no number to list
        return g[key]["value"] if key in g and g[key].get("measured", True) else float("nan")

    return {"hole": hole, "status": status, "verdict": g["verdict"],
            "minor_diameter_mm": value("minor_diameter_mm"), "major_diameter_mm": value("major_diameter_mm"),
            "pitch_diameter_mm": value("pitch_diameter_mm"), "pitch_mm": value("pitch_mm"),
            "defects": len(g["defects"]), "time_s": sum(v for v in report.get("timings_s", {}).values() if v),
            "message": ""}


def scan_hole(dataset_dir: str, out_dir: str, options: ThreadScanOptions, hole: str,
              finish: Callable[[Path, str], None] | None = None) -> dict:
    """One hole, as a cluster task: scan ``dataset_dir`` into ``out_dir`` (written atomically) and return
    its summary row. Bad input gives an ``error`` row (retrying would not help). finish : called with the
    hole's folder, still temporary, and the hole's name before the folder is renamed into place (the CLI
    writes the hole's report.html there; it must be picklable for the cluster)."""
    from scope3d.io.dataset import load_dataset
    from scope3d.pipelines import thread_scan

    try:
        with atomic_directory(Path(out_dir)) as staged:
            result = thread_scan.run(options, load_dataset(dataset_dir), staged)
            if finish is not None:
                finish(staged, hole)
    except InputError as exc:
        return {"hole": hole, "status": "error", "verdict": "", "message": str(exc)}
    return _row_from_report(hole, result.report(), "done")


def run(options: ThreadScanOptions, datasets: list[str | Path], out_dir: str | Path, *,
        scheduler: str | None = None, n_workers: int = 2, progress: Progress | None = None,
        client=None, finish: Callable[[Path, str], None] | None = None) -> ThreadBatchResult:
    """Scan every hole in ``datasets`` on a Dask cluster into ``out_dir/<hole>/``, skipping holes done
    before; write ``out_dir/summary.csv`` and ``summary.json``. scheduler : a Dask scheduler's address
    (``tcp://host:8786``) or None for a LocalCluster of ``n_workers`` single-threaded processes.
    client : an existing ``distributed.Client`` (tests), used as is and not closed. finish : see
    :func:`scan_hole`."""
    from distributed import Client, LocalCluster, as_completed

    if not datasets:
        raise InputError("no datasets given")
    for d in datasets:
        if not Path(d).is_dir():
            raise InputError(f"{d}: not a dataset folder")
    if n_workers < 1:
        raise InputError(f"need at least one worker, got {n_workers}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    names = hole_names([Path(d) for d in datasets])
    rows, skipped, todo = {}, [], []
    for d, name in zip(datasets, names):
        report = out_dir / name / "report.json"
        if report.is_file():
            rows[name] = _row_from_report(name, read_json_object(report), "skipped")
            skipped.append(name)
        else:
            todo.append((str(Path(d).resolve()), name))
    # one thread per worker process: the job's own threads would fight over the cores
    job_options = ThreadScanOptions(**{**options.__dict__, "threads": 1})
    own = client is None
    cluster = None
    workers = n_workers
    stage(progress, "holes", len(todo))
    try:
        if own and todo:
            if scheduler:
                client = Client(scheduler)
            else:
                cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                       dashboard_address=None)
                client = Client(cluster)
        if todo:
            workers = len(client.scheduler_info()["workers"]) or n_workers
            futures = {client.submit(scan_hole, d, str(out_dir / name), job_options, name, finish,
                                     key=f"hole-{name}",
                                     pure=False): name for d, name in todo}
            for future in as_completed(futures):
                name = futures[future]
                try:
                    rows[name] = future.result()
                except Exception as exc:  # a task that kept killing workers, or a bug: record it, go on
                    rows[name] = {"hole": name, "status": "error", "verdict": "", "message": f"{type(exc).__name__}: {exc}"}
                advance(progress)
    finally:
        if own and client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
    ordered = [rows[n] for n in names]
    result = ThreadBatchResult(ordered, skipped, time.perf_counter() - t0, workers)
    write_summary(result, out_dir)
    return result


def write_summary(result: ThreadBatchResult, out_dir: Path) -> None:
    """summary.csv (one row per hole) and summary.json, each written atomically."""
    with atomic_file(out_dir / "summary.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=SUMMARY_FIELDS, extrasaction="ignore")
        writer.writeheader()
        for r in result.rows:
            writer.writerow({k: r.get(k, "") for k in SUMMARY_FIELDS})
    write_json(out_dir / "summary.json", {"holes": result.rows, "skipped": result.skipped, "time_s": result.time_s,
                                          "workers": result.workers})
