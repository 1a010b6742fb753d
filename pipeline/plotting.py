"""Figures, made in one place: matplotlib's object-oriented API, no global backend.

Every figure hdrcap draws is a :class:`matplotlib.figure.Figure` made by :func:`new_figure`
and written by :func:`save_figure` through :func:`hdrcap.pipeline.io.files.atomic_output`. Nothing
calls ``matplotlib.use`` or ``pyplot``: the Agg canvas is attached to each figure, so drawing
works on a headless rig and never changes the backend of a notebook or program that imports
hdrcap.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # matplotlib is imported when a figure is made
    from matplotlib.figure import Figure

__all__ = ["new_figure", "save_figure"]


def new_figure(
    nrows: int = 1,
    ncols: int = 1,
    *,
    figsize: tuple[float, float] = (6.4, 4.8),
    squeeze: bool = True,
    **subplot_kw: Any,
) -> tuple[Figure, Any]:
    """A new figure with a grid of axes, drawn on its own Agg canvas.

    Parameters
    ----------
    nrows, ncols : int
        Grid of axes.
    figsize : (float, float)
        Size in inches.
    squeeze : bool
        As in :meth:`matplotlib.figure.Figure.subplots`.
    **subplot_kw
        Passed to :meth:`matplotlib.figure.Figure.subplots` (``sharex``, ``gridspec_kw``, ...).

    Returns
    -------
    (Figure, Axes or array of Axes)
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=squeeze, **subplot_kw)
    return fig, axes


def save_figure(fig: Figure, path: str | os.PathLike[str], force: bool = False, dpi: int = 110) -> Path:
    """Write ``fig`` as PNG to ``path`` atomically (never over an existing file unless ``force``).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure (from :func:`new_figure`).
    path : str or Path
        Output PNG.
    force : bool
        Replace an existing file.
    dpi : int
        Resolution, dots per inch.

    Returns
    -------
    Path
        ``path``.
    """
    from hdrcap.pipeline.io.files import atomic_output

    path = Path(path)
    with atomic_output(path, force=force, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    return path
