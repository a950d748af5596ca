"""Bound-constrained Levenberg–Marquardt with the Schur complement (reference sec. 6.2, eq. 6.1–6.13).

One iteration, at parameters ``s`` inside the box ``[l, u]``:

1. residuals ``r`` (pixels) and analytic Jacobians ``J`` at ``s`` (eq. 6.1), reweighted by the robust
   loss if any; gradient ``g = J^T r`` and ``D = diag(J^T J)`` (eq. 6.8, clamped to
   ``[min_diagonal, max_diagonal]`` as Ceres does);
2. active set ``A(s)`` (eq. 6.10): scalars at a bound whose gradient pushes outward, plus fixed ones;
   projected gradient ``g_hat`` (eq. 6.11) = ``g`` with active entries zeroed;
3. reduced Hessian ``H_hat`` (eq. 6.12): rows and columns of active scalars zeroed but their diagonal
   kept — done by zeroing their Jacobian columns and putting the diagonal back in the damping term;
4. damped system ``(H_hat + lambda D) delta = -g_hat`` (eq. 6.13) solved through the Schur complement on
   the points (eq. 6.7): the reduced camera system is dense Cholesky when small, sparse LU (SuperLU) when
   medium, block-Jacobi preconditioned conjugate gradients when large;
5. trial ``s' = proj(s + delta)`` (eq. 6.9), accepted when the cost decreases; lambda follows Nielsen's
   rule (as in Ceres): shrunk by ``max(1/3, 1 - (2 rho - 1)^3)`` on success, multiplied by a growing
   factor on failure.

Stops on the projected-gradient, step and relative-cost tolerances, the iteration cap, or when lambda
exceeds its maximum (the reference's ``lambda_max``). Iterations count linear solves, accepted or not,
as Ceres counts them. The active set is recomputed at every accepted iterate, so a scalar can leave a
bound when its gradient turns inward (Ceres only clamps).
"""
from __future__ import annotations

import json
import math
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from typing import Callable, Iterator

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg

from scope3d.errors import InputError
from scope3d.estimators.bundle.losses import LOSS_NAMES, loss_rho, loss_weight
from scope3d.estimators.bundle.problem import BundleParameters, BundleProblem
from scope3d.sensor.camera_models import DEFAULT_MODEL, lens_model
from scope3d.utils.aot import is_compiled, load_kernels
from scope3d.utils.blas import blas_threads
from scope3d.utils.threads import available_cores

# compiled at install (scope3d.utils.aot) or, failing that, by numba on first use; the same functions
kernels = load_kernels("scope3d.estimators.bundle.kernels")
lens_kernels = load_kernels("scope3d.estimators.bundle.lens_kernels")

LINEAR_SOLVERS = ("auto", "dense", "sparse", "pcg")
TERMINATIONS = (
    "gradient_tolerance", "function_tolerance", "parameter_tolerance", "max_iterations", "damping_limit",
)


class BoundsWarning(UserWarning):
    """Initial values lay outside their bounds and were clamped onto them."""


