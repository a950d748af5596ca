"""Dense axial stereo of a threaded hole with the Python API: a borescope moving along its viewing
direction, two frames (semi-global matching on the log-polar grid), against the thread's ground truth.

    python examples/axial_stereo.py --out runs/example_axial [--size 256] [--frames 6]
"""
from __future__ import annotations

import argparse
from pathlib import Path

from scope3d import phantoms
from scope3d.io.dataset import load_dataset
from scope3d.pipelines.axial import AxialOptions, run
from scope3d.report import write_report


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/example_axial"))
    parser.add_argument("--size", type=int, default=256, help="square image size in pixels")
    parser.add_argument("--frames", type=int, default=6)
    args = parser.parse_args(argv)

    sequence = phantoms.generate("thread", "axial", size=(args.size, args.size), n_frames=args.frames, seed=0)
    dataset = load_dataset(phantoms.write(sequence, args.out / "dataset"))
    middle = args.frames // 2
    result = run(AxialOptions(method="sgm", frames=(middle - 1, middle)), dataset, args.out / "axial")
    page = write_report(args.out / "axial")
    print(result.summary())
    print(f"open {page}")
    return result.report


if __name__ == "__main__":
    main()
