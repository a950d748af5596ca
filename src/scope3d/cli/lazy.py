"""Argument choices named by the library, imported only when a parser needs them, so that building the
``scope3d`` parser (``--version``, ``--help``) imports no NumPy, SciPy or OpenCV."""
from __future__ import annotations

import importlib
from collections.abc import Sequence


class LazyChoices(Sequence):
    """The names in ``module.attribute`` (a sequence or a dict's keys), looked up on first use.

    Give the argument an explicit ``metavar``: argparse otherwise lists the choices while the argument is
    being added. ``%(choices)s`` in its help lists them only when that help is printed.
    """

    def __init__(self, module: str, attribute: str, *, sort: bool = False) -> None:
        self._module, self._attribute, self._sort = module, attribute, sort
        self._names: list[str] | None = None

    def _load(self) -> list[str]:
        if self._names is None:
            names = list(getattr(importlib.import_module(self._module), self._attribute))
            self._names = sorted(names) if self._sort else names
        return self._names

    def __getitem__(self, index):
        return self._load()[index]

    def __len__(self) -> int:
        return len(self._load())

    def __contains__(self, name) -> bool:
        return name in self._load()
