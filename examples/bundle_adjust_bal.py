"""Bundle-adjust a BAL problem file with the Python API (bound-constrained Levenberg-Marquardt).

    python examples/bundle_adjust_bal.py PROBLEM.txt [--max-iterations 20] [--fix-first-camera]

Prints the solver's summary; the BAL "ladybug" set is in the project's shared data.
"""
from __future__ import annotations

import argparse

from scope3d.estimators.bundle import SolverOptions, bal_to_problem, read_bal, solve


def main(argv: list[str] | None = None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("problem", help="BAL problem file (text)")
    parser.add_argument("--max-iterations", type=int, default=20)
    parser.add_argument("--fix-first-camera", action="store_true", help="fix the gauge on camera 0")
    args = parser.parse_args(argv)

    problem = bal_to_problem(read_bal(args.problem))
    if args.fix_first_camera:
        problem.fix("pose", [0])  # what is free or fixed belongs to the problem ...
    options = SolverOptions(max_iterations=args.max_iterations, loss="huber", loss_scale_px=2.0)  # ... how to solve, to the options
    result = solve(problem, options)
    print(result.summary())
    return result


if __name__ == "__main__":
    main()
