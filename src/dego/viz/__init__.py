"""Pictures of occupancy grids and camera renders, in the DeGO paper's palette.

Bird's-eye (BEV) and 3D views of Occ3D-style label grids, prediction vs ground truth
side by side, and per-camera image / depth / semantics panels. The plotting functions
need the optional extra ``dego-occupancy[viz]`` (matplotlib), imported lazily so that
``import dego`` never needs it; :func:`colorize_labels` and :func:`bev_labels` are plain
torch/numpy.

Figures are built with :class:`matplotlib.figure.Figure` on an Agg canvas, never through
pyplot: nothing opens a window and the global backend is left alone. Save them with
:func:`save_figure`. Every function accepts torch tensors (CPU or GPU; moved to the CPU
for drawing) or numpy arrays.

Label arguments take any integer dtype (uint8 as Occ3D ships them, int8 ... int64; the
pictures do not depend on it). Values outside [0, 17], such as -1 or 255, raise a
``ValueError`` naming the argument and the range found; bool and floating labels raise a
``TypeError`` (jaxtyping's ``TypeCheckError``) naming the argument. Empty grids and
batches give empty results.

Orientation (ego frame, x forward, y left, z up): BEV pictures put +x up and +y to the
left, as a map seen from above with the ego driving up the page; the 3D view looks
forward from behind and above the ego by default.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, overload

import numpy as np
import torch
from jaxtyping import Bool, Float, Integer, UInt8
from torch import Tensor

from dego._checks import check_int, check_positive
from dego._typing import typechecked
from dego.classes import CLASS_NAMES, FREE_LABEL, NUM_CLASSES, PALETTE
from dego.grid import VoxelGrid

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.legend import Legend
else:  # matplotlib is optional and imported inside the functions; the run-time check sees Any
    Axes = Figure = Legend = Any

RGB = tuple[int, int, int]
WHITE: RGB = (255, 255, 255)
UNSCORED_RGBA = (0.45, 0.45, 0.45, 0.55)
"""The grey veil :func:`plot_bev` lays over columns outside its ``mask`` (RGBA, 0-1)."""
UNSCORED_HATCH = "////"
"""The hatch drawn over that veil, so that "not scored" is not read as ``other_flat``'s grey."""


_INSTALL_HINT = (
    'dego.viz needs matplotlib, an optional dependency: pip install "dego-occupancy[viz]" '
    '(or pip install "matplotlib>=3.7")'
)


def _require_matplotlib() -> None:
    """Import matplotlib or raise an ImportError that says how to install it."""
    try:
        import matplotlib  # noqa: F401
    except ImportError as error:
        raise ImportError(_INSTALL_HINT, name="matplotlib") from error


def new_figure(figsize: tuple[float, float]) -> Figure:
    """A constrained-layout Figure on its own Agg canvas (no pyplot, no window)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure as MplFigure

    fig = MplFigure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


# --------------------------------------------------------------------------- checks


def _check_free(free_label: int, free_color: RGB) -> None:
    check_int("free_label", free_label)
    if not 0 <= free_label < NUM_CLASSES:
        raise ValueError(
            f"free_label: expected a label in [0, {NUM_CLASSES - 1}], got {free_label}"
        )
    if any(isinstance(c, bool) or not 0 <= c <= 255 for c in free_color):
        raise ValueError(f"free_color: expected three ints in [0, 255], got {free_color}")


def _label_tensor(name: str, labels: Tensor | np.ndarray) -> Tensor:
    """``labels`` as int64 (a tensor stays on its device), checked to lie in [0, 17]."""
    if isinstance(labels, Tensor):
        index = labels.detach().long()
    else:
        index = torch.from_numpy(np.array(labels, dtype=np.int64))  # copy: read-only/strided ok
    if index.numel():
        low, high = (int(v) for v in torch.aminmax(index))
        if low < 0 or high >= NUM_CLASSES:
            raise ValueError(
                f"{name}: expected Occ3D labels in [0, {NUM_CLASSES - 1}], "
                f"got values in [{low}, {high}]"
            )
    return index


def _float_numpy(x: Tensor | np.ndarray) -> np.ndarray:
    if isinstance(x, Tensor):
        x = x.detach().cpu()
        return (x if x.dtype == torch.uint8 else x.float()).numpy()
    x = np.asarray(x)
    return x.astype(np.float32) if x.dtype == np.float16 else x  # matplotlib has no float16


def _unit_rgb(rgb: RGB) -> tuple[float, float, float]:
    """0-255 RGB as matplotlib's 0-1 floats."""
    r, g, b = (v / 255.0 for v in rgb)
    return r, g, b


