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
"""
from __future__ import annotations

import multiprocessing
import sys
import traceback
from typing import Callable


def _serve(inherited, tasks, failures) -> None:
    """The child's loop: the calls it inherited, then each queued one until the ``None`` sentinel; the
    first failure's traceback (or None) goes back through ``failures``."""
    try:
        for function, args, kwargs in inherited:
            function(*args, **kwargs)
        for function, args, kwargs in iter(tasks.get, None):
            function(*args, **kwargs)
    except BaseException:  # noqa: BLE001 - everything goes back to the parent, which re-raises
        failures.send(traceback.format_exc())
        return
    failures.send(None)


class BackgroundCalls:
    """A child process running submitted calls in order (module docstring).

    Calls submitted before :meth:`start` are inherited by the child (their arguments are not pickled:
    large objects cost nothing); calls submitted after it go through a queue (pickled).
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
            self._tasks.put((function, args, kwargs))

    def start(self) -> None:
        """Fork the child: it runs the calls submitted so far, then those submitted later."""
        if not self._fork or self._process is not None:
            return
        context = multiprocessing.get_context("fork")
        # a Queue (not a bare pipe): its feeder thread sends, so submit() never waits for the child
        self._tasks = context.Queue()
        self._failures, child_end = context.Pipe(duplex=False)
        self._process = context.Process(target=_serve, args=(self._inherited, self._tasks, child_end), daemon=True)
        self._process.start()
        child_end.close()
        self._inherited = []

    def wait(self) -> None:
        """Wait for every submitted call; raise RuntimeError with the child's traceback if one failed."""
        self.start()  # calls submitted but never started still run
        process, self._process, self._fork = self._process, None, False
        if process is None:
            return
        self._tasks.put(None)
        self._tasks.close()
        try:
            failure = self._failures.recv()
        except EOFError:  # the child died without a word (killed)
            failure = "the process ended without reporting"
        process.join()
        self._tasks.join_thread()
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
            self._tasks.cancel_join_thread()

    def __enter__(self) -> "BackgroundCalls":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.wait()
        else:
            self.cancel()
