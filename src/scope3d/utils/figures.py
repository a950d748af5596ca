"""Figures drawn through matplotlib's object API on an Agg canvas: no pyplot, no global backend switch.

Library code never calls ``matplotlib.use`` (that would change the backend of the program that imports
us); it draws on a :class:`~matplotlib.figure.Figure` of its own::

    fig = new_figure((5.5, 4.5), dpi=110)
    ax = fig.add_subplot()
    ...
    save_figure(fig, path)

matplotlib is imported when the first figure is made, so importing a module that can plot stays cheap.
"""
from __future__ import annotations

import os

from scope3d.utils.atomic import atomic_path


def new_figure(figsize: tuple[float, float] | None = None, dpi: float | None = None, **figure_kwargs):
    """A :class:`matplotlib.figure.Figure` (size in inches, ``dpi`` dots per inch; None = matplotlib's
    defaults) attached to a :class:`~matplotlib.backends.backend_agg.FigureCanvasAgg`, so that it can
    be drawn and saved without pyplot. It is garbage-collected like any object: nothing to close."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=dpi, **figure_kwargs)
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig, path: str | os.PathLike, **savefig_kwargs) -> None:
    """Write ``fig`` to ``path`` (format from the suffix, e.g. PNG) atomically: a failure leaves no file."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, **savefig_kwargs)
