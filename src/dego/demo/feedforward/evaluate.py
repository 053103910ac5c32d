"""Score a trained network on held-out scenes at t = 0, what inference sees."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from jaxtyping import Int
from torch import Tensor

from dego._units import percent
from dego.classes import FREE_LABEL, HUMAN_CENTRIC_CLASSES
from dego.demo.evaluate import DYNAMIC_GROUPS, DynamicCounts, dynamic_counts
from dego.demo.feedforward.data import SceneRecord
from dego.demo.feedforward.network import GaussianPredictor, Prediction
from dego.demo.feedforward.training import DepthSource, predict
from dego.demo.fit import most_likely_in
from dego.demo.score import VariantScore, predict_labels
from dego.metrics import OccupancyMetrics, RayIoU

PEOPLE_SCORES = ("people voxels", "people blocks")
"""Two columns that show people being erased before HCM does: the predicted people voxels
as a percentage of the true ones (inside the camera mask; 100 = as many as there are), and
the share of people blocks (reference-frame image blocks whose most frequent pseudo label
is a person or a cycle) whose Gaussian's most likely class is one, percent."""

SCORES = ("IoU", "mIoU", "InsM", "ScnM", "HCM", "RayIoU", "vehicles", "articulated", *PEOPLE_SCORES)
"""The columns of :func:`score_scenes`, percent: weak-protocol IoU, mIoU and class-group
means inside the camera mask, RayIoU@1/2/4, IoU on moving vehicles / on moving
pedestrians and cyclists (their voxels grown by one), all at the reference frame and
pooled over the scenes, and :data:`PEOPLE_SCORES`."""


@dataclasses.dataclass(frozen=True)
class PeopleCounts:
    """Pooled counts behind :data:`PEOPLE_SCORES` (people: :data:`~dego.HUMAN_CENTRIC_CLASSES`).

    Attributes:
        predicted_voxels, true_voxels: people voxels inside the camera mask.
        blocks, blocks_right: people blocks, and those whose Gaussian's argmax is people.
    """

    predicted_voxels: int = 0
    true_voxels: int = 0
    blocks: int = 0
    blocks_right: int = 0

    def __add__(self, other: PeopleCounts) -> PeopleCounts:
        return PeopleCounts(
            *(getattr(self, f.name) + getattr(other, f.name) for f in dataclasses.fields(self))
        )

    def scores(self) -> dict[str, float]:
        """:data:`PEOPLE_SCORES` (NaN where nothing is counted)."""
        return {
            "people voxels": percent(self.predicted_voxels / self.true_voxels)
            if self.true_voxels
            else float("nan"),
            "people blocks": percent(self.blocks_right / self.blocks)
            if self.blocks
            else float("nan"),
        }


def _people(labels: Tensor) -> Tensor:
    return torch.isin(labels, torch.tensor(HUMAN_CENTRIC_CLASSES, device=labels.device))


@torch.no_grad()
def people_counts(
    labels: Int[Tensor, "X Y Z"], prediction: Prediction, record: SceneRecord
) -> PeopleCounts:
    """:class:`PeopleCounts` of one scene: ``labels`` (voxelised) against its ground truth,
    and ``prediction``'s per-block classes (one Gaussian per block, in camera, row, column
    order, as :class:`GaussianPredictor` makes them) against the reference frame's pseudo
    labels."""
    mask = record.mask_camera
    predicted = int((_people(labels.to(mask.device)) & mask).sum())
    true = int((_people(record.occupancy) & mask).sum())
    semantics = record.semantics[record.reference]  # (V, H, W)
    v, h, w = semantics.shape
    n = prediction.logits.shape[1]
    blocks = [2**k for k in range(1, 12) if v * -(-h // 2**k) * -(-w // 2**k) == n]
    if not blocks:
        raise ValueError(
            f"prediction: {n} Gaussians are not one per square block of {v} images of "
            f"{h}x{w} pixels"
        )
    histogram = F.avg_pool2d(
        F.one_hot(semantics, FREE_LABEL + 1).permute(0, 3, 1, 2).float(),
        blocks[0],
        ceil_mode=True,
    )  # (V, K + 1, h', w'): edge blocks count the pixels they have
    block_label = histogram.argmax(1).flatten()  # camera, row, column order
    people_blocks = _people(block_label)
    right = most_likely_in(prediction.logits[0], HUMAN_CENTRIC_CLASSES) & people_blocks
    return PeopleCounts(predicted, true, int(people_blocks.sum()), int(right.sum()))


@torch.no_grad()
def predict_scene_labels(
    network: GaussianPredictor, record: SceneRecord, depth_source: DepthSource = "anchored"
) -> Int[Tensor, "X Y Z"]:
    """The network's occupancy labels of ``record``'s reference frame (voxelised with
    :func:`~dego.demo.predict_labels`)."""
    return predict_labels(predict(network, record, depth_source).gaussians, record.reference_clip())


@torch.no_grad()
def score_scenes(
    labels: Sequence[Tensor],
    records: Sequence[SceneRecord],
    people: Sequence[PeopleCounts] | None = None,
) -> dict[str, float]:
    """:data:`SCORES` of ``labels[i]`` against ``records[i]``'s reference frame, pooled
    (:data:`PEOPLE_SCORES` from ``people``, one per scene; NaN without)."""
    if len(labels) != len(records) or not records:
        raise ValueError(
            f"labels: expected one grid per scene ({len(records)}, at least one), got {len(labels)}"
        )
    if people is not None and len(people) != len(records):
        raise ValueError(
            f"people: expected one count per scene ({len(records)}), got {len(people)}"
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
    row |= {name: percent(counts.iou) for name, counts in dynamic.items()}
    if people is None:
        return row | dict.fromkeys(PEOPLE_SCORES, float("nan"))
    return row | sum(people, PeopleCounts()).scores()


@torch.no_grad()
def predict_scene(
    network: GaussianPredictor, record: SceneRecord, depth_source: DepthSource = "anchored"
) -> tuple[Int[Tensor, "X Y Z"], PeopleCounts]:
    """:func:`predict_scene_labels` and the scene's :func:`people_counts`, from one
    forward pass."""
    prediction = predict(network, record, depth_source)
    labels = predict_labels(prediction.gaussians, record.reference_clip())
    return labels, people_counts(labels, prediction, record)


@torch.no_grad()
def evaluate(
    network: GaussianPredictor,
    records: Sequence[SceneRecord],
    depth_source: DepthSource = "anchored",
) -> dict[str, float]:
    """:func:`score_scenes` of ``network``'s predictions on ``records``, with
    :data:`PEOPLE_SCORES`."""
    network.eval()
    labels, people = zip(*(predict_scene(network, r, depth_source) for r in records), strict=True)
    return score_scenes(labels, records, people)
