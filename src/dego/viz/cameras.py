"""Per-camera panels: images, depth and semantics, one column per camera."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from jaxtyping import Float, Integer, UInt8
from torch import Tensor

from dego._checks import check_positive
from dego._typing import typechecked
from dego.classes import FREE_LABEL
from dego.viz._figure import _require_matplotlib, new_figure
from dego.viz._labels import RGB, WHITE, _check_free, _label_tensor
from dego.viz.colors import colorize_labels
from dego.viz.legend import add_class_legend

if TYPE_CHECKING:
    from matplotlib.figure import Figure
else:  # matplotlib is optional and imported inside the functions; the run-time check sees Any
    Figure = Any


def _float_numpy(x: Tensor | np.ndarray) -> np.ndarray:
    if isinstance(x, Tensor):
        x = x.detach().cpu()
        return (x if x.dtype == torch.uint8 else x.float()).numpy()
    x = np.asarray(x)
    return x.astype(np.float32) if x.dtype == np.float16 else x  # matplotlib has no float16


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
