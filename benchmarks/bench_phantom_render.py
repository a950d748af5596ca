"""Time the phantom lab: seconds per rendered frame for each scene at the reference's image sizes.

Run:  .venv/bin/python benchmarks/bench_phantom_render.py [--frames N] [--before OLD.json] [--cases dome,sheet]
Writes benchmarks/results/phantom_render.json. Scene construction (mesh, texture, target ground truth)
is timed separately: it happens once per process (scenes are cached). Each case reports wall and CPU
(process) seconds per frame and the 1-minute load average around it: the machine is shared, so CPU time
is the steadier figure. ``--before`` embeds an earlier run's JSON (e.g. this script run on the code
before a change) and the per-frame CPU ratio after/before of each case.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import trimesh

from scope3d.phantoms import build_scene, default_camera, generate

CASES = [  # (scene, trajectory, frames)
    ("dome", "grid5x6", 30),
    ("sheet", "grid5x6", 30),
    ("bladder", "spiral", 12),
    ("thread", "axial", 12),
    ("thread", "quadrants", 12),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, help="frames per case (default: per case, 30 for the grids)")
    parser.add_argument("--before", help="JSON of an earlier run to embed for comparison")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "phantom_render.json"))
    parser.add_argument("--cases", help="comma-separated scene or scene/trajectory names to run (default: all)")
    args = parser.parse_args()
    wanted = None if not args.cases else set(args.cases.split(","))
    results = []
    for scene_name, traj, n in CASES:
        if wanted is not None and scene_name not in wanted and f"{scene_name}/{traj}" not in wanted:
            continue
        n = args.frames or n
        t0 = time.perf_counter()
        scene = build_scene(scene_name)
        t_build = time.perf_counter() - t0
        load_before = os.getloadavg()[0]
        t0, c0 = time.perf_counter(), time.process_time()
        seq = generate(scene_name, traj, n_frames=n)
        t_render, c_render = time.perf_counter() - t0, time.process_time() - c0
        cam = default_camera(scene, traj)
        row = {
            "scene": scene_name, "trajectory": traj, "frames": len(seq), "image": f"{cam.width}x{cam.height}",
            "mesh_faces": int(len(scene.mesh.faces)), "scene_build_s": round(t_build, 3),
            "sequence_s": round(t_render, 3), "seconds_per_frame": round(t_render / len(seq), 4),
            "cpu_seconds_per_frame": round(c_render / len(seq), 4),
            "load_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        }
        results.append(row)
        print(f"{scene_name:8s} {traj:10s} {row['image']:>10s} {len(seq):3d} frames  "
              f"{row['seconds_per_frame']:.3f} s/frame wall, {row['cpu_seconds_per_frame']:.3f} CPU  "
              f"(scene build {t_build:.1f} s, load {row['load_1min']})")
    out = {
        "benchmark": "phantom_render",
        "note": "seconds per frame include ray casting, shading, noise, depth and fluorescence; the sequence's "
                "auto-exposure probe is included, scene construction is not; cpu_seconds_per_frame is process time",
        "ray_backend": "embree" if trimesh.ray.has_embree else "numpy",
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine()},
        "results": results,
    }
    if args.before:
        before = json.loads(Path(args.before).read_text())
        out["before"] = before
        old = {(r["scene"], r["trajectory"], r["image"]): r for r in before["results"]}
        out["cpu_ratio_after_before"] = {
            f"{r['scene']}/{r['trajectory']}/{r['image']}": round(r["cpu_seconds_per_frame"]
                                                                / old[key]["cpu_seconds_per_frame"], 3)
            for r in results if (key := (r["scene"], r["trajectory"], r["image"])) in old
            and old[key].get("cpu_seconds_per_frame")}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
