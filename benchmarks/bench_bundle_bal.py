"""scope3d's bundle adjuster vs Ceres (through pycolmap) vs scipy.optimize.least_squares on BAL ladybug-49-7776.

Same start (the "-pre" file), same camera model (per-camera f, k1, k2; principal point fixed at the image
centre), same stopping tolerances (Ceres's defaults: function 1e-6, gradient 1e-10, parameter 1e-8, at
most 100 iterations). Times are the best of ``--repeats`` runs (the machine is shared), kernels
loaded beforehand. scope3d runs with the kernels compiled at install (scope3d.utils.aot) when this
checkout has them, and again with numba's JIT of the same source ("scope3d_jit_kernels"). Costs are
0.5 sum |r|^2 in pixels^2.

Two cost columns: COLMAP's residual skips observations whose point is behind the camera (about 30 of
31843 here), so Ceres's own "final cost" omits them; "BAL cost" evaluates every solution with the plain
BAL formula over all observations. A second run on "ladybug-front" (those observations dropped from the
file) compares the solvers on one identical objective.

Run: ``.venv/bin/python benchmarks/bench_bundle_bal.py`` (about 1-2 minutes; scipy is capped, see
``--scipy-max-nfev``). Writes benchmarks/results/bundle_bal.json and bundle_bal_convergence.png.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "bal_ladybug_49_7776" / "problem-49-7776-pre.txt"
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "src"))

from scope3d.estimators.bundle import (  # noqa: E402
    BALProblem,
    SolverOptions,
    bal_to_problem,
    read_bal,
    result_to_bal,
    solve,
    warm_up,
)
from scope3d.estimators.bundle import kernels as jit_kernels  # noqa: E402
from scope3d.estimators.bundle import solver as solver_module  # noqa: E402
from scope3d.geometry.rotation import matrix_to_rotvec, rotvec_to_matrix  # noqa: E402

FLIP = np.array([1.0, -1.0, -1.0])
TOLERANCES = dict(function_tolerance=1e-6, gradient_tolerance=1e-10, parameter_tolerance=1e-8, max_iterations=100)


# --- Ceres through pycolmap --------------------------------------------------------------------


def ceres_solve(bal: BALProblem, num_threads: int):
    """Build a pycolmap Reconstruction of the BAL problem (RADIAL camera per image) and bundle-adjust it."""
    import pycolmap

    m = bal.cameras.shape[0]
    rec = pycolmap.Reconstruction()
    rot = FLIP[None, :, None] * rotvec_to_matrix(bal.cameras[:, :3])
    trans = FLIP * bal.cameras[:, 3:6]
    obs = bal.observations_px * np.array([1.0, -1.0])
    index_in_image = np.zeros(bal.num_observations, dtype=np.int64)
    for c in range(m):
        cam = pycolmap.Camera(model="RADIAL", width=1000, height=1000, camera_id=c + 1,
                              params=[bal.cameras[c, 6], 0.0, 0.0, bal.cameras[c, 7], bal.cameras[c, 8]])
        rec.add_camera_with_trivial_rig(cam)
        sel = np.flatnonzero(bal.camera_index == c)
        index_in_image[sel] = np.arange(sel.size)
        image = pycolmap.Image(name=str(c), points2D=[pycolmap.Point2D(obs[k]) for k in sel], camera_id=c + 1,
                               image_id=c + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(rot[c]), trans[c]))
    order = np.argsort(bal.point_index, kind="stable")
    ptr = np.searchsorted(bal.point_index[order], np.arange(bal.points.shape[0] + 1))
    point_ids = []
    for j in range(bal.points.shape[0]):
        track = pycolmap.Track()
        for k in order[ptr[j]:ptr[j + 1]]:
            track.add_element(int(bal.camera_index[k]) + 1, int(index_in_image[k]))
        point_ids.append(rec.add_point3D(bal.points[j], track))

    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.refine_principal_point = False
    solver = options.ceres.solver_options
    solver.function_tolerance = TOLERANCES["function_tolerance"]
    solver.gradient_tolerance = TOLERANCES["gradient_tolerance"]
    solver.parameter_tolerance = TOLERANCES["parameter_tolerance"]
    solver.max_num_iterations = TOLERANCES["max_iterations"]
    solver.num_threads = num_threads
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.images:
        config.add_image(image_id)
    adjuster = pycolmap.create_default_bundle_adjuster(options, config, rec)
    start = time.perf_counter()
    summary = adjuster.solve()
    elapsed = time.perf_counter() - start
    ceres = summary.ceres_summary

    cams = np.zeros((m, 9))
    for c in range(m):
        image = rec.images[c + 1]
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        cams[c, :3] = matrix_to_rotvec(FLIP[:, None] * pose.rotation.matrix())
        cams[c, 3:6] = FLIP * np.asarray(pose.translation)
        params = rec.cameras[c + 1].params
        cams[c, 6], cams[c, 7], cams[c, 8] = params[0], params[3], params[4]
    points = np.array([rec.points3D[pid].xyz for pid in point_ids])
    solved = BALProblem(bal.camera_index, bal.point_index, bal.observations_px, cams, points)
    iterations = int(ceres.num_successful_steps + ceres.num_unsuccessful_steps)
    return {
        "time_s": elapsed,
        "ceres_total_time_s": ceres.total_time_in_seconds,
        "iterations": iterations,
        "initial_cost_reported": ceres.initial_cost,
        "final_cost_reported": ceres.final_cost,
        "final_bal_cost": solved.cost(),
        "linear_solver": str(ceres.linear_solver_type_used),
        "num_threads": int(ceres.num_threads_used),
        "termination": str(ceres.termination_type),
    }


# --- scipy least_squares -----------------------------------------------------------------------


def scipy_solve(bal: BALProblem, max_nfev: int):
    """The SciPy cookbook approach: trf, finite-difference Jacobian with jac_sparsity, x_scale='jac'."""
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    m, n, k = bal.cameras.shape[0], bal.points.shape[0], bal.num_observations

    def unpack(x):
        cams = x[: 9 * m].reshape(m, 9)
        return cams, x[9 * m:].reshape(n, 3)

    # f, k1, k2 per camera are free; the principal point is the image centre in BAL
    def residuals(x):
        cams, pts = unpack(x)
        cam = cams[bal.camera_index]
        p = np.einsum("kij,kj->ki", rotvec_to_matrix(cam[:, :3]), pts[bal.point_index]) + cam[:, 3:6]
        xy = -p[:, :2] / p[:, 2:3]
        r2 = np.sum(xy * xy, axis=1, keepdims=True)
        return (cam[:, 6:7] * (1 + cam[:, 7:8] * r2 + cam[:, 8:9] * r2 * r2) * xy - bal.observations_px).ravel()

    sparsity = lil_matrix((2 * k, 9 * m + 3 * n), dtype=int)
    rows = np.arange(k)
    for s in range(9):
        sparsity[2 * rows, 9 * bal.camera_index + s] = 1
        sparsity[2 * rows + 1, 9 * bal.camera_index + s] = 1
    for s in range(3):
        sparsity[2 * rows, 9 * m + 3 * bal.point_index + s] = 1
        sparsity[2 * rows + 1, 9 * m + 3 * bal.point_index + s] = 1
    x0 = np.concatenate([bal.cameras.ravel(), bal.points.ravel()])
    history = []
    start = time.perf_counter()

    def tracked(x):
        # every call, finite-difference Jacobian columns included; the plot shows the best cost so far
        r = residuals(x)
        cost = 0.5 * float(r @ r)
        best = min(cost, history[-1][1]) if history else cost
        history.append((time.perf_counter() - start, best))
        return r

    res = least_squares(tracked, x0, jac_sparsity=sparsity, method="trf", x_scale="jac",
                        ftol=TOLERANCES["function_tolerance"], xtol=TOLERANCES["parameter_tolerance"],
                        gtol=TOLERANCES["gradient_tolerance"], max_nfev=max_nfev)
    elapsed = time.perf_counter() - start
    return {
        "time_s": elapsed,
        "iterations": int(res.nfev),
        "final_cost": float(res.cost),
        "final_bal_cost": float(res.cost),
        "status": int(res.status),
        "message": res.message,
        "max_nfev": max_nfev,
        "capped": bool(res.status == 0),
        "history": history,
    }


# --- scope3d -----------------------------------------------------------------------------------


def scope3d_solve(bal: BALProblem, num_threads: int = 0, *, jit: bool = False):
    """scope3d's solve; ``jit``: with numba's JIT kernels instead of those compiled at install."""
    problem = bal_to_problem(bal)
    installed = solver_module.kernels
    if jit:
        solver_module.kernels = jit_kernels
    try:
        start = time.perf_counter()
        result = solve(problem, SolverOptions(**TOLERANCES, num_threads=num_threads))
        elapsed = time.perf_counter() - start
        kernels_used = result.to_dict()["kernels"]
    finally:
        solver_module.kernels = installed
    return {
        "kernels": kernels_used,
        "time_s": elapsed,
        "iterations": result.iterations,
        "initial_cost": result.initial_cost,
        "final_cost": result.final_cost,
        "final_bal_cost": result_to_bal(bal, result).cost(),
        "termination": result.termination,
        "linear_solver": result.linear_solver,
        "threads": result.threads,
        "history": [(rec.time_s, rec.cost) for rec in result.log],
    }, result


def drop_behind_camera(bal: BALProblem) -> BALProblem:
    """Remove observations whose point is behind its camera at the start (P.z >= 0 in BAL's -z camera)."""
    cam = bal.cameras[bal.camera_index]
    p = np.einsum("kij,kj->ki", rotvec_to_matrix(cam[:, :3]), bal.points[bal.point_index]) + cam[:, 3:6]
    keep = p[:, 2] < 0
    counts = np.bincount(bal.point_index[keep], minlength=bal.points.shape[0])
    keep &= counts[bal.point_index] >= 2
    used = np.flatnonzero(np.bincount(bal.point_index[keep], minlength=bal.points.shape[0]) > 0)
    remap = -np.ones(bal.points.shape[0], dtype=np.int64)
    remap[used] = np.arange(used.size)
    return BALProblem(bal.camera_index[keep], remap[bal.point_index[keep]], bal.observations_px[keep],
                      bal.cameras.copy(), bal.points[used])


def cli_peak_memory_mb() -> dict:
    """Peak RSS of ``scope3d bundle-adjust`` on ladybug in a fresh process (/usr/bin/time -v)."""
    report = RESULTS / ".bundle_bal_cli_report.json"
    cmd = [sys.executable, "-m", "scope3d.cli.main", "bundle-adjust", str(DATA), "--report", str(report), "--quiet"]
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    out = subprocess.run(["/usr/bin/time", "-v"] + cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    if out.returncode != 0:
        raise RuntimeError(out.stderr)
    match = re.search(r"Maximum resident set size \(kbytes\): (\d+)", out.stderr)
    data = json.loads(report.read_text())
    report.unlink()
    return {
        "command": "scope3d bundle-adjust ../shared/data/bal_ladybug_49_7776/problem-49-7776-pre.txt "
                   "--report report.json --quiet",
        "peak_rss_mb_time_v": int(match.group(1)) / 1024.0 if match else None,
        "peak_memory_mb_reported": data["peak_memory_mb"],
        "solve_time_s": data["solve_time_s"],
        "final_cost": data["final_cost"],
    }


def plot(histories: dict, ceres: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, hist in histories.items():
        t, c = zip(*hist)
        ax.semilogy(t, c, ".-" if name.startswith("scope3d") else "-", label=name, ms=3)
    ax.axhline(ceres["final_cost_reported"], color="k", lw=0.6, ls=":")
    ax.semilogy([ceres["time_s"]], [ceres["final_cost_reported"]], "k*", ms=12,
                label=f"Ceres (pycolmap), final ({ceres['iterations']} it)")
    ax.set_xscale("symlog", linthresh=1.0)
    ax.set_xlabel("wall time [s]")
    ax.set_ylabel("cost 0.5 Σ r² [px²]")
    ax.set_title("BAL ladybug-49-7776")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--scipy-max-nfev", type=int, default=60)
    parser.add_argument("--ceres-threads", type=int, default=-1, help="-1: all cores (Ceres's default)")
    args = parser.parse_args()

    bal = read_bal(DATA)
    warm_up()
    scope3d_solve(bal, jit=True)  # numba's JIT kernels compiled (or loaded) before any timing
    out = {"load_average_before": os.getloadavg(), "problem": "ladybug-49-7776-pre", "machine": f"{platform.processor() or platform.machine()}, "
           f"{os.cpu_count()} cores (shared)", "tolerances": TOLERANCES, "repeats": args.repeats, "runs": {}}
    rows = []
    for label, problem in (("ladybug", bal), ("ladybug-front", drop_behind_camera(bal))):
        ours_runs, ceres_runs, ours1_runs, ceres1_runs, jit_runs = [], [], [], [], []
        for _ in range(args.repeats):  # interleaved so that load from other users hits both alike
            ours_runs.append(scope3d_solve(problem)[0])
            ceres_runs.append(ceres_solve(problem, args.ceres_threads))
            ours1_runs.append(scope3d_solve(problem, 1)[0])
            ceres1_runs.append(ceres_solve(problem, 1))
            jit_runs.append(scope3d_solve(problem, jit=True)[0])
        ours = min(ours_runs, key=lambda r: r["time_s"])
        ceres = min(ceres_runs, key=lambda r: r["time_s"])
        ours1 = min(ours1_runs, key=lambda r: r["time_s"])
        ceres1 = min(ceres1_runs, key=lambda r: r["time_s"])
        entry = {"num_observations": problem.num_observations, "scope3d": ours, "ceres": ceres,
                 "scope3d_1_thread": {k: v for k, v in ours1.items() if k != "history"},
                 "ceres_1_thread": ceres1,
                 "scope3d_times_s": [r["time_s"] for r in ours_runs],
                 "ceres_times_s": [r["time_s"] for r in ceres_runs],
                 "scope3d_1_thread_times_s": [r["time_s"] for r in ours1_runs],
                 "ceres_1_thread_times_s": [r["time_s"] for r in ceres1_runs],
                 "scope3d_jit_kernels": {k: v for k, v in min(jit_runs, key=lambda r: r["time_s"]).items()
                                         if k != "history"},
                 "scope3d_jit_kernels_times_s": [r["time_s"] for r in jit_runs],
                 "time_ratio_1_thread_scope3d_over_ceres": ours1["time_s"] / ceres1["time_s"]}
        entry["cost_ratio_scope3d_over_ceres_reported"] = ours["final_cost"] / ceres["final_cost_reported"]
        entry["cost_ratio_scope3d_over_ceres_bal"] = ours["final_bal_cost"] / ceres["final_bal_cost"]
        entry["time_ratio_scope3d_over_ceres"] = ours["time_s"] / ceres["time_s"]
        entry["time_ratio_jit_kernels_over_ceres"] = entry["scope3d_jit_kernels"]["time_s"] / ceres["time_s"]
        out["runs"][label] = entry
        rows.append((label, f"scope3d ({ours['threads']} threads)", ours["time_s"], ours["iterations"],
                     ours["final_cost"], ours["final_bal_cost"]))
        jit_best = entry["scope3d_jit_kernels"]
        rows.append((label, "scope3d, JIT kernels", jit_best["time_s"], jit_best["iterations"],
                     jit_best["final_cost"], jit_best["final_bal_cost"]))
        rows.append((label, f"ceres ({ceres['num_threads']} threads)", ceres["time_s"], ceres["iterations"],
                     ceres["final_cost_reported"], ceres["final_bal_cost"]))
        rows.append((label, "scope3d (1 thread)", ours1["time_s"], ours1["iterations"], ours1["final_cost"],
                     ours1["final_bal_cost"]))
        rows.append((label, "ceres (1 thread)", ceres1["time_s"], ceres1["iterations"], ceres1["final_cost_reported"],
                     ceres1["final_bal_cost"]))

    sp = scipy_solve(bal, args.scipy_max_nfev)
    out["runs"]["ladybug"]["scipy"] = {k: v for k, v in sp.items() if k != "history"}
    out["runs"]["ladybug"]["time_ratio_scipy_over_scope3d"] = sp["time_s"] / out["runs"]["ladybug"]["scope3d"]["time_s"]
    rows.append(("ladybug", "scipy trf" + (" (capped)" if sp["capped"] else ""), sp["time_s"], sp["iterations"],
                 sp["final_cost"], sp["final_bal_cost"]))
    # scipy's time to reach scope3d's final cost (or not reached)
    target = out["runs"]["ladybug"]["scope3d"]["final_cost"] * 1.001
    reached = [t for t, c in sp["history"] if c <= target]
    out["runs"]["ladybug"]["scipy_time_to_scope3d_cost_s"] = reached[0] if reached else None

    out["cli"] = cli_peak_memory_mb()
    out["load_average_after"] = os.getloadavg()
    RESULTS.mkdir(parents=True, exist_ok=True)
    ours_hist = scope3d_solve(bal)[0]["history"]
    plot({"scope3d": ours_hist, "scipy least_squares trf (best so far)": sp["history"]}, out["runs"]["ladybug"]["ceres"],
         RESULTS / "bundle_bal_convergence.png")
    (RESULTS / "bundle_bal.json").write_text(json.dumps(out, indent=2, default=str))

    print(f"{'problem':14s} {'solver':24s} {'time [s]':>9s} {'iters':>6s} {'final cost':>13s} {'BAL cost':>13s}")
    for label, name, t, it, cost, bal_cost in rows:
        print(f"{label:14s} {name:24s} {t:9.3f} {it:6d} {cost:13.6e} {bal_cost:13.6e}")
    for label, entry in out["runs"].items():
        print(f"{label}: time scope3d ({entry['scope3d']['kernels']} kernels)/Ceres "
              f"{entry['time_ratio_scope3d_over_ceres']:.2f}, JIT kernels {entry['time_ratio_jit_kernels_over_ceres']:.2f}"
              f" (1 thread each: "
              f"{entry['time_ratio_1_thread_scope3d_over_ceres']:.2f}), cost scope3d/Ceres "
              f"{entry['cost_ratio_scope3d_over_ceres_reported']:.5f} (Ceres's own cost), "
              f"{entry['cost_ratio_scope3d_over_ceres_bal']:.5f} (BAL cost)")
    print(f"scipy/scope3d time {out['runs']['ladybug']['time_ratio_scipy_over_scope3d']:.1f}x"
          + (f" (scipy capped at max_nfev={args.scipy_max_nfev})" if sp["capped"] else ""))
    print(f"CLI peak memory {out['cli']['peak_rss_mb_time_v']:.0f} MB (/usr/bin/time -v)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
