"""Where a rendered phantom frame spends its CPU (issue 17): CPU ms per frame of each stage of
``phantoms.render.render_frame``, and of the sequence's exposure probe.

Each stage is a function of the renderer wrapped in a process-CPU timer (``time.process_time``: all threads,
so Embree's split over the cores counts in full): the Embree first-hit query (``RayCaster._first_triangles``,
inside the cast), the whole cast (query, then the float64 refinement), the scene's albedo, the target ids,
the radiance (rays, cast, shading, depth), and the sensor model (noise draws, exposure, 8 bits). The
machine is shared: compare CPU, and run the code before and after a change one after the other. Prints
the table and merges the run into benchmarks/results/profile_render.json under LABEL (default: the scene,
trajectory and frames). Run:
    PYTHONPATH=src .venv/bin/python benchmarks/profile_render.py [SCENE [TRAJECTORY [FRAMES [LABEL]]]]
"""
from __future__ import annotations

import collections
import json
import os
import sys
import time
from pathlib import Path

from scope3d.phantoms import build_scene, default_camera
from scope3d.phantoms import raycast, render
from scope3d.phantoms.trajectories import build_trajectory
from scope3d.utils.jsonio import write_json

OUT = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "profile_render.json"


def main() -> None:
    scene_name = sys.argv[1] if len(sys.argv) > 1 else "dome"
    trajectory = sys.argv[2] if len(sys.argv) > 2 else "grid5x6"
    n = int(sys.argv[3]) if len(sys.argv) > 3 else 12
    label = sys.argv[4] if len(sys.argv) > 4 else f"{scene_name}/{trajectory}/{n}"
    cpu = collections.defaultdict(float)

    def timed(owner, name: str, label: str) -> None:
        function = getattr(owner, name)

        def wrapper(*args, **kwargs):
            c0 = time.process_time()
            try:
                return function(*args, **kwargs)
            finally:
                cpu[label] += time.process_time() - c0

        setattr(owner, name, wrapper)

    scene = build_scene(scene_name)
    camera = default_camera(scene, trajectory)
    poses = build_trajectory(trajectory, n_frames=n).poses[:n]
    render.render_frame(scene, camera, poses[0], exposure=1.0)  # kernels loaded, caches filled
    c0 = time.process_time()
    exposure = render.sequence_exposure(scene, camera, poses)
    probe = time.process_time() - c0
    timed(raycast.RayCaster, "_first_triangles", "Embree first-hit query")
    timed(raycast.RayCaster, "cast", "cast (query + float64 refinement)")
    timed(scene, "albedo", "albedo (texture lookups)")
    timed(render, "_target_ids", "target ids")
    timed(render, "_radiance", "radiance (rays, cast, shading, depth)")
    timed(render, "_to_image", "sensor model (noise draws, gain, 8 bits)")
    load = os.getloadavg()[0]
    c0 = time.process_time()
    for i, pose in enumerate(poses):
        render.render_frame(scene, camera, pose, frame_index=i, exposure=exposure)
    total = time.process_time() - c0
    load_after = os.getloadavg()[0]
    per_frame = {"exposure probe (sequence_exposure)": 1000 * probe / len(poses)}
    per_frame.update({label_: 1000 * seconds / len(poses) for label_, seconds in cpu.items()})
    per_frame["render_frame total"] = 1000 * total / len(poses)
    print(f"{scene_name}/{trajectory} {camera.width} x {camera.height}, {len(poses)} frames, "
          f"load {load:.1f} -> {load_after:.1f}; CPU ms per frame:")
    for label_, ms in per_frame.items():
        print(f"  {label_:42s} {ms:6.1f}")
    runs = json.loads(OUT.read_text()) if OUT.exists() else {}
    runs[label] = {"scene": scene_name, "trajectory": trajectory, "frames": len(poses),
                   "size_px": [camera.width, camera.height], "load_average_before_after": [load, load_after],
                   "cpu_ms_per_frame": per_frame}
    write_json(OUT, runs)
    print(f"wrote {OUT} [{label}]")


if __name__ == "__main__":
    main()
