"""Matplotlib figures without pyplot: every PNG of the package is drawn on an Agg canvas made here.

:func:`agg_figure` never imports ``matplotlib.pyplot`` and never calls ``matplotlib.use``, so it works without a
display and leaves the caller's backend alone; matplotlib (the ``plot`` extra) is imported on the first call, never
at import time. :func:`save_png` writes a figure, creating the folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["agg_figure", "save_png"]


def agg_figure(width_in: float, height_in: float, dpi: float, what: str, **options: Any) -> Figure:
    """A figure of ``width_in`` x ``height_in`` inches on an Agg canvas, constrained layout unless ``options`` say.

    Args:
        width_in: Width in inches.
        height_in: Height in inches.
        dpi: Dots per inch.
        what: What is being drawn, for the error message (``"learning curves"``).
        **options: Further :class:`matplotlib.figure.Figure` arguments.

    Raises:
        ImportError: matplotlib is not installed (the message names ``what`` and the ``plot`` extra).
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as err:  # pragma: no cover - matplotlib is in the dev and plot extras
        raise ImportError(f"{what}: matplotlib is needed (pip install 'lcreg[plot]')") from err
    fig = Figure(figsize=(width_in, height_in), dpi=dpi, **{"layout": "constrained", **options})
    FigureCanvasAgg(fig)
    return fig


def save_png(fig: Figure, path: str | Path, dpi: float | None = None) -> Path:
    """Write ``fig`` as a PNG at ``path`` (folders created; ``dpi``: the figure's); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi or fig.dpi, format="png")
    return path
