"""SIGKILL the scope3d jobs at random moments and check what they leave behind. Shared by
``tests/test_kill_and_interrupt.py`` (a few trials per job) and ``benchmarks/bench_kill.py`` (>= 50).

For one job: run it to completion once (the new result, and how long a run takes), then for each trial
put a *previous* complete result in the output location, start the job, SIGKILL its process group at a
random moment within the run's duration, and classify the output location:

* ``previous``: exactly the previous result (the kill came before the job put anything in place);
* ``new``: exactly the new result, file for file and byte for byte (report.json compared without its
  timing fields, :func:`scope3d.utils.jsonio.without_timings`);
* ``mix``: anything else: a failure.

A kill lands when the job dies of it. One that does not (the job ended first: a fast run, or a machine so
loaded or so idle that the moment came late) tests nothing and is not a trial: it is tried again at an
earlier moment, up to :data:`ATTEMPTS` times, and a trial whose kills never landed is counted in
``trials_not_killed`` (a failure for the tests), never as an outcome.

Temporaries a killed job leaves beside (or, for files, inside) the output location are counted as
litter; a final uninterrupted run must succeed, give the new result again, and remove every stale one.
"""
from __future__ import annotations

import hashlib
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
_TEMPORARY = re.compile(r"^\..+\.\d+\.[^.]+\.(tmp|old)(\.[^.]*)?$")


def scope3d(*args: str) -> list[str]:
    return [sys.executable, "-m", "scope3d.cli.main", *args]


def environment(threads: int | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "NUMBA_NUM", "OMP_"))}
    env["PYTHONPATH"] = str(REPO / "src")
    if threads is not None:
        env["NUMBA_NUM_THREADS"] = env["OMP_NUM_THREADS"] = env["OPENBLAS_NUM_THREADS"] = str(threads)
    return env


@dataclass
class Job:
    """A command writing one output location (a folder, or for bundle-adjust a folder of named files)."""

    name: str
    argv: list[str]
    out: Path  # the output location the command writes
    files_in_folder: bool = False  # bundle-adjust: separate files inside ``out``, not one folder


def snapshot(out: Path) -> dict[str, str]:
    """relative path -> SHA-256 of every file under ``out`` (report.json without its timings); temporaries
    are left out (they are litter, counted by :func:`litter`)."""
    from scope3d.utils.jsonio import without_timings

    if not out.exists():
        return {}
    result = {}
    for path in sorted(out.rglob("*")):
        if not path.is_file() or _TEMPORARY.match(path.name):
            continue
        data = path.read_bytes()
        if path.name == "report.html":  # its timings section is the only part allowed to differ
            data = re.sub(rb'<section id="timings">.*?</section>', b"", data, flags=re.S)
        if path.name == "report.json":
            try:
                data = json.dumps(without_timings(json.loads(data)), sort_keys=True).encode()
            except ValueError:
                pass  # a torn report stays as it is, and differs from every complete one
        result[str(path.relative_to(out))] = hashlib.sha256(data).hexdigest()
    return result


def litter(job: Job) -> list[Path]:
    """Temporaries beside the output location and directly inside it (where a job writing files one by
    one into the folder would put them)."""
    found = [p for p in job.out.parent.iterdir() if _TEMPORARY.match(p.name) and p.name.startswith(f".{job.out.name}.")]
    if job.out.is_dir():
        found += [p for p in job.out.iterdir() if _TEMPORARY.match(p.name)]
    return found


def put_previous(job: Job) -> dict[str, str]:
    """Replace the output location with a small complete 'previous result' and return its snapshot."""
    if job.out.is_dir():
        shutil.rmtree(job.out)
    job.out.mkdir(parents=True)
    (job.out / "report.json").write_text(json.dumps({"previous": True}))
    if job.files_in_folder:  # the same names the job writes, holding the previous run's content
        for name in ("solved.txt", "curve.png"):
            (job.out / name).write_text(f"previous {name}\n")
    else:
        (job.out / "previous.txt").write_text("the previous complete result\n")
    return snapshot(job.out)


def run_to_completion(job: Job, env: dict, timeout: float = 900) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(job.argv, env=env, capture_output=True, text=True, timeout=timeout, cwd=REPO)
    if proc.returncode != 0:
        raise RuntimeError(f"{job.name} failed ({proc.returncode}): {proc.stderr[-800:]}")
    return time.perf_counter() - t0


