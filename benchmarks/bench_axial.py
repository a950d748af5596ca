"""Axial-stereo benchmark (issue 5): phantom M8x1.25 hole, 608x608, 0.25 mm steps; Middlebury Cones.

Writes benchmarks/results/axial.json, axial_depth.png, axial_cloud.png and prints a table. Run:
    .venv/bin/python benchmarks/bench_axial.py

Speed of one two-view pair only (issue 17), CPU and wall time with the machine load, merged into
benchmarks/results/axial_speed.json under LABEL (run it with another checkout's src on PYTHONPATH for a
"before" row; the digest of the output arrays shows whether two rows computed the same result):
    .venv/bin/python benchmarks/bench_axial.py --speed LABEL
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from scope3d import phantoms
from scope3d.io.dataset import load_dataset
from scope3d.metrology.evaluation import distance_summary
from scope3d.mvs.dense_matching import SadOptions, SgmOptions, sad_disparity, sgm_disparity
from scope3d.mvs.two_view import reconstruct_pair, to_image
from scope3d.pipelines.axial import AxialOptions, run, save_depth_png
from scope3d.scene.mesh import SampledSurface

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
DATA = ROOT.parent / "shared" / "data" / "middlebury2003_cones"
N_FRAMES = 24


def phantom_methods(ds_path: Path) -> dict:
    ds = load_dataset(ds_path)
    rows = {}
    mid = len(ds) // 2
    for method in ("sgm", "sad"):
        times = []
        for _ in range(3):  # best of 3: the machine is shared
            res = run(AxialOptions(method=method, frames=(mid - 1, mid)), ds, None)
            times.append(res.report["timings_s"]["per_pair"])
        rows[method] = {"time_per_pair_s": min(times), "n_points": res.report["n_points"],
                        "surface_error_mm": res.report["surface_error_mm"]}
        if method == "sgm":
            save_depth_png(OUT / "axial_depth.png", res.depths[0], title="axial SGM, M8 phantom: z-depth")
    rows["sgm_tradeoff"] = tradeoff(ds, mid)
    res = run(AxialOptions(method="multiview"), ds, OUT / "axial_multiview_run")
    rows["multiview"] = {"time_per_pair_s": res.report["timings_s"]["per_pair"], "n_points": res.report["n_points"],
                         "pairs": res.report["pairs"], "surface_error_mm": res.report["surface_error_mm"]}
    save_cloud_picture(res.cloud.points, res.cloud.colors, OUT / "axial_cloud.png")
    return rows


def tradeoff(ds, mid: int) -> list[dict]:
    """Points vs error of two-view SGM as the confidence threshold (predicted range sigma) moves, and the
    first version's settings (5x5 blocks, 3 refinement iterations, sigma_d floor 0.05, 0.1 mm) for reference."""
    base = AxialOptions().two_view
    first = replace(base, sgm=replace(base.sgm, block_size=5, refine_iterations=3),
                    confidence=replace(base.confidence, disparity_sigma_floor_px=0.05, max_range_sigma_mm=0.1))
    out = [{"label": "first version (block 5, 3 LK iterations, floor 0.05 col, 0.1 mm)", **_pair_row(ds, mid, first)}]
    for thr in (0.1, 0.07, 0.05, 0.04, 0.03):
        opts = replace(base, confidence=replace(base.confidence, max_range_sigma_mm=thr))
        out.append({"label": f"max_range_sigma_mm {thr}", "max_range_sigma_mm": thr, **_pair_row(ds, mid, opts)})
    return out


def _pair_row(ds, mid, two_view) -> dict:
    res = run(AxialOptions(method="sgm", frames=(mid - 1, mid), two_view=two_view), ds, None)
    e = res.report["surface_error_mm"]
    return {"n_points": res.report["n_points"], "mean_mm": e.get("mean"), "median_mm": e.get("median"),
            "p95_mm": e.get("p95")}


