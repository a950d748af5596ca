"""The cores this process may run on (:func:`available_cores`): its CPU affinity mask, so that a ``taskset``
or a container's CPU limit counts.
"""
from __future__ import annotations

import os


def available_cores() -> int:
    """CPUs this process may run on (its affinity mask where the platform has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)
