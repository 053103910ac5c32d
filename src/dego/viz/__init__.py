"""Pictures of occupancy grids and camera renders, in the DeGO paper's palette.

Bird's-eye (BEV) and 3D views of Occ3D-style label grids, prediction vs ground truth
side by side, and per-camera image / depth / semantics panels. The plotting functions
need the optional extra ``dego-occupancy[viz]`` (matplotlib), imported lazily so that
``import dego`` never needs it; :func:`colorize_labels` and :func:`bev_labels` are plain
torch/numpy.

Figures are built with :class:`matplotlib.figure.Figure` on an Agg canvas, never through
pyplot: nothing opens a window and the global backend is left alone. Save them with
:func:`save_figure`. Every function accepts torch tensors (CPU or GPU; moved to the CPU
for drawing) or numpy arrays. Labels take any integer dtype and must lie in [0, 17];
pictures are in the ego frame (x forward, y left, z up), BEV with +x up the page.

Modules: ``colors`` (:func:`colorize_labels`, :func:`bev_labels`), ``bev``
(:func:`plot_bev`, :func:`compare_bev`), ``occupancy_3d`` (:func:`plot_occupancy_3d`),
``cameras`` (:func:`camera_panels`), ``legend`` (:func:`add_class_legend`), ``_figure``
(:func:`new_figure`, :func:`save_figure`, :func:`png_bytes`), ``_labels`` (the label and
palette checks, the label dtypes accepted), ``_veil`` (the grey, hatched veil over
unscored columns); ``rerun``, ``eval_recording`` and ``viewer``: recordings for rerun's
viewer.
"""

from dego.viz._figure import new_figure, png_bytes, save_figure
from dego.viz._labels import RGB as RGB
from dego.viz._labels import WHITE as WHITE
from dego.viz._veil import UNSCORED_HATCH, UNSCORED_RGBA
from dego.viz.bev import compare_bev, plot_bev
from dego.viz.cameras import camera_panels
from dego.viz.colors import bev_labels, colorize_labels
from dego.viz.legend import add_class_legend
from dego.viz.occupancy_3d import plot_occupancy_3d

__all__ = [
    "UNSCORED_HATCH",
    "UNSCORED_RGBA",
    "add_class_legend",
    "bev_labels",
    "camera_panels",
    "colorize_labels",
    "compare_bev",
    "new_figure",
    "plot_bev",
    "plot_occupancy_3d",
    "png_bytes",
    "save_figure",
]