def save_cloud_picture(points, colors, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(0)
    idx = rng.choice(len(points), size=min(40000, len(points)), replace=False)
    fig = plt.figure(figsize=(6, 6), dpi=110)
    ax = fig.add_subplot(projection="3d")
    p = points[idx]
    ax.scatter(p[:, 0], p[:, 1], p[:, 2], c=colors[idx] / 255.0, s=0.3, linewidths=0)
    ax.set_xlabel("x (mm)"); ax.set_ylabel("y (mm)"); ax.set_zlabel("z (mm)")
    ax.set_title("axial multi-view, M8x1.25 phantom")
    ax.view_init(elev=20, azim=-60)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def misalignment(seq_scene, camera, surface: SampledSurface) -> list[dict]:
    """Two frames with the scope offset sideways and tilted w.r.t. its motion (the hole axis), from the
    phantom's own ``axial`` trajectory options (``axis_offset_mm``, ``axis_tilt_deg``), starting 1 mm
    inside the hole."""
    rows = []
    for offset in (0.0, 0.1, 0.3):
        for tilt in (0.0, 1.0, 3.0):
            poses = phantoms.axial_trajectory(2, start_z_mm=-1.0, axis_offset_mm=offset, axis_tilt_deg=tilt).poses
            gain = phantoms.sequence_exposure(seq_scene, camera, poses)
            imgs = [cv2.cvtColor(phantoms.render_frame(seq_scene, camera, p, seed=0, frame_index=k, exposure=gain).image,
                                 cv2.COLOR_RGB2GRAY) for k, p in enumerate(poses)]
            row = {"offset_mm": offset, "tilt_deg": tilt}
            for label, aligned in (("true_poses", False), ("aligned_model", True)):
                opts = replace(AxialOptions().two_view, assume_aligned=aligned)
                res = reconstruct_pair(camera, imgs[0], imgs[1], poses[0], poses[1], options=opts)
                depth = to_image(res.pair, res.range_mm)
                pts = depth.points_world[depth.valid]
                d = surface.distances(pts) if len(pts) else np.array([])
                s = distance_summary(d)
                row[label] = {"n_points": int(len(pts)), "mean_mm": s.get("mean"), "p95_mm": s.get("p95")}
            rows.append(row)
    return rows


def middlebury() -> dict:
    left = cv2.imread(str(DATA / "im2.ppm"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(DATA / "im6.ppm"), cv2.IMREAD_GRAYSCALE)
    gt = cv2.imread(str(DATA / "disp2.pgm"), cv2.IMREAD_GRAYSCALE).astype(float) / 4
    g6 = cv2.imread(str(DATA / "disp6.pgm"), cv2.IMREAD_GRAYSCALE).astype(float) / 4
    h, w = gt.shape
    xr = np.clip(np.round(np.arange(w)[None] - gt).astype(int), 0, w - 1)
    nonocc = (gt > 0) & (np.abs(g6[np.arange(h)[:, None], xr] - gt) <= 1)
    out = {}
    for name, fn in (("sgm", lambda: sgm_disparity(left, right, options=SgmOptions(num_disparities=64))),
                     ("sad", lambda: sad_disparity(left, right, options=SadOptions(num_disparities=64)))):
        t = time.perf_counter()
        d = fn().disparity
        dt = time.perf_counter() - t
        matched = nonocc & np.isfinite(d)
        bad = ~(np.abs(d - gt) <= 1.0)
        out[name] = {"bad1_matched_nonocc": float(bad[matched].mean()),
                     "bad1_nonocc_unmatched_as_bad": float(bad[nonocc].mean()),
                     "coverage_nonocc": float(matched.sum() / nonocc.sum()), "time_s": dt}
    return out


def speed(label: str, repeats: int = 7) -> dict:
    """Best-of-``repeats`` CPU (process_time) and wall time of one 608x608 thread pair: the two-view
    reconstruction alone (``reconstruct_pair``, the figure issue 17 targets) and the whole ``run`` without
    files (reconstruction, image resampling, cloud and mesh). The load average is read before and after."""
    from scope3d.mvs.two_view import reconstruct_pair as pair_fn

    with tempfile.TemporaryDirectory() as tmp:
        seq = phantoms.generate("thread", "axial", seed=0, n_frames=4)
        ds = load_dataset(phantoms.write(seq, Path(tmp) / "thread"))
        opts = AxialOptions(method="sgm", frames=(1, 2))
        imgs = [ds.frame(k, grey=True) for k in (1, 2)]
        poses = [m.pose for m in ds.poses]
        res = run(opts, ds, None)  # warm: imports, OpenCV's first calls
        load_before = os.getloadavg()
        rows = {"pair": [], "run": []}
        for _ in range(repeats):
            c, w = time.process_time(), time.perf_counter()
            pair_fn(ds.camera, imgs[0], imgs[1], poses[1], poses[2], options=opts.two_view)
            rows["pair"].append((time.process_time() - c, time.perf_counter() - w))
            c, w = time.process_time(), time.perf_counter()
            res = run(opts, ds, None)
            rows["run"].append((time.process_time() - c, time.perf_counter() - w, res.report["time_s"]))
        load_after = os.getloadavg()
    d = res.depths[0]
    digest = hashlib.sha256()
    for a in (d.z_depth_mm, d.range_mm, d.points_world, d.confidence, res.cloud.points, res.mesh.faces):
        digest.update(np.ascontiguousarray(a).tobytes())
    out = {"label": label, "size_px": [ds.camera.width, ds.camera.height], "repeats": repeats,
           "pair_cpu_s": min(r[0] for r in rows["pair"]), "pair_wall_s": min(r[1] for r in rows["pair"]),
           "run_cpu_s": min(r[0] for r in rows["run"]), "run_wall_s": min(r[1] for r in rows["run"]),
           "run_time_s_reported": min(r[2] for r in rows["run"]),
           "load_1min_before_after": [load_before[0], load_after[0]], "cpu_count": os.cpu_count(),
           "n_points": res.report["n_points"], "mean_error_mm": res.report["surface_error_mm"]["mean"],
           "output_sha256": digest.hexdigest()}
    path = OUT / "axial_speed.json"
    table = json.loads(path.read_text()) if path.exists() else {}
    table[label] = out
    path.write_text(json.dumps(table, indent=2) + "\n")
    return out


def main() -> int:
    if len(sys.argv) == 3 and sys.argv[1] == "--speed":
        OUT.mkdir(parents=True, exist_ok=True)
        print(json.dumps(speed(sys.argv[2]), indent=2))
        return 0
    OUT.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        seq = phantoms.generate("thread", "axial", seed=0, n_frames=N_FRAMES)
        ds_path = phantoms.write(seq, Path(tmp) / "thread")
        render_s = time.perf_counter() - t
        rows = phantom_methods(ds_path)
        surface = SampledSurface(seq.surface, 0.05)
        mis = misalignment(seq.scene, seq.camera, surface)
    mb = middlebury()
    result = {"phantom": {"scene": "thread M8x1.25", "size_px": [608, 608], "step_mm": 0.25, "frames": N_FRAMES,
                          "render_s": render_s, "supersample": seq.scene_info["render"]["supersample"],
                          "methods": rows},
              "reference": {"time_s": 250.0, "icp_error_mm": 0.4333},
              "misalignment": mis, "middlebury_cones": mb}
    (OUT / "axial.json").write_text(json.dumps(result, indent=2) + "\n")
    print(f"{'method':<10} {'s/pair':>8} {'points':>8} {'mean mm':>8} {'p95 mm':>8}")
    for k, r in rows.items():
        if k == "sgm_tradeoff":
            continue
        e = r["surface_error_mm"]
        print(f"{k:<10} {r['time_per_pair_s']:>8.2f} {r['n_points']:>8d} {e['mean']:>8.4f} {e['p95']:>8.4f}")
    for r in rows["sgm_tradeoff"]:
        print(f"  sgm {r['label']:<60s} {r['n_points']:>7d} pts mean {r['mean_mm']:.4f} p95 {r['p95_mm']:.4f}")
    print("misalignment (mean mm: true poses / aligned model)")
    for r in mis:
        print(f"  offset {r['offset_mm']:.1f} mm tilt {r['tilt_deg']:.0f} deg: "
              f"{r['true_poses']['mean_mm'] or float('nan'):.4f} ({r['true_poses']['n_points']}) / "
              f"{r['aligned_model']['mean_mm'] or float('nan'):.4f} ({r['aligned_model']['n_points']})")
    for k, r in mb.items():
        print(f"cones {k}: bad1 {100 * r['bad1_matched_nonocc']:.1f} % of matched non-occluded, "
              f"coverage {100 * r['coverage_nonocc']:.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
