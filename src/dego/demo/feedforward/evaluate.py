"""Score a trained network on held-out scenes at t = 0, what inference sees."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from jaxtyping import Int
from torch import Tensor

from dego._units import percent
from dego.demo.evaluate import DYNAMIC_GROUPS, DynamicCounts, dynamic_counts
from dego.demo.feedforward.data import SceneRecord
from dego.demo.feedforward.network import GaussianPredictor
from dego.demo.feedforward.training import predict
from dego.demo.score import VariantScore, predict_labels
from dego.metrics import OccupancyMetrics, RayIoU

SCORES = ("IoU", "mIoU", "InsM", "ScnM", "HCM", "RayIoU", "vehicles", "articulated")
"""The columns of :func:`score_scenes`, percent: weak-protocol IoU, mIoU and class-group
means inside the camera mask, RayIoU@1/2/4, and IoU on moving vehicles / on moving
pedestrians and cyclists (their voxels grown by one), all at the reference frame and
pooled over the scenes."""


@torch.no_grad()
def predict_scene_labels(network: GaussianPredictor, record: SceneRecord) -> Int[Tensor, "X Y Z"]:
    """The network's occupancy labels of ``record``'s reference frame (voxelised with
    :func:`~dego.demo.predict_labels`)."""
    return predict_labels(predict(network, record).gaussians, record.reference_clip())


@torch.no_grad()
def score_scenes(labels: Sequence[Tensor], records: Sequence[SceneRecord]) -> dict[str, float]:
    """:data:`SCORES` of ``labels[i]`` against ``records[i]``'s reference frame, pooled."""
    if len(labels) != len(records) or not records:
        raise ValueError(
            f"labels: expected one grid per scene ({len(records)}, at least one), got {len(labels)}"
        )
    occupancy, rays = OccupancyMetrics("weak"), RayIoU()
    dynamic = dict.fromkeys(DYNAMIC_GROUPS, DynamicCounts())
    for grid, record in zip(labels, records, strict=True):
        clip = record.reference_clip()
        target = record.occupancy.cpu()
        occupancy.update(grid.cpu(), target, record.mask_camera.cpu())
        rays.update(grid.cpu(), target, record.ray_origins.cpu())
        for name, counts in dynamic_counts(grid, clip, 0).items():
            dynamic[name] = dynamic[name] + counts
    row = VariantScore(occupancy.compute(), rays.compute()).row()
    return row | {name: percent(counts.iou) for name, counts in dynamic.items()}


def evaluate(network: GaussianPredictor, records: Sequence[SceneRecord]) -> dict[str, float]:
    """:func:`score_scenes` of ``network``'s predictions on ``records``."""
    network.eval()
    return score_scenes([predict_scene_labels(network, r) for r in records], records)
