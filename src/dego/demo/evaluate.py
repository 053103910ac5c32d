"""4D evaluation: score fitted Gaussians at every frame of a clip, and on moving agents.

At frame t the canonical Gaussians are deformed to t's time offset (not at all for the
``static`` variant), moved from the world (reference ego) frame into frame t's ego
coordinates, voxelised and scored against frame t's ground truth and camera mask.
"""

from __future__ import annotations

import dataclasses
import math

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Int
from torch import Tensor

from dego._units import percent
from dego.classes import FREE_LABEL, HUMAN_CENTRIC_CLASSES
from dego.deformation import DecoupledDeformation
from dego.demo.clip import DemoClip, backproject
from dego.demo.fit import gaussians_at
from dego.demo.model import VEHICLE_CLASSES, GaussianSceneModel
from dego.demo.offsets import FrameOffsets
from dego.demo.score import OCCUPANCY_THRESHOLD, VariantScore, predict_labels, score_labels
from dego.gaussians import GaussianSet
from dego.metrics import OccupancyMetrics, OccupancyReport

DYNAMIC_GROUPS: dict[str, tuple[int, ...]] = {
    "vehicles": VEHICLE_CLASSES,
    "articulated": HUMAN_CENTRIC_CLASSES,
}
"""Moving agents scored on their own: rigid movers (bus, car, construction vehicle,
trailer, truck) and articulated agents (bicycle, motorcycle, pedestrian: riders and
walkers whose limbs move)."""

LIFT_SCALE = 0.1
"""Metres: the standard deviation of each Gaussian of :func:`lift_labels`."""


@dataclasses.dataclass(frozen=True)
class DynamicCounts:
    """Voxel counts of one group of moving agents, near those agents.

    Attributes:
        intersection: voxels where the prediction equals the ground truth's agent class.
        target: ground-truth voxels of the group's classes.
        predicted: predicted voxels of the group's classes.
    """

    intersection: int = 0
    target: int = 0
    predicted: int = 0

    def __add__(self, other: DynamicCounts) -> DynamicCounts:
        return DynamicCounts(
            self.intersection + other.intersection,
            self.target + other.target,
            self.predicted + other.predicted,
        )

    @property
    def iou(self) -> float:
        """``intersection / (target + predicted - intersection)``; NaN if both are empty."""
        union = self.target + self.predicted - self.intersection
        return self.intersection / union if union else math.nan


