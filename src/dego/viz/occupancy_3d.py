"""3D pictures of label grids: the visible occupied voxels as a scatter in the palette.

Orientation (ego frame, x forward, y left, z up): the view looks forward from behind and
above the ego by default.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from jaxtyping import Integer
from torch import Tensor

from dego._checks import check_int, check_positive
from dego._typing import typechecked
from dego.classes import FREE_LABEL
from dego.grid import VoxelGrid
from dego.viz._figure import _require_matplotlib, new_figure
from dego.viz._labels import WHITE, _check_free, _extents, _label_tensor
from dego.viz.colors import colorize_labels

if TYPE_CHECKING:
    from matplotlib.axes import Axes
else:  # matplotlib is optional and imported inside the functions; the run-time check sees Any
    Axes = Any


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
