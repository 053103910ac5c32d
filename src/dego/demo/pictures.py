"""The demo's pictures: BEV prediction vs ground truth, one camera's renders, loss curves.

Needs matplotlib (``pip install -e ".[viz]"`` from the clone). Each ``*_figure`` function
draws a Figure; :func:`png_bytes` (from :mod:`dego.viz`) encodes one, so that ``dego demo``
writes its pictures with its results, all or nothing (:func:`dego._atomic.write_files`);
each ``*_picture`` function writes one PNG file atomically.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from jaxtyping import Int
from torch import Tensor

from dego._atomic import write_bytes
from dego._units import percent_text
from dego.classes import FREE_LABEL
from dego.data.synthetic import CAMERAS
from dego.demo.clip import DemoClip
from dego.demo.fit import LOSS_TERMS, FitResult, gaussians_at, render
from dego.metrics import OccupancyMetrics
from dego.viz import colorize_labels, compare_bev, new_figure, png_bytes

CAMERA = 0  # CAM_FRONT


def bev_picture(
    labels: Int[Tensor, "X Y Z"], clip: DemoClip, variant: str, path: Path, index: int | None = None
) -> Path:
    """Write :func:`bev_figure` to ``path`` (PNG, atomically)."""
    return write_bytes(path, png_bytes(bev_figure(labels, clip, variant, index)))


def camera_picture(result: FitResult, clip: DemoClip, path: Path, camera: int = CAMERA) -> Path:
    """Write :func:`camera_figure` to ``path`` (PNG, atomically)."""
    return write_bytes(path, png_bytes(camera_figure(result, clip, camera)))


def loss_picture(results: list[FitResult], path: Path) -> Path:
    """Write :func:`loss_figure` to ``path`` (PNG, atomically)."""
    return write_bytes(path, png_bytes(loss_figure(results)))


def bev_figure(
    labels: Int[Tensor, "X Y Z"], clip: DemoClip, variant: str, index: int | None = None
) -> Any:
    """Top-down prediction next to the ground truth of frame ``index`` (default: the
    reference frame), in that frame's ego coordinates. Columns outside the camera mask
    (not scored) are greyed; the prediction's title carries its weak-protocol IoU and
    mIoU on this frame (the demo table's metrics, for this frame alone)."""
    index = clip.reference if index is None else index
    offset = int(clip.times[index])
    target, scored = clip.occupancy[index].cpu(), clip.mask_camera[index].cpu()
    metrics = OccupancyMetrics("weak")
    metrics.update(labels.cpu(), target, scored)
    report = metrics.compute()
    score = f"IoU {percent_text(report.iou)}, mIoU {percent_text(report.miou)} (%, weak)"
    return compare_bev(
        labels.cpu(),
        target,
        grid=clip.grid,
        titles=(
            f"{variant}: prediction, t = {offset:+d}\n{score}",
            f"ground truth, t = {offset:+d}\nhatched: outside the camera mask",
        ),
        mask=scored,
    )


@torch.no_grad()
def camera_figure(result: FitResult, clip: DemoClip, camera: int = CAMERA) -> Any:
    """Pseudo labels vs the fitted Gaussians' render, depth and semantics, of one camera
    (default ``CAM_FRONT``) at the reference frame; the figure's title names both."""
    if not 0 <= camera < len(CAMERAS):
        raise ValueError(f"camera: expected an index in [0, {len(CAMERAS) - 1}], got {camera!r}")
    index = clip.reference
    gaussians, _ = gaussians_at(result.model, result.deformation, clip, index)
    rendered = render(gaussians, clip, index, torch.tensor([camera]))  # that camera only
    probabilities = torch.cat([rendered.features[0], 1 - rendered.alpha[0][:, None]], 1)
    semantics = probabilities.argmax(1)[0].cpu()
    assert rendered.depth is not None  # splat renders the expected depth by default
    depth = torch.where(rendered.alpha[0, 0] > 0.5, rendered.depth[0, 0], 0).cpu()
    pseudo_depth = clip.depth[index, camera].cpu()
    far = float(pseudo_depth.max().clamp_min(1))

    figure = new_figure((9.0, 3.9))
    figure.suptitle(
        f"{CAMERAS[camera][0]} (camera {camera}), frame t = {int(clip.times[index]):+d} "
        f"(the reference frame, {index + 1} of {clip.num_frames})",
        fontsize=10,
    )
    axes = figure.subplots(2, 2)
    panels = [
        (pseudo_depth, "pseudo depth", "depth"),
        (depth, f"{result.variant}: rendered depth (alpha > 0.5)", "depth"),
        (clip.semantics[index, camera].cpu(), "pseudo semantics", "labels"),
        (semantics, f"{result.variant}: rendered semantics", "labels"),
    ]
    for ax, (image, title, kind) in zip(axes.flat, panels, strict=True):
        if kind == "depth":
            shown = ax.imshow(
                torch.where(image > 0, image, float("nan")).numpy(),
                cmap="turbo_r",
                vmin=0,
                vmax=far,
            )
            figure.colorbar(shown, ax=ax, shrink=0.8, label="m")
        else:
            ax.imshow(colorize_labels(image.clamp(0, FREE_LABEL)).numpy())
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
    return figure


def loss_figure(results: list[FitResult]) -> Any:
    """Every loss term of every variant against the iteration (log scale)."""
    terms = [term for term in LOSS_TERMS if term != "total"]
    figure = new_figure((3.2 * len(terms), 2.8))
    axes = figure.subplots(1, len(terms))
    for ax, term in zip(axes, terms, strict=True):
        for result in results:
            values = torch.tensor(result.history[term])
            window = max(1, len(values) // 20)  # a moving average: one frame per step is noisy
            smooth = values.unfold(0, window, 1).mean(-1) if len(values) >= window else values
            ax.plot(range(window - 1, window - 1 + len(smooth)), smooth, label=result.variant)
        ax.set_title(term, fontsize=9)
        ax.set_xlabel("iteration")
        if term != "deformation":
            ax.set_yscale("log")
        ax.legend(fontsize=8)
    return figure
