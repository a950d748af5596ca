"""Time the phantom lab: seconds per rendered frame for each scene at the reference's image sizes.

Run:  .venv/bin/python benchmarks/bench_phantom_render.py [--frames N]
Writes benchmarks/results/phantom_render.json. Scene construction (mesh, texture, target ground truth)
is timed separately: it happens once per process (scenes are cached).
"""
from __future__ import annotations

import argparse
import json
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
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "phantom_render.json"))
    args = parser.parse_args()
    results = []
    for scene_name, traj, n in CASES:
        n = args.frames or n
        t0 = time.perf_counter()
        scene = build_scene(scene_name)
        t_build = time.perf_counter() - t0
        t0 = time.perf_counter()
        seq = generate(scene_name, traj, n_frames=n)
        t_render = time.perf_counter() - t0
        cam = default_camera(scene, traj)
        row = {
            "scene": scene_name, "trajectory": traj, "frames": len(seq), "image": f"{cam.width}x{cam.height}",
            "mesh_faces": int(len(scene.mesh.faces)), "scene_build_s": round(t_build, 3),
            "sequence_s": round(t_render, 3), "seconds_per_frame": round(t_render / len(seq), 4),
        }
        results.append(row)
        print(f"{scene_name:8s} {traj:10s} {row['image']:>10s} {len(seq):3d} frames  "
              f"{row['seconds_per_frame']:.3f} s/frame  (scene build {t_build:.1f} s)")
    out = {
        "benchmark": "phantom_render",
        "note": "seconds per frame include ray casting, shading, noise, depth and fluorescence; the sequence's "
                "auto-exposure probe is included, scene construction is not",
        "ray_backend": "embree" if trimesh.ray.has_embree else "numpy",
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine()},
        "results": results,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