def _palette_lut(free_label: int, free_color: RGB) -> Tensor:
    lut = torch.tensor(PALETTE, dtype=torch.uint8)
    lut[free_label] = torch.tensor(free_color, dtype=torch.uint8)
    return lut


def _extents(
    grid: VoxelGrid | None, shape: tuple[int, ...]
) -> tuple[list[tuple[float, float]], str]:
    """Per-axis ``(low, high)`` and unit for a grid of ``shape`` (2 or 3 axes)."""
    if grid is None:
        occ3d = VoxelGrid.occ3d()
        if shape != occ3d.shape[: len(shape)]:
            return [(0.0, float(n)) for n in shape], "voxel"
        grid = occ3d
    elif grid.shape[: len(shape)] != shape:
        raise ValueError(
            f"grid: its shape {grid.shape} does not match the labels' shape {shape}; "
            "pass the VoxelGrid the labels live on"
        )
    return [(grid.lower[a], grid.upper[a]) for a in range(len(shape))], "m"


def _present_classes(labels: Tensor, free_label: int) -> list[int]:
    return [int(c) for c in torch.unique(labels) if int(c) != free_label]


# --------------------------------------------------------------------------- pure


@overload
def colorize_labels(
    labels: Integer[Tensor, "*shape"], *, free_label: int = ..., free_color: RGB = ...
) -> UInt8[Tensor, "*shape 3"]: ...
@overload
def colorize_labels(
    labels: Integer[np.ndarray, "*shape"], *, free_label: int = ..., free_color: RGB = ...
) -> UInt8[np.ndarray, "*shape 3"]: ...
@typechecked
def colorize_labels(
    labels: Integer[Tensor, "*shape"] | Integer[np.ndarray, "*shape"],
    *,
    free_label: int = FREE_LABEL,
    free_color: RGB = WHITE,
) -> UInt8[Tensor, "*shape 3"] | UInt8[np.ndarray, "*shape 3"]:
    """RGB colours of Occ3D labels in the paper's palette (:data:`dego.PALETTE`).

    Args:
        labels: ``(...)`` integer labels in [0, 17], any shape (a grid, a BEV map, an image).
        free_label: the label drawn as ``free_color`` (Occ3D: 17).
        free_color: RGB (0-255) of free space; white by default.

    Returns:
        ``(..., 3)`` uint8 colours; a tensor on ``labels``' device for a tensor input,
        a numpy array for a numpy input.

    Raises:
        ValueError: a label outside [0, 17], or a bad ``free_label`` / ``free_color``.
    """
    _check_free(free_label, free_color)
    index = _label_tensor("labels", labels)
    lut = _palette_lut(free_label, free_color)
    if isinstance(labels, Tensor):
        return lut.to(index.device)[index]
    return lut[index].numpy()


@overload
def bev_labels(
    labels: Integer[Tensor, "*batch X Y Z"], *, free_label: int = ...
) -> Integer[Tensor, "*batch X Y"]: ...
@overload
def bev_labels(
    labels: Integer[np.ndarray, "*batch X Y Z"], *, free_label: int = ...
) -> Integer[np.ndarray, "*batch X Y"]: ...
@typechecked
def bev_labels(
    labels: Integer[Tensor, "*batch X Y Z"] | Integer[np.ndarray, "*batch X Y Z"],
    *,
    free_label: int = FREE_LABEL,
) -> Integer[Tensor, "*batch X Y"] | Integer[np.ndarray, "*batch X Y"]:
    """Top-down view of a label grid: per ``(x, y)`` column, the label of its highest
    non-free voxel, or ``free_label`` where the whole column is free.

    Args:
        labels: ``(*, X, Y, Z)`` labels in [0, 17], z up (index order x, y, z).
        free_label: the empty-space label (Occ3D: 17).

    Returns:
        ``(*, X, Y)`` labels with ``labels``' dtype and type (tensor on its device, or numpy).
    """
    _check_free(free_label, WHITE)
    index = _label_tensor("labels", labels)
    if index.shape[-1] == 0:
        raise ValueError(f"labels: the z axis is empty (shape {tuple(index.shape)})")
    occupied = index != free_label
    height = torch.arange(1, index.shape[-1] + 1, device=index.device)
    top = torch.where(occupied, height, 0).argmax(dim=-1, keepdim=True)  # highest occupied z
    bev = index.gather(-1, top).squeeze(-1)
    bev = torch.where(occupied.any(dim=-1), bev, free_label)
    if isinstance(labels, Tensor):
        return bev.to(labels.dtype)
    return bev.numpy().astype(labels.dtype, copy=False)


