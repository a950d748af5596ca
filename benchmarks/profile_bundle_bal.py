"""Where one bundle adjustment of BAL ladybug-49-7776 spends its time, stage by stage.

Wraps each stage of :func:`scope3d.estimators.bundle.solve` (the kernels and the reduced system's
assembly and solve) in wall and CPU timers (``time.process_time``: all threads of the process), solves
``--repeats`` times after a warm-up and keeps the fastest solve. Same tolerances as
``bench_bundle_bal.py``. CPU time is the figure to compare on the shared machine; with more than one
thread the per-kernel rows add up both threads' CPU time (``time.process_time`` is per process).

Run: ``PYTHONPATH=src .venv/bin/python benchmarks/profile_bundle_bal.py [--threads 1] [--repeats 3] [--jit]``.
Writes benchmarks/results/profile_bundle_bal_<threads>t[_jit].json and prints the table.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
import types
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "bal_ladybug_49_7776" / "problem-49-7776-pre.txt"
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "src"))

from scope3d.estimators.bundle import SolverOptions, bal_to_problem, read_bal, solve  # noqa: E402
from scope3d.estimators.bundle import solver as solver_module  # noqa: E402
from scope3d.utils.aot import is_compiled  # noqa: E402

TOLERANCES = dict(function_tolerance=1e-6, gradient_tolerance=1e-10, parameter_tolerance=1e-8, max_iterations=100)
# stage name -> what it wraps; the kernels are timed where the solver calls them
KERNEL_STAGES = {
    "residuals_and_jacobians": "residuals and Jacobians (kernel)",
    "squared_residuals": "cost of the trial step (kernel)",
    "gradient_and_diagonal": "gradient and diag(J^T J)",
    "zero_frozen_columns": "active columns zeroed (eq. 6.12)",
    "assemble_point_range": "Schur complement: reduced camera system build",
    "back_substitute": "back-substitution (point steps)",
    "jacobian_step_norm2": "model decrease |J delta|^2",
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=0, help="0: all cores (the solver's default)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--jit", action="store_true",
                        help="numba's JIT kernels instead of those compiled at install (as bench_bundle_bal.py)")
    args = parser.parse_args()
    if args.jit:
        from scope3d.estimators.bundle import kernels as jit_kernels

        solver_module.kernels = jit_kernels

    problem = bal_to_problem(read_bal(DATA))
    options = SolverOptions(**TOLERANCES, num_threads=args.threads)
    solve(problem, options)  # kernels loaded (or compiled, on the JIT path) before any timing

    totals: dict = defaultdict(lambda: [0.0, 0.0, 0])

    def timed(name, fn):
        def wrapper(*a, **k):
            wall, cpu = time.perf_counter(), time.process_time()
            out = fn(*a, **k)
            entry = totals[name]
            entry[0] += time.perf_counter() - wall
            entry[1] += time.process_time() - cpu
            entry[2] += 1
            return out
        return wrapper

    kernels = solver_module.kernels
    proxy = types.SimpleNamespace(**{name: getattr(kernels, name) for name in dir(kernels) if not name.startswith("__")})
    for name, label in KERNEL_STAGES.items():
        setattr(proxy, name, timed(label, getattr(kernels, name)))
    system = solver_module._ReducedSystem
    originals = (solver_module.kernels, system.assemble, system.solve, solver_module._linearise,
                 solver_module._squared_residuals)
    solver_module.kernels = proxy
    system.assemble = timed("Schur complement, in all (threads, copies, damping)", system.assemble)
    system.solve = timed("reduced camera system solve (dense Cholesky)", system.solve)
    solver_module._linearise = timed("linearisation, in all (pose and point state, kernel)", solver_module._linearise)
    solver_module._squared_residuals = timed("cost of the trial step, in all", solver_module._squared_residuals)
    best = None
    try:
        for _ in range(args.repeats):
            totals.clear()
            wall, cpu = time.perf_counter(), time.process_time()
            result = solve(problem, options)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            if best is None or wall < best["wall_s"]:
                best = {"wall_s": wall, "cpu_s": cpu, "stages": {k: list(v) for k, v in totals.items()},
                        "iterations": result.iterations, "final_cost": result.final_cost,
                        "threads": result.threads, "linear_solver": result.linear_solver}
    finally:
        (solver_module.kernels, system.assemble, system.solve, solver_module._linearise,
         solver_module._squared_residuals) = originals

    its = best["iterations"]
    out = {"load_average": os.getloadavg(), "kernels": "ahead of time" if is_compiled(kernels) else "numba JIT",
           "threads": best["threads"], "linear_solver": best["linear_solver"], "iterations": its,
           "final_cost": best["final_cost"], "wall_s": best["wall_s"], "cpu_s": best["cpu_s"],
           "stages": {name: {"wall_s": w, "cpu_s": c, "calls": n, "cpu_ms_per_iteration": 1000 * c / its}
                      for name, (w, c, n) in best["stages"].items()}}
    RESULTS.mkdir(parents=True, exist_ok=True)
    name = f"profile_bundle_bal_{args.threads}t{'_jit' if args.jit else ''}.json"
    (RESULTS / name).write_text(json.dumps(out, indent=2))
    print(f"{out['kernels']} kernels, {best['threads']} thread(s), {its} iterations, wall {best['wall_s']:.3f} s, "
          f"CPU {best['cpu_s']:.3f} s, load {out['load_average'][0]:.1f}")
    print(f"{'stage':56s} {'CPU s':>7s} {'ms/it':>7s} {'share':>6s}")
    for name, entry in sorted(out["stages"].items(), key=lambda kv: -kv[1]["cpu_s"]):
        print(f"{name:56s} {entry['cpu_s']:7.3f} {entry['cpu_ms_per_iteration']:7.2f} "
              f"{entry['cpu_s'] / best['cpu_s']:6.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