ATTEMPTS = 5  # kills per trial at ever earlier moments before the trial counts as not killed


@dataclass
class KillReport:
    job: str
    run_time_s: float
    trials: int = 0
    outcomes: dict = field(default_factory=lambda: {"previous": 0, "new": 0, "mix": 0})
    kills_missed: int = 0  # kills that came after the job had ended, each retried earlier (not outcomes)
    trials_not_killed: int = 0  # trials none of whose ATTEMPTS kills landed (not outcomes)
    mixes: list = field(default_factory=list)
    litter_after_kills: int = 0  # temporaries found right after a kill (the next run removes them)
    litter_after_final_run: int = -1
    final_run_is_new_result: bool | None = None
    kill_times_s: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def _kill_at_random_moment(job: Job, env: dict, delay: float) -> tuple[float, bool]:
    """Kill ``delay`` s after the start; (delay, whether the kill landed)."""
    proc = subprocess.Popen(job.argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO,
                            start_new_session=True)
    try:
        proc.wait(timeout=delay)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    return delay, proc.returncode == -signal.SIGKILL


def _kill_while_writing(job: Job, env: dict, rng: random.Random, latest: float) -> tuple[float, bool]:
    """Kill within ``latest`` s of the moment the job's first temporary output appears (it is writing);
    (seconds from the start to the kill, whether the kill landed)."""
    before = set(litter(job))
    t0 = time.perf_counter()
    proc = subprocess.Popen(job.argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO,
                            start_new_session=True)
    while proc.poll() is None and not (set(litter(job)) - before):
        time.sleep(0.001)
    if proc.poll() is None:
        time.sleep(rng.uniform(0.0, latest))
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    return time.perf_counter() - t0, proc.returncode == -signal.SIGKILL


def kill_trials(job: Job, trials: int, *, seed: int = 0, env: dict | None = None,
                while_writing: bool = False) -> KillReport:
    """Kill ``trials`` runs of the job, then run it once uninterrupted; see the module docstring.

    while_writing : kill within 0.3 s of the job starting to write its outputs (the moment a kill can
    tear a result), instead of at a moment uniform over a run's duration (measured by a first
    uninterrupted run).
    """
    env = env or environment()
    rng = random.Random(seed)
    duration = first = None
    if not while_writing:
        put_previous(job)
        duration = run_to_completion(job, env)
        first = snapshot(job.out)
    states = []
    kill_times = []
    missed = not_killed = 0
    for _ in range(trials):
        # while writing: within 0.3 s of the first temporary, then 0.1, 0.03, 0.01 s, then at once; at a
        # random moment: from the start (imports, reading) to past the usual end (a run can be slower under
        # load), then uniform before the moment that came too late
        latest = 0.3 if while_writing else 1.1 * duration
        for _ in range(ATTEMPTS):
            previous = put_previous(job)
            if while_writing:
                at, landed = _kill_while_writing(job, env, rng, latest)
            else:
                at, landed = _kill_at_random_moment(job, env, rng.uniform(0.0, latest))
            if landed:
                kill_times.append(at)
                states.append((previous, snapshot(job.out), len(litter(job))))
                break
            missed += 1
            if while_writing:
                latest = latest / 3 if latest > 0.02 else 0.0
            else:
                latest = at
        else:
            not_killed += 1
    final_duration = run_to_completion(job, env)  # must succeed whatever the kills left behind
    new = first or snapshot(job.out)
    report = KillReport(job.name, round(duration or final_duration, 2), trials=len(states),
                        kills_missed=missed, trials_not_killed=not_killed,
                        kill_times_s=[round(t, 2) for t in kill_times])
    for (previous, state, left), at in zip(states, kill_times):
        outcome = "previous" if state == previous else "new" if state == new else "mix"
        report.outcomes[outcome] += 1
        if outcome == "mix":
            report.mixes.append({"kill_at_s": round(at, 2), "files": sorted(state)})
        report.litter_after_kills += left
    # with a first run: the last run gives it again, byte for byte (None: not measured)
    report.final_run_is_new_result = None if first is None else snapshot(job.out) == first
    report.litter_after_final_run = len(litter(job))
    return report


