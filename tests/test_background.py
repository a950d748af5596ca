"""BackgroundCalls: calls run in a forked child, in order, a failure comes back to the caller, and the child
ends when its parent is killed."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from kill_harness import REPO, environment, left_alive, waits_on_a_pipe
from scope3d.utils.background import BackgroundCalls

FORKS = sys.platform.startswith("linux")


def _append(path: Path, text: str) -> None:
    with open(path, "a") as handle:
        handle.write(f"{text}:{os.getpid()}\n")


def _save_sum(path: Path, values: np.ndarray) -> None:
    path.write_text(repr(float(values.sum())))


def _fail(message: str) -> None:
    raise ValueError(message)


def test_calls_run_in_order_in_a_child_process(tmp_path):
    log = tmp_path / "log.txt"
    big = np.arange(200_000, dtype=np.float64)  # 1.6 MB: inherited before the fork, pickled after it
    with BackgroundCalls() as background:
        background.submit(_append, log, "first")
        background.submit(_save_sum, tmp_path / "inherited.txt", big)
        background.start()
        background.submit(_append, log, "second")
        background.submit(_save_sum, tmp_path / "queued.txt", big)
    lines = log.read_text().split()
    assert [line.split(":")[0] for line in lines] == ["first", "second"]
    pids = {int(line.split(":")[1]) for line in lines}
    assert (pids != {os.getpid()} and len(pids) == 1) if FORKS else pids == {os.getpid()}
    assert float((tmp_path / "inherited.txt").read_text()) == float((tmp_path / "queued.txt").read_text()) == big.sum()


def test_a_failure_is_raised_by_wait_with_the_childs_traceback(tmp_path):
    background = BackgroundCalls()
    background.start()
    if not FORKS:
        with pytest.raises(ValueError):
            background.submit(_fail, "broken figure")
        return
    background.submit(_fail, "broken figure")
    background.submit(_append, tmp_path / "never.txt", "after the failure")
    with pytest.raises(RuntimeError, match="broken figure"):
        background.wait()
    assert not (tmp_path / "never.txt").exists()


def test_disabled_runs_at_once_and_an_error_in_the_block_cancels(tmp_path):
    with BackgroundCalls(enabled=False) as background:
        background.submit(_append, tmp_path / "now.txt", "now")
        assert (tmp_path / "now.txt").read_text().startswith("now:")
    assert not background.in_background
    with pytest.raises(KeyError):
        with BackgroundCalls() as background:
            background.start()
            raise KeyError("the caller failed")
    background.wait()  # cancelled: nothing left to wait for


# A parent that forks a BackgroundCalls child and then computes for ever; its one call reports the
# child's pid, then returns (the child waits for the next call) or never returns (a drawing under way).
_PARENT = """
import os, sys, time
from scope3d.utils.background import BackgroundCalls

def report_pid(path, then_never_return):
    with open(path + ".tmp", "w") as f:
        f.write(str(os.getpid()))
    os.replace(path + ".tmp", path)
    if then_never_return:
        time.sleep(3600)

background = BackgroundCalls()
background.submit(report_pid, sys.argv[1], sys.argv[2] == "in a call")
background.start()
time.sleep(3600)
"""


def _pipe_ends(pid: int) -> dict[str, set[str]]:
    """pipe -> the ends ('r', 'w') the process holds of it."""
    ends: dict[str, set[str]] = {}
    for fd in os.listdir(f"/proc/{pid}/fd"):
        target = os.readlink(f"/proc/{pid}/fd/{fd}")
        if target.startswith("pipe:"):
            with open(f"/proc/{pid}/fdinfo/{fd}") as f:
                flags = int(f.read().split("flags:")[1].split()[0], 8)
            ends.setdefault(target, set()).add("w" if flags & os.O_ACCMODE == os.O_WRONLY else "r")
    return ends


@pytest.mark.parametrize("child", ["waiting for calls", "in a call"])
def test_the_child_ends_when_its_parent_is_killed(tmp_path, child):
    # issue 39: a SIGKILLed map left its figures child alive for ever, blocked reading a pipe whose write
    # end it held itself. The parent runs in a session of its own: every process it started shares it.
    pid_file = tmp_path / "child.pid"
    parent = subprocess.Popen([sys.executable, "-c", _PARENT, str(pid_file), child], env=environment(), cwd=REPO,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    deadline = time.monotonic() + 120  # bounds the polls below, should the child never get there
    try:
        while not pid_file.exists():
            assert parent.poll() is None and time.monotonic() < deadline, parent.stderr.read()
            time.sleep(0.01)
        pid = int(pid_file.read_text())
        assert pid != parent.pid if FORKS else pid == parent.pid
        if FORKS and child == "waiting for calls":
            while not waits_on_a_pipe(pid):  # back from the call, reading the next one
                assert time.monotonic() < deadline
                time.sleep(0.01)
            # the pipe it reads from must not be held open by the child itself: no pipe with both ends here
            assert [p for p, ends in _pipe_ends(pid).items() if ends == {"r", "w"}] == []
    finally:  # whatever failed above, nothing of this test may stay alive
        parent.kill()
        parent.wait()
        alive = left_alive(parent.pid)
    assert alive == {}
