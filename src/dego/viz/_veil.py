"""The veil over BEV columns outside the scored region (e.g. Occ3D's ``mask_camera``):
grey and hatched, so that "not scored" is not read as a class's colour.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

if TYPE_CHECKING:
    from matplotlib.axes import Axes
else:  # matplotlib is optional and imported inside the functions; the run-time check sees Any
    Axes = Any

UNSCORED_RGBA = (0.45, 0.45, 0.45, 0.55)
"""The grey veil :func:`plot_bev` lays over columns outside its ``mask`` (RGBA, 0-1)."""
UNSCORED_HATCH = "////"
"""The hatch drawn over that veil, so that "not scored" is not read as ``other_flat``'s grey."""


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
    # hatched as well as greyed: a grey alone reads like other_flat's grey. One path of
    # row runs, hatched once (a hatched quad per cell took seconds per panel).
    import matplotlib
    from matplotlib.collections import PathCollection

    with matplotlib.rc_context({"hatch.linewidth": 0.5, "hatch.color": "black"}):
        hatched = PathCollection(
            [_runs_path(~shown, x_edges, y_edges)],
            facecolors="none", edgecolors="none", linewidths=0, hatch=UNSCORED_HATCH,
            transform=ax.transData,
        )  # fmt: skip
        ax.add_collection(hatched, autolim=False)
    if shown.any():
        xs = np.linspace(x_hi, x_lo, rows, endpoint=False) - (x_hi - x_lo) / rows / 2
        ys = np.linspace(y_hi, y_lo, cols, endpoint=False) - (y_hi - y_lo) / cols / 2
        ax.contour(ys, xs, shown.astype(float), levels=[0.5], colors="black", linewidths=0.8)


def _runs_path(cells: np.ndarray, x_edges: np.ndarray, y_edges: np.ndarray) -> Any:
    """One matplotlib ``Path`` of rectangles covering the ``True`` cells of ``cells``
    (rows x columns), a rectangle per run of neighbouring cells in a row; row ``r`` spans
    ``x_edges[r : r + 2]``, column ``c`` spans ``y_edges[c : c + 2]`` (plot x = y_edges)."""
    from matplotlib.path import Path

    padded = np.pad(cells.astype(np.int8), ((0, 0), (1, 1)))
    change = np.diff(padded, axis=1)
    rows, starts = np.nonzero(change == 1)
    _, ends = np.nonzero(change == -1)  # same row-major order: run k starts and ends
    left, right = y_edges[starts], y_edges[ends]
    top, bottom = x_edges[rows], x_edges[rows + 1]
    corners = np.stack(
        [
            np.stack([left, top], -1),
            np.stack([right, top], -1),
            np.stack([right, bottom], -1),
            np.stack([left, bottom], -1),
            np.stack([left, top], -1),
        ],
        1,
    )  # (runs, 5, 2)
    codes = np.tile(
        [Path.MOVETO, Path.LINETO, Path.LINETO, Path.LINETO, Path.CLOSEPOLY], len(corners)
    )
    return Path(corners.reshape(-1, 2), codes.astype(Path.code_type))
