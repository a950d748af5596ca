"""How many threads a stage runs on: one convention for every ``threads`` option.

``threads = 0``, every option's default, means every core this process may run on (its CPU affinity mask,
so a ``taskset`` or a container's CPU limit counts); ``threads = n >= 1`` means at most ``n``. A Dask worker
runs its jobs with ``threads = 1`` (the cluster spreads the holes over the cores). The stages give the
same results on any number of threads: each task (a frame, a pair, an ICP start) is computed alone and
collected in order.
"""
from __future__ import annotations

import os


def available_cores() -> int:
    """CPUs this process may run on (its affinity mask where the platform has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def check_threads(threads: int) -> None:
    """Raise ValueError unless ``threads`` is 0 (every core) or a positive count."""
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 0:
        raise ValueError(f"threads must be 0 (every available core) or a positive count, got {threads!r}")


def resolve_threads(threads: int, tasks: int | None = None) -> int:
    """The threads to start for a ``threads`` option: every available core for 0, else ``threads``; never
    more than ``tasks`` (when given: threads beyond the work would idle), never fewer than one."""
    n = available_cores() if threads == 0 else threads
    if tasks is not None:
        n = min(n, tasks)
    return max(1, n)
