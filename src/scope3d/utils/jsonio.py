"""JSON files for reports and metadata: numpy values and paths allowed, written atomically."""
from __future__ import annotations

import json
import os
from pathlib import PurePath

import numpy as np

from scope3d.utils.atomic import atomic_file


def json_default(obj):
    """The ``default=`` hook of :func:`json.dump`/:func:`json.dumps`: a numpy array becomes a (nested)
    list, a numpy scalar (float, int, bool) the Python number, a path its string; anything else is a
    TypeError naming its type, as without the hook."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return obj.item()
    if isinstance(obj, PurePath):
        return str(obj)
    raise TypeError(f"cannot serialise {type(obj).__name__}")


def write_json(path: str | os.PathLike, obj, *, indent: int = 2) -> None:
    """Write ``obj`` to ``path`` as indented JSON with one trailing newline, atomically (never half a file);
    numpy values and paths are converted by :func:`json_default`."""
    with atomic_file(path) as fh:
        fh.write(json.dumps(obj, indent=indent, default=json_default) + "\n")


# What a report measures of the machine rather than of the data: these fields differ between runs.
TIMING_FIELD_SUFFIXES = ("time_s", "timings_s")
MACHINE_FIELDS = ("peak_memory_mb",)


def without_timings(report):
    """A copy of a report (nested dicts and lists) without its timing fields: keys ending in ``time_s`` or
    ``timings_s`` and :data:`MACHINE_FIELDS`. Everything that remains is a function of the input, the
    options and the seed (``docs/reliability.md``)."""
    if isinstance(report, dict):
        return {k: without_timings(v) for k, v in report.items()
                if not (k.endswith(TIMING_FIELD_SUFFIXES) or k in MACHINE_FIELDS)}
    if isinstance(report, list):
        return [without_timings(v) for v in report]
    return report
