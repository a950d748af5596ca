"""The kernels compiled ahead of time at install (scope3d.utils.aot) against numba's JIT of the same source:
the bundle adjuster's, the pose refinement's and the descriptor distances.

Both paths must give the same numbers: the same LLVM code from the same source, tuned for a generic CPU
(AOT) or for this one (JIT). Instruction selection (fused multiply-adds) may change the last bits of a
sum, so arrays are compared to 1e-12 relative (a few hundred ulps of float64 over sums of tens of
terms), not bit for bit.
"""
from __future__ import annotations

import importlib
import importlib.util
import sys
import sysconfig
import threading
import time

import numpy as np
import pytest
import scipy.sparse

from scope3d.estimators.bundle import BundleProblem, SolverOptions, kernels
from scope3d.estimators.bundle import solver as solver_module
from scope3d.phantoms.bundle_scene import make_scene
from scope3d.utils import aot

BUNDLE = "scope3d.estimators.bundle.kernels"

RTOL = 1e-12  # rounding only (see the module docstring)


def _compiled(kernel_module: str, folder):
    """The module the install built; built here into ``folder`` if this checkout has none (e.g. sources
    updated without reinstalling), so that the comparison always runs."""
    try:
        return aot.load_kernels(kernel_module, "aot")
    except ImportError:
        name = aot.aot_module_name(kernel_module).rpartition(".")[2]
        path = folder / (name + sysconfig.get_config_var("EXT_SUFFIX"))
        aot.compile_kernels(importlib.import_module(kernel_module), path)
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module


@pytest.fixture(scope="module")
def aot_kernels(tmp_path_factory):
    return _compiled(BUNDLE, tmp_path_factory.mktemp("aot"))


def scene_problem(num_cameras=6, num_points=150, seed=0, **kw) -> BundleProblem:
    scene = make_scene(num_cameras, num_points, seed=seed, pixel_noise_px=0.5)
    return BundleProblem(scene.observations_px, scene.camera_index, scene.point_index, scene.rotations,
                         scene.translations, scene.points, scene.intrinsics, **kw)


