"""A legend of class names in their palette colours, for a figure or an axes."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from jaxtyping import Integer
from torch import Tensor

from dego._checks import check_int
from dego._typing import typechecked
from dego.classes import CLASS_NAMES, FREE_LABEL, NUM_CLASSES, PALETTE
from dego.viz._figure import _require_matplotlib
from dego.viz._labels import WHITE, _check_free, _label_tensor, _present_classes, _unit_rgb
from dego.viz._veil import UNSCORED_HATCH, UNSCORED_RGBA

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.legend import Legend
else:  # matplotlib is optional and imported inside the functions; the run-time check sees Any
    Axes = Figure = Legend = Any


@typechecked
def add_class_legend(
    target: Figure | Axes,
    classes: Sequence[int]
    | Integer[Tensor, "*shape"]
    | Integer[np.ndarray, "*shape"]
    | None = None,
    *,
    free_label: int = FREE_LABEL,
    unscored: bool = False,
    **legend_kwargs: Any,
) -> Legend:
    """Add a legend of class names with their palette colours to a figure or axes.

    Args:
        target: a matplotlib ``Figure`` (legend below the panels, in ``ncols`` up to 6) or
            ``Axes`` (legend outside on the right).
        classes: which classes to list. ``None``: the 17 semantic classes 0..16; a label
            tensor/array of any shape: the classes present in it except ``free_label``;
            a sequence of ints: those classes, in that order (``free_label`` included if
            given).
        free_label: the empty-space label skipped when ``classes`` is a label array.
        unscored: add an entry for the greyed columns outside the scored region (what
            :func:`plot_bev` draws for its ``mask``).
        **legend_kwargs: passed to ``legend(...)``, overriding the defaults
            (e.g. ``loc``, ``ncols``, ``fontsize``).

    Returns:
        The matplotlib ``Legend``.
    """
    _require_matplotlib()
    from matplotlib.axes import Axes as MplAxes
    from matplotlib.figure import FigureBase
    from matplotlib.layout_engine import ConstrainedLayoutEngine
    from matplotlib.patches import Patch

    _check_free(free_label, WHITE)
    if classes is None:
        chosen = [c for c in range(NUM_CLASSES) if c != FREE_LABEL]
    elif isinstance(classes, Tensor | np.ndarray):
        chosen = _present_classes(_label_tensor("classes", classes).cpu(), free_label)
    else:
        chosen = [check_int("classes", c) for c in classes]
        _label_tensor("classes", torch.tensor(chosen, dtype=torch.long))
    handles = [
        Patch(
            facecolor=_unit_rgb(PALETTE[c]),
            edgecolor="0.35",
            linewidth=0.5,
            label=CLASS_NAMES[c],
        )
        for c in chosen
    ]
    if unscored:
        handles.append(
            Patch(
                facecolor=UNSCORED_RGBA,
                edgecolor="black",
                linewidth=0.8,
                hatch=UNSCORED_HATCH,
                label="not scored",
            )
        )
    if isinstance(target, FigureBase):
        engine = target.get_layout_engine()
        defaults: dict[str, Any] = {
            "loc": (
                "outside lower center"
                if isinstance(engine, ConstrainedLayoutEngine)
                else "lower center"
            ),
            "ncols": max(1, min(6, len(handles))),
            "fontsize": "small",
            "frameon": False,
        }
    elif isinstance(target, MplAxes):
        defaults = {
            "loc": "upper left",
            "bbox_to_anchor": (1.02, 1.0),
            "fontsize": "small",
            "frameon": False,
        }
    else:
        raise TypeError(
            f"target: expected a matplotlib Figure or Axes, got {type(target).__name__}"
        )
    return target.legend(handles=handles, **{**defaults, **legend_kwargs})
