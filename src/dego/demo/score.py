"""Voxelise fitted Gaussians and score them against the clip's ground truth."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Protocol

import torch
from jaxtyping import Int
from torch import Tensor

from dego._units import percent
from dego.demo.clip import DemoClip
from dego.gaussians import GaussianSet
from dego.metrics import OccupancyMetrics, OccupancyReport, RayIoU, RayIoUReport
from dego.voxelizer import voxelize

OCCUPANCY_THRESHOLD = 0.3
"""A voxel is occupied when the Gaussians' summed density ``sum_i o_i g_i`` at its
centre reaches this; chosen a priori (about one half-opaque Gaussian within 1 sigma),
not tuned on the ground truth."""


@torch.no_grad()
def predict_labels(
    gaussians: GaussianSet, clip: DemoClip, threshold: float = OCCUPANCY_THRESHOLD
) -> Int[Tensor, "X Y Z"]:
    """Occ3D labels of ``(1, N)`` Gaussians whose features are class probabilities.

    Additive voxelisation over each Gaussian's 3-sigma ellipsoid; label = argmax of the
    density-weighted probabilities where the density reaches ``threshold``, free elsewhere.
    """
    voxels = voxelize(gaussians.detach(), clip.grid)
    return voxels.labels(threshold=threshold, label_offset=0)[0]


@dataclasses.dataclass(frozen=True)
class VariantScore:
    """Scores of one label grid: weak-protocol voxel metrics and RayIoU."""

    occupancy: OccupancyReport
    rayiou: RayIoUReport

    def row(self) -> dict[str, float]:
        """``{"IoU", "mIoU", "InsM", "ScnM", "HCM", "RayIoU"}`` in percent."""
        report = self.occupancy
        values = {
            "IoU": report.iou,
            "mIoU": report.miou,
            "InsM": report.insm,
            "ScnM": report.scnm,
            "HCM": report.hcm,
            "RayIoU": self.rayiou.rayiou,
        }
        return {name: percent(value) for name, value in values.items()}


@torch.no_grad()
def score_labels(labels: Int[Tensor, "X Y Z"], clip: DemoClip) -> VariantScore:
    """Weak-protocol :class:`~dego.OccupancyMetrics` (camera mask) and RayIoU@1/2/4 of
    labels at the reference frame."""
    target = clip.occupancy[clip.reference].cpu()
    metrics = OccupancyMetrics("weak")
    metrics.update(labels.cpu(), target, clip.mask_camera[clip.reference].cpu())
    ray_metric = RayIoU()
    ray_metric.update(labels.cpu(), target, clip.ray_origins.cpu())
    return VariantScore(metrics.compute(), ray_metric.compute())


class _Scored(Protocol):
    def row(self) -> dict[str, float]: ...


def format_table(rows: Mapping[str, _Scored], seconds: dict[str, float] | None = None) -> str:
    """A Markdown table with one row per variant: the columns of the scores' ``row()``
    (percent; NaN where undefined; a column NaN in every row, such as ``t=±2+`` of a
    3-frame clip, is left out), and the fit time where ``seconds`` has one."""
    values = {name: score.row() for name, score in rows.items()}
    columns = list(next(iter(values.values()))) if values else []
    columns = [c for c in columns if not all(math.isnan(row[c]) for row in values.values())]
    head = "| variant | " + " | ".join(columns) + (" | fit (s) |" if seconds else " |")
    rule = "|---|" + "---:|" * (len(columns) + (1 if seconds else 0))
    lines = [head, rule]
    for name, row in values.items():
        cells = [_cell(row[c]) for c in columns]
        if seconds:
            cells.append(f"{seconds[name]:.1f}" if name in seconds else "-")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _cell(value: float) -> str:
    return "nan" if math.isnan(value) else f"{value:.2f}"