def perturbed(problem: BundleProblem, seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = problem.initial
    x.pose[:, :3] += rng.uniform(-0.01, 0.01, x.pose[:, :3].shape)
    x.pose[:, 3:] += rng.uniform(-0.05, 0.05, x.pose[:, 3:].shape)
    x.points += rng.uniform(-0.1, 0.1, x.points.shape)


@pytest.mark.parametrize("kernel_module", aot.KERNEL_MODULES)
def test_every_kernel_module_is_built_from_its_source(kernel_module, tmp_path):
    compiled = _compiled(kernel_module, tmp_path)
    source = importlib.import_module(kernel_module)
    assert compiled.source_digest() == aot.source_digest(aot.source_path(kernel_module))
    assert set(source.AOT_SIGNATURES) <= set(dir(compiled))
    assert aot.is_compiled(compiled) and not aot.is_compiled(source)


def test_load_kernels_falls_back_to_jit_when_the_module_is_stale(monkeypatch, aot_kernels):
    monkeypatch.setattr(aot, "source_digest", lambda path: -1)
    assert aot.load_kernels(BUNDLE, "auto") is kernels
    with pytest.raises(ImportError, match="another kernels.py"):
        aot.load_kernels(BUNDLE, "aot")
    assert aot.load_kernels(BUNDLE, "jit") is kernels
    with pytest.raises(ValueError):
        aot.load_kernels(BUNDLE, "fast")


def test_pose_and_descriptor_kernels_agree_with_the_jit(tmp_path):
    rng = np.random.default_rng(0)
    points = np.ascontiguousarray(rng.normal(size=(80, 3)) + [0.0, 0.0, 20.0])
    pixels = np.ascontiguousarray(rng.uniform(0.0, 300.0, size=(80, 2)))
    rotation = np.ascontiguousarray(np.linalg.qr(rng.normal(size=(3, 3)))[0])
    intrinsics = np.array([300.0, 310.0, 150.0, 160.0, -0.1, 0.02])
    # a rotation vector inside the series' range and one outside it: both branches of the rotation maths
    for x in (np.array([1e-9, 0.0, 0.0, 0.1, 0.2, 0.3]), np.array([0.1, -0.2, 0.05, 0.1, 0.2, 0.3])):
        args = (points, pixels, x, rotation, intrinsics, 1.0, 1e-8)
        jit = importlib.import_module("scope3d.estimators.pose_kernels").huber_normal_equations(*args)
        compiled = _compiled("scope3d.estimators.pose_kernels", tmp_path).huber_normal_equations(*args)
        for a, b in zip(compiled, jit):
            np.testing.assert_allclose(a, b, rtol=RTOL, atol=0)
    desc = rng.normal(size=(200, 128)).astype(np.float32)
    a, b = rng.integers(0, 200, 500), rng.integers(0, 200, 500)
    out = {}
    for name, module in (("jit", importlib.import_module("scope3d.feature.descriptor_kernels")),
                         ("aot", _compiled("scope3d.feature.descriptor_kernels", tmp_path))):
        out[name] = np.empty(500, np.float32)
        module.candidate_squared_distances(desc, desc, a, b, out[name])
    # float32 sums of 128 squares in the same order: the same bits but for a fused multiply-add
    np.testing.assert_allclose(out["aot"], out["jit"], rtol=1e-6, atol=0)
    np.testing.assert_allclose(out["jit"], ((desc[a] - desc[b]) ** 2).sum(1), rtol=1e-5)


@pytest.mark.parametrize("position_parameter, square", [("centre", False), ("translation", True)])
def test_every_kernel_agrees_with_the_jit(aot_kernels, position_parameter, square):
    problem = scene_problem(position_parameter=position_parameter, square_pixels=square)
    perturbed(problem, 1)
    x = problem.initial
    rot, trans, rot_jac = problem.camera_state(x.pose)
    world, point_jac = problem.points_world(x.points, with_jacobian=True)
    args = (problem.observations_px, problem.camera_index, problem.point_index,
            np.ascontiguousarray(problem.intrinsics_index[problem.camera_index]), np.ascontiguousarray(rot),
            np.ascontiguousarray(trans), np.ascontiguousarray(rot_jac), position_parameter == "centre",
            np.ascontiguousarray(world), np.ascontiguousarray(point_jac), np.ascontiguousarray(x.intrinsics), square)
    k, n = problem.num_observations, problem.num_points
    out = {}
    for name, module in (("jit", kernels), ("aot", aot_kernels)):
        r, jc, jp = np.empty((k, 2)), np.empty((k, 2, 12)), np.empty((k, 2, 3))
        module.residuals_and_jacobians(*args, r, jc, jp)
        sq = np.empty(k)
        module.squared_residuals(*args[:6], args[8], args[10], args[11], sq)
        cam_blocks = problem.cam_blocks()
        n_blocks = problem.num_cameras + problem.num_groups
        grads = module.gradient_and_diagonal(r, jc, jp, cam_blocks, problem.point_index, n_blocks, n)
        weights = np.linspace(0.5, 1.0, k)
        module.scale_rows(r, jc, jp, weights)
        frozen_c = np.zeros(6 * n_blocks, dtype=bool)
        frozen_c[[0, 5, 6 * problem.num_cameras + 1]] = True
        frozen_p = np.zeros((n, 3), dtype=bool)
        frozen_p[::7, 2] = True
        module.zero_frozen_columns(jc, jp, cam_blocks, problem.point_index, frozen_c, frozen_p)
        keys = np.unique(module.block_structure_keys(cam_blocks, problem.point_ptr, n_blocks))
        indices = np.ascontiguousarray(keys % n_blocks)
        indptr = np.searchsorted(keys // n_blocks, np.arange(n_blocks + 1)).astype(np.int64)
        slots, slot_ptr = module.pair_slots(cam_blocks, problem.point_ptr, indptr, indices)
        damp_c, damp_p = np.full(6 * n_blocks, 1e-3), np.full((n, 3), 1e-3)
        v_inv, gp = np.empty((n, 3, 3)), np.empty((n, 3))

        def assembled(start, stop, dense):
            """S and rhs of points [start, stop), as the BSR blocks or the dense matrix."""
            out = np.zeros(36 * n_blocks * n_blocks if dense else 36 * keys.size)
            rhs = np.zeros(6 * n_blocks)
            assert module.assemble_point_range(start, stop, 0 if dense else int(slot_ptr[start]), r, jc, jp,
                                               cam_blocks, problem.point_ptr, damp_p, out, dense,
                                               6 * n_blocks if dense else 6, rhs, v_inv, gp, slots)
            return out, rhs

        data, rhs = assembled(0, n, False)
        data = data.reshape(-1, 6, 6)
        module.add_diagonal(indptr, indices, data, damp_c)
        dense, rhs_dense = assembled(0, n, True)
        dense = dense.reshape(6 * n_blocks, 6 * n_blocks) + np.diag(damp_c)
        # the same system from two point ranges added up (what the threads do)
        half = n // 2
        parts = [assembled(start, stop, False) for start, stop in ((0, half), (half, n))]
        data_split = (parts[0][0] + parts[1][0]).reshape(-1, 6, 6)
        module.add_diagonal(indptr, indices, data_split, damp_c)
        delta_c = np.linspace(-1e-3, 1e-3, 6 * n_blocks)
        delta_p = module.back_substitute(jc, jp, cam_blocks, problem.point_ptr, v_inv, gp, delta_c)
        norm2 = module.jacobian_step_norm2(jc, jp, cam_blocks, problem.point_index, delta_c, delta_p)
        out[name] = dict(r=r, jc=jc, jp=jp, sq=sq, gc=grads[0], dc=grads[1], gp_=grads[2], dp=grads[3], keys=keys,
                         slots=slots, slot_ptr=slot_ptr, data=data, rhs=rhs, v_inv=v_inv, gp=gp,
                         data_split=data_split, rhs_split=parts[0][1] + parts[1][1], dense=dense,
                         rhs_dense=rhs_dense, delta_p=delta_p, norm2=norm2)
    for key, value in out["jit"].items():
        np.testing.assert_allclose(out["aot"][key], value, rtol=RTOL, atol=0, err_msg=key)
    # and the split assembly is the one-pass assembly, up to the order of the sums
    for name in ("jit", "aot"):
        scale = np.abs(out[name]["data"]).max()
        np.testing.assert_allclose(out[name]["data_split"], out[name]["data"], rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(out[name]["rhs_split"], out[name]["rhs"], rtol=0,
                                   atol=1e-12 * np.abs(out[name]["rhs"]).max())
        # the dense layout holds the same upper block triangle as the blocks
        upper = scipy.sparse.bsr_matrix((out[name]["data"], out[name]["keys"] % n_blocks, indptr),
                                        shape=(6 * n_blocks, 6 * n_blocks)).toarray()
        np.testing.assert_allclose(out[name]["dense"], upper, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(out[name]["rhs_dense"], out[name]["rhs"], rtol=0, atol=0)


@pytest.mark.parametrize("options", [SolverOptions(max_iterations=15),
                                     SolverOptions(max_iterations=15, loss="huber", loss_scale_px=1.0,
                                                   linear_solver="sparse")])
def test_solve_gives_the_same_result_on_both_paths(monkeypatch, aot_kernels, options):
    problem = scene_problem(num_cameras=8, num_points=300, seed=3)
    perturbed(problem, 4)
    problem.fix("pose", [0])
    results = {}
    for name, module in (("jit", kernels), ("aot", aot_kernels)):
        monkeypatch.setattr(solver_module, "kernels", module)
        results[name] = solver_module.solve(problem, options)
    jit, aot_ = results["jit"], results["aot"]
    assert jit.iterations == aot_.iterations and jit.termination == aot_.termination
    # 15 LM steps amplify rounding differences a little; 1e-9 relative is still far below any pixel effect
    assert aot_.final_cost == pytest.approx(jit.final_cost, rel=1e-9)
    np.testing.assert_allclose(aot_.parameters.points, jit.parameters.points, rtol=1e-7, atol=1e-9)
    # and it converged: 0.5 px of noise per coordinate is sqrt(2) * 0.5 = 0.71 px of RMS error per
    # observation; fitting the parameters can only leave less (the start is ~3 px)
    assert aot_.rms_final_px <= 0.5 * np.sqrt(2) < aot_.rms_initial_px


def test_parallel_assembly_matches_one_thread():
    # large enough that the solver splits the points into one chunk per thread (see _ReducedSystem)
    problem = scene_problem(num_cameras=12, num_points=4000, seed=5)
    perturbed(problem, 6)
    one = solver_module.solve(problem, SolverOptions(max_iterations=5, num_threads=1))
    two = solver_module.solve(problem, SolverOptions(max_iterations=5, num_threads=2))
    assert one.threads == 1 and two.threads == 2
    assert two.final_cost == pytest.approx(one.final_cost, rel=1e-10)


def _step_norm_args(k: int = 400_000) -> tuple:
    """Arguments of ``jacobian_step_norm2`` for ``k`` observations (~20 ms per call at 400 000)."""
    rng = np.random.default_rng(0)
    jc, jp = rng.normal(size=(k, 2, 12)), rng.normal(size=(k, 2, 3))
    cam_blocks = np.ascontiguousarray(rng.integers(0, 10, size=(k, 2)))
    point_index = np.ascontiguousarray(rng.integers(0, 1000, size=k))
    return jc, jp, cam_blocks, point_index, rng.normal(size=60), rng.normal(size=(1000, 3))


def _python_ran_inside(kernel, args, max_calls: int = 200) -> int:
    """Call ``kernel`` on another thread until the main thread has run Python while that thread was inside
    it, or ``max_calls`` times; returns how many times the main thread saw it inside.

    The switch interval is raised far above the whole loop, so that the GIL changes hands only when a thread
    releases it: a kernel that holds the GIL keeps the main thread out for every call (0, however many
    calls), one that releases it lets the main thread in as soon as the OS schedules it. Nothing is timed:
    on a loaded machine the main thread may miss a call or many, and the worker simply calls again (the
    main thread's short naps only hand the GIL back, so that the worker can return from each call).
    """
    state = {"inside": False, "seen": 0, "done": False}

    def worker():
        for _ in range(max_calls):
            state["inside"] = True
            kernel(*args)
            state["inside"] = False
            if state["seen"]:
                break
        state["done"] = True

    previous = sys.getswitchinterval()
    sys.setswitchinterval(1000.0)  # far above any loop here (200 calls of ~20 ms: 4 s, ~20 s at load 4)
    try:
        thread = threading.Thread(target=worker)
        thread.start()
        while not state["done"]:
            state["seen"] += state["inside"]
            time.sleep(0.0005)
        thread.join()
    finally:
        sys.setswitchinterval(previous)
    return state["seen"]


def test_kernels_are_declared_nogil():
    # the JIT path releases the GIL only where the source says so (the AOT build sets the flag for all)
    for name in aot.KERNEL_MODULES:
        module = importlib.import_module(name)
        held = [f for f in module.AOT_SIGNATURES if not getattr(module, f).targetoptions.get("nogil")]
        assert not held, (name, held)


@pytest.mark.parametrize("backend", ["jit", "aot"])
def test_kernels_release_the_gil(aot_kernels, backend):
    module = kernels if backend == "jit" else aot_kernels
    args = _step_norm_args()
    module.jacobian_step_norm2(*args)  # compiled (JIT) before the measurement
    assert _python_ran_inside(module.jacobian_step_norm2, args) > 0


def test_the_check_sees_a_kernel_that_holds_the_gil():
    # the same check on a kernel compiled without nogil: the main thread never gets in
    import numba

    args = _step_norm_args()
    holding = numba.njit(nogil=False)(kernels.jacobian_step_norm2.py_func)
    holding(*args)
    assert _python_ran_inside(holding, args, max_calls=20) == 0
