"""Bird's-eye (BEV) pictures of label grids: one grid, or prediction vs ground truth.

Orientation (ego frame, x forward, y left, z up): BEV pictures put +x up and +y to the
left, as a map seen from above with the ego driving up the page.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from jaxtyping import Bool, Integer
from torch import Tensor

from dego._typing import typechecked
from dego.classes import FREE_LABEL
from dego.grid import VoxelGrid
from dego.viz._figure import _require_matplotlib, new_figure
from dego.viz._labels import RGB, WHITE, _check_free, _extents, _label_tensor, _present_classes
from dego.viz._veil import _bev_mask, _veil_unscored
from dego.viz.colors import bev_labels, colorize_labels
from dego.viz.legend import add_class_legend

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
else:  # matplotlib is optional and imported inside the functions; the run-time check sees Any
    Axes = Figure = Any


@typechecked
def plot_bev(
    labels: Integer[Tensor, "X Y Z"]
    | Integer[np.ndarray, "X Y Z"]
    | Integer[Tensor, "X Y"]
    | Integer[np.ndarray, "X Y"],
    *,
    grid: VoxelGrid | None = None,
    ax: Axes | None = None,
    title: str | None = None,
    free_label: int = FREE_LABEL,
    free_color: RGB = WHITE,
    mask: Bool[Tensor, "X Y Z"]
    | Bool[np.ndarray, "X Y Z"]
    | Bool[Tensor, "X Y"]
    | Bool[np.ndarray, "X Y"]
    | None = None,
) -> Axes:
    """Draw a bird's-eye view of a label grid: +x (forward) up, +y (left) to the left.

    Args:
        labels: ``(X, Y, Z)`` label grid (reduced with :func:`bev_labels`) or an
            ``(X, Y)`` BEV map, labels in [0, 17].
        grid: the grid the labels live on; sets the axis extents in metres. ``None``:
            the Occ3D grid when the shape is (200, 200[, 16]), else voxel units.
        ax: axes to draw into; ``None`` makes a new figure (``ax.figure``).
        title: axes title.
        free_label: the empty-space label; drawn in ``free_color`` (white).
        free_color: RGB (0-255) of free columns.
        mask: the scored voxels (e.g. Occ3D's ``mask_camera``), ``(X, Y, Z)`` or an
            ``(X, Y)`` map; columns without a scored voxel are greyed
            (:data:`UNSCORED_RGBA`) and the scored region is outlined in black.

    Returns:
        The axes; save with ``save_figure(ax.figure, "bev.png")``.
    """
    _require_matplotlib()
    _check_free(free_label, free_color)
    index = _label_tensor("labels", labels).cpu()
    bev = bev_labels(index, free_label=free_label) if index.ndim == 3 else index
    bounds, unit = _extents(grid, tuple(index.shape))
    (x_lo, x_hi), (y_lo, y_hi) = bounds[:2]
    rgb = colorize_labels(bev, free_label=free_label, free_color=free_color).numpy()
    image = np.ascontiguousarray(rgb[::-1, ::-1])  # row 0 = highest x, column 0 = highest y
    if ax is None:
        ax = new_figure((5.0, 5.0)).add_subplot()
    extent = (y_hi, y_lo, x_lo, x_hi)
    ax.imshow(image, extent=extent, origin="upper", interpolation="nearest")
    if mask is not None:
        _veil_unscored(ax, _bev_mask(mask), extent)
    ax.set_xlabel(f"y [{unit}] (left)")
    ax.set_ylabel(f"x [{unit}] (forward)")
    if title is not None:
        ax.set_title(title)
    return ax


@typechecked
def compare_bev(
    pred: Integer[Tensor, "X Y Z"]
    | Integer[np.ndarray, "X Y Z"]
    | Integer[Tensor, "X Y"]
    | Integer[np.ndarray, "X Y"],
    gt: Integer[Tensor, "X Y Z"]
    | Integer[np.ndarray, "X Y Z"]
    | Integer[Tensor, "X Y"]
    | Integer[np.ndarray, "X Y"],
    *,
    grid: VoxelGrid | None = None,
    titles: tuple[str, str] = ("prediction", "ground truth"),
    legend: bool = True,
    free_label: int = FREE_LABEL,
    mask: Bool[Tensor, "X Y Z"]
    | Bool[np.ndarray, "X Y Z"]
    | Bool[Tensor, "X Y"]
    | Bool[np.ndarray, "X Y"]
    | None = None,
) -> Figure:
    """Prediction and ground truth side by side as BEV pictures (see :func:`plot_bev`).

    Args:
        pred: ``(X, Y, Z)`` predicted labels (or an ``(X, Y)`` BEV map).
        gt: ground-truth labels of the same shape as ``pred``.
        grid: the grid both live on (axes in metres); ``None`` as in :func:`plot_bev`.
        titles: the two panel titles.
        legend: add a legend of the classes visible in either picture.
        free_label: the empty-space label.
        mask: the scored voxels, greyed outside in both panels (see :func:`plot_bev`);
            the legend then names the grey.

    Returns:
        A new Figure with two axes; save with :func:`save_figure`.
    """
    _require_matplotlib()
    if tuple(pred.shape) != tuple(gt.shape):
        raise ValueError(
            f"gt: shape {tuple(gt.shape)} does not match pred's shape {tuple(pred.shape)}"
        )
    maps = []
    for name, labels in (("pred", pred), ("gt", gt)):
        index = _label_tensor(name, labels).cpu()
        maps.append(bev_labels(index, free_label=free_label) if index.ndim == 3 else index)
    # Room for the legend's rows (up to 6 names per row) below the square panels.
    entries = len(_present_classes(torch.cat([m.flatten() for m in maps]), free_label))
    rows = math.ceil((entries + (mask is not None)) / 6)
    fig = new_figure((10.0, 5.0 + (0.25 + 0.3 * rows if legend and rows else 0.0)))
    axes = fig.subplots(1, 2, sharex=True, sharey=True)
    for ax, bev, title in zip(axes, maps, titles, strict=True):
        plot_bev(bev, grid=grid, ax=ax, title=title, free_label=free_label, mask=mask)
    if legend:
        labels = torch.cat([m.flatten() for m in maps])
        add_class_legend(fig, labels, free_label=free_label, unscored=mask is not None)
    return fig
