"""Long fuzzing run of every file reader: hypothesis mutations of valid files, then atheris (coverage-guided,
libFuzzer) from the same seeds. Writes benchmarks/results/fuzz.json: inputs tried per reader and engine,
the outcomes (parsed / refused), and every crash (an outcome other than a parse or one InputError line
naming the file), with the input that caused it.

    PYTHONPATH=src python benchmarks/bench_fuzz.py [--seconds-per-reader 60] [--engines hypothesis,random,atheris]
    # a million inputs per reader and engine, however long that takes (CPU time is recorded per reader):
    PYTHONPATH=src nice -n 19 python benchmarks/bench_fuzz.py --engines random,atheris --inputs-per-reader 1000000

atheris runs in a child process per reader (libFuzzer owns its process and exits on the first crash); the
others run in this process, one input after another, with no process or temporary file per input.

Every input is written to a file before its reader reads it (the readers take paths, as users give them),
so the files live in memory (``--work-dir``, default /dev/shm where it exists): on this machine's loaded
disk a write took 3-12 ms, more than most reads (0.1-7 ms), and on tmpfs 0.05-0.6 ms.
"""
from __future__ import annotations

import argparse
import base64
import importlib.util
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "src"))

from fuzz_targets import MUTATIONS, FuzzCrash, build_targets, mutate  # noqa: E402

RESULTS = REPO / "benchmarks" / "results" / "fuzz.json"
# a crash's input is kept whole up to this size (the first 4 kB were kept before: a 10.8 kB ROS 1 bag's
# crash could then only be found again by replaying the seeded run)
MAX_RECORDED_INPUT = 1 << 20


def run_hypothesis(target, seconds: float, max_inputs: int | None = None) -> dict:
    """Random mutation chains (1-4 mutations) for ``seconds``; hypothesis draws them and shrinks crashes."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st
    from hypothesis.errors import HypothesisException

    counts = {"ok": 0, "refused": 0}
    crashes = []
    deadline = time.monotonic() + seconds
    chains = st.lists(st.tuples(st.sampled_from(MUTATIONS), st.floats(0, 1, exclude_max=True),
                                st.floats(0, 1, exclude_max=True), st.integers(0, 999)), min_size=1, max_size=4)

    class Done(Exception):
        pass

    @settings(max_examples=10**9, deadline=None, database=None, derandomize=False,
              suppress_health_check=list(HealthCheck))
    @given(chains)
    def check(mutations):
        if time.monotonic() > deadline or (max_inputs and sum(counts.values()) + len(crashes) >= max_inputs):
            raise Done
        data = target.seed
        for kind, a, b, pick in mutations:
            data = mutate(data, kind, a, b, pick)
        try:
            counts[target.run(data)] += 1
        except FuzzCrash as exc:
            kept = base64.b64encode(data[:MAX_RECORDED_INPUT]).decode()
            crashes.append({"error": str(exc)[:300], "input_b64": kept})

    try:
        check()
    except (Done, HypothesisException):
        pass
    except Exception as exc:  # hypothesis re-raises the first failure after shrinking
        if not isinstance(exc, Done):
            crashes.append({"error": f"{type(exc).__name__}: {exc}"[:300]})
    target.restore()
    return {"inputs": counts["ok"] + counts["refused"] + len(crashes), "parsed": counts["ok"],
            "refused": counts["refused"], "crashes": crashes}


def run_random(target, seconds: float, seed: int = 0, max_inputs: int | None = None) -> dict:
    """The same mutation chains (1-4 of ``MUTATIONS``) drawn by a seeded ``random.Random`` for ``seconds``:
    no shrinking and no example database, so ~10x the inputs of hypothesis's engine, whose bookkeeping
    took 12-20 ms of CPU per input here (the reads themselves 0.1-7 ms); a crash keeps its input."""
    import random

    rng = random.Random(seed)
    counts = {"ok": 0, "refused": 0}
    crashes = []
    deadline = time.monotonic() + seconds
    tried = 0
    while time.monotonic() < deadline and (max_inputs is None or tried < max_inputs):
        tried += 1
        data = target.seed
        for _ in range(rng.randint(1, 4)):
            data = mutate(data, rng.choice(MUTATIONS), rng.random(), rng.random(), rng.randint(0, 999))
        try:
            counts[target.run(data)] += 1
        except FuzzCrash as exc:
            kept = base64.b64encode(data[:MAX_RECORDED_INPUT]).decode()
            crashes.append({"error": str(exc)[:300], "input_b64": kept})
    target.restore()
    return {"inputs": counts["ok"] + counts["refused"] + len(crashes), "parsed": counts["ok"],
            "refused": counts["refused"], "crashes": crashes}


def profile_inputs(target, seconds: float, seed: int = 0) -> dict:
    """Where one input's CPU time goes, in this process: drawing its mutation chain (as ``run_random``),
    writing the file (to the work folder: /dev/shm by default), and the reader. Milliseconds of CPU per
    input, averaged over the inputs of ``seconds`` of wall time."""
    import random

    rng = random.Random(seed)
    spent = {"mutate": 0.0, "write": 0.0, "read": 0.0}
    n = 0
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        start = time.process_time()
        data = target.seed
        for _ in range(rng.randint(1, 4)):
            data = mutate(data, rng.choice(MUTATIONS), rng.random(), rng.random(), rng.randint(0, 999))
        written = time.process_time()
        target.path.write_bytes(data)
        read = time.process_time()
        try:
            target.call()
        except Exception:  # the outcome is the other engines' business; here only its cost
            pass
        done = time.process_time()
        spent["mutate"] += written - start
        spent["write"] += read - written
        spent["read"] += done - read
        n += 1
    target.restore()
    total = sum(spent.values())
    return {"inputs": n, "seed_bytes": len(target.seed),
            **{f"{part}_cpu_ms": round(1e3 * value / max(n, 1), 3) for part, value in spent.items()},
            "inputs_per_cpu_s": round(n / max(total, 1e-9), 1)}


_ATHERIS_CHILD = r"""
import sys, json, tempfile
from pathlib import Path
sys.path[:0] = [{src!r}, {tests!r}]
import atheris
with atheris.instrument_imports(include=["scope3d"]):
    import scope3d.io, scope3d.io.dataset, scope3d.io.ply, scope3d.io.images, scope3d.io.bal
    import scope3d.estimators.bundle
    import scope3d.io.tracker, scope3d.io.rosbag, scope3d.io.video, scope3d.io.scan_plan, scope3d.io.quadrants
    import scope3d.io.intrinsic_bounds, scope3d.io.map_points, scope3d.io.json_object, scope3d.report
    import scope3d.pipelines.hand_eye
