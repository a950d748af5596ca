"""``scope3d report``: (re)write a run folder's report.html (see :mod:`scope3d.report`, docs/report.md)."""
from __future__ import annotations

from pathlib import Path

from scope3d.cli.job_output import add_job_arguments, finish_job


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "report",
        help="write RUN_DIR/report.html: figures, pictures, 3D view, targets (one offline page)",
        description="Write RUN_DIR/report.html from a run folder of `scope3d map` or `scope3d axial` "
                    "(every job writes it already; run this after moving a dataset or to change the page's "
                    "point budget). The page is self-contained: it opens from the file system with no network.",
    )
    p.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="folder holding report.json")
    p.add_argument("--max-points", type=int, default=200_000,
                   help="vertices drawn per cloud at most; more are thinned to a seeded random subset and the "
                        "full PLY is linked (default 200000)")
    p.add_argument("--seed", type=int, default=0, help="seed of that thinning (default 0)")
    add_job_arguments(p)  # --quiet accepted for uniformity: the page is written without a progress bar
    p.set_defaults(func=_run)


def _run(args) -> int:
    from scope3d.errors import InputError
    from scope3d.report import ReportOptions, write_report

    if args.max_points < 1:
        raise InputError("--max-points must be >= 1")
    path = write_report(args.run_dir, ReportOptions(max_points=args.max_points, seed=args.seed))
    return finish_job(args, None, {"job": "report", "run_dir": str(args.run_dir), "report_html": str(path)},
                      [f"wrote {path}"])