# --------------------------------------------------------------------------- plots


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


def _bev_mask(mask: Tensor | np.ndarray) -> np.ndarray:
    """``(X, Y)`` bool: the columns holding a scored voxel of ``mask`` (its shape is the
    labels', checked by the annotations)."""
    scored = torch.as_tensor(mask).cpu()
    return (scored.any(dim=-1) if scored.ndim == 3 else scored).numpy()


def _veil_unscored(ax: Axes, scored: np.ndarray, extent: tuple[float, float, float, float]) -> None:
    """Grey the unscored columns and outline the scored region (image orientation as in
    :func:`plot_bev`: row 0 = highest x, column 0 = highest y)."""
    shown = np.ascontiguousarray(scored[::-1, ::-1])
    veil = np.zeros((*shown.shape, 4))
    veil[~shown] = UNSCORED_RGBA
    ax.imshow(veil, extent=extent, origin="upper", interpolation="nearest")
    if shown.all():
        return
    (y_hi, y_lo, x_lo, x_hi) = extent
    rows, cols = shown.shape
    # cell edges and centres, in the same orientation as the image
    x_edges, y_edges = np.linspace(x_hi, x_lo, rows + 1), np.linspace(y_hi, y_lo, cols + 1)
    # hatched as well as greyed: a grey alone reads like other_flat's grey
    import matplotlib

    with matplotlib.rc_context({"hatch.linewidth": 0.5, "hatch.color": "black"}):
        ax.pcolor(
            y_edges, x_edges, np.ma.masked_where(shown, ~shown), hatch=UNSCORED_HATCH,
            facecolor="none", edgecolor="none", linewidth=0,
        )  # fmt: skip
    if shown.any():
        xs = np.linspace(x_hi, x_lo, rows, endpoint=False) - (x_hi - x_lo) / rows / 2
        ys = np.linspace(y_hi, y_lo, cols, endpoint=False) - (y_hi - y_lo) / cols / 2
        ax.contour(ys, xs, shown.astype(float), levels=[0.5], colors="black", linewidths=0.8)


