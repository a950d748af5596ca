"""Throughput of `scope3d import frames` on a long video with a 250 Hz robot log (issue 33: >= 200 frames/s
for a 20,000-frame video on 2 cores).

A synthetic scan: a textured plane sliding under the camera (cheap to make, any length), written as Motion
JPEG (a frame grabber's recording), and a robot log at 250 Hz on its own clock. Times the import (decode,
PNG encode, pose interpolation, the dataset write) and writes benchmarks/results/import_frames.json.

    python benchmarks/bench_import_frames.py [--frames 20000] [--size 320]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from scope3d.io.camera_json import camera_to_dict
from scope3d.io.robot_log import PoseLogFormat
from scope3d.io.video import write_video
from scope3d.pipelines.frames_import import FramesImportOptions, run
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import PoseTolerance

RESULTS = Path(__file__).resolve().parent / "results" / "import_frames.json"
FPS, LOG_HZ, CLOCK_OFFSET_S = 30.0, 250.0, 1000.137


def _frames(n: int, size: int):
    texture = cv2.GaussianBlur(np.random.default_rng(0).integers(0, 255, (size * 4, size * 4), np.uint8), (0, 0), 2)
    for i in range(n):
        x = int(i * 0.7) % (size * 3)
        yield np.repeat(texture[size:2 * size, x:x + size, None], 3, axis=2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20000)
    parser.add_argument("--size", type=int, default=320)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-import-") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        write_video(tmp / "scan.avi", _frames(args.frames, args.size), FPS)
        duration = args.frames / FPS
        t = np.arange(-0.5, duration + 0.5, 1.0 / LOG_HZ)
        lines = ["t,x,y,z,qx,qy,qz,qw"] + [f"{v + CLOCK_OFFSET_S:.4f},{0.0007 * v * FPS:.6f},0.01,0.015,0,0,0,1"
                                            for v in t]
        (tmp / "log.csv").write_text("\n".join(lines) + "\n")
        made_s = time.perf_counter() - t0
        camera = Camera.from_fov(args.size, args.size, 70.0)
        (tmp / "camera.json").write_text(json.dumps(camera_to_dict(camera)))
        options = FramesImportOptions(log=PoseLogFormat(length_unit="m"), tolerance=PoseTolerance.from_degrees(0.5, 0.25))
        times = {str(i): i / FPS + CLOCK_OFFSET_S for i in range(args.frames)}
        cpu0, t0 = time.process_time(), time.perf_counter()
        result = run(options, tmp / "scan.avi", tmp / "log.csv", camera, tmp / "dataset", frame_times=times)
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    row = {"frames": len(result.names), "size_px": args.size, "log_rows": len(result.log), "wall_s": round(wall, 2),
           "cpu_s": round(cpu, 2), "frames_per_s": round(len(result.names) / wall, 1),
           "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
           "making_the_input_s": round(made_s, 1), "machine": platform.platform(), "cpus": os.cpu_count(),
           "load_average": os.getloadavg()}
    print(json.dumps(row))
    RESULTS.write_text(json.dumps(row, indent=2) + "\n")


if __name__ == "__main__":
    main()
