"""Map a rendered phantom with the Python API: render the dome, map it, compare with its ground truth.

    python examples/map_phantom.py --out runs/example_map [--size 400x400] [--frames 30]

Writes the dataset and the map (report.json, PLYs, pictures, report.html) under --out.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from scope3d import phantoms
from scope3d.io.dataset import load_dataset
from scope3d.pipelines.surgical_map import MapOptions, run
from scope3d.report import write_report


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/example_map"))
    parser.add_argument("--size", default="400x400", help="image size WxH in pixels")
    parser.add_argument("--frames", type=int, default=30, help="frames of the 5x6 grid trajectory")
    parser.add_argument("--pose-noise", type=float, default=0.25, help="reported poses off by up to ± MM")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.split("x"))

    # 1. the phantom lab: a dome with fluorescent targets, seen from a grid of robot poses
    sequence = phantoms.generate("dome", "grid5x6", size=(width, height), n_frames=args.frames, seed=0,
                                 pose_noise_mm=args.pose_noise)
    dataset = load_dataset(phantoms.write(sequence, args.out / "dataset"))
    # 2. the map: features, pose-guided matching, bounded bundle adjustment, surface, targets
    result = run(MapOptions(pose_mode="bounded"), dataset, args.out / "map")
    # 3. one page to open in a browser
    page = write_report(args.out / "map")
    print(result.summary())
    print(f"open {page}")
    return result.report


if __name__ == "__main__":
    main()
