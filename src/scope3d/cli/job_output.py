"""What every job does on the command line around its work: build its run folder in a temporary sibling
with report.html (the report layer) inside before the folder is renamed into place, and speak the habits
shared by every job: ``--json`` prints the report as JSON on stdout
(nothing else goes there), ``--quiet`` silences progress; the exit codes are in every job's ``--help``."""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

EXIT_CODES = """\
exit status: 0 ok; 2 bad input (a missing or malformed file, a bad option: one line on stderr, nothing
half-written); 130 interrupted (Ctrl-C); 1 any other failure (a bug: the traceback is printed)."""


def add_job_arguments(parser: argparse.ArgumentParser, *, quiet: bool = True) -> None:
    """Add ``--json`` (and ``--quiet`` unless the job has its own) and the exit codes to the epilog."""
    parser.add_argument("--json", action="store_true",
                        help="print the job's report as JSON on stdout (and nothing else there)")
    if quiet:
        parser.add_argument("--quiet", action="store_true", help="no progress bars")
        # the old spelling of --quiet, kept hidden so that scripts written with it still run
        parser.add_argument("--no-progress", dest="quiet", action="store_true", help=argparse.SUPPRESS)
    parser.epilog = f"{parser.epilog}\n\n{EXIT_CODES}" if parser.epilog else EXIT_CODES
    if parser.formatter_class is argparse.HelpFormatter:
        parser.formatter_class = argparse.RawDescriptionHelpFormatter


def show_progress(args) -> bool:
    """Progress bars unless --quiet (or its hidden old spelling --no-progress) asks for silence."""
    return not getattr(args, "quiet", False)


def dataset_report_writer(report: dict, name: str, started: float) -> Callable[[Path], None]:
    """For a job whose output is a dataset folder (phantom, import): the ``finish`` hook of
    :func:`scope3d.io.dataset.write_dataset`. It completes ``report`` (in place) with what the folder holds
    and the job's wall time since ``started`` (``time.perf_counter()``), and writes report.json and
    report.html into the folder being built, so that they appear with the dataset or not at all. name : the
    folder's final name (the page's title)."""

    def finish(folder: Path) -> None:
        from scope3d.io.dataset import load_dataset
        from scope3d.report import write_report
        from scope3d.utils.jsonio import write_json

        dataset = load_dataset(folder)
        camera = dataset.camera
        report.update({
            "dataset": ".",  # the report's own folder: the page draws its cameras
            "n_frames": len(dataset), "image_size_px": [camera.width, camera.height], "fov_deg": camera.fov_deg,
            "fluorescence": dataset.fluorescence_paths is not None, "ground_truth": dataset.ground_truth is not None,
            "time_s": round(time.perf_counter() - started, 3)})
        write_json(folder / "report.json", report)
        write_report(folder, name=name)

    return finish


@contextmanager
def job_folder(out_dir: str | Path) -> Iterator[Path]:
    """The run folder ``out_dir`` built whole: yields a temporary sibling for the job to write into; when the
    block succeeds, report.html is written there and the folder is renamed onto ``out_dir`` (replacing a
    previous run's), so that a kill or an error never leaves a run without its page or half-written. A
    pipeline that writes its own folder atomically is given the temporary path and simply swaps it too.

    Raises InputError, before any work, if ``out_dir`` is a file, or a non-empty folder that is not a
    scope3d run (no report.json): the job replaces its folder whole and must not delete a user's files."""
    from scope3d.errors import InputError
    from scope3d.report import write_report
    from scope3d.utils.atomic import atomic_directory

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: is a file; --out needs a folder (it is replaced whole)")
    if out.is_dir() and any(out.iterdir()) and not (out / "report.json").is_file():
        raise InputError(f"{out}: a non-empty folder that is not a scope3d run (no report.json); the job "
                         "replaces its --out folder whole: give a new folder or a previous run's")
    with atomic_directory(out) as staged:
        yield staged
        write_report(staged, name=out.resolve().name)


def finish_job(args, out_dir: str | Path | None, report: dict, summary_lines: list[str]) -> int:
    """Print the report as JSON (``--json``) or the summary lines, with the page :func:`job_folder` wrote
    into ``out_dir`` (when the job has an output folder). Returns the exit status 0."""
    from scope3d.utils.jsonio import json_default

    lines = list(summary_lines)
    if out_dir is not None:
        lines.append(f"wrote {Path(out_dir) / 'report.html'}")
    if getattr(args, "json", False):
        sys.stdout.write(json.dumps(report, indent=2, default=json_default) + "\n")
    else:
        for line in lines:
            print(line)
    return 0


def check_dataset_output(out: Path) -> None:
    """For a job whose output is a dataset (phantom, import): refuse to replace a folder that is not a
    scope3d dataset, since it may be someone's work."""
    from scope3d.errors import InputError

    if out.exists() and not (out.is_dir() and (not any(out.iterdir()) or (out / "dataset.json").is_file())):
        raise InputError(f"{out}: exists and is not a scope3d dataset; choose another --out")


def finish_import(args, out: Path, report: dict, notes: tuple[str, ...] = ()) -> int:
    """An import's summary (or its report as JSON, --json), then ``notes`` (lines of warning); report.json
    and report.html are in ``out``."""
    from scope3d.io.dataset import load_dataset

    return finish_job(args, None, report, [load_dataset(out).summary(), *notes, f"wrote {out / 'report.html'}"])