def make_inputs(root: Path) -> dict[str, Path]:
    """The small inputs the jobs read: a dome dataset (map), a thread bore (axial), a BAL problem."""
    from scope3d import phantoms
    from scope3d.phantoms.bundle_scene import make_scene
    from scope3d.geometry.rotation import matrix_to_rotvec
    from scope3d.io.bal import BALProblem, write_bal

    root.mkdir(parents=True, exist_ok=True)
    dome = phantoms.write(phantoms.generate("dome", "grid5x6", size=(128, 128), seed=0, n_frames=6), root / "dome")
    thread = phantoms.write(phantoms.generate("thread", "axial", seed=0, n_frames=4, size=(160, 160)),
                            root / "thread")
    scene = make_scene(12, 300, observations_per_point=4, pixel_noise_px=0.5, seed=0)
    flip = np.array([1.0, -1.0, -1.0])  # BAL cameras look down -z with y up (scope3d.estimators.bundle.bal)
    rng = np.random.default_rng(0)
    cameras = np.column_stack([matrix_to_rotvec(flip[None, :, None] * scene.rotations), flip * scene.translations,
                               np.full(12, 500.0), np.zeros(12), np.zeros(12)])
    obs = (scene.observations_px - [320.0, 240.0]) * [1.0, -1.0]
    bal = BALProblem(scene.camera_index, scene.point_index, obs, cameras,
                     scene.points + rng.normal(0, 0.05, scene.points.shape))
    write_bal(root / "problem.txt", bal)
    return {"dome": dome, "thread": thread, "bal": root / "problem.txt"}


def jobs(inputs: dict[str, Path], work: Path) -> list[Job]:
    """The four jobs on small inputs, each writing under ``work``."""
    return [
        Job("phantom", scope3d("phantom", "dome", "--trajectory", "grid5x6", "--size", "96x96", "--frames", "4",
                               "--seed", "1", "--no-progress", "--out", str(work / "phantom")), work / "phantom"),
        Job("map", scope3d("map", str(inputs["dome"]), "--no-progress", "--out", str(work / "map")), work / "map"),
        Job("bundle-adjust", scope3d("bundle-adjust", str(inputs["bal"]), "--quiet", "--report",
                                     str(work / "ba" / "report.json"), "--output", str(work / "ba" / "solved.txt"),
                                     "--plot", str(work / "ba" / "curve.png")), work / "ba", files_in_folder=True),
        Job("axial", scope3d("axial", str(inputs["thread"]), "--out", str(work / "axial")), work / "axial"),
    ]


def live_processes(session: int) -> dict[int, str]:
    """pid -> state letter (R running, S sleeping, D...) of every process in ``session`` (a job started
    with ``start_new_session=True`` has its pid as its session id, and every process it starts inherits
    it); zombies (dead, not yet reaped) are left out."""
    found = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            if os.getsid(int(name)) != session:
                continue
            with open(f"/proc/{name}/stat") as f:
                state = f.read().rsplit(")", 1)[1].split()[0]
        except OSError:  # ended meanwhile
            continue
        if state != "Z":
            found[int(name)] = state
    return found


def waits_on_a_pipe(pid: int) -> bool:
    """True when the process sleeps in a pipe read (its kernel wait channel: pipe_read, anon_pipe_read)."""
    try:
        with open(f"/proc/{pid}/wchan") as f:
            return "pipe" in f.read()
    except OSError:
        return False


def kill_the_leader_when(job: Job, env: dict, moment: Callable[[int, dict[int, str]], bool],
                         attempts: int = ATTEMPTS) -> int | None:
    """Start the job in a session of its own and SIGKILL its first process alone (as the out-of-memory
    killer or a time limit would, not its process group) at the first ``moment(pid, others)`` that
    holds, ``pid`` being that process and ``others`` the session's other live processes (pid -> state);
    the session id, or None if every attempt finished before such a moment came (a kill before it would
    prove nothing: retried)."""
    for _ in range(attempts):
        proc = subprocess.Popen(job.argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO,
                                start_new_session=True)
        while proc.poll() is None:
            others = {p: s for p, s in live_processes(proc.pid).items() if p != proc.pid}
            if moment(proc.pid, others):
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait()
                return proc.pid
            time.sleep(0.002)
    return None


def left_alive(session: int, patience_s: float = 20.0) -> dict[int, str]:
    """The session's processes still alive once they all ended or ``patience_s`` passed (a bound on the
    poll, not a timing target); those found are SIGKILLed after being listed, so a failing check leaves
    nothing behind either."""
    deadline = time.monotonic() + patience_s
    while (alive := live_processes(session)) and time.monotonic() < deadline:
        time.sleep(0.05)
    for pid in alive:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return alive