@typechecked
def plot_occupancy_3d(
    labels: Integer[Tensor, "X Y Z"] | Integer[np.ndarray, "X Y Z"],
    *,
    grid: VoxelGrid | None = None,
    ax: Axes | None = None,
    title: str | None = None,
    max_voxels: int = 50_000,
    marker_size: float | int | None = None,
    elev: float | int = 30.0,
    azim: float | int = 180.0,
    shade: bool = True,
    free_label: int = FREE_LABEL,
) -> Axes:
    """Draw the occupied voxels of a label grid as a 3D scatter in the paper's palette.

    Voxels hidden on all six sides by occupied neighbours are skipped (they cannot be
    seen). If more than ``max_voxels`` remain, a fixed-seed random subset of
    ``max_voxels`` is drawn, so the same input always gives the same picture.

    Args:
        labels: ``(X, Y, Z)`` labels in [0, 17].
        grid: the grid the labels live on (axes in metres). ``None``: the Occ3D grid when
            the shape is (200, 200, 16), else voxel units.
        ax: a 3D axes (``projection="3d"``) to draw into; ``None`` makes a new figure.
        title: axes title.
        max_voxels: the most voxels drawn (speed), an int >= 1.
        marker_size: scatter marker area in points^2; ``None`` sizes markers to the voxels.
        elev: view elevation (degrees).
        azim: view azimuth (degrees); the defaults look forward (+x) from behind and
            above the ego, with +y on the left.
        shade: draw voxels with an occupied voxel right above them (seen only from the
            side) at 70% brightness, so that heights read; voxels whose top is open keep
            the exact palette colour.
        free_label: the empty-space label, not drawn.

    Returns:
        The 3D axes.
    """
    _require_matplotlib()
    _check_free(free_label, WHITE)
    check_int("max_voxels", max_voxels, 1)
    if marker_size is not None:
        check_positive("marker_size", marker_size)
    index = _label_tensor("labels", labels).cpu()
    shape = tuple(index.shape)
    bounds, unit = _extents(grid, shape)
    if ax is None:
        ax = new_figure((6.0, 5.0)).add_subplot(projection="3d")
    elif getattr(ax, "name", None) != "3d":
        raise ValueError("ax: expected a 3D axes, e.g. fig.add_subplot(projection='3d')")
    # an mpl_toolkits.mplot3d Axes3D, which matplotlib ships without type information
    axes3d: Any = ax

    occupied = index != free_label
    padded = torch.zeros(tuple(n + 2 for n in shape), dtype=torch.bool)
    padded[1:-1, 1:-1, 1:-1] = occupied
    hidden = occupied.clone()
    for axis in range(3):
        for start in (0, 2):
            hidden &= padded.narrow(axis, start, shape[axis])[
                tuple(slice(None) if a == axis else slice(1, -1) for a in range(3))
            ]
    covered = occupied & padded[1:-1, 1:-1, 2:]  # an occupied voxel right above
    voxels = (occupied & ~hidden).nonzero()  # (N, 3)
    if voxels.shape[0] > max_voxels:
        generator = torch.Generator().manual_seed(0)
        keep = torch.randperm(voxels.shape[0], generator=generator)[:max_voxels]
        voxels = voxels[keep.sort().values]

    lower = torch.tensor([lo for lo, _ in bounds], dtype=torch.float64)
    size = torch.tensor([(hi - lo) / n for (lo, hi), n in zip(bounds, shape, strict=True)])
    centres = ((voxels.double() + 0.5) * size + lower).numpy()
    colours = colorize_labels(index[tuple(voxels.T)]).numpy() / 255.0
    if shade:  # side-only voxels darker, so that heights read; top faces keep the palette
        colours[covered[tuple(voxels.T)].numpy()] *= 0.7
    if marker_size is None:
        fig = ax.figure.figure  # the root Figure (ax.figure may be a SubFigure)
        width_pt = ax.get_position().width * fig.get_figwidth() * 72.0
        marker_size = max(0.5, (1.4 * width_pt / max(shape[0], shape[1])) ** 2)
    axes3d.scatter(
        centres[:, 0],
        centres[:, 1],
        centres[:, 2],
        c=colours,
        marker="s",
        s=marker_size,
        depthshade=False,
        linewidths=0,
    )
    (x_lo, x_hi), (y_lo, y_hi), (z_lo, z_hi) = bounds
    ax.set_xlim(x_lo, x_hi)
    ax.set_ylim(y_lo, y_hi)
    axes3d.set_zlim(z_lo, z_hi)
    axes3d.set_box_aspect((x_hi - x_lo, y_hi - y_lo, z_hi - z_lo))
    axes3d.view_init(elev=float(elev), azim=float(azim))
    ax.set_xlabel(f"x [{unit}]")
    ax.set_ylabel(f"y [{unit}]")
    axes3d.set_zlabel(f"z [{unit}]")
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