from fuzz_targets import build_targets, FuzzCrash
target = build_targets(Path(tempfile.mkdtemp(dir={work!r})))[{name!r}]
counts = {{"ok": 0, "refused": 0}}
def one(data):
    counts[target.run(bytes(data))] += 1
    if sum(counts.values()) % 200 == 1:  # libFuzzer may exit without running atexit handlers
        Path({progress!r}).write_text(json.dumps(counts))
atheris.Setup([sys.argv[0], "-max_total_time={seconds}", {runs} "-rss_limit_mb=2048", "-timeout=20",
               "-max_len=65536", "-print_final_stats=1", "-artifact_prefix={artifacts}/", {corpus!r}], one)
atheris.Fuzz()
"""


def run_atheris(name: str, seed: bytes, seconds: float, work: Path, max_inputs: int | None = None) -> dict:
    """libFuzzer from the seed file; a crash ends the child (its message and input are recorded). The
    child's CPU time (its instrumented imports included) is recorded as ``cpu_s``."""
    children_cpu = _children_cpu_s()
    result = _run_atheris(name, seed, seconds, work, max_inputs)
    result["cpu_s"] = round(_children_cpu_s() - children_cpu, 1)
    return result


def _children_cpu_s() -> float:
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _run_atheris(name: str, seed: bytes, seconds: float, work: Path, max_inputs: int | None) -> dict:
    corpus = work / f"corpus_{name.replace(' ', '_')}"
    corpus.mkdir(parents=True, exist_ok=True)
    (corpus / "seed").write_bytes(seed)
    progress = work / f"progress_{name.replace(' ', '_')}.json"
    artifacts = work / f"artifacts_{name.replace(' ', '_')}"  # one folder per reader: a crash file is its own
    artifacts.mkdir(parents=True, exist_ok=True)
    script = _ATHERIS_CHILD.format(src=str(REPO / "src"), tests=str(REPO / "tests"), name=name,
                                   progress=str(progress), seconds=int(seconds) if math.isfinite(seconds) else 0, corpus=str(corpus), work=str(work),
                                   artifacts=str(artifacts), runs=f'"-runs={max_inputs}",' if max_inputs else "")
    try:
        proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=work,
                              timeout=seconds + 300 if math.isfinite(seconds) else None)
    except subprocess.TimeoutExpired as exc:
        # the child outlived its time by 300 s. libFuzzer stops an input after -timeout=20 s of wall time and
        # writes it as timeout-*: with such a file it is a hang (a crash); without, the child was starved of
        # CPU (at nice 19 on a loaded machine its instrumented imports alone took minutes), which is recorded
        # as unfinished, not as a crash
        stderr = exc.stderr.decode(errors="replace") if isinstance(exc.stderr, bytes) else (exc.stderr or "")
        counts = json.loads(progress.read_text()) if progress.is_file() else {"ok": 0, "refused": 0}
        hangs = sorted(artifacts.glob("timeout-*")) + sorted(artifacts.glob("crash-*")) + sorted(artifacts.glob("oom-*"))
        kept = base64.b64encode(hangs[-1].read_bytes()[:MAX_RECORDED_INPUT]).decode() if hangs else None
        return {"inputs": counts["ok"] + counts["refused"], "parsed": counts["ok"], "refused": counts["refused"],
                "crashes": [{"error": f"{hangs[-1].name}: {stderr[-400:]}", "input_b64": kept}] if hangs else [],
                "unfinished": f"the child ran {seconds + 300:.0f} s wall, past -max_total_time={seconds:.0f}, "
                              f"without a timeout or crash file (starved of CPU)",
                "corpus_files": len(list(corpus.iterdir()))}
    stats = {}
    for line in proc.stderr.splitlines():
        if line.startswith("stat::number_of_executed_units:"):
            stats["inputs"] = int(line.split(":")[-1])
    counts = json.loads(progress.read_text()) if progress.is_file() else {"ok": 0, "refused": 0}
    crashes = []
    if proc.returncode != 0:  # a negative code is the signal that ended the child (-9: killed from outside)
        stats["returncode"] = proc.returncode
        # atheris prints an uncaught Python exception on stdout, libFuzzer its own reports on stderr
        tail = [line for line in (proc.stdout + proc.stderr).splitlines()
                if "FuzzCrash" in line or "Error" in line or "ERROR" in line][-3:]
        crash_files = sorted(p for pattern in ("crash-*", "oom-*", "timeout-*") for p in artifacts.glob(pattern))
        crashes.append({"error": " | ".join(tail)[:500] or proc.stderr[-500:],
                        "input_b64": base64.b64encode(crash_files[-1].read_bytes()[:MAX_RECORDED_INPUT]).decode()
                        if crash_files else None})
    return {**({"returncode": stats["returncode"]} if "returncode" in stats else {}),
            "inputs": stats.get("inputs", counts["ok"] + counts["refused"]), "parsed": counts["ok"],
            "refused": counts["refused"], "crashes": crashes, "corpus_files": len(list(corpus.iterdir()))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds-per-reader", type=float, default=None,
                        help="wall time per reader and engine (default 60, or no limit with --inputs-per-reader)")
    parser.add_argument("--engines", default="hypothesis,atheris", help="any of hypothesis, random, atheris")
    parser.add_argument("--readers", default="", help="comma-separated target names (default: all)")
    parser.add_argument("--seed", type=int, default=0, help="the random engine's seed (another seed, other chains)")
    parser.add_argument("--inputs-per-reader", type=int, default=None,
                        help="stop each engine on a reader after this many inputs (with no --seconds-per-reader: "
                             "however long that takes)")
    parser.add_argument("--results", type=Path, default=RESULTS, help="JSON to write (benchmarks/results/fuzz.json)")
    parser.add_argument("--work-dir", default="/dev/shm" if Path("/dev/shm").is_dir() else None,
                        help="where the mutated files are written (default: /dev/shm, memory, where it exists)")
    parser.add_argument("--profile", action="store_true",
                        help="instead of fuzzing: the CPU cost of an input's mutation, file write and read per reader")
    args = parser.parse_args()
    if args.profile:
        _profile(args)
        return
    if args.seconds_per_reader is None:
        args.seconds_per_reader = 60.0 if args.inputs_per_reader is None else math.inf
    engines = args.engines.split(",")
    with tempfile.TemporaryDirectory(dir=args.work_dir) as tmp:
        work = Path(tmp)
        targets = build_targets(work / "targets")
        names = [n for n in targets if not args.readers or n in args.readers.split(",")]
        report = {
            "what": "mutated copies of a valid file per reader; acceptable outcomes: a parse, or one InputError "
                    "line naming the file. A crash is anything else.",
            "seconds_per_reader_and_engine": args.seconds_per_reader,
            "inputs_per_reader_and_engine": args.inputs_per_reader,
            "load_average_at_start": os.getloadavg(),
            "python": sys.version.split()[0],
            "random_seed": args.seed,
            "work_dir": str(work),
            "readers": {},
        }
        for name in names:
            entry = {}
            if "hypothesis" in engines:
                start = time.process_time()
                wall = time.monotonic()
                entry["hypothesis"] = run_hypothesis(targets[name], args.seconds_per_reader, args.inputs_per_reader)
                _rates(entry["hypothesis"], time.monotonic() - wall, time.process_time() - start)
            if "random" in engines:
                start = time.process_time()
                wall = time.monotonic()
                entry["random"] = run_random(targets[name], args.seconds_per_reader, seed=args.seed,
                                             max_inputs=args.inputs_per_reader)
                _rates(entry["random"], time.monotonic() - wall, time.process_time() - start)
            if "atheris" in engines:
                if importlib.util.find_spec("atheris") is None:
                    entry["atheris"] = {"skipped": "atheris is not installed"}
                else:
                    wall = time.monotonic()
                    entry["atheris"] = run_atheris(name, targets[name].seed, args.seconds_per_reader, work,
                                                   args.inputs_per_reader)
                    _rates(entry["atheris"], time.monotonic() - wall, entry["atheris"]["cpu_s"])
            report["readers"][name] = entry
            print(name, {k: {kk: (len(vv) if kk == "crashes" else vv) for kk, vv in v.items()}
                         for k, v in entry.items()}, flush=True)
            _write(report, engines, args.results)  # after every reader: a stopped run keeps what it did
    print("totals", report["totals"])


