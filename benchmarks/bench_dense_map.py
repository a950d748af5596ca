"""The dense surgical-field map against today's thin-plate surface (issue 35).

Per scene (the dome and the resection cavity, grid5x6, 30 frames) and per pose error of the reports (0: the
micro-stage; 3: robot-grade, +-3 mm and +-1.5 deg, uniform), one map (``pipelines.surgical_map``, BCBA) with
the dense stage (``MapOptions.dense``). Against the truth, direct (no alignment), DTU style: accuracy (mesh
vertices to the true surface: mean, median, p95) and completeness (the fraction of the visible true surface,
every frame's true depth pixels, within 0.1 mm of the mesh), for the dense mesh and the thin-plate mesh of
the same map, and the sparse points' distances. On the cavity also per feature (the recess under the lip, the
creases at the rim and the wall's foot, the step): the median distance from the true surface there to each
mesh. Times: the sparse map's stages and the dense stage's (depth, fusion, mesh), per frame.

No Open3D peer: Open3D has no multi-view stereo from images (its reconstruction system starts from RGB-D
frames), and its TSDF volumes meshed nothing in the installed 0.20 (mvs/dense_map.py); its screened Poisson
surface is the mesh step here.

Run (one benchmark at a time; a few minutes per map at 304 px on 2 loaded cores):
    .venv/bin/python benchmarks/bench_dense_map.py [--size 304] [--noise 0 3] [--scenes dome cavity]
Writes benchmarks/results/dense_map.json. The (scene, noise) runs not asked for keep their rows from the
existing file; each run records its command, the commit and the machine's load average at its start and end.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from scope3d import phantoms
from scope3d.io.dataset import load_dataset
from scope3d.metrology.evaluation import visible_true_points
from scope3d.mvs.dense_map import DenseOptions
from scope3d.phantoms.scenes import (
    CAVITY_LIP_HALF_WIDTH_DEG,
    CAVITY_STEP_FRACTION,
    cavity_floor_radius,
    cavity_lip_weight,
    cavity_rim_radius,
    cavity_shelf_weight,
    cavity_wall_depth,
)
from scope3d.pipelines.surgical_map import MapOptions
from scope3d.pipelines.surgical_map import run as run_map
from scope3d.scene.mesh import SampledSurface

OUT = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


def cavity_regions(points: np.ndarray) -> dict[str, np.ndarray]:
    """Masks of true cavity points near its features (from the scene's functions): the recess under the lip
    (beyond the rim, inside the lip's sector), the creases (within 0.5 mm of the rim's edge or of the wall's
    foot), the step (within 0.5 mm of its face where the shelf is at least half raised)."""
    theta, r, z = np.arctan2(points[:, 1], points[:, 0]), np.hypot(points[:, 0], points[:, 1]), points[:, 2]
    rim = cavity_rim_radius(theta)
    foot_r, foot_z = cavity_floor_radius(theta), -cavity_wall_depth(theta)
    step_r = CAVITY_STEP_FRACTION * foot_r
    lip = (r > rim) & (z < -0.05) & (cavity_lip_weight(theta) > 0.5)
    crease = ((np.hypot(r - rim, z) < 0.5) | (np.hypot(r - foot_r, z - foot_z) < 0.5)) & (z < -1e-6)
    step = (np.abs(r - step_r) < 0.5) & (cavity_shelf_weight(theta) > 0.5) & (z < -1.0)
    return {"lip": lip, "creases": crease, "step": step}


def mesh_region_errors(mesh_vertices, mesh_faces, visible, regions) -> dict:
    from scope3d.scene.mesh import Mesh

    if len(mesh_faces) == 0:
        return {}
    d = SampledSurface(Mesh(mesh_vertices, mesh_faces), 0.02).distances(visible)
    return {name: {"n": int(m.sum()), "median_mm": float(np.median(d[m])) if m.any() else None,
                   "within_0.1mm": float(np.mean(d[m] <= 0.1)) if m.any() else None}
            for name, m in regions.items()}


def one(scene: str, noise_mm: float, size: int, work: Path) -> dict:
    data = work / f"{scene}_{noise_mm:g}"
    seq = phantoms.generate(scene, seed=0, pose_noise_mm=noise_mm, size=(size, size))
    phantoms.write(seq, data)
    dataset = load_dataset(data)
    options = MapOptions(dense=DenseOptions(), figures=False)
    load_at_start = os.getloadavg()  # the times are the machine's as much as the code's: say how busy it was
    t0, cpu0 = time.perf_counter(), time.process_time()
    result = run_map(options, dataset, work / f"map_{scene}_{noise_mm:g}")
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    rep = result.report
    out = {"scene": scene, "pose_noise_mm": noise_mm, "orientation_noise_deg": noise_mm * 0.5, "size_px": size,
           "frames": len(dataset), "wall_s": wall, "cpu_s": cpu,  # cpu: every thread of the process
           "measured": {"command": "benchmarks/bench_dense_map.py " + " ".join(sys.argv[1:]), "commit": _commit(),
                        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "cores": os.cpu_count(),
                        "load_average_at_start": list(load_at_start), "load_average_at_end": list(os.getloadavg())},
           "timings_s": rep["timings_s"], "dense": rep["dense"],
           "dense_error_mm": rep["dense_error_mm"], "spline_error_mm": rep["spline_error_mm"],
           "sparse_points_error_mm": rep["surface_error_mm"]["direct"],
           "pose_error": rep.get("pose_error")}
    sparse_s = sum(v for k, v in rep["timings_s"].items() if k not in ("dense", "evaluation", "outputs"))
    out["sparse_map_s"] = sparse_s
    out["dense_s_per_frame"] = rep["timings_s"]["dense"] / len(dataset)
    if scene == "cavity":
        gt = dataset.ground_truth
        visible = visible_true_points(dataset.camera, gt.poses, gt.depth, max_points=60000)
        regions = cavity_regions(visible)
        d = result.dense.mesh
        s = result.surface.surface.mesh(result.surface.colors)
        out["regions"] = {"dense": mesh_region_errors(d.vertices, d.faces, visible, regions),
                          "spline": mesh_region_errors(s.vertices, s.faces, visible, regions),
                          "definition": cavity_regions.__doc__.split("\n", 1)[1].strip() if cavity_regions.__doc__ else "",
                          "lip_half_width_deg": CAVITY_LIP_HALF_WIDTH_DEG}
    return out


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=304)
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 3.0])
    ap.add_argument("--scenes", nargs="+", default=["dome", "cavity"])
    ap.add_argument("--results", default=str(OUT / "dense_map.json"))
    args = ap.parse_args()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes:
            for noise in args.noise:
                r = one(scene, noise, args.size, Path(tmp))
                runs.append(r)
                for when in ("direct", "after_icp"):
                    d, s = r["dense_error_mm"], r["spline_error_mm"]
                    if when == "after_icp":
                        d, s = d["after_icp"], s["after_icp"]
                    print(f"{scene} ±{noise:g} mm {when}: dense acc {d['accuracy']['mean']:.4f} "
                          f"(p95 {d['accuracy']['p95']:.3f}) compl {d['completeness']:.3f} "
                          f"({d['completeness_seen_by_3']:.3f} of what 3 frames see) | spline acc "
                          f"{s['accuracy']['mean']:.4f} (p95 {s['accuracy']['p95']:.3f}) compl {s['completeness']:.3f} "
                          f"({s['completeness_seen_by_3']:.3f})", flush=True)
                print(f"  dense {r['timings_s']['dense']:.1f} s, sparse map {r['sparse_map_s']:.1f} s", flush=True)
    path = Path(args.results)
    done = {(r["scene"], r["pose_noise_mm"]) for r in runs}
    kept = []
    if path.exists():  # the runs not asked for stay, each with when and at what load it was measured
        previous = json.loads(path.read_text())
        for r in previous.get("runs", []):
            if (r["scene"], r["pose_noise_mm"]) not in done:
                r.setdefault("measured", {"command": previous.get("command"), "machine": previous.get("machine")})
                kept.append(r)
    order = {"dome": 0, "cavity": 1}
    runs = sorted(runs + kept, key=lambda r: (order.get(r["scene"], 2), r["scene"], r["pose_noise_mm"]))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"machine": "2 cores, shared with another job; each run's load average in its "
                                "'measured'", "runs": runs}, indent=1))
    print(f"wrote {args.results}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
