"""``quadrants.json``: which frames of a dataset form each side-view quadrant, and the stage's angle.

Layout (written by the phantom lab for the ``quadrants`` trajectory)::

    {"thread": "M8x1.25", "angle_step_deg": 30, "step_mm": 0.1, "side_view_deg": 45,
     "quadrants": [{"index": 0, "angle_deg": 0, "frames": ["0000.png", ...]}, ...]}

Frames are listed in order of advance; quadrants in stage order. ``thread`` (optional) is the hole's
nominal thread, as on its drawing.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from scope3d.errors import InputError
from scope3d.io.json_object import read_json_object

FILE_NAME = "quadrants.json"


@dataclass(frozen=True)
class Quadrant:
    """index : stage order; angle_deg : the stage's rotation (degrees); frames : indices into the dataset."""

    index: int
    angle_deg: float
    frames: tuple[int, ...]


def read_quadrants(root: str | Path, names: list[str]) -> list[Quadrant]:
    """Read ``root/quadrants.json``; ``names`` are the dataset's frame names. Raises :class:`InputError`
    naming the file and the quadrant for a missing file, unknown frames or a malformed entry."""
    path = Path(root) / FILE_NAME
    if not path.is_file():
        raise InputError(f"{path}: missing (a thread scan needs the quadrant layout)")
    entries = read_json_object(path).get("quadrants")
    if not isinstance(entries, list) or len(entries) < 2:
        raise InputError(f"{path}: needs a list of at least 2 quadrants")
    index = {n: k for k, n in enumerate(names)}
    out = []
    for k, q in enumerate(entries):
        if not isinstance(q, dict):
            raise InputError(f"{path}: quadrant {k}: expected an object {{...}}, found {type(q).__name__}")
        try:
            frames = tuple(index[f] for f in q["frames"])
            angle = float(q["angle_deg"])
            number = int(q.get("index", k))
        except KeyError as exc:
            raise InputError(f"{path}: quadrant {k}: unknown frame or missing field {exc}") from None
        except (TypeError, ValueError, OverflowError) as exc:
            raise InputError(f"{path}: quadrant {k}: {exc}") from None
        if not math.isfinite(angle):
            raise InputError(f"{path}: quadrant {k}: angle_deg is {angle}")
        if len(frames) < 2:
            raise InputError(f"{path}: quadrant {number}: needs at least 2 frames, has {len(frames)}")
        out.append(Quadrant(number, angle, frames))
    return out


def read_quadrant_thread(root: str | Path) -> str | None:
    """The hole's nominal thread named in ``root/quadrants.json`` (its ``thread``), or None when it names
    none. Raises :class:`InputError` for a missing file or a ``thread`` that is not a string."""
    path = Path(root) / FILE_NAME
    if not path.is_file():
        raise InputError(f"{path}: missing (a thread scan needs the quadrant layout)")
    thread = read_json_object(path).get("thread")
    if thread is not None and not isinstance(thread, str):
        raise InputError(f"{path}: thread must be a designation such as \"M8x1.25\", found {thread!r}")
    return thread
