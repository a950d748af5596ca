"""Bound-constrained bundle adjustment (BCBA, reference chapter 6).

Two objects, as pycolmap keeps them apart: a :class:`BundleProblem` says *what* is estimated and which
scalars are fixed, free or bounded; :class:`SolverOptions` says *how* to solve it. :func:`solve` returns a
:class:`BundleResult` with the solution, a ``summary()`` and the per-iteration log.

>>> problem = BundleProblem.from_measured_poses(measured, camera, points, obs_px, cam_idx, pt_idx)
>>> result = solve(problem, SolverOptions(loss="huber", loss_scale_px=2.0))
>>> print(result.summary()); result.plot_convergence("convergence.png")
"""
from scope3d.estimators.bundle.bal import apply_bounds, apply_bounds_file, bal_to_problem, result_to_bal
from scope3d.estimators.bundle.losses import LOSS_NAMES
from scope3d.estimators.bundle.problem import BundleParameters, BundleProblem
from scope3d.estimators.bundle.solver import (
    BoundsWarning,
    BundleResult,
    IterationRecord,
    SolverOptions,
    evaluate,
    solve,
    warm_up,
)
from scope3d.io.bal import BALProblem, read_bal, write_bal

__all__ = [
    "BALProblem", "BoundsWarning", "BundleParameters", "BundleProblem", "BundleResult", "IterationRecord",
    "LOSS_NAMES", "SolverOptions", "apply_bounds", "apply_bounds_file", "bal_to_problem", "evaluate", "read_bal",
    "result_to_bal", "solve", "warm_up", "write_bal",
]
