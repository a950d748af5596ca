"""Long kill harness: SIGKILL ``scope3d phantom``, ``map``, ``bundle-adjust`` and ``axial`` at random moments
(uniform over a run's measured duration) and while they write their outputs, on small inputs; count what the
output location held afterwards (the previous result, the new one, or a mix) and the temporaries left.
Writes benchmarks/results/kill.json. See tests/kill_harness.py for the method.

    PYTHONPATH=src python benchmarks/bench_kill.py [--trials 50] [--while-writing 10] [--jobs map,axial]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "src"))

from kill_harness import jobs, kill_trials, make_inputs  # noqa: E402

RESULTS = REPO / "benchmarks" / "results" / "kill.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=50, help="kills at random moments per job (50)")
    parser.add_argument("--while-writing", type=int, default=10, help="kills while writing per job (10)")
    parser.add_argument("--jobs", default="phantom,map,bundle-adjust,axial")
    parser.add_argument("--results", type=Path, default=RESULTS, help="JSON to write (benchmarks/results/kill.json)")
    args = parser.parse_args()
    report = {"load_average_at_start": os.getloadavg(), "trials_random_moment": args.trials,
              "trials_while_writing": args.while_writing, "jobs": {}}
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        inputs = make_inputs(Path(tmp) / "in")
        for job in jobs(inputs, Path(tmp) / "out"):
            if job.name not in args.jobs.split(","):
                continue
            entry = {}
            if args.trials:
                entry["random_moment"] = kill_trials(job, args.trials, seed=1).to_dict()
            if args.while_writing:
                entry["while_writing"] = kill_trials(job, args.while_writing, seed=2, while_writing=True).to_dict()
            report["jobs"][job.name] = entry
            print(job.name, json.dumps({k: {kk: v[kk] for kk in ("trials", "outcomes", "litter_after_kills",
                                                                  "litter_after_final_run", "final_run_is_new_result")}
                                        for k, v in entry.items()}), flush=True)
            args.results.write_text(json.dumps(report, indent=2) + "\n")  # partial results survive a stopped run
    report["wall_time_s"] = round(time.perf_counter() - start, 1)
    report["load_average_at_end"] = os.getloadavg()
    report["mixes_total"] = sum(e[k]["outcomes"]["mix"] for e in report["jobs"].values() for k in e)
    args.results.write_text(json.dumps(report, indent=2) + "\n")
    print("mixes", report["mixes_total"])


if __name__ == "__main__":
    main()
