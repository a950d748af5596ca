"""BackgroundCalls: calls run in a forked child, in order, and a failure comes back to the caller."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

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
