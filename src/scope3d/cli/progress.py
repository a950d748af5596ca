"""The command line's progress bars: tqdm on stderr, the library's progress convention (a tqdm-like
object or None, :mod:`scope3d.utils.progress`)."""
from __future__ import annotations

import sys
from contextlib import contextmanager
from typing import Iterator


@contextmanager
def progress_bar(enabled: bool, unit: str) -> Iterator[object | None]:
    """A tqdm bar counting ``unit`` on stderr, closed on the way out (also on errors); None if disabled."""
    if not enabled:
        yield None
        return
    from tqdm import tqdm

    bar = tqdm(unit=unit, leave=False, file=sys.stderr)
    try:
        yield bar
    finally:
        bar.close()