def dynamic_regions(clip: DemoClip, index: int) -> dict[str, Bool[Tensor, "X Y Z"]]:
    """Per group of :data:`DYNAMIC_GROUPS`: the voxels of frame ``index``'s moving agents
    of that group, grown by one voxel (so that predictions beside an agent count as
    false positives), inside the camera mask."""
    ids = clip.instances[index]
    agent = (ids - 1).clamp_min(0)
    moving = (ids > 0) & clip.agent_moving.to(ids.device)[agent]
    articulated = clip.agent_articulated.to(ids.device)[agent]
    regions = {}
    for name, members in (
        ("vehicles", moving & ~articulated),
        ("articulated", moving & articulated),
    ):
        grown = F.max_pool3d(members[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
        regions[name] = grown & clip.mask_camera[index]
    return regions


def dynamic_counts(
    labels: Int[Tensor, "X Y Z"], clip: DemoClip, index: int
) -> dict[str, DynamicCounts]:
    """:class:`DynamicCounts` of ``labels`` against frame ``index`` in each dynamic region."""
    target_labels = clip.occupancy[index]
    labels = labels.to(target_labels.device)
    counts = {}
    for name, region in dynamic_regions(clip, index).items():
        classes = torch.tensor(DYNAMIC_GROUPS[name], device=labels.device)
        target = torch.isin(target_labels, classes) & region
        predicted = torch.isin(labels, classes) & region
        counts[name] = DynamicCounts(
            int((target & (labels == target_labels)).sum()),
            int(target.sum()),
            int(predicted.sum()),
        )
    return counts


@torch.no_grad()
def predict_clip(
    model: GaussianSceneModel,
    deformation: DecoupledDeformation | FrameOffsets | None,
    clip: DemoClip,
    threshold: float = OCCUPANCY_THRESHOLD,
) -> Int[Tensor, "T X Y Z"]:
    """Labels at every frame: deform to t, move into t's ego frame, voxelise."""
    frames = []
    for index in range(clip.num_frames):
        gaussians, _ = gaussians_at(model, deformation, clip, index)
        frames.append(predict_labels(to_ego(gaussians, clip, index), clip, threshold))
    return torch.stack(frames)


def to_ego(gaussians: GaussianSet, clip: DemoClip, index: int) -> GaussianSet:
    """World (reference ego) Gaussians in frame ``index``'s ego coordinates."""
    return gaussians.transformed(torch.linalg.inv(clip.ego_poses[index].double()).float())


@torch.no_grad()
def lift_labels(clip: DemoClip, index: int, scale: float = LIFT_SCALE) -> GaussianSet:
    """The "lifted labels" ceiling: one opaque isotropic Gaussian of std ``scale`` per
    supervised surface pixel of frame ``index`` at its pseudo depth, its features the
    one-hot pseudo label, in frame ``index``'s ego coordinates. No learning at all."""
    surface = clip.supervised[index] & (clip.depth[index] > 0)
    surface &= clip.semantics[index] < FREE_LABEL
    points = backproject(clip.depth[index], clip.world_to_cam[index], clip.intrinsics[index])
    means = points[surface]
    n = means.shape[0]
    quats = torch.zeros(n, 4, dtype=means.dtype, device=means.device)
    quats[:, 0] = 1
    world = GaussianSet(
        means=means[None],
        quats=quats[None],
        scales=torch.full_like(means, scale)[None],
        opacities=torch.ones(1, n, dtype=means.dtype, device=means.device),
        features=F.one_hot(clip.semantics[index][surface], FREE_LABEL).to(means.dtype)[None],
    )
    return to_ego(world, clip, index)


OFFSET_GROUPS: tuple[str, ...] = ("t=±1", "t=±2+")
"""How the frames other than the reference are pooled: one frame from it (offset +-1) and
two or more (in the demo's 5-frame clips: exactly +-2). Pooling them together hid how fast
a fit's gain falls with the offset."""


def offset_group(offset: float) -> str | None:
    """The :data:`OFFSET_GROUPS` entry of a frame offset (``None`` for the reference)."""
    if offset == 0:
        return None
    return OFFSET_GROUPS[0] if abs(offset) == 1 else OFFSET_GROUPS[1]


@dataclasses.dataclass(frozen=True)
class ClipScore:
    """Scores of one variant over a clip.

    Attributes:
        reference: the reference frame's weak-protocol metrics and RayIoU.
        others: per :data:`OFFSET_GROUPS` entry, weak-protocol metrics pooled over its
            frames (``None`` where the clip has none: a 3-frame clip has no +-2).
        dynamic: per group of :data:`DYNAMIC_GROUPS`, :class:`DynamicCounts` at the
            reference frame (``"reference"``) and pooled per :data:`OFFSET_GROUPS` entry.
    """

    reference: VariantScore
    others: dict[str, OccupancyReport | None]
    dynamic: dict[str, dict[str, DynamicCounts]]

    def row(self) -> dict[str, float]:
        """The demo table's columns, percent (NaN where undefined)."""
        values = dict(self.reference.row())
        for metric in ("mIoU", "HCM"):
            for scope in OFFSET_GROUPS:
                report = self.others.get(scope)
                value = getattr(report, metric.lower()) if report is not None else math.nan
                values[f"{metric} {scope}"] = percent(value)
        for name in DYNAMIC_GROUPS:
            for scope in OFFSET_GROUPS:
                values[f"{name} {scope}"] = percent(self.dynamic[name][scope].iou)
        return values


@torch.no_grad()
def score_clip(labels: Int[Tensor, "T X Y Z"], clip: DemoClip) -> ClipScore:
    """Score labels predicted at every frame of ``clip`` (:func:`predict_clip`)."""
    if labels.shape[0] != clip.num_frames:
        raise ValueError(
            f"labels: expected one grid per frame ({clip.num_frames}), got {labels.shape[0]}"
        )
    others = {scope: OccupancyMetrics("weak") for scope in OFFSET_GROUPS}
    seen: set[str] = set()
    scopes = ("reference", *OFFSET_GROUPS)
    dynamic = {name: dict.fromkeys(scopes, DynamicCounts()) for name in DYNAMIC_GROUPS}
    for index, offset in enumerate(clip.times.tolist()):
        scope = offset_group(offset) if index != clip.reference else None
        if scope is not None:
            seen.add(scope)
            others[scope].update(
                labels[index].cpu(), clip.occupancy[index].cpu(), clip.mask_camera[index].cpu()
            )
        for name, counts in dynamic_counts(labels[index], clip, index).items():
            key = scope or "reference"
            dynamic[name][key] = dynamic[name][key] + counts
    return ClipScore(
        reference=score_labels(labels[clip.reference], clip),
        others={s: (others[s].compute() if s in seen else None) for s in OFFSET_GROUPS},
        dynamic=dynamic,
    )


def lifted_clip_labels(clip: DemoClip) -> Int[Tensor, "T X Y Z"]:
    """:func:`lift_labels` voxelised at every frame: the ceiling row of the demo table."""
    return torch.stack(
        [predict_labels(lift_labels(clip, index), clip) for index in range(clip.num_frames)]
    )
