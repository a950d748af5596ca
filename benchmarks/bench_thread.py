"""Side-view thread metrology benchmark (issue 13).

1. Registration: an M8x1.25 hole scanned in 12 quadrants of 4 frames (400x320 px, 60° FOV), 45° and 90°
   side views, the camera 0.22 mm off and 0.5° tilted from the rotation axis (unknown to the stage).
   scope3d's feature-based registration (rotation-stage model; free pose graph) side by side with
   Open3D point-to-point and point-to-plane ICP and small_gicp GICP, each from the stacked initial guess
   on the same quadrant clouds, chained round the hole: rotation and offset errors against the truth, time.
2. Gauge accuracy on clouds sampled from the true meshes of M6x1, M8x1.25, M10x1.5 mid-class holes
   (0.01 mm noise), against the as-made sizes.
3. Whole-hole time of ``thread-scan`` (wall and CPU), and batch throughput on 1 and 2 Dask workers.

The gauge from images (pass/fail on rendered 90°-view holes) is benchmarks/bench_thread_gauge.py.

Writes benchmarks/results/thread.json and thread_registration.png. Run:
    .venv/bin/python benchmarks/bench_thread.py
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.io.dataset import load_dataset
from scope3d.phantoms import generate, write
from scope3d.pipelines import thread_batch
from scope3d.pipelines.thread_scan import ThreadScanOptions, map_quadrants, run, true_world_from_stacked
from scope3d.registration.panorama import PanoramaOptions, register_quadrants, registration_errors
from scope3d.utils.figures import new_figure, save_figure

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
MOUNT = (0.2, -0.1, 0.5)
MID_CLASS = {"M6x1": (0.118, 0.075, 0.05), "M8x1.25": (0.132, 0.08, 0.05), "M10x1.5": (0.15, 0.09, 0.05)}


def load() -> str:
    return os.popen("uptime").read().strip()


def icp_chain(clouds, method: str) -> tuple[list[Pose], float]:
    """Neighbour-to-neighbour ICP from the stacked guess (identity), chained from quadrant 0."""
    import open3d as o3d

    poses, t0 = [Pose.identity()], time.perf_counter()
    for q in range(1, len(clouds)):
        src, dst = clouds[q].points, clouds[q - 1].points
        if method == "small_gicp":
            import small_gicp

            res = small_gicp.align(dst, src, np.eye(4), registration_type="GICP", max_correspondence_distance=0.5,
                                   num_threads=2)
            m = res.T_target_source
        else:
            a, b = o3d.geometry.PointCloud(), o3d.geometry.PointCloud()
            a.points, b.points = o3d.utility.Vector3dVector(src), o3d.utility.Vector3dVector(dst)
            if method == "o3d_point_to_plane":
                for pc in (a, b):
                    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
                est = o3d.pipelines.registration.TransformationEstimationPointToPlane()
            else:
                est = o3d.pipelines.registration.TransformationEstimationPointToPoint()
            m = o3d.pipelines.registration.registration_icp(
                a, b, 0.5, np.eye(4), est, o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=100)
            ).transformation
        poses.append(poses[-1] @ Pose(np.asarray(m)[:3, :3], np.asarray(m)[:3, 3]))
    return poses, time.perf_counter() - t0


def registration_bench(tmp: Path) -> dict:
    rows = {}
    for view in (45.0, 90.0):
        path = tmp / f"m8_{int(view)}"
        seq = generate("thread", "quadrants", n_frames=48, size=(400, 320), side_view_deg=view,
                       quadrant_mount=MOUNT, thread_offsets_mm=MID_CLASS["M8x1.25"])
        write(seq, path)
        ds = load_dataset(path)
        t0, c0 = time.perf_counter(), time.process_time()
        clouds, mount = map_quadrants(ThreadScanOptions(), ds)
        truth = true_world_from_stacked(ds, mount)
        mapping = (time.perf_counter() - t0, time.process_time() - c0)
        view_rows = {"mapping_wall_s": mapping[0], "mapping_cpu_s": mapping[1],
                     "points_per_quadrant": [len(c.points) for c in clouds]}
        rot, off = registration_errors([Pose.identity()] * len(clouds), truth, clouds)
        view_rows["stacked"] = {"rotation_error_deg": float(rot.max()), "offset_error_mm": float(off.max())}
        for name, opts in (("scope3d_stage_model", PanoramaOptions()), ("scope3d_free", PanoramaOptions(model="free"))):
            t0 = time.perf_counter()
            try:
                res = register_quadrants(clouds, options=opts)
            except Exception as exc:  # a failed registration is a result too
                view_rows[name] = {"error": str(exc)}
                continue
            dt = time.perf_counter() - t0
            rot, off = registration_errors(res.world_from_stacked, truth, clouds)
            view_rows[name] = {"rotation_error_deg": float(rot.max()), "offset_error_mm": float(off.max()),
                               "loop_closure_deg": res.loop_closure_deg, "time_s": dt}
        for name in ("o3d_point_to_point", "o3d_point_to_plane", "small_gicp"):
            try:
                poses, dt = icp_chain(clouds, name)
            except ImportError as exc:
                view_rows[name] = {"error": f"not installed: {exc}"}
                continue
            rot, off = registration_errors(poses, truth, clouds)
            view_rows[name] = {"rotation_error_deg": float(rot.max()), "offset_error_mm": float(off.max()), "time_s": dt}
        rows[f"side_view_{int(view)}deg"] = view_rows
    return rows


def gauge_bench() -> dict:
    import trimesh

    from scope3d.metrology.thread_gauge import GaugeOptions, gauge_thread
    from scope3d.phantoms.scenes import build_thread

    rows = {}
    for size, offsets in MID_CLASS.items():
        scene = build_thread(size, minor_diameter_offset_mm=offsets[0], pitch_diameter_offset_mm=offsets[1],
                             major_diameter_offset_mm=offsets[2])
        made = scene.info["thread"]["as_made"]
        pts, _ = trimesh.sample.sample_surface(scene.mesh.to_trimesh(), 120000, seed=0)
        pts = pts[pts[:, 2] < -0.05]
        pts = pts + np.random.default_rng(0).normal(0, 0.01, pts.shape)
        t0 = time.process_time()
        g = gauge_thread(pts, options=GaugeOptions(designation=size))
        rows[size] = {"verdict": g.verdict, "cpu_s": time.process_time() - t0,
                      "minor_error_mm": g.minor_diameter_mm.value - made["minor_diameter_mm"],
                      "major_error_mm": g.major_diameter_mm.value - made["major_diameter_mm"],
                      "pitch_diameter_error_mm": g.pitch_diameter_mm.value - made["pitch_diameter_mm"],
                      "pitch_error_mm": g.pitch_mm.value - float(size.split("x")[1]),
                      "flank_angle_deg": g.flank_angle_deg.value,
                      "minor_sigma_mm": g.minor_diameter_mm.uncertainty}
    return rows


def throughput_bench(tmp: Path) -> dict:
    holes = [tmp / "m8_45", tmp / "m8_90"]
    out = {}
    t0, c0 = time.perf_counter(), time.process_time()
    res = run(ThreadScanOptions(), load_dataset(holes[0]), tmp / "one_hole")
    out["whole_hole"] = {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                         "stages_s": res.timings_s, "verdict": res.gauge.verdict if res.gauge else "indeterminate"}
    for workers in (1, 2):
        dest = tmp / f"line_{workers}"
        t0 = time.perf_counter()
        b = thread_batch.run(ThreadScanOptions(), holes * 2 if workers == 2 else holes, dest, n_workers=workers)
        dt = time.perf_counter() - t0
        out[f"batch_{workers}_workers"] = {"holes": len(b.rows), "wall_s": dt, "holes_per_min": 60 * len(b.rows) / dt}
    return out


def figure(reg: dict, path: Path) -> None:
    fig = new_figure((11, 4.5))
    for k, metric in enumerate(("rotation_error_deg", "offset_error_mm")):
        ax = fig.add_subplot(1, 2, 1 + k)
        methods = ["stacked", "scope3d_stage_model", "scope3d_free", "o3d_point_to_point", "o3d_point_to_plane",
                   "small_gicp"]
        x = np.arange(len(methods))
        for j, (view, rows) in enumerate(reg.items()):
            vals = [rows.get(m, {}).get(metric, np.nan) for m in methods]
            ax.bar(x + 0.4 * j - 0.2, vals, 0.4, label=view)
        ax.axhline(0.5 if k == 0 else 0.02, color="red", ls="--", label="target")
        ax.set_yscale("log")
        ax.set_xticks(x, [m.replace("_", "\n") for m in methods], fontsize=7)
        ax.set_ylabel(metric)
        ax.legend(fontsize=7)
    fig.suptitle("M8 quadrant registration, 12 x 4 frames 400x320, mount 0.22 mm / 0.5° (max over quadrants)")
    save_figure(fig, path)


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="bench_thread_"))
    results = {"load_before": load()}
    try:
        results["gauge_true_meshes"] = gauge_bench()
        results["registration"] = registration_bench(tmp)
        results["load_mid"] = load()
        results["throughput"] = throughput_bench(tmp)
    finally:
        results["load_after"] = load()
        (OUT / "thread.json").write_text(json.dumps(results, indent=2, default=float))
        shutil.rmtree(tmp, ignore_errors=True)
    figure(results["registration"], OUT / "thread_registration.png")
    print(json.dumps(results, indent=2, default=float))


if __name__ == "__main__":
    main()
