"""Calls that write files (figures) in a child process while the caller goes on computing.

matplotlib's Agg drawing holds the GIL, so a thread cannot draw while the main thread computes; a
process can. On Linux the child is forked: it inherits the caller's data as it is at the moment of the
fork (no pickling, no second import of NumPy or the caller's modules), and only the calls submitted
later, with their arguments, travel through a queue. Where ``fork`` is not the platform's way (macOS,
Windows) or when disabled, :meth:`BackgroundCalls.submit` runs the call at once, in the caller.

    with BackgroundCalls() as background:
        background.submit(save_depth_map_png, out / "depth_map.png", surface)
        background.start()                                   # fork: the depth map is drawn meanwhile
        ...                                                  # compute
        background.submit(save_error_map_png, out / "error_map.png", points, distances)
    # here every call has run (or the first failure was raised here, as a RuntimeError)

The calls run one after another, in the order submitted; their return values are dropped (they write
files). A call that raises stops the child; :meth:`BackgroundCalls.wait` (also run on leaving the
``with`` block) raises ``RuntimeError`` carrying the child's traceback.

The child ends when its parent ends, whatever ends the parent (SIGKILL, the out-of-memory killer, a
scheduler's time limit): its work is only ever used by the parent. The child keeps no copy of the tasks
pipe's write end (a forked child inherits every descriptor, and a reader holding the write end itself
never sees end-of-file: issue 39's orphans, blocked in a pipe read for ever), so a read after the
parent's death ends it; on Linux it also asks for SIGKILL on the parent's death (``PR_SET_PDEATHSIG``),
which ends it in the middle of a drawing too. Linux sends that signal when the *thread* that forked
ends, so :meth:`BackgroundCalls.start` and :meth:`BackgroundCalls.wait` belong to one thread (the
``with`` block does it).
"""
from __future__ import annotations

import ctypes
import multiprocessing
import os
import queue
import signal
import sys
import threading
import traceback
from typing import Callable

_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def _end_with_parent(parent: int) -> bool:
    """In the child: ask Linux for SIGKILL when the parent ends; False if it has already ended (it may
    have died between the fork and the request, which then never comes)."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    return os.getppid() == parent


def _received(tasks):
    """The calls the parent sends, until its sentinel (None) or its end: end-of-file means the parent is
    gone, and nobody wants the rest."""
    try:
        yield from iter(tasks.recv, None)
    except EOFError:
        return


def _serve(inherited, parent: int, tasks, failures, parents_ends) -> None:
    """The child's loop: the calls it inherited, then each sent one until the ``None`` sentinel; the
    first failure's traceback (or None) goes back through ``failures``. It closes its copies of the
    parent's ends first: with the tasks pipe's write end open here, a read would wait for ever once the
    parent is gone instead of seeing end-of-file."""
    for end in parents_ends:
        end.close()
    try:
        if not _end_with_parent(parent):
            return
        for function, args, kwargs in inherited:
            function(*args, **kwargs)
        for function, args, kwargs in _received(tasks):
            function(*args, **kwargs)
    except BaseException:  # noqa: BLE001 - everything goes back to the parent, which re-raises
        failures.send(traceback.format_exc())
        return
    failures.send(None)


def _feed(pending: queue.SimpleQueue, tasks) -> None:
    """The parent's feeder thread: send each pending call to the child, so that submit() never waits for
    the child to read (a pickled call can be larger than the pipe's buffer); then the sentinel, None.
    A child that has ended (failed, cancelled, killed) closed its end: the rest is dropped."""
    try:
        for item in iter(pending.get, None):
            tasks.send(item)
        tasks.send(None)
    except OSError:  # BrokenPipeError: the child is gone; wait() reports why
        pass
    finally:
        tasks.close()


class BackgroundCalls:
    """A child process running submitted calls in order (module docstring).

    Calls submitted before :meth:`start` are inherited by the child (their arguments are not pickled:
    large objects cost nothing); calls submitted after it go through a pipe (pickled).
    enabled : False runs every call at once in the caller (as on platforms without ``fork``).
    """

    def __init__(self, enabled: bool = True) -> None:
        self._fork = enabled and sys.platform.startswith("linux")
        self._inherited: list = []
        self._process = None

    @property
    def in_background(self) -> bool:
        """True when calls run (or will run, once started) in a child process."""
        return self._fork

    def submit(self, function: Callable, *args, **kwargs) -> None:
        """Run ``function(*args, **kwargs)`` in the child, or here and now when not in the background."""
        if not self._fork:
            function(*args, **kwargs)
        elif self._process is None:
            self._inherited.append((function, args, kwargs))
        else:
            self._pending.put((function, args, kwargs))

    def start(self) -> None:
        """Fork the child: it runs the calls submitted so far, then those submitted later."""
        if not self._fork or self._process is not None:
            return
        context = multiprocessing.get_context("fork")
        tasks_read, tasks_write = context.Pipe(duplex=False)
        self._failures, failures_write = context.Pipe(duplex=False)
        self._process = context.Process(
            target=_serve, daemon=True,
            args=(self._inherited, os.getpid(), tasks_read, failures_write, (tasks_write, self._failures)))
        self._process.start()
        tasks_read.close()  # the child's ends: with them closed here, each side sees the other's end
        failures_write.close()
        self._inherited = []
        # a feeder thread (started after the fork: the child has no copy of it) sends the calls
        self._pending = queue.SimpleQueue()
        self._feeder = threading.Thread(target=_feed, args=(self._pending, tasks_write), daemon=True,
                                        name="scope3d-background-feeder")
        self._feeder.start()

    def wait(self) -> None:
        """Wait for every submitted call; raise RuntimeError with the child's traceback if one failed."""
        self.start()  # calls submitted but never started still run
        process, self._process, self._fork = self._process, None, False
        if process is None:
            return
        self._pending.put(None)
        try:
            failure = self._failures.recv()
        except EOFError:  # the child died without a word (killed)
            failure = "the process ended without reporting"
        self._failures.close()
        process.join()
        self._feeder.join()  # the child has ended: a send still under way fails at once
        if failure is None and process.exitcode != 0:
            failure = f"the process ended with exit code {process.exitcode}"
        if failure is not None:
            raise RuntimeError(f"a background call failed:\n{failure}")

    def cancel(self) -> None:
        """Stop the child without waiting for its calls (nothing runs any more)."""
        process, self._process, self._fork = self._process, None, False
        self._inherited = []
        if process is not None:
            process.terminate()
            process.join()
            self._failures.close()
            self._pending.put(None)  # wakes the feeder; its sends to the ended child fail at once
            self._feeder.join()

    def __enter__(self) -> "BackgroundCalls":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.wait()
        else:
            self.cancel()
