"""Where a rendered phantom frame spends its CPU (issue 17): CPU ms per frame of each stage of
``phantoms.render.render_frame``, and of the sequence's exposure probe.

Each stage is a function of the renderer wrapped in a process-CPU timer (``time.process_time``: all threads,
so Embree's split over the cores counts in full): the Embree first-hit query (``RayCaster._first_triangles``,
inside the cast), the whole cast (query, then the float64 refinement), the scene's albedo, the target ids,
the radiance (rays, cast, shading, depth), and the sensor model (noise draws, exposure, 8 bits). The
machine is shared: compare CPU, and run the code before and after a change one after the other. Run:
    PYTHONPATH=src .venv/bin/python benchmarks/profile_render.py [SCENE [TRAJECTORY [FRAMES]]]
"""
from __future__ import annotations

import collections
import os
import sys
import time

from scope3d.phantoms import build_scene, default_camera
from scope3d.phantoms import raycast, render
from scope3d.phantoms.trajectories import build_trajectory


def main() -> None:
    scene_name = sys.argv[1] if len(sys.argv) > 1 else "dome"
    trajectory = sys.argv[2] if len(sys.argv) > 2 else "grid5x6"
    n = int(sys.argv[3]) if len(sys.argv) > 3 else 12
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
    print(f"{scene_name}/{trajectory} {camera.width} x {camera.height}, {len(poses)} frames, "
          f"load {load:.1f} -> {os.getloadavg()[0]:.1f}; CPU ms per frame:")
    print(f"  exposure probe (sequence_exposure)         {1000 * probe / len(poses):6.1f}")
    for label, seconds in cpu.items():
        print(f"  {label:42s} {1000 * seconds / len(poses):6.1f}")
    print(f"  render_frame total                         {1000 * total / len(poses):6.1f}")


if __name__ == "__main__":
    main()
