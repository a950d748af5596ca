"""Which frames does the pose check's screen send to the exact test for losing observations to the map's
gate? (scope3d.sfm.gate_loss.lost_to_the_gate, issue 16 section 5)

For each case (survey, seed, glitch; the same phantoms and glitches as bench_pose_check_rate.py) the map's
stages run up to the bounded adjustment, then the screen (one bounded adjustment of every matched
observation); recorded per frame: its matched observations and those the gate dropped, and whether the
gate-loss test sent it on, with the beta-binomial test (the check's) and with the binomial at the median
lost fraction it replaced. A clean frame sent on costs one exact leave-one-out (a bounded adjustment of
the whole map); a glitched frame not sent on is left to the screen's own statistic, which misses most
(docs/reliability.md section 5). The test's level is the check's per-frame one, the false-alarm rate
(0.01).

    PYTHONPATH=src python benchmarks/bench_pose_gate_loss.py --cases dome12:21:0,dome30:21:0,dome12:21:3

Results: results/pose_gate_loss.json (per case and frame, and a summary: clean frames sent on by either
test, glitched frames sent on). ``--cache DIR`` keeps each case's bounded map (pickles) to run again
without the stages.
"""
from __future__ import annotations

import argparse
import json
import os
import pickle
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_pose_check_rate import glitched_dataset  # noqa: E402

from scope3d.feature.tracks import build_tracks  # noqa: E402
from scope3d.pipelines import surgical_map as sm  # noqa: E402
from scope3d.sfm.gate_loss import lost_to_the_gate  # noqa: E402
from scope3d.sfm.leave_one_out import linearise, screen_reported_poses  # noqa: E402
from scope3d.sfm.pose_checks import PoseCheckOptions  # noqa: E402
from scope3d.utils.jsonio import write_json  # noqa: E402


def bounded_map(case: str, tmp: Path, cache: Path | None) -> dict:
    """The case's bounded map and every matched observation (the check's inputs), from ``cache`` if there."""
    path = cache / f"{case.replace(':', '_')}.pkl" if cache else None
    if path is not None and path.is_file():
        return pickle.loads(path.read_bytes())
    survey, seed, size = case.split(":")
    size, frame = size.split("@") if "@" in size else (size, None)
    shift, turn = (0.0, float(size[:-3])) if size.endswith("deg") else (float(size), 0.0)
    dataset, glitched = glitched_dataset(survey, int(seed), shift, tmp, turn, None if frame is None else int(frame))
    options = replace(sm.MapOptions(), figures=False, fluorescence=None)
    frames = [dataset.frame(k) for k in range(len(dataset))]
    features = sm.detect_features(options, dataset, frames)
    matching = sm.match_frames(options, dataset, features)
    sparse = sm.reconstruct(options, dataset, features, matching)
    tracks = build_tracks(features, matching.matches, min_track_length=options.tracks.min_track_length)
    out = dict(case=case, camera=sparse.camera, measured=dataset.poses, tracks=tracks, poses=sparse.poses,
               track_options=options.tracks, glitched=glitched)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(out))
    return out


def median_binomial(screened: dict, level: float) -> set[int]:
    """The gate-loss test the beta-binomial replaced: binomial at the median of the frames' lost fractions."""
    from scipy.stats import binom

    rows = [(k, t.observations, t.observations - t.inliers) for k, t in screened.items() if t.status != "unseen"]
    rate = float(np.median([lost / total for _, total, lost in rows]))
    return {k for k, total, lost in rows if lost > 0 and binom.sf(lost - 1, total, rate) < level}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", required=True, help="comma-separated survey:seed:shift_mm or survey:seed:Gdeg[@frame]")
    ap.add_argument("--cache", default="", help="a folder keeping each case's bounded map")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "pose_gate_loss.json"))
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="pose_gate_loss_"))
    options = PoseCheckOptions()
    level = options.false_alarm_rate
    runs = []
    for case in args.cases.split(","):
        d = bounded_map(case, tmp, Path(args.cache) if args.cache else None)
        testable = [k for k in range(len(d["measured"])) if not d["measured"][k].tolerance.is_exact]
        model = linearise(d["camera"], d["measured"], d["tracks"], d["poses"], d["track_options"],
                          options.leave_one_out)
        screened = screen_reported_poses(model, d["measured"], testable, d["tracks"], options.leave_one_out)
        t0 = time.process_time()
        sent = lost_to_the_gate(screened, level)
        cpu = time.process_time() - t0
        before = median_binomial(screened, level)
        runs.append({"case": case, "glitched": d["glitched"], "sent_on": sorted(sent),
                     "sent_on_by_the_binomial": sorted(before), "gate_test_cpu_s": round(cpu, 3),
                     "frames": [{"frame": k, "observations": t.observations, "lost": t.observations - t.inliers}
                                for k, t in screened.items() if t.status != "unseen"]})
        print(json.dumps({k: v for k, v in runs[-1].items() if k != "frames"}), flush=True)
    summary = {}
    for survey in sorted({r["case"].split(":")[0] for r in runs}):
        rows = [r for r in runs if r["case"].startswith(survey + ":")]
        clean = [r for r in rows if not r["glitched"]]
        glitched = [r for r in rows if r["glitched"]]
        summary[survey] = {
            "clean_maps": len(clean), "clean_frames": sum(len(r["frames"]) for r in clean),
            "clean_frames_sent_on": sum(len(r["sent_on"]) for r in clean),
            "clean_frames_sent_on_by_the_binomial": sum(len(r["sent_on_by_the_binomial"]) for r in clean),
            "glitched_maps": len(glitched),
            "glitched_frames_sent_on": sum(bool(set(r["glitched"]) & set(r["sent_on"])) for r in glitched),
            "glitched_frames_sent_on_by_the_binomial": sum(bool(set(r["glitched"]) & set(r["sent_on_by_the_binomial"]))
                                                           for r in glitched)}
    write_json(Path(args.out), {"level": level, "load_average": list(os.getloadavg()), "summary": summary,
                                "runs": runs})
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
