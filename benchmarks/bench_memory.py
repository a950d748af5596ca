"""Peak memory of ``scope3d check`` (loads a dataset and decodes every frame once) on 200 and 2,000 frames:
bounded memory means the peak does not grow with the number of frames. Writes
benchmarks/results/memory.json (peak resident set size of the child process, from GNU time's %M).

    PYTHONPATH=src python benchmarks/bench_memory.py [--frames 200,2000] [--size 320x240]
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

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

RESULTS = REPO / "benchmarks" / "results" / "memory.json"


def write_frames_dataset(root: Path, n: int, width: int, height: int) -> Path:
    """n textured frames along a line (random textures: only the file handling is measured here)."""
    import cv2

    from scope3d.geometry.pose import Pose
    from scope3d.geometry.rotation import look_at
    from scope3d.io.dataset import write_dataset
    from scope3d.sensor.camera import Camera
    from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance

    rng = np.random.default_rng(0)
    src = root / "src"
    src.mkdir(parents=True)
    paths, poses = [], []
    tol = PoseTolerance.from_degrees([0.1] * 3, [0.1] * 3)
    for k in range(n):
        path = src / f"{k:05d}.png"
        cv2.imwrite(str(path), rng.integers(0, 255, (height, width, 3), dtype=np.uint8))
        centre = np.array([0.1 * k, 0.0, -50.0])
        poses.append(MeasuredPose(Pose.from_centre(look_at(centre, centre + [0, 0, 50.0]), centre), tol))
        paths.append(path)
    camera = Camera(width, height, 300.0, 300.0, (width - 1) / 2, (height - 1) / 2)
    return write_dataset(root / "dataset", camera, paths, poses, names=[p.name for p in paths])


def peak_mb(argv: list[str]) -> tuple[float, float]:
    """(peak resident set size in MB, wall seconds) of one child process."""
    env = dict(os.environ, PYTHONPATH=str(REPO / "src"))
    t0 = time.perf_counter()
    proc = subprocess.run(["/usr/bin/time", "-f", "%M", *argv], env=env, capture_output=True, text=True, check=True)
    return int(proc.stderr.strip().splitlines()[-1]) / 1024.0, time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", default="200,2000")
    parser.add_argument("--size", default="320x240")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    report = {"load_average_at_start": os.getloadavg(), "image_size": [width, height], "runs": []}
    with tempfile.TemporaryDirectory() as tmp:
        for n in (int(v) for v in args.frames.split(",")):
            ds = write_frames_dataset(Path(tmp) / f"n{n}", n, width, height)
            mb, wall = peak_mb([sys.executable, "-m", "scope3d.cli.main", "check", str(ds)])
            row = {"command": "check", "frames": n, "peak_rss_mb": round(mb, 1), "wall_s": round(wall, 1),
                   "frames_decoded_mb": round(n * width * height * 3 / 1e6, 1)}
            report["runs"].append(row)
            print(row, flush=True)
    report["load_average_at_end"] = os.getloadavg()
    RESULTS.write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
