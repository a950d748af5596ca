"""``scope3d thread-scan`` (one tapped hole) and ``scope3d batch thread-scan`` (many, on Dask)."""
from __future__ import annotations

from pathlib import Path

from scope3d.cli.job_output import add_job_arguments, finish_job, job_folder, show_progress
from scope3d.cli.lazy import LazyChoices


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "thread-scan",
        help="measure a tapped hole from a side-view quadrant scan (virtual 6H thread gauge)",
        description="Side-view thread metrology (reference ch. 8): a sparse map per quadrant with the stage's "
                    "axial poses, feature-based registration of the quadrants with the loop closure, outlier "
                    "removal, and a virtual ISO 965-1 6H gauge (minor, major, pitch diameter, pitch, flank angle, "
                    "damaged crests). Writes cloud.ply, quadrants/, report.json, registration.png, unwrapped.png.",
    )
    p.add_argument("dataset", type=Path, help="dataset folder with quadrants.json (see docs/thread_metrology.md)")
    p.add_argument("--out", type=Path, required=True, help="output folder (replaced when complete)")
    p.add_argument("--thread", metavar="SIZE", choices=LazyChoices("scope3d.geometry.iso_thread", "THREAD_SIZES"),
                   help="nominal thread: %(choices)s (default: the one quadrants.json names, else M8x1.25)")
    p.add_argument("--frame-gap", type=int, metavar="N",
                   help="match frames up to N steps apart within a quadrant (default: from the scan itself, "
                        "its step and side view read off the poses, so that matched frames' views of the "
                        "nominal thread's wall overlap by half, as the scan plan does)")
    add_job_arguments(p)
    p.set_defaults(func=_run_scan)

    b = subparsers.add_parser(
        "batch", help="run a job over many datasets on a Dask cluster (thread-scan)",
        description="Production-line runs on Dask: one result folder per dataset and a summary table; a rerun "
                    "skips finished datasets; a killed worker's dataset is run again.")
    bsub = b.add_subparsers(dest="job", metavar="JOB")
    t = bsub.add_parser("thread-scan", help="thread-scan every hole",
                        description="Thread-scan every DATASET into OUT/<dataset name>/ (each with its report.json "
                                    "and report.html); OUT/summary.csv holds a verdict per hole, OUT/report.json "
                                    "and OUT/report.html the batch's.")
    t.add_argument("datasets", type=Path, nargs="+", metavar="DATASET", help="hole dataset folders")
    t.add_argument("--out", type=Path, required=True, help="folder of the per-hole results and the summary")
    t.add_argument("--thread", metavar="SIZE", choices=LazyChoices("scope3d.geometry.iso_thread", "THREAD_SIZES"),
                   help="nominal thread: %(choices)s (default: the one each hole's quadrants.json names, else "
                        "M8x1.25)")
    t.add_argument("--frame-gap", type=int, metavar="N",
                   help="match frames up to N steps apart within a quadrant (default: from the scan itself, "
                        "its step and side view read off the poses, so that matched frames' views of the "
                        "nominal thread's wall overlap by half, as the scan plan does)")
    t.add_argument("--scheduler", metavar="ADDRESS",
                   help="Dask scheduler address (e.g. tcp://host:8786); default: a local cluster")
    t.add_argument("--workers", type=int, default=2, metavar="N",
                   help="local cluster worker processes (default 2; ignored with --scheduler)")
    add_job_arguments(t)
    t.epilog += "\nA batch also exits with 1 when a hole failed (its row in summary.csv says why)."
    t.set_defaults(func=_run_batch)
    b.set_defaults(func=_batch_help, batch_parser=b)


def _batch_help(args) -> int:
    args.batch_parser.print_help()
    return 2


def _run_scan(args) -> int:
    from scope3d.cli.progress import progress_bar
    from scope3d.io.dataset import load_dataset
    from scope3d.pipelines.thread_scan import run

    dataset = load_dataset(args.dataset)
    with job_folder(args.out) as staged, progress_bar(show_progress(args), "quadrant") as progress:
        result = run(_options(args), dataset, staged, progress=progress)
    return finish_job(args, args.out, result.report(), [
        result.summary(), f"wrote {args.out}/ (cloud.ply, quadrants/, report.json, registration.png, unwrapped.png)"])


def _run_batch(args) -> int:
    from scope3d.cli.progress import progress_bar
    from scope3d.pipelines.thread_batch import run
    from scope3d.report import write_report
    from scope3d.utils.jsonio import write_json

    with progress_bar(show_progress(args), "hole") as progress:
        result = run(_options(args), args.datasets, args.out, scheduler=args.scheduler,
                     n_workers=args.workers, progress=progress, finish=hole_page)
    report = result.report()
    # the batch folder is resumable (holes done before are kept), so it is not built whole: its page follows
    # its report.json, each written atomically
    write_json(args.out / "report.json", report)
    write_report(args.out)
    finish_job(args, args.out, report, [result.summary(), f"wrote {args.out}/summary.csv, report.json"])
    return 0 if report["n_errors"] == 0 else 1


def hole_page(folder, hole: str) -> None:
    """A hole's report.html, written in its folder before the folder is renamed into place (a cluster task:
    module-level, so that it pickles)."""
    from scope3d.report import write_report

    write_report(folder, name=hole)


def _options(args):
    from scope3d.errors import InputError
    from scope3d.pipelines.thread_scan import ThreadScanOptions

    if args.frame_gap is not None and args.frame_gap < 1:
        raise InputError(f"--frame-gap must be at least 1, got {args.frame_gap}")
    return ThreadScanOptions(designation=args.thread, frame_gap=args.frame_gap)