def _profile(args) -> None:
    seconds = args.seconds_per_reader or 2.0
    with tempfile.TemporaryDirectory(dir=args.work_dir) as tmp:
        targets = build_targets(Path(tmp) / "targets")
        names = [n for n in targets if not args.readers or n in args.readers.split(",")]
        report = {"what": "CPU milliseconds per input: mutation chain, file write, read (profile_inputs)",
                  "seconds_per_reader": seconds, "work_dir": str(tmp), "load_average_at_start": os.getloadavg(),
                  "readers": {}}
        for name in names:
            report["readers"][name] = profile_inputs(targets[name], seconds, seed=args.seed)
            print(name, report["readers"][name], flush=True)
        report["load_average_at_end"] = os.getloadavg()
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(report, indent=2) + "\n")


def _rates(result: dict, wall_s: float, cpu_s: float) -> None:
    """Wall and CPU time of one engine on one reader, and inputs per second of each: on a shared machine a
    niced run gets what CPU is idle, so the CPU rate is the one that carries over."""
    result["wall_s"] = round(wall_s, 1)
    result["cpu_s"] = round(cpu_s, 1)
    result["inputs_per_s"] = round(result["inputs"] / max(wall_s, 1e-9), 1)
    result["inputs_per_cpu_s"] = round(result["inputs"] / max(cpu_s, 1e-9), 1)


def _write(report: dict, engines: list[str], path: Path) -> None:
    readers = report["readers"].values()
    report["totals"] = {e: {"inputs": sum(r[e].get("inputs", 0) for r in readers if e in r),
                            "crashes": sum(len(r[e].get("crashes", [])) for r in readers if e in r),
                            "cpu_s": round(sum(r[e].get("cpu_s", 0) for r in readers if e in r), 1)}
                        for e in engines}
    report["load_average_at_end"] = os.getloadavg()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
