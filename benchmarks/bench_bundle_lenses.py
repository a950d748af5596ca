"""Bundle adjustment through each lens model on the same problem (issue 32's target: a fisheye costs at most
1.3x the radial model's time).

The same synthetic scene (``phantoms.bundle_scene.make_scene``: a row of cameras, each point seen by 4
consecutive ones) is observed through scope3d's radial model (the scene's own 500 px camera), the
``fisheye-140`` lens (OPENCV_FISHEYE) and the ``barrel-70`` lens (OPENCV), each on a 640 x 480 sensor, with
0.5 px noise; each problem starts from the same perturbed poses, points and intrinsics (one shared
intrinsic group, all six of fx, fy, cx, cy, k1, k2 refined), centre-parameterised poses with camera 0
fixed. The two lenses run twice: with the model's later parameters (the fisheye's k3, k4; OPENCV's p1, p2)
held at their values, and refined too (``fisheye+later``, ``barrel+later``: started 10 % off, so that
they have something to do; the camera side then has a third 6-block per group). Two timings per model and
size, the best of ``--repeats`` runs each:

* ``iteration_s``: LM iterations with the convergence tests off (``--iterations``), the setup excluded;
* ``solve_s``: the whole adjustment to the default stopping rule (the iterations it took are reported).

Run: ``.venv/bin/python benchmarks/bench_bundle_lenses.py`` (about a minute on 2 cores).
Writes benchmarks/results/bundle_lenses.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "src"))

SIZES = {"10k": (50, 2_500), "100k": (250, 25_000)}


def problems(m: int, n: int):
    """{model label: BundleProblem} of one scene seen through each lens, perturbed alike."""
    from scope3d.estimators.bundle import BundleProblem
    from scope3d.estimators.bundle.problem import lens_block
    from scope3d.phantoms.bundle_scene import make_scene
    from scope3d.phantoms.lenses import LENSES
    from scope3d.sensor.camera import Camera

    scene = make_scene(m, n, observations_per_point=4, seed=1)
    cameras = {
        "radial": Camera.from_intrinsics(640, 480, scene.intrinsics),
        "fisheye": LENSES["fisheye-140"].camera(640, 480, fov_deg=60.0, mask_radius_px=None),
        "barrel": LENSES["barrel-70"].camera(640, 480, fov_deg=60.0, mask_radius_px=None),
    }
    rng = np.random.default_rng(2)
    noise = rng.normal(0, 0.5, scene.observations_px.shape)
    d_trans = rng.normal(0, 0.01, (m, 3))
    d_points = rng.normal(0, 0.05, (n, 3))
    d_intr = 1 + rng.normal(0, 0.002, 6)
    p_cam = np.einsum("kij,kj->ki", scene.rotations[scene.camera_index], scene.points[scene.point_index]) \
        + scene.translations[scene.camera_index]
    out = {}
    for label, camera in cameras.items():
        pixels = camera.project(p_cam)
        assert np.all(np.isfinite(pixels)), label
        block, model, extra = lens_block(camera)
        for later in (False, True) if label != "radial" else (False,):
            problem = BundleProblem(pixels + noise, scene.camera_index, scene.point_index, scene.rotations,
                                    scene.translations + d_trans, scene.points + d_points, block * d_intr,
                                    model=model, extra=extra * 1.1 if later else extra)
            problem.fix("pose", [0])
            if later:
                problem.free("intrinsics", components=[n for n in problem.intrinsic_names[6:]
                                                       if not problem.intrinsic_absent[problem.intrinsic_names.index(n)]])
            out[label + ("+later" if later else "")] = problem
    return out


def best_time(fn, repeats: int) -> tuple[float, object]:
    best, result = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - start)
    return best, result


def main() -> None:
    from scope3d.estimators.bundle import SolverOptions, solve, warm_up
    from scope3d.estimators.bundle.solver import kernels, lens_kernels
    from scope3d.utils.aot import is_compiled

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--results", type=Path, default=RESULTS / "bundle_lenses.json")
    args = parser.parse_args()
    warm_up()
    fixed = SolverOptions(max_iterations=args.iterations, function_tolerance=0.0, gradient_tolerance=0.0,
                          parameter_tolerance=0.0)
    rows = []
    for size in args.sizes:
        m, n = SIZES[size]
        built = problems(m, n)
        for label, problem in built.items():
            solve(problem, SolverOptions(max_iterations=1))  # the JIT path's first call compiles, not timed
            t_fixed, r_fixed = best_time(lambda: solve(problem, fixed), args.repeats)
            per_iteration = (t_fixed - r_fixed.log[0].time_s) / max(1, len(r_fixed.log) - 1)
            t_solve, r_solve = best_time(lambda: solve(problem, SolverOptions()), args.repeats)
            rows.append({"size": size, "model": problem.model, "lens": label, "observations": len(problem.observations_px),
                         "iteration_s": per_iteration, "solve_s": t_solve, "solve_iterations": len(r_solve.log) - 1,
                         "rms_final_px": r_solve.rms_final_px})
            print(f"{size:5s} {label:8s} {per_iteration * 1e3:8.1f} ms/iteration  solve {t_solve:6.2f} s "
                  f"({len(r_solve.log) - 1} iterations, RMS {r_solve.rms_final_px:.3f} px)", flush=True)
    ratios = {}
    for size in args.sizes:
        base = next(r for r in rows if r["size"] == size and r["lens"] == "radial")
        for r in rows:
            if r["size"] == size and r["lens"] != "radial":
                ratios[f"{size} {r['lens']}"] = {"iteration": r["iteration_s"] / base["iteration_s"],
                                                 "solve": r["solve_s"] / base["solve_s"]}
    report = {
        "command": "python benchmarks/bench_bundle_lenses.py " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform(), "cores": os.cpu_count(), "load_1min": os.getloadavg()[0]},
        "kernels": {"radial": "ahead of time" if is_compiled(kernels) else "numba JIT",
                    "lenses": "ahead of time" if is_compiled(lens_kernels) else "numba JIT"},
        "target": "fisheye <= 1.3 x radial time on the same problem (issue 32), also with the later parameters "
                  "refined (+later)",
        "rows": rows, "ratio_to_radial": ratios,
    }
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(report, indent=1) + "\n")
    for key, value in ratios.items():
        print(f"{key}: {value['iteration']:.2f}x per iteration, {value['solve']:.2f}x per solve")
    print(f"wrote {args.results}")


if __name__ == "__main__":
    main()
