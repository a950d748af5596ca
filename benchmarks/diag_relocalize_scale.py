"""What SIFT's resolution costs and gives in a 1 Mpx relocalization (issue 34: <= 0.3 s at 1 Mpx).

The split of ``bench_localize_speed.py`` (Strecha fountain-P11 at ``SCALE`` 0.4, 1229 x 819; the map of the
even views must exist: run that benchmark first with the same ``WORK``). Each odd view relocalized with the
localizer's own pieces, SIFT on the frame resized by 1, 0.75 and 0.5 (keypoints scaled back, as the
``refresh_image_scale`` refresh does), then the global match and the pose: process CPU time of each part,
errors against the calibrated pose. Nothing in the localizer uses a scale below 1 for relocalization; this
measures whether it should.

Writes benchmarks/results/diag_relocalize_scale.json. Run:
    WORK=/tmp/n34work .venv/bin/python benchmarks/diag_relocalize_scale.py
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from scope3d.io.map_points import read_map_points
from scope3d.sfm.localization import Localizer, LocalizerOptions

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_localize_real import strecha  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


def main() -> None:
    work = Path(os.environ["WORK"])
    scale = float(os.environ.get("SCALE", "0.4"))
    ds = strecha(work, "strecha_fountain_p11", scale)
    points = read_map_points(work / f"strecha_fountain_p11_x{scale:g}_speed_map")
    loc = Localizer(points, ds.camera, LocalizerOptions(tracking=False))
    odd = list(range(1, len(ds), 2))
    loc.localize(ds.frame(odd[0]))  # warm-up
    out = {"camera": f"{ds.camera.width}x{ds.camera.height}", "load_average_at_start": os.getloadavg()[0], "runs": {}}
    for sift_scale in (1.0, 0.75, 0.5):
        rows = []
        for i in odd:
            grey = cv2.cvtColor(ds.frame(i), cv2.COLOR_RGB2GRAY)
            c0 = time.process_time()
            kp, desc = loc._features(grey, loc._usable(None), sift_scale)
            c1 = time.process_time()
            ids, feat = loc._match_global(desc)
            r, _, _ = loc._pose(ids, kp[feat], None)
            c2 = time.process_time()
            row = {"view": ds.names[i], "sift_cpu_s": c1 - c0, "match_and_pose_cpu_s": c2 - c1, "keypoints": len(kp),
                   "status": r.status, "inliers": int(r.n_inliers)}
            if r.ok:
                d_mm, d_rad = r.pose.distance_to(ds.poses[i].pose)
                row.update(position_error_mm=d_mm, orientation_error_deg=float(np.rad2deg(d_rad)))
            rows.append(row)
        ok = [r for r in rows if r["status"] == "ok"]
        out["runs"][f"{sift_scale:g}"] = {
            "median_cpu_s": float(np.median([r["sift_cpu_s"] + r["match_and_pose_cpu_s"] for r in rows])),
            "median_sift_cpu_s": float(np.median([r["sift_cpu_s"] for r in rows])),
            "localized": f"{len(ok)}/{len(rows)}",
            "median_position_error_mm": float(np.median([r["position_error_mm"] for r in ok])),
            "median_orientation_error_deg": float(np.median([r["orientation_error_deg"] for r in ok])),
            "views": rows}
    out["load_average_at_end"] = os.getloadavg()[0]
    (OUT / "diag_relocalize_scale.json").write_text(json.dumps(out, indent=1, default=float))
    print(json.dumps({k: {a: b for a, b in v.items() if a != "views"} for k, v in out["runs"].items()}, indent=1))


if __name__ == "__main__":
    main()
