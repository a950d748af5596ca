"""One progress convention for every long-running function: a tqdm-like object, or None.

A function that reports progress takes ``progress=None`` and calls ``progress.update(n)`` as work gets
done; a multi-stage job calls :func:`stage` before each stage to reset the count and name it. Any object
with tqdm's ``update``, ``reset`` and ``set_description`` works (``tqdm.tqdm`` itself, a GUI's adapter,
a test's recorder). The command line makes the tqdm bar; library code never prints.
"""
from __future__ import annotations

from typing import Protocol


class Progress(Protocol):
    def update(self, n: int = 1) -> object: ...

    def reset(self, total: int | None = None) -> object: ...

    def set_description(self, desc: str | None = None, refresh: bool = True) -> object: ...


def advance(progress: Progress | None, n: int = 1) -> None:
    """Count ``n`` units of work done (nothing when ``progress`` is None)."""
    if progress is not None:
        progress.update(n)


def stage(progress: Progress | None, description: str, total: int | None = None) -> None:
    """Start a new stage of ``total`` units (None: unknown) named ``description``."""
    if progress is not None:
        progress.reset(total=total)
        if total is None and getattr(progress, "total", None) is not None:
            # tqdm's reset(total=None) keeps the last stage's total: the bar then showed "1/36" and counted
            # past it for a stage of unknown length
            progress.total = None
        progress.set_description(description)
