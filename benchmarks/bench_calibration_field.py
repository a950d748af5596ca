"""Non-parametric distortion field on the real EndoSLAM capsule images (issue 14, sec. 3): does a smooth
2-D field fitted to board residuals lower the error the pinhole + k1, k2 model leaves on a fisheye lens?

Leave-one-view-out: calibrate (pinhole + k1, k2, with and without the field) on all views but one, then
find the held-out board's pose by solvePnP through that calibration (its corners corrected by the field)
and measure its RMS reprojection error. Swept: the field's knot spacing.

Writes benchmarks/results/calibration_field.json and calibration_field.png. Run:
    PYTHONPATH=src .venv/bin/python benchmarks/bench_calibration_field.py
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from scope3d.io.images import read_image
from scope3d.sensor.calibration import BoardSpec, DetectionOptions, calibrate, detect_board
from scope3d.sensor.distortion_field import DistortionFieldOptions, calibrate_with_field
from scope3d.utils.figures import new_figure, save_figure

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
REAL = ROOT.parent / "shared" / "data" / "endoslam_pillcam_cam1"
SPACINGS_PX = (16.0, 32.0, 64.0)


def held_out_sq_errors(cal, det, obj, field) -> np.ndarray:
    px = det.pixels if field is None else det.pixels - field.correction(det.pixels)
    k = cal.camera().K
    dist = cal.camera().distortion_coeffs
    _, r, t = cv2.solvePnP(obj, px, k, dist)
    _, r, t = cv2.solvePnP(obj, px, k, dist, r, t, True)
    proj = cv2.projectPoints(obj, r, t, k, dist)[0].reshape(-1, 2)
    return np.sum((proj - px) ** 2, axis=1)


def main() -> int:
    load = os.getloadavg()
    c0 = time.process_time()
    board = BoardSpec(8, 6, 2.0)
    obj = board.object_points()
    paths = sorted(p for p in REAL.iterdir() if p.suffix in (".bmp", ".png"))
    dets = [detect_board(read_image(p, grey=True), board, name=p.name, options=DetectionOptions(refine_corners=False))
            for p in paths]
    dets = [d for d in dets if d.found]
    plain = []
    fields = {s: [] for s in SPACINGS_PX}
    for hold in range(len(dets)):
        train = [d for i, d in enumerate(dets) if i != hold]
        plain.append(held_out_sq_errors(calibrate(train, board, (256, 256)), dets[hold], obj, None))
        for spacing in SPACINGS_PX:
            cal, field = calibrate_with_field(train, board, (256, 256),
                                              field_options=DistortionFieldOptions(knot_spacing_px=spacing))
            fields[spacing].append(held_out_sq_errors(cal, dets[hold], obj, field))
        print(f"held out {dets[hold].name}", flush=True)
    rms = lambda e: float(np.sqrt(np.mean(np.concatenate(e))))  # noqa: E731
    result = {"views": [d.name for d in dets], "held_out_rms_px_pinhole": rms(plain),
              "held_out_rms_px_with_field": {str(s): rms(e) for s, e in fields.items()},
              "rounds": 10, "roughness": DistortionFieldOptions().roughness,
              "machine": {"loadavg_at_start": load, "loadavg_at_end": os.getloadavg(),
                          "cpu_s": time.process_time() - c0}}
    (OUT / "calibration_field.json").write_text(json.dumps(result, indent=2) + "\n")
    fig = new_figure((5, 3.5), dpi=110)
    ax = fig.add_subplot()
    ax.plot(SPACINGS_PX, [result["held_out_rms_px_with_field"][str(s)] for s in SPACINGS_PX], "o-",
            label="pinhole k1, k2 + field")
    ax.axhline(result["held_out_rms_px_pinhole"], color="k", ls="--", label="pinhole k1, k2")
    ax.set_xlabel("knot spacing (px)")
    ax.set_ylabel("held-out RMS reprojection error (px)")
    ax.set_title("EndoSLAM capsule, leave one view out")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, OUT / "calibration_field.png")
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
