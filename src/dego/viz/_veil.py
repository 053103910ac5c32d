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