@typechecked
def camera_panels(
    images: Float[Tensor, "V 3 Hi Wi"]
    | Float[np.ndarray, "V 3 Hi Wi"]
    | UInt8[Tensor, "V 3 Hi Wi"]
    | UInt8[np.ndarray, "V 3 Hi Wi"]
    | None = None,
    depth: Float[Tensor, "V Hd Wd"] | Float[np.ndarray, "V Hd Wd"] | None = None,
    semantics: Integer[Tensor, "V Hs Ws"] | Integer[np.ndarray, "V Hs Ws"] | None = None,
    *,
    max_depth: float | int | None = None,
    camera_names: Sequence[str] | None = None,
    depth_cmap: str = "turbo_r",
    legend: bool = True,
    free_label: int = FREE_LABEL,
    free_color: RGB = WHITE,
    panel_width: float | int = 3.0,
) -> Figure:
    """Per-camera panels: one row per kind given (image, depth, semantics), one column
    per camera. For a batch ``(B, V, ...)`` pass one sample, e.g. ``depth[b]``.

    Args:
        images: ``(V, 3, H, W)`` RGB, float in [0, 1] (a 1e-4 overshoot is clipped) or
            uint8 in [0, 255].
        depth: ``(V, H, W)`` depth in metres; pixels that are not finite or <= 0 (nothing
            rendered) are drawn black; values above ``max_depth`` take the far colour.
        semantics: ``(V, H, W)`` labels in [0, 17] (e.g. a rendered argmax), drawn in the
            paper's palette; ``free_label`` pixels in ``free_color``.
        max_depth: top of the depth colour scale (metres); ``None``: the largest valid depth.
        camera_names: V column titles; ``None``: "camera 0", "camera 1", ...
        depth_cmap: matplotlib colormap name for depth (default: near red, far blue).
        legend: with semantics, add a legend of the classes present.
        free_label: the empty-space label.
        free_color: its colour.
        panel_width: width of one panel in inches.

    Returns:
        A new Figure (a depth colour bar on the right of the depth row).
    """
    _require_matplotlib()
    from matplotlib import colormaps

    _check_free(free_label, free_color)
    panel_width = check_positive("panel_width", panel_width)
    offered = {"images": images, "depth": depth, "semantics": semantics}
    given = {name: value for name, value in offered.items() if value is not None}
    if not given:
        raise ValueError("camera_panels: pass at least one of images, depth, semantics")
    first, num_cameras = next((name, value.shape[0]) for name, value in given.items())
    if num_cameras == 0:
        raise ValueError(f"{first}: expected at least one camera (V >= 1), got 0")
    rows = [({"images": "image"}.get(name, name), value) for name, value in given.items()]
    names = [f"camera {v}" for v in range(num_cameras)]
    if camera_names is not None:
        if isinstance(camera_names, str) or len(camera_names) != num_cameras:
            raise ValueError(f"camera_names: expected {num_cameras} names, got {camera_names!r}")
        names = list(camera_names)
    try:
        cmap = colormaps[depth_cmap].with_extremes(bad="black")
    except KeyError:
        raise ValueError(f"depth_cmap: unknown matplotlib colormap {depth_cmap!r}") from None
    if max_depth is not None:
        max_depth = check_positive("max_depth", max_depth)

    aspect = max(v.shape[-2] / max(v.shape[-1], 1) for _, v in rows)
    height = panel_width * aspect * len(rows) + (0.6 if semantics is not None and legend else 0)
    width = panel_width * num_cameras + (0.9 if depth is not None else 0)
    fig = new_figure((width, height + 0.4))
    axes = fig.subplots(len(rows), num_cameras, squeeze=False)
    for row, (kind, data) in enumerate(rows):
        if kind == "image":
            pixels = _float_numpy(data)
            if pixels.dtype == np.uint8:
                pixels = pixels.astype(np.float32) / 255.0
            low, high = float(np.min(pixels)), float(np.max(pixels))
            if not (np.isfinite(low) and np.isfinite(high)) or low < -1e-4 or high > 1 + 1e-4:
                raise ValueError(
                    f"images: expected float values in [0, 1] (or uint8), got [{low}, {high}]"
                )
            panels = np.clip(pixels, 0.0, 1.0).transpose(0, 2, 3, 1)
            for v in range(num_cameras):
                axes[row, v].imshow(panels[v], interpolation="nearest")
        elif kind == "depth":
            values = _float_numpy(data)
            valid = np.isfinite(values) & (values > 0)
            top = max_depth or (float(values[valid].max()) if valid.any() else 1.0)
            masked = np.ma.masked_array(values, mask=~valid)
            drawn = [
                axes[row, v].imshow(
                    masked[v], cmap=cmap, vmin=0.0, vmax=top, interpolation="nearest"
                )
                for v in range(num_cameras)
            ]
            fig.colorbar(drawn[-1], ax=list(axes[row]), label="depth [m]", shrink=0.9)
        else:
            labels = _label_tensor("semantics", data).cpu()
            rgb = colorize_labels(labels, free_label=free_label, free_color=free_color).numpy()
            for v in range(num_cameras):
                axes[row, v].imshow(rgb[v], interpolation="nearest")
            if legend:
                add_class_legend(fig, labels, free_label=free_label)
        axes[row, 0].set_ylabel(kind)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    for v in range(num_cameras):
        axes[0, v].set_title(names[v], fontsize="medium")
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


__all__ = [
    "add_class_legend",
    "bev_labels",
    "camera_panels",
    "colorize_labels",
    "compare_bev",
    "plot_bev",
    "plot_occupancy_3d",
    "save_figure",
]
