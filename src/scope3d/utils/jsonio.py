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