@dataclass(frozen=True)
class SolverOptions:
    """How to solve a :class:`BundleProblem` (the problem says what is fixed, free or bounded).

    Defaults follow Ceres's (``ceres::Solver::Options``) so results compare like for like.
    """

    max_iterations: int = 100  # cap on LM iterations (linear solves, accepted or not)
    function_tolerance: float = 1e-6  # stop when an accepted step lowers the cost by < this fraction
    gradient_tolerance: float = 1e-10  # stop when max |projected gradient| (eq. 6.11) <= this
    parameter_tolerance: float = 1e-8  # stop when |step| <= tol * (|s| + tol)
    initial_damping: float = 1e-4  # lambda_0 of eq. 6.8 (Ceres: 1 / initial_trust_region_radius)
    max_damping: float = 1e32  # lambda_max: beyond it no descent step exists; stop
    min_damping: float = 1e-16  # floor on lambda so it can grow again within a few failures
    min_diagonal: float = 1e-6  # clamp of D = diag(J^T J) from below (Ceres min_lm_diagonal)
    max_diagonal: float = 1e32  # and from above (Ceres max_lm_diagonal)
    loss: str = "none"  # "none", "huber" or "cauchy" (see scope3d.estimators.bundle.losses)
    loss_scale_px: float = 1.0  # robust loss scale, pixels of reprojection error
    linear_solver: str = "auto"  # "auto", "dense", "sparse" or "pcg" for the reduced camera system
    dense_max_parameters: int = 2000  # auto: dense Cholesky up to this many camera-side parameters
    sparse_max_parameters: int = 30000  # auto: sparse LU up to this many, PCG beyond
    pcg_tolerance: float = 1e-6  # relative residual of the conjugate-gradient solve
    pcg_max_iterations: int = 500
    blas_threads: int = 1  # OpenBLAS threads for the dense Cholesky (0: library default); see scope3d.utils.blas
    num_threads: int = 0  # threads for the Schur assembly: 0 = all cores (as Ceres's -1), 1 = serial

    def __post_init__(self) -> None:
        if not (isinstance(self.max_iterations, int) and self.max_iterations >= 0):
            raise InputError(f"max_iterations must be a non-negative integer, got {self.max_iterations!r}")
        for name in ("function_tolerance", "gradient_tolerance", "parameter_tolerance"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"{name} must be finite and >= 0, got {value!r}")
        if not (0 < self.min_damping <= self.initial_damping < self.max_damping):
            raise InputError(
                "need 0 < min_damping <= initial_damping < max_damping, got "
                f"{self.min_damping}, {self.initial_damping}, {self.max_damping}"
            )
        if not (0 < self.min_diagonal <= self.max_diagonal):
            raise InputError("need 0 < min_diagonal <= max_diagonal")
        if self.loss not in LOSS_NAMES:
            raise InputError(f"loss must be one of {', '.join(LOSS_NAMES)}, got {self.loss!r}")
        if not (math.isfinite(self.loss_scale_px) and self.loss_scale_px > 0):
            raise InputError(f"loss_scale_px must be a positive number of pixels, got {self.loss_scale_px!r}")
        if self.linear_solver not in LINEAR_SOLVERS:
            raise InputError(f"linear_solver must be one of {', '.join(LINEAR_SOLVERS)}, got {self.linear_solver!r}")
        if self.dense_max_parameters < 0 or self.sparse_max_parameters < 0:
            raise InputError("dense_max_parameters and sparse_max_parameters must be >= 0")
        if not (isinstance(self.num_threads, int) and self.num_threads >= 0):
            raise InputError(f"num_threads must be an integer >= 0, got {self.num_threads!r}")
        if not (isinstance(self.blas_threads, int) and self.blas_threads >= 0):
            raise InputError(f"blas_threads must be an integer >= 0, got {self.blas_threads!r}")
        if not (0 < self.pcg_tolerance < 1) or self.pcg_max_iterations < 1:
            raise InputError("need 0 < pcg_tolerance < 1 and pcg_max_iterations >= 1")


@dataclass(frozen=True)
class IterationRecord:
    """One line of the per-iteration log. Iteration 0 is the initial state."""

    iteration: int
    cost: float  # 0.5 * sum rho(|r|^2), pixels^2, after this iteration
    cost_change: float  # decrease achieved (0 when the step was rejected)
    damping: float  # lambda used for this iteration's step
    active_set_size: int  # |A(s)| of eq. 6.10, excluding fixed parameters
    projected_gradient_norm: float  # max |g_hat| of eq. 6.11 at the iterate the step started from
    step_norm: float  # |proj(s + delta) - s|
    accepted: bool
    time_s: float  # wall time since the solve started


