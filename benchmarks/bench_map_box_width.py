"""Does `scope3d map` keep true poses where they are when their declared box is wide? (issue 33's open gap)

For each seed: the phantom lab's raw recording (as docs/own_data.md's walkthrough, exact robot) is imported
with the true camera and hand-eye (`scope3d import frames ... --every 3`), and its frames are written with
their *true* poses declared in a box of half-width W mm and W/2 deg (the walkthrough's 0.5 mm / 0.25 deg at
W = 0.5). Each such twin is mapped ``--runs`` times, each run in a fresh process under a different OpenBLAS
kernel (``OPENBLAS_CORETYPE``: the last bits of every BLAS product differ between them), and compared with the
truth: the surface error direct and after ICP, and the adjusted poses' centre and orientation error.

    python benchmarks/bench_map_box_width.py [--widths 0.1 0.25 0.5 1 2] [--seeds 0 5 17] [--runs 2]
                                             [--results FILE]

Which scope3d is measured is whichever the interpreter imports (run it once with the old sources first on
PYTHONPATH to get the "before" figures).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results" / "map_box_width.json"
#: BLAS kernels the runs cycle through (the machine's own first): same arithmetic, different last bits
CORETYPES = ("", "Haswell", "Sandybridge", "Prescott")


def prepare(root: Path, seed: int, size: int, sync_error_s: float = 0.0) -> Path:
    """The recording's scan imported with the true camera and hand-eye: frames, and the truth beside them
    (``sync_error_s``: the frame times that far off on the robot's clock)."""
    from scope3d.cli.main import main as scope3d
    from scope3d.phantoms.recording import RecordingOptions, write_recording

    write_recording(RecordingOptions(size=(size, size), speed_mm_s=50.0, robot_error_mm=0.0, seed=seed,
                                     sync_error_s=sync_error_s), root / "rec")
    rec = root / "rec"
    if scope3d(["import", "frames", str(rec / "scan" / "video.mkv"), "--camera", str(rec / "truth" / "camera.json"),
                "--poses", str(rec / "scan" / "robot_log.csv"), "--pose-format", "xyz-qxyzw", "--unit", "m",
                "--frame-times", str(rec / "scan" / "frame_times.csv"), "--hand-eye", str(rec / "truth" / "hand_eye.json"),
                "--tolerance", "0.5", "--tolerance-deg", "0.25", "--every", "3", "--out", str(root / "scan"),
                "--quiet"]) != 0:
        raise SystemExit(f"import of seed {seed} failed")
    return root / "scan"


def twin(root: Path, scan: Path, width_mm: float) -> Path:
    """The scan's frames with their true poses, declared in a box of ``width_mm`` and ``width_mm / 2`` deg."""
    from scope3d.io.dataset import load_dataset, write_dataset
    from scope3d.io.ply import read_ply
    from scope3d.io.poses_csv import read_poses_csv
    from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance

    ds = load_dataset(scan)
    rec = root / "rec" / "truth"
    names, truth = read_poses_csv(rec / "poses.csv")
    true = [dict(zip(names, truth))[n].pose for n in ds.names]
    box = PoseTolerance.from_degrees(np.full(3, width_mm), np.full(3, width_mm / 2))
    out = root / f"twin_{width_mm:g}"
    write_dataset(out, ds.camera, [scan / "frames" / n for n in ds.names], [MeasuredPose(p, box) for p in true],
                  names=ds.names, true_poses=true, true_surface=read_ply(rec / "surface.ply"),
                  scene=json.loads((rec / "scene.json").read_text()))
    return out


def map_once(dataset: Path, out: Path, coretype: str) -> dict:
    """``scope3d map`` in a fresh process under the BLAS kernel ``coretype`` ("" = the machine's own)."""
    env = dict(os.environ)
    if coretype:
        env["OPENBLAS_CORETYPE"] = coretype
    code = "import sys; from scope3d.cli.main import main; sys.exit(main(sys.argv[1:]))"
    started = time.perf_counter()
    subprocess.run([sys.executable, "-c", code, "map", str(dataset), "--out", str(out), "--no-figures", "--quiet"],
                   env=env, check=True)
    report = json.loads((out / "report.json").read_text())
    s, p = report["surface_error_mm"], report["pose_error"]
    return {"blas_coretype": coretype or "native", "direct_mean_mm": s["direct"]["mean"],
            "after_icp_mean_mm": s["after_icp"]["mean"], "pose_centre_mean_mm": p["position_mm_mean"],
            "pose_centre_max_mm": p["position_mm_max"], "pose_orientation_mean_deg": p["orientation_deg_mean"],
            "wall_s": round(time.perf_counter() - started, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--widths", type=float, nargs="+", default=[0.1, 0.25, 0.5, 1.0, 2.0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 5, 17])
    parser.add_argument("--runs", type=int, default=2, help="maps per case, each under another BLAS kernel")
    parser.add_argument("--size", type=int, default=304)
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    import scope3d

    rows = []
    for seed in args.seeds:
        with tempfile.TemporaryDirectory(prefix="bench-box-width-") as tmp:
            root = Path(tmp)
            scan = prepare(root, seed, args.size)
            for width in args.widths:
                dataset = twin(root, scan, width)
                runs = [map_once(dataset, root / f"map_{width:g}_{k}", CORETYPES[k % len(CORETYPES)])
                        for k in range(args.runs)]
                direct = [r["direct_mean_mm"] for r in runs]
                rows.append({"seed": seed, "box_mm": width, "box_deg": width / 2, "runs": runs,
                             "direct_spread_mm": float(np.ptp(direct))})
                print(json.dumps(rows[-1]), flush=True)
    args.results.resolve().write_text(json.dumps({
        "scope3d": str(Path(scope3d.__file__).parent), "machine": platform.platform(), "cpus": os.cpu_count(),
        "load_average": os.getloadavg(), "size_px": args.size, "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
