"""Figures without pyplot: the matplotlib check, a new figure, a PNG file or PNG bytes.

Figures are built with :class:`matplotlib.figure.Figure` on an Agg canvas, never through
pyplot: nothing opens a window and the global backend is left alone. matplotlib is the
optional extra ``dego-occupancy[viz]``, imported inside the functions, so that importing
``dego.viz`` never needs it.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dego._checks import check_positive

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
else:  # matplotlib is optional and imported inside the functions; the run-time check sees Any
    Axes = Figure = Any


_INSTALL_HINT = (
    'dego.viz needs matplotlib, an optional dependency: pip install -e ".[viz]" in your dego '
    'clone (or pip install "matplotlib>=3.7")'
)


def _require_matplotlib() -> None:
    """Import matplotlib or raise an ImportError that says how to install it."""
    try:
        import matplotlib  # noqa: F401
    except ImportError as error:
        raise ImportError(_INSTALL_HINT, name="matplotlib") from error


def new_figure(figsize: tuple[float, float]) -> Figure:
    """A constrained-layout Figure on its own Agg canvas (no pyplot, no window)."""
    _require_matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure as MplFigure

    fig = MplFigure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_figure(
    fig: Figure | Axes, path: str | os.PathLike[str], *, dpi: float | int = 100.0
) -> Path:
    """Write ``fig`` (a Figure, or the figure of an Axes) as a PNG, creating parent folders.

    Args:
        fig: a matplotlib ``Figure`` (or ``Axes``, whose figure is saved).
        path: the file to write; must end in ``.png``.
        dpi: resolution in dots per inch.

    Returns:
        ``path`` as a :class:`pathlib.Path`.
    """
    _require_matplotlib()
    from matplotlib.figure import Figure as MplFigure

    root: Any = fig
    for _ in range(3):  # Axes -> (Sub)Figure -> Figure
        if isinstance(root, MplFigure):
            break
        root = getattr(root, "figure", None)
    if not isinstance(root, MplFigure):
        raise TypeError(f"fig: expected a matplotlib Figure or Axes, got {type(fig).__name__}")
    if not isinstance(path, str | os.PathLike):
        raise TypeError(f"path: expected a str or os.PathLike, got {type(path).__name__}")
    dpi = check_positive("dpi", dpi)
    target = Path(path)
    if target.suffix.lower() != ".png":
        raise ValueError(f"path: expected a file name ending in .png, got {str(target)!r}")
    target.parent.mkdir(parents=True, exist_ok=True)
    root.savefig(target, format="png", dpi=dpi)
    return target


def png_bytes(figure: Any, dpi: float = 80) -> bytes:
    """``figure`` (a matplotlib Figure) encoded as a PNG, at ``dpi`` dots per inch."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=dpi)
    return buffer.getvalue()