@dataclass
class BundleResult:
    """Outcome of :func:`solve`: the solution, costs, and the per-iteration log."""

    problem: BundleProblem
    parameters: BundleParameters
    initial_cost: float
    final_cost: float
    iterations: int
    successful_iterations: int
    termination: str
    log: list[IterationRecord]
    solve_time_s: float
    linear_solver: str
    clamped_initial_values: int
    options: SolverOptions = field(default_factory=SolverOptions)
    threads: int = 1  # threads used by the Schur assembly

    @property
    def extra(self) -> np.ndarray:
        """(g, E) the lens model's solved later parameters (:func:`scope3d.estimators.bundle.problem.lens_block`'s
        layout; as they started where held)."""
        return self.parameters.extra.copy()

    @property
    def rotations(self) -> np.ndarray:
        """(m, 3, 3) solved cam_from_world rotations."""
        return self.problem.camera_state(self.parameters.pose)[0]

    @property
    def translations(self) -> np.ndarray:
        """(m, 3) mm solved cam_from_world translations."""
        return self.problem.camera_state(self.parameters.pose)[1]

    @property
    def poses(self):
        return self.problem.poses(self.parameters.pose)

    @property
    def points_world(self) -> np.ndarray:
        """(n, 3) mm solved points in the world."""
        return self.problem.points_world(self.parameters.points)

    @property
    def intrinsics(self) -> np.ndarray:
        """(g, 6) solved intrinsics; with square pixels fy is reported equal to fx."""
        intr = self.parameters.intrinsics.copy()
        if self.problem.square_pixels:
            intr[:, 1] = intr[:, 0]
        return intr

    @property
    def rms_initial_px(self) -> float:
        """RMS reprojection error (px) at the start, from the cost: ``sqrt(2 cost / observations)``, i.e.
        ``sqrt(mean rho(|r|^2))`` (the plain RMS without a robust loss); 0 without observations."""
        return math.sqrt(2 * self.initial_cost / max(self.problem.num_observations, 1))

    @property
    def rms_final_px(self) -> float:
        """RMS reprojection error (px) at the solution, from the cost, as :attr:`rms_initial_px`."""
        return math.sqrt(2 * self.final_cost / max(self.problem.num_observations, 1))

    def reprojection_errors_px(self) -> np.ndarray:
        """(K,) reprojection error per observation, pixels, in the problem's input order."""
        r = evaluate(self.problem, self.parameters)[0]
        out = np.empty(r.shape[0])
        out[self.problem.observation_order] = np.linalg.norm(r, axis=1)
        return out

    def summary(self) -> str:
        last = self.log[-1]
        return "\n".join([
            "Bundle adjustment (bound-constrained Levenberg-Marquardt, Schur complement)",
            f"  {self.problem.summary()}",
            f"  linear solver        {self.linear_solver} ({self.threads} thread(s) for the Schur complement);"
            f" loss {self.options.loss}"
            + (f" (scale {self.options.loss_scale_px:g} px)" if self.options.loss != "none" else ""),
            f"  initial cost         {self.initial_cost:.6e}  (RMS {self.rms_initial_px:.4f} px)",
            f"  final cost           {self.final_cost:.6e}  (RMS {self.rms_final_px:.4f} px)",
            f"  iterations           {self.iterations} ({self.successful_iterations} accepted)",
            f"  active bounds        {last.active_set_size}",
            f"  termination          {self.termination}",
            f"  time                 {self.solve_time_s:.3f} s",
        ] + ([f"  clamped initial values {self.clamped_initial_values}"] if self.clamped_initial_values else []))

    def to_dict(self) -> dict:
        """JSON-ready report (costs 0.5 sum r^2 in pixels^2, times in seconds)."""
        return {
            "initial_cost": self.initial_cost,
            "final_cost": self.final_cost,
            "iterations": self.iterations,
            "successful_iterations": self.successful_iterations,
            "termination": self.termination,
            "solve_time_s": self.solve_time_s,
            "linear_solver": self.linear_solver,
            "assembly_threads": self.threads,
            # "ahead of time": compiled at install (utils/aot.py); "numba JIT": compiled on first use, then cached
            "kernels": "ahead of time" if is_compiled(kernels) else "numba JIT",
            "loss": self.options.loss,
            "loss_scale_px": self.options.loss_scale_px,
            "num_cameras": self.problem.num_cameras,
            "num_points": self.problem.num_points,
            "num_observations": self.problem.num_observations,
            "num_free_parameters": self.problem.num_free_parameters(),
            "clamped_initial_values": self.clamped_initial_values,
            "iteration_log": [asdict(rec) for rec in self.log],
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    def plot_convergence(self, path, *, title: str | None = None) -> None:
        """Write the convergence curve (cost and projected gradient per iteration) to a PNG at ``path``."""
        from scope3d.utils.figures import new_figure, save_figure

        its = [rec.iteration for rec in self.log]
        fig = new_figure((9, 3.5))
        ax1, ax2 = fig.subplots(1, 2)
        ax1.semilogy(its, [rec.cost for rec in self.log], "o-", ms=3)
        rejected = [rec for rec in self.log if rec.iteration > 0 and not rec.accepted]
        if rejected:
            ax1.semilogy([r.iteration for r in rejected], [r.cost for r in rejected], "rx", label="rejected step")
            ax1.legend()
        ax1.set_xlabel("iteration")
        ax1.set_ylabel("cost 0.5 Σ ρ(r²) [px²]")
        ax1.grid(True, which="both", alpha=0.3)
        ax2.semilogy(its, [max(rec.projected_gradient_norm, 1e-300) for rec in self.log], "o-", ms=3)
        ax2.set_xlabel("iteration")
        ax2.set_ylabel("max |projected gradient| (eq. 6.11)")
        ax2.grid(True, which="both", alpha=0.3)
        fig.suptitle(title or f"{self.termination}, {self.solve_time_s:.2f} s")
        fig.tight_layout()
        save_figure(fig, path, dpi=110)


# --- evaluation ----------------------------------------------------------------------------------


def evaluate(problem: BundleProblem, parameters: BundleParameters):
    """Residuals and Jacobians at ``parameters`` (no loss), in the problem's stored observation order.

    Returns residuals (K, 2) px = projected - observed; jc (K, 2, 6 H) d residual / d (pose block
    ``(w, position)``, intrinsic block ``(fx, fy, cx, cy, k1, k2)``, and when the problem refines the lens
    model's later parameters (H = 3) their block, :meth:`BundleProblem.cam_blocks`); jp (K, 2, 3) d residual
    / d point parameters.
    """
    k = problem.num_observations
    r = np.empty((k, 2))
    jc = np.empty((k, 2, 6 * problem.cam_blocks().shape[1]))
    jp = np.empty((k, 2, 3))
    extra = parameters.extra if parameters.extra.shape == problem.extra.shape else problem.extra
    _linearise(problem, parameters.pose, parameters.intrinsics, extra, parameters.points, r, jc, jp)
    return r, jc, jp


class _Ranges:
    """Point ranges and their observations, ``(point start, point stop, observation start, observation
    stop)``, on which the per-observation kernels run, one thread each (they release the GIL): the
    ranges of the Schur assembly's threads, or all in one."""

    def __init__(self, point_ptr: np.ndarray, point_chunks: np.ndarray | None = None,
                 pool: ThreadPoolExecutor | None = None) -> None:
        bounds = point_chunks if pool is not None and point_chunks is not None else [0, point_ptr.size - 1]
        self.ranges = [(int(a), int(b), int(point_ptr[a]), int(point_ptr[b])) for a, b in zip(bounds[:-1], bounds[1:])]
        self.pool = pool

    def map(self, fn: Callable[[int, int, int, int], object]) -> list:
        """``fn(*range)`` for every range, in order."""
        if len(self.ranges) == 1:
            return [fn(*self.ranges[0])]
        return list(self.pool.map(lambda bounds: fn(*bounds), self.ranges))


def _linearise(problem, pose, intrinsics, extra, points, r, jc, jp, ranges: _Ranges | None = None):
    rot, trans, rot_jac = problem.camera_state(pose)
    world, point_jac = problem.points_world(points, with_jacobian=True)
    # contiguous arrays: the ahead-of-time kernels take exactly the types of kernels.AOT_SIGNATURES
    state = (np.ascontiguousarray(rot), np.ascontiguousarray(trans), np.ascontiguousarray(rot_jac),
             problem.position_parameter == "centre", np.ascontiguousarray(world), np.ascontiguousarray(point_jac),
             np.ascontiguousarray(intrinsics), bool(problem.square_pixels))
    intr_obs = problem.intrinsics_index[problem.camera_index]
    if problem.model != DEFAULT_MODEL:  # another lens: its kernel, the model's parameters after k2
        fisheye = lens_model(problem.model).is_fisheye
        state = state[:7] + (np.ascontiguousarray(extra),) + state[7:]

        def run(_pa, _pb, oa, ob):
            lens_kernels.residuals_and_jacobians(
                fisheye, problem.observations_px[oa:ob], problem.camera_index[oa:ob], problem.point_index[oa:ob],
                intr_obs[oa:ob], *state, r[oa:ob], jc[oa:ob], jp[oa:ob])
    else:
        def run(_pa, _pb, oa, ob):
            kernels.residuals_and_jacobians(
                problem.observations_px[oa:ob], problem.camera_index[oa:ob], problem.point_index[oa:ob],
                intr_obs[oa:ob], *state, r[oa:ob], jc[oa:ob], jp[oa:ob])

    (ranges or _Ranges(problem.point_ptr)).map(run)


def _squared_residuals(problem, pose, intrinsics, extra, points, intr_obs, out, ranges: _Ranges | None = None):
    rot, trans, _ = problem.camera_state(pose)
    state = (np.ascontiguousarray(rot), np.ascontiguousarray(trans), np.ascontiguousarray(problem.points_world(points)),
             np.ascontiguousarray(intrinsics), bool(problem.square_pixels))

    if problem.model != DEFAULT_MODEL:
        fisheye = lens_model(problem.model).is_fisheye
        state = state[:4] + (np.ascontiguousarray(extra),) + state[4:]

        def run(_pa, _pb, oa, ob):
            lens_kernels.squared_residuals(fisheye, problem.observations_px[oa:ob], problem.camera_index[oa:ob],
                                           problem.point_index[oa:ob], intr_obs[oa:ob], *state, out[oa:ob])
    else:
        def run(_pa, _pb, oa, ob):
            kernels.squared_residuals(problem.observations_px[oa:ob], problem.camera_index[oa:ob],
                                      problem.point_index[oa:ob], intr_obs[oa:ob], *state, out[oa:ob])

    (ranges or _Ranges(problem.point_ptr)).map(run)
    return out


def warm_up() -> None:
    """Load the kernels (compile them the first time, on the JIT path) so that timings exclude it."""
    from scope3d.phantoms.bundle_scene import make_scene

    scene = make_scene(12, 4000, seed=0)
    problem = BundleProblem(scene.observations_px, scene.camera_index, scene.point_index, scene.rotations,
                            scene.translations, scene.points, scene.intrinsics)
    solve(problem, SolverOptions(max_iterations=1, num_threads=2))
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(6, 3)) + [0.0, 0.0, 10.0]
    rot = np.broadcast_to(np.eye(3), (2, 3, 3))
    trans = np.array([[0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    cam = np.repeat([0, 1], 6)
    pt = np.tile(np.arange(6), 2)
    obs = 100.0 * (pts[pt, :2] + (cam[:, None] == 1) * [-1.0, 0.0]) / pts[pt, 2:] + 50.0
    problem = BundleProblem(obs, cam, pt, rot, trans, pts, [100.0, 100.0, 50.0, 50.0, 0.0, 0.0])
    problem.fix("pose", [0])
    problem.fix("intrinsics")
    for method in ("dense", "sparse", "pcg"):
        solve(problem, SolverOptions(max_iterations=1, linear_solver=method))


# --- linear algebra ------------------------------------------------------------------------------


class _ReducedSystem:
    """Layout of the reduced camera matrix and the chosen way of solving it.

    The dense solver assembles straight into a dense matrix and factors only the rows and columns of
    parameters not fixed in every block of their kind (BAL: fy, cx, cy fixed; 441 of 588 on ladybug-49; a
    fisheye's padding in the blocks of its later parameters). The sparse and PCG solvers assemble 6x6 blocks
    in BSR layout.
    """

    def __init__(self, problem: BundleProblem, cam_blocks: np.ndarray, method: str, fixed_c: np.ndarray,
                 num_threads: int) -> None:
        n_blocks = problem.num_camera_blocks
        point_ptr = problem.point_ptr
        self.method = method
        self.dense = method == "dense"
        self.size = 6 * n_blocks
        if self.dense:
            self.stride = self.size
            self.out = np.empty(self.size * self.size)
            self.slots = np.empty(0, dtype=np.int32)
            self.slot_ptr = kernels.term_counts(cam_blocks, point_ptr)
            # a column fixed in every block of its kind (pose or intrinsics) is zero in S but for the damping, and
            # is left out of the factorisation. Not in the later lens parameters' blocks: their held columns (a
            # fisheye's padding, OPENCV's absent k3..k6) are a few of thousands, and copying out the rest of S
            # each iteration cost more (8 ms at 1500 columns) than factoring them as the decoupled rows they are
            m, g = problem.num_cameras, problem.num_groups
            kind_fixed = np.concatenate([
                np.broadcast_to(fixed_c[:6 * m].reshape(m, 6).all(axis=0), (m, 6)).ravel(),
                np.broadcast_to(fixed_c[6 * m:6 * (m + g)].reshape(g, 6).all(axis=0), (g, 6)).ravel(),
                np.zeros(6 * (n_blocks - m - g), dtype=bool)])
            self.free_index = np.flatnonzero(~kind_fixed) if not kind_fixed.all() else np.arange(self.size)
            pieces = int(self.slot_ptr[-1])
        else:
            keys = np.unique(kernels.block_structure_keys(cam_blocks, point_ptr, n_blocks))
            self.indices = np.ascontiguousarray(keys % n_blocks)
            self.indptr = np.searchsorted(keys // n_blocks, np.arange(n_blocks + 1)).astype(np.int64)
            self.data = np.empty((keys.size, 6, 6))
            self.out = self.data.reshape(-1)
            self.stride = 6
            self.slots, self.slot_ptr = kernels.pair_slots(cam_blocks, point_ptr, self.indptr, self.indices)
            self.diag_slots = self.indptr[:-1] + np.array(
                [np.searchsorted(self.indices[self.indptr[b]:self.indptr[b + 1]], b) for b in range(n_blocks)]
            )
            pieces = self.slots.size
        threads = num_threads or available_cores()
        # parallel only when there is enough work (terms, one 6x6 quadrant each) to pay for the per-thread
        # copies of S
        if threads > 1 and pieces > 20 * (self.out.size // 36) and pieces > 50_000:
            targets = np.linspace(0, pieces, threads + 1)
            self.chunks = np.unique(np.searchsorted(self.slot_ptr, targets)).astype(np.int64)
            self.chunks[-1] = problem.num_points
            self.out_t = np.empty((self.chunks.size - 1, self.out.size))
            self.rhs_t = np.empty((self.chunks.size - 1, self.size))
        else:
            self.chunks = None
        self.threads = 1 if self.chunks is None else self.chunks.size - 1
        self.rhs = np.empty(self.size)

    def assemble(self, r, jc, jp, cam_blocks, point_ptr, damp_c, damp_p, v_inv, gp, pool,
                 prior_gradient: np.ndarray | None = None) -> bool:
        """Fill the damped reduced camera system (eq. 6.7 with eq. 6.13); with point chunks, one thread
        per chunk (the kernels release the GIL) into its own copy, then summed. prior_gradient : the
        camera scalars' prior gradient (active scalars zeroed), taken off the right-hand side."""
        if self.chunks is None:
            self.out[:] = 0.0
            self.rhs[:] = 0.0
            ok = kernels.assemble_point_range(0, point_ptr.size - 1, 0, r, jc, jp, cam_blocks, point_ptr, damp_p,
                                              self.out, self.dense, self.stride, self.rhs, v_inv, gp, self.slots)
        else:
            def chunk(t: int) -> bool:
                self.out_t[t] = 0.0
                self.rhs_t[t] = 0.0
                start, stop = int(self.chunks[t]), int(self.chunks[t + 1])
                pos = 0 if self.dense else int(self.slot_ptr[start])
                return kernels.assemble_point_range(
                    start, stop, pos, r, jc, jp, cam_blocks, point_ptr, damp_p, self.out_t[t], self.dense,
                    self.stride, self.rhs_t[t], v_inv, gp, self.slots)

            ok = all(list(pool.map(chunk, range(self.threads))))
            np.sum(self.out_t, axis=0, out=self.out)
            np.sum(self.rhs_t, axis=0, out=self.rhs)
        if prior_gradient is not None:
            self.rhs -= prior_gradient
        if self.dense:
            self.out[:: self.size + 1] += damp_c
        else:
            kernels.add_diagonal(self.indptr, self.indices, self.data, damp_c)
        return ok

    def solve(self, options: SolverOptions) -> np.ndarray | None:
        """delta_c of eq. 6.7 (6 n_blocks,) or None when the matrix is not positive definite."""
        if self.dense:
            # only the upper triangle is filled; an upper Cholesky factorisation reads nothing else
            free = self.free_index
            s = self.out.reshape(self.size, self.size)
            if free.size < self.size:
                s = s[np.ix_(free, free)]
            with blas_threads(options.blas_threads):
                try:
                    factor = scipy.linalg.cho_factor(s, lower=False, overwrite_a=True, check_finite=False)
                except np.linalg.LinAlgError:
                    return None
                solved = scipy.linalg.cho_solve(factor, self.rhs[free], check_finite=False)
            if not np.all(np.isfinite(solved)):
                return None
            out = np.zeros(self.size)
            out[free] = solved  # the rows of fixed columns are decoupled and their right-hand side is 0
            return out
        upper = scipy.sparse.bsr_matrix((self.data, self.indices, self.indptr), shape=(self.size, self.size))
        off_diagonal = self.data.copy()
        off_diagonal[self.diag_slots] = 0.0  # diagonal blocks are stored whole, not halved
        strict = scipy.sparse.bsr_matrix((off_diagonal, self.indices, self.indptr), shape=upper.shape)
        mat = (upper.tocsr() + strict.T.tocsr()).tocsr()
        if self.method == "sparse":
            try:
                lu = scipy.sparse.linalg.splu(mat.tocsc(), permc_spec="MMD_AT_PLUS_A",
                                              options={"SymmetricMode": True})
            except RuntimeError:
                return None
            out = lu.solve(self.rhs)
        else:
            diag = self.data[self.diag_slots]  # full 6x6 blocks (diagonal blocks are stored whole)
            try:
                inv_blocks = np.linalg.inv(diag)
            except np.linalg.LinAlgError:
                return None

            def precondition(v):
                return np.einsum("bij,bj->bi", inv_blocks, v.reshape(-1, 6)).ravel()

            prec = scipy.sparse.linalg.LinearOperator(mat.shape, matvec=precondition, dtype=float)
            out, _ = scipy.sparse.linalg.cg(mat, self.rhs, rtol=options.pcg_tolerance,
                                            maxiter=options.pcg_max_iterations, M=prec)
        if not np.all(np.isfinite(out)):
            return None
        return out


@contextmanager
def _thread_pool(threads: int) -> Iterator[ThreadPoolExecutor | None]:
    """Threads for the Schur assembly during one solve (None for one thread)."""
    if threads <= 1:
        yield None
        return
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="scope3d-schur") as pool:
        yield pool


def _choose_method(options: SolverOptions, size: int) -> str:
    if options.linear_solver != "auto":
        return options.linear_solver
    if size <= options.dense_max_parameters:
        return "dense"
    if size <= options.sparse_max_parameters:
        return "sparse"
    return "pcg"


# --- the solver ----------------------------------------------------------------------------------


def solve(
    problem: BundleProblem,
    options: SolverOptions | None = None,
    *,
    callback: Callable[[IterationRecord, BundleParameters], None] | None = None,
) -> BundleResult:
    """Minimise 0.5 sum rho(|r|^2) (plus the poses' prior, :meth:`BundleProblem.set_box_prior`, when set) subject
    to the problem's bounds (eq. 6.2) by BCBA (eq. 6.9–6.13).

    problem : the BundleProblem; it is not modified. options : SolverOptions (defaults if None).
    callback : called after every iteration with its log record and the current (accepted) parameters;
        the parameters are live arrays, copy them to keep them.
    Returns a BundleResult.
    """
    options = options or SolverOptions()
    start = time.perf_counter()
    problem.validate()
    m, g, n = problem.num_cameras, problem.num_groups, problem.num_points
    n_blocks = problem.num_camera_blocks
    with_extra = problem.refines_extra
    lower_c, upper_c, fixed_c = problem.camera_bounds()
    lower_p, upper_p, fixed_p = problem.point_lower, problem.point_upper, problem.point_fixed

    x = problem.initial.copy()
    xc = x.camera_vector(with_extra)
    xp = x.points
    clamped = int(np.sum((xc < lower_c) | (xc > upper_c)) + np.sum((xp < lower_p) | (xp > upper_p)))
    if clamped:
        warnings.warn(
            f"{clamped} initial value(s) lay outside their bounds and were clamped onto them (eq. 6.9)",
            BoundsWarning, stacklevel=2,
        )
        xc = np.clip(xc, lower_c, upper_c)
        xp = np.clip(xp, lower_p, upper_p)

    cam_blocks = problem.cam_blocks()
    point_index = problem.point_index
    intr_obs = np.ascontiguousarray(problem.intrinsics_index[problem.camera_index])
    system = _ReducedSystem(problem, cam_blocks, _choose_method(options, 6 * n_blocks), fixed_c, options.num_threads)
    k = problem.num_observations
    r = np.empty((k, 2))
    jc = np.empty((k, 2, 6 * cam_blocks.shape[1]))
    jp = np.empty((k, 2, 3))
    sq = np.empty(k)
    v_inv = np.empty((n, 3, 3))
    gp_buf = np.empty((n, 3))

    n_extra = problem.extra.shape[1]

    def split(vec):
        """pose (m, 6), intrinsics (g, 6) and the later lens parameters (g, E) of a camera vector."""
        extra = vec[6 * (m + g):].reshape(g, 6)[:, :n_extra] if with_extra else problem.extra
        return vec[: 6 * m].reshape(m, 6), vec[6 * m:6 * (m + g)].reshape(g, 6), np.ascontiguousarray(extra)

    # the poses' Gaussian prior (BundleProblem.set_box_prior), on the camera vector: a residual block of its own
    prior_weight = np.concatenate([problem.pose_prior_weight.ravel(), np.zeros(6 * (n_blocks - m))])
    prior_mean = np.concatenate([problem.pose_prior_mean.ravel(), np.zeros(6 * (n_blocks - m))])
    has_prior = bool(np.any(prior_weight > 0))

    def prior_cost(vc) -> float:
        return 0.5 * float(prior_weight @ (vc - prior_mean) ** 2) if has_prior else 0.0

    def cost_of(vc, vp) -> float:
        pose, intr, extra = split(vc)
        _squared_residuals(problem, pose, intr, extra, vp, intr_obs, sq, ranges)
        return 0.5 * float(np.sum(loss_rho(options.loss, sq, options.loss_scale_px))) + prior_cost(vc)

    def linearise(vc, vp) -> float:
        pose, intr, extra = split(vc)
        _linearise(problem, pose, intr, extra, vp, r, jc, jp, ranges)
        np.einsum("ki,ki->k", r, r, out=sq)
        weights = loss_weight(options.loss, sq, options.loss_scale_px)
        if weights is not None:
            kernels.scale_rows(r, jc, jp, weights)
        return 0.5 * float(np.sum(loss_rho(options.loss, sq, options.loss_scale_px))) + prior_cost(vc)

    def params_view(vc, vp) -> BundleParameters:
        pose, intr, extra = split(vc)
        return BundleParameters(pose, intr, vp, extra)

    with _thread_pool(system.threads) as pool:
        ranges = _Ranges(problem.point_ptr, system.chunks, pool)
        cost = linearise(xc, xp)
        if not math.isfinite(cost):
            raise InputError("the initial cost is not finite (a point projects through a camera's centre?)")
        initial_cost = cost
        lam = options.initial_damping
        nu = 2.0
        log: list[IterationRecord] = []
        iterations = successes = 0
        termination = None
        need_gradient = True
        pg_norm = 0.0
        n_active = 0
        while termination is None:
            if need_gradient:
                parts = ranges.map(lambda _pa, _pb, oa, ob: kernels.gradient_and_diagonal(
                    r[oa:ob], jc[oa:ob], jp[oa:ob], cam_blocks[oa:ob], point_index[oa:ob], n_blocks, n))
                gc, dc, gp, dp = (sum(part[q] for part in parts) for q in range(4))
                prior_g = None
                if has_prior:  # the prior's gradient and its (diagonal) Gauss-Newton Hessian
                    prior_g = prior_weight * (xc - prior_mean)
                    gc = gc + prior_g
                    dc = dc + prior_weight
                # eq. 6.10: a scalar is active at a bound whose gradient points out of the box
                active_c = fixed_c | ((xc <= lower_c) & (gc > 0)) | ((xc >= upper_c) & (gc < 0))
                active_p = fixed_p | ((xp <= lower_p) & (gp > 0)) | ((xp >= upper_p) & (gp < 0))
                n_active = int(active_c.sum() - fixed_c.sum() + active_p.sum() - fixed_p.sum())
                ghat_c = np.where(active_c, 0.0, gc)  # eq. 6.11
                if prior_g is not None:
                    prior_g = np.where(active_c, 0.0, prior_g)
                ghat_p = np.where(active_p, 0.0, gp)
                pg_norm = float(max(np.abs(ghat_c).max(initial=0.0), np.abs(ghat_p).max(initial=0.0)))
                diag_c = np.clip(dc, options.min_diagonal, options.max_diagonal)
                diag_p = np.clip(dp, options.min_diagonal, options.max_diagonal)
                ranges.map(lambda _pa, _pb, oa, ob: kernels.zero_frozen_columns(  # eq. 6.12
                    jc[oa:ob], jp[oa:ob], cam_blocks[oa:ob], point_index[oa:ob], active_c, active_p))
                need_gradient = False
                if not log:
                    log.append(IterationRecord(0, cost, 0.0, lam, n_active, pg_norm, 0.0, True,
                                               time.perf_counter() - start))
                    if callback:
                        callback(log[-1], params_view(xc, xp))
                if pg_norm <= options.gradient_tolerance:
                    termination = "gradient_tolerance"
                    break
            if iterations >= options.max_iterations:
                termination = "max_iterations"
                break
            iterations += 1
            # eq. 6.13: B_hat = H_hat + lambda D_hat; the active scalars keep only their diagonal
            damp_c = np.where(active_c, diag_c * (1.0 + lam), lam * diag_c + prior_weight)
            damp_p = np.where(active_p, diag_p * (1.0 + lam), lam * diag_p)
            ok = system.assemble(r, jc, jp, cam_blocks, problem.point_ptr, damp_c, damp_p, v_inv, gp_buf, pool,
                                  prior_g)
            delta_c = system.solve(options) if ok else None
            step_norm = 0.0
            accepted = False
            change = 0.0
            if delta_c is not None:
                delta_p = np.concatenate(ranges.map(lambda pa, pb, _oa, _ob: kernels.back_substitute(
                    jc, jp, cam_blocks, problem.point_ptr[pa:pb + 1], v_inv[pa:pb], gp_buf[pa:pb], delta_c)))
                trial_c = np.where(active_c, xc, np.clip(xc + delta_c, lower_c, upper_c))  # eq. 6.9
                trial_p = np.where(active_p, xp, np.clip(xp + delta_p, lower_p, upper_p))
                step_c = trial_c - xc
                step_p = trial_p - xp
                step_norm = math.sqrt(float(step_c @ step_c) + float(np.sum(step_p * step_p)))
                x_norm = math.sqrt(float(xc @ xc) + float(np.sum(xp * xp)))
                if step_norm <= options.parameter_tolerance * (x_norm + options.parameter_tolerance):
                    termination = "parameter_tolerance"
                    log.append(IterationRecord(iterations, cost, 0.0, lam, n_active, pg_norm, step_norm, False,
                                               time.perf_counter() - start))
                    break
                new_cost = cost_of(trial_c, trial_p)
                model_decrease = -(float(ghat_c @ step_c) + float(np.sum(ghat_p * step_p))
                                   + 0.5 * sum(ranges.map(lambda _pa, _pb, oa, ob: kernels.jacobian_step_norm2(
                                       jc[oa:ob], jp[oa:ob], cam_blocks[oa:ob], point_index[oa:ob], step_c,
                                       step_p)))
                                   + 0.5 * float(prior_weight @ step_c**2))
                change = cost - new_cost
                accepted = math.isfinite(new_cost) and change > 0
            if accepted:
                rho = change / model_decrease if model_decrease > 0 else 0.0
                used_lam = lam
                lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), options.min_damping)
                nu = 2.0
                previous = cost
                xc, xp = trial_c, trial_p
                cost = linearise(xc, xp)
                need_gradient = True
                successes += 1
                log.append(IterationRecord(iterations, cost, change, used_lam, n_active, pg_norm, step_norm, True,
                                           time.perf_counter() - start))
                if change <= options.function_tolerance * previous:
                    termination = "function_tolerance"
            else:
                log.append(IterationRecord(iterations, cost, 0.0, lam, n_active, pg_norm, step_norm, False,
                                           time.perf_counter() - start))
                lam *= nu
                nu *= 2.0
                if lam > options.max_damping:
                    termination = "damping_limit"
            if callback:
                callback(log[-1], params_view(xc, xp))

    pose, intr, extra = split(xc)
    solution = BundleParameters(pose.copy(), intr.copy(), xp.copy(), extra.copy())
    return BundleResult(
        problem=problem,
        parameters=solution,
        initial_cost=initial_cost,
        final_cost=cost,
        iterations=iterations,
        successful_iterations=successes,
        termination=termination,
        log=log,
        solve_time_s=time.perf_counter() - start,
        linear_solver=system.method,
        clamped_initial_values=clamped,
        options=options,
        threads=system.threads,
    )
