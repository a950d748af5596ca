"""``scope3d bundle-adjust``: bound-constrained bundle adjustment of a BAL problem file."""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time

from scope3d.cli.job_output import add_job_arguments, finish_job

_BOUNDS_HELP = """\
BOUNDS_FILE format (one rule per line, '#' starts a comment; indices 0-based: *, 7, 0-9 or 1,4,10-12):
  camera INDICES COMPONENTS SPEC   components: rx ry rz (rotation relative to the initial one, rad,
                                   BAL frame), tx ty tz (translation), f k1 k2, or the groups
                                   rotation, translation, intrinsics, all (comma-separated)
  point INDICES COMPONENTS SPEC    components: x y z or all
      SPEC is 'fixed', 'LOWER UPPER' (absolute; -inf/inf allowed) or '+- HALF' (initial ± HALF)
  depth INDICES OX OY OZ AX AY AZ MIN MAX   depth (X - O).A/|A| of the points within [MIN, MAX]
  shell INDICES CX CY CZ RMIN RMAX          points within the spherical shell RMIN <= |X - C| <= RMAX
Example:
  camera 0 all fixed          # fix the gauge on the first camera
  camera * k1,k2 -1e-6 1e-6
  camera 1-5 translation +- 0.05
  shell * 0 0 0 1 50
Initial values outside their bounds are clamped onto them (with a warning).
See docs/bundle_adjustment.md."""


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "bundle-adjust",
        help="bound-constrained bundle adjustment of a BAL problem file",
        description="Refine cameras (pose, f, k1, k2) and points of a BAL problem "
        "(https://grail.cs.washington.edu/projects/bal/) by bound-constrained Levenberg-Marquardt "
        "(reference eq. 6.9-6.13); cost = 0.5 * sum of squared reprojection errors (pixels^2).",
        epilog=_BOUNDS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("problem_file", metavar="PROBLEM_FILE", help="BAL problem (uncompressed text)")
    parser.add_argument("--out", metavar="DIR",
                        help="write report.json (costs, iterations, times, memory, per-iteration log), "
                             "solution.bal (the solved problem) and convergence.png into DIR (created; the three "
                             "files are replaced together)")
    parser.add_argument("--bounds", metavar="BOUNDS_FILE", help="fixed/bounded parameters, format below")
    parser.add_argument("--intrinsic-bounds", metavar="FILE",
                        help="intrinsic_bounds.json from `scope3d calibrate`: every camera's f (from fx), k1 and "
                        "k2 stay within its bounds (cx, cy do not apply: BAL's principal point is the origin)")
    parser.add_argument("--loss", choices=["none", "huber", "cauchy"], default="none", help="robust loss")
    parser.add_argument("--loss-scale-px", type=float, default=1.0, help="robust loss scale in pixels (1.0)")
    parser.add_argument("--max-iterations", type=int, default=100, help="iteration cap (100)")
    parser.add_argument("--function-tolerance", type=float, default=1e-6,
                        help="stop when a step lowers the cost by less than this fraction (1e-6)")
    parser.add_argument("--linear-solver", choices=["auto", "dense", "sparse", "pcg"], default="auto",
                        help="reduced camera system solver (auto: dense when small, sparse LU, then PCG)")
    # the file-by-file outputs of before --out, kept (hidden) so that scripts written with them still run
    parser.add_argument("--report", metavar="REPORT_JSON", help=argparse.SUPPRESS)
    parser.add_argument("--output", metavar="BAL_FILE", help=argparse.SUPPRESS)
    parser.add_argument("--plot", metavar="PNG", help=argparse.SUPPRESS)
    add_job_arguments(parser)  # --quiet: no per-iteration progress on stderr
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from scope3d.estimators.bundle import (
        SolverOptions,
        apply_bounds_file,
        bal_to_problem,
        read_bal,
        result_to_bal,
        solve,
        write_bal,
    )
    from scope3d.errors import InputError
    from scope3d.utils.atomic import atomic_files

    options = SolverOptions(
        max_iterations=args.max_iterations, loss=args.loss, loss_scale_px=args.loss_scale_px,
        function_tolerance=args.function_tolerance, linear_solver=args.linear_solver,
    )
    if args.out is not None:
        if any((args.report, args.output, args.plot)):
            raise InputError("--out writes report.json, solution.bal and convergence.png: give it or the old "
                             "--report/--output/--plot, not both")
        if os.path.exists(args.out) and not os.path.isdir(args.out):
            raise InputError(f"{args.out}: is a file; --out needs a folder")
        os.makedirs(args.out, exist_ok=True)
        args.report, args.output, args.plot = (os.path.join(args.out, name)
                                               for name in ("report.json", "solution.bal", "convergence.png"))
    elif args.report is None:
        raise InputError("--out DIR is required (where report.json, solution.bal and convergence.png go)")
    outputs = [args.report] + [p for p in (args.output, args.plot) if p]
    if len({os.path.realpath(p) for p in outputs}) != len(outputs):
        raise InputError("--report, --output and --plot must name different files")
    t0 = time.perf_counter()
    bal = read_bal(args.problem_file)
    problem = bal_to_problem(bal)
    rules = apply_bounds_file(problem, args.bounds) if args.bounds else 0
    intrinsic_bounded: list[str] = []
    if args.intrinsic_bounds:
        from scope3d.estimators.bundle.bal import bound_bal_intrinsics
        from scope3d.io.intrinsic_bounds import read_intrinsic_bounds

        intrinsic_bounded = bound_bal_intrinsics(problem, *read_intrinsic_bounds(args.intrinsic_bounds))
    read_time = time.perf_counter() - t0
    if not args.quiet:
        print(f"{problem.summary()}; {rules} bound rule(s)", file=sys.stderr)

    def progress(record, _params) -> None:
        if args.quiet:
            return
        mark = "" if record.accepted else "  (rejected)"
        print(
            f"iter {record.iteration:4d}  cost {record.cost:.6e}  lambda {record.damping:.1e}  "
            f"|g_proj| {record.projected_gradient_norm:.2e}  active {record.active_set_size}  "
            f"{record.time_s:7.3f} s{mark}",
            file=sys.stderr,
        )

    result = solve(problem, options, callback=progress)
    if not args.quiet:
        print(result.summary(), file=sys.stderr)
    report = result.to_dict()
    report.update({
        "problem_file": str(args.problem_file),
        "bounds_file": str(args.bounds) if args.bounds else None,
        "bound_rules": rules,
        "intrinsic_bounds_file": str(args.intrinsic_bounds) if args.intrinsic_bounds else None,
        "intrinsics_bounded": intrinsic_bounded,
        "read_time_s": read_time,
        "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "cost_definition": "0.5 * sum over observations of rho(|projected - observed|^2), pixels^2",
    })
    # the report, the solution and the plot are renamed into place together once all are written, so a
    # kill never leaves a new solution beside an old report (the report is renamed last)
    with atomic_files(outputs) as tmps:
        staged = dict(zip(outputs, tmps))
        if args.output:
            write_bal(staged[args.output], result_to_bal(bal, result))
        if args.plot:
            result.plot_convergence(staged[args.plot], title=f"{args.problem_file}: {result.termination}")
        staged[args.report].write_text(json.dumps(report, indent=2))
    # a BAL problem has no run folder: report.json goes where --report says, no page
    return finish_job(args, None, report, [])
