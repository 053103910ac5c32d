"""Counting and summarising one benchmark's scores from its :class:`Benchmark` spec: the
voxel protocols (a confusion matrix per protocol, then the protocol's per-class rule and
averaging), RayIoU over the benchmark's class sets, and OpenOcc v2's ray flow error
(mAVE) and OccScore in both of its official variants.

Counts are int64 and pooled; the per-class rules reproduce the official float arithmetic
(float32 where GaussianFormer counts in float32, the per-sample mean where SurroundOcc
averages counts, MonoScene's ``+1e-5``). mAVE keeps one row per sample and adds the rows
in sample order, as the official loops do, so sharding never changes its bits.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from dego.evaluation.benchmarks import MAVE_VARIANTS, Benchmark, VoxelProtocol
from dego.evaluation.layouts import GroundTruth
from dego.metrics.confusion import binary_occupancy_confusion, confusion_matrix
from dego.metrics.rayiou import RayIoUReport, RayIoUSpec
from dego.metrics.report import OccupancyReport, per_class_iou
from dego.raycast import _voxel_rays, cast_product

MONOSCENE_EPSILON = 1e-5


# ----------------------------------------------------------------------------------------
# Voxel protocols
# ----------------------------------------------------------------------------------------


def voxel_counts(
    benchmark: Benchmark, protocol: VoxelProtocol, pred: Tensor, gt: GroundTruth
) -> tuple[Tensor, Tensor]:
    """``(C, C)`` confusion (rows gt) and ``(2, 2)`` occupied/free counts of one sample."""
    mask = None
    for name in protocol.masks:
        mask = gt.masks[name] if mask is None else mask & gt.masks[name]
    confusion = confusion_matrix(
        pred,
        gt.semantics,
        mask,
        num_classes=benchmark.num_classes,
        ignore_label=benchmark.ignore_label,
        removed_classes=protocol.removed_classes,
    )
    return confusion, binary_occupancy_confusion(confusion, benchmark.free_label)


def class_iou(confusion: Tensor, rule: str, samples: int) -> Tensor:
    """Per-class IoU of pooled counts under one of
    :data:`~dego.evaluation.benchmarks.PER_CLASS_RULES`, float64 (see there)."""
    c = confusion.to(torch.int64)
    tp, gt, pred = c.diagonal(), c.sum(1), c.sum(0)
    if rule == "ratio":
        return per_class_iou(c)
    if rule == "sample-mean":  # np.stack(per_sample).mean(0), then a / (b + c - a)
        a, b, p = (v.double() / samples for v in (tp, gt, pred))
        return a / (b + p - a)
    if rule == "absent-is-one-float32":
        a, b, p = tp.float(), gt.float(), pred.float()
        iou = (a / (b + p - a)).double()
        return torch.where(gt == 0, torch.ones_like(iou), iou)
    if rule == "epsilon":
        a, fp, fn = tp.double(), (pred - tp).double(), (gt - tp).double()
        return a / (a + fp + fn + MONOSCENE_EPSILON)
    raise ValueError(f"rule: unknown per-class rule {rule!r}")


def geometric_iou(geometric: Tensor, rule: str, samples: int) -> float:
    """The occupied-vs-free IoU under the protocol's arithmetic (``geometric``: rows gt,
    0 occupied, 1 free)."""
    tp, fn, fp = (int(geometric[0, 0]), int(geometric[0, 1]), int(geometric[1, 0]))
    if rule == "sample-mean":
        a, b, p = tp / samples, (tp + fn) / samples, (tp + fp) / samples
        return a / (b + p - a) if b + p - a else math.nan
    if rule == "absent-is-one-float32":
        t, g, q = (torch.tensor(float(v), dtype=torch.float32) for v in (tp, tp + fn, tp + fp))
        return float(t / (g + q - t))
    if rule == "epsilon":  # MonoScene's completion IoU: 0 when nothing is right
        return tp / (tp + fp + fn) if tp else 0.0
    return tp / (tp + fp + fn) if tp + fp + fn else math.nan


def voxel_report(
    benchmark: Benchmark,
    protocol: VoxelProtocol,
    confusion: Tensor,
    geometric: Tensor,
    samples: int,
    classes: Sequence[int] | None = None,
) -> OccupancyReport:
    """The :class:`~dego.OccupancyReport` of one protocol's pooled counts (``classes``:
    averaged instead of the protocol's)."""
    if int(geometric[:, 1].sum()) == 0 and int(geometric[1].sum()) > 0:
        warnings.warn(
            f"no voxel was predicted free (label {benchmark.free_label}) while the ground "
            "truth has free voxels: were the predictions overlaid with free space?",
            UserWarning,
            stacklevel=3,
        )
    return OccupancyReport.from_per_class(
        class_iou(confusion, protocol.per_class, samples),
        evaluated_classes=protocol.classes if classes is None else classes,
        groups=protocol.class_sets,
        class_names=benchmark.class_names,
        iou=geometric_iou(geometric, protocol.per_class, samples),
        protocol=protocol.name,
        averaging=protocol.averaging,
    )


# ----------------------------------------------------------------------------------------
# Rays: RayIoU over class sets, OpenOcc v2's flow error
# ----------------------------------------------------------------------------------------


def ray_spec(benchmark: Benchmark, class_ids: Sequence[int] | None = None) -> RayIoUSpec:
    """The RayIoU configuration of the benchmark (the first class set unless given)."""
    assert benchmark.ray is not None
    ids = next(iter(benchmark.ray.class_sets.values())) if class_ids is None else class_ids
    return RayIoUSpec.make(
        benchmark.ray.thresholds, benchmark.num_classes, benchmark.free_label, ids, None, None
    )


def ray_reports(
    benchmark: Benchmark, gt: Tensor, pred: Tensor, tp: Tensor, classes: Sequence[int] | None
) -> dict[str, RayIoUReport]:
    """RayIoU over every class set of the benchmark (or only ``classes``), by set name."""
    assert benchmark.ray is not None
    sets = benchmark.ray.class_sets if classes is None else {"--classes": tuple(classes)}
    return {
        name: dataclasses.replace(
            ray_spec(benchmark, ids).report(gt, pred, tp), class_names=benchmark.class_names
        )
        for name, ids in sets.items()
    }


_LABEL_BITS = 32  # labels < 32 share an int64 with their voxel's index in one cast


@functools.lru_cache(maxsize=4)
def _encoding_base(shape: tuple[int, int, int]) -> Tensor:
    """``(index + 1) * 32`` of every voxel of a grid (cached: the grids share a shape)."""
    return (torch.arange(math.prod(shape), dtype=torch.int64).view(shape) + 1) * _LABEL_BITS


def _flat_index(
    index: Tensor, fallback: Tensor, distance: Tensor, origins: Tensor, rays: Tensor, b: Benchmark
) -> Tensor:
    """The flat voxel index each ray reads its flow from: the hit voxel (``index``), or for
    the rays in ``fallback`` (no hit) the last voxel inside the grid, found from the exit
    distance (a ray that grazes an edge may differ from the DVR kernel's choice there),
    or voxel (0, 0, 0) for a ray that never enters (the DVR kernel's ``coord_index``)."""
    index = torch.where(fallback, torch.zeros_like(index), index)
    missed = fallback & (distance >= 0)
    if bool(missed.any()):
        ray_id = missed.nonzero()[:, 0]
        start, unit, metres = _voxel_rays(
            origins[ray_id // rays.shape[0]], rays[ray_id % rays.shape[0]], b.grid, True
        )
        point = start + unit * ((distance[ray_id].double() / metres)[:, None] - 1e-6)
        shape = torch.tensor(b.shape)
        voxel = point.floor().long().clamp(torch.zeros(3, dtype=torch.long), shape - 1)
        index[ray_id] = (voxel[:, 0] * shape[1] + voxel[:, 1]) * shape[2] + voxel[:, 2]
    return index


def cast_with_flow(
    benchmark: Benchmark,
    pred: Tensor,
    gt: Tensor,
    pred_flow: Tensor,
    gt_flow: Tensor,
    origins: Tensor,
    rays: Tensor,
    *,
    missed: str = "scored",
) -> dict[str, Tensor]:
    """Per ray (origin-major, as the official scripts concatenate them): class, distance
    (float32) and flow ``(N, 2)`` of the ground truth and the prediction.

    One traversal serves both grids: each occupied voxel holds ``(index + 1) * 32 +
    label`` (free voxels hold the free label), so the first hit gives the label and the
    voxel whose flow the ray reads. A ray that hits nothing reads the flow of the last
    voxel it crosses (:func:`_flat_index`) where ``missed`` asks for it: ``"scored"``, on
    rays whose ground truth hits something (the only rays scored; OpenOcc v2's server
    script reads their flow); ``"every"``, on every ray (the submission file holds them
    all); ``"none"`` (the dataset script reads flow on true positives only, which hit)."""
    free = benchmark.free_label
    base = _encoding_base(tuple(gt.shape))
    encoded = [torch.where(g != free, base + g, free) for g in (gt, pred)]
    origins = origins.to(torch.float64)
    rays = rays.to(torch.float32)
    distance, value = cast_product(
        encoded, origins, rays, benchmark.grid, free, "OpenOcc v2 RayIoU"
    )
    hits = [v != free for v in value]
    scored = {"scored": hits[0], "every": torch.ones_like(hits[0])}.get(
        missed, torch.zeros_like(hits[0])
    )
    out = {}
    for k, (name, flow) in enumerate((("gt", gt_flow), ("pred", pred_flow))):
        label = torch.where(hits[k], value[k] % _LABEL_BITS, free)
        fallback = scored & ~hits[k]
        index = _flat_index(
            value[k] // _LABEL_BITS - 1, fallback, distance[k], origins, rays, benchmark
        )
        out[f"{name}_cls"] = label
        out[f"{name}_dist"] = distance[k].float()
        out[f"{name}_flow"] = flow.reshape(-1, 2)[index].float()
    return out


def ray_flow_counts(
    benchmark: Benchmark, rays_out: Mapping[str, Tensor], variant: str
) -> tuple[tuple[Tensor, Tensor, Tensor], np.ndarray, np.ndarray]:
    """RayIoU counts ``(gt_count, pred_count, true_positives)`` and this sample's mAVE row
    (flow-error sums as float64 of the float32 ``np.sum``, and ray counts, one per flow
    class) under ``variant`` (:data:`~dego.evaluation.benchmarks.MAVE_VARIANTS`)."""
    if variant not in MAVE_VARIANTS:
        raise ValueError(f"mave: expected one of {list(MAVE_VARIANTS)}, got {variant!r}")
    assert benchmark.ray is not None
    r = {k: v.cpu().numpy() for k, v in rays_out.items()}
    if variant == "server":  # the submission stores distances and flow as float16
        for key in ("gt_dist", "pred_dist", "gt_flow", "pred_flow"):
            r[key] = r[key].astype(np.float16).astype(np.float32)
    gt_cls, pred_cls = r["gt_cls"].astype(np.int64), r["pred_cls"].astype(np.int64)
    valid = gt_cls != benchmark.free_label
    gt_cls, pred_cls = gt_cls[valid], pred_cls[valid]
    error = np.abs(r["pred_dist"][valid] - r["gt_dist"][valid])
    c = benchmark.num_classes
    thresholds = benchmark.ray.thresholds
    same = gt_cls == pred_cls
    tp = np.stack([np.bincount(gt_cls[same & (error < t)], minlength=c) for t in thresholds])
    counts = (
        torch.from_numpy(np.bincount(gt_cls, minlength=c)),
        torch.from_numpy(np.bincount(pred_cls, minlength=c)),
        torch.from_numpy(tp),
    )
    flow_classes = benchmark.ray.flow_classes
    sums = np.zeros(len(flow_classes), dtype=np.float64)
    numbers = np.zeros(len(flow_classes), dtype=np.int64)
    gt_flow, pred_flow = r["gt_flow"][valid], r["pred_flow"][valid]
    close = same & (error < benchmark.ray.mave_threshold)
    all_errors = None
    for i, cls in enumerate(flow_classes):
        tp_mask = close & (gt_cls == cls)
        if not tp_mask.any():
            continue
        if variant == "dataset":
            errors = np.linalg.norm(gt_flow[tp_mask] - pred_flow[tp_mask], axis=1)
        else:
            if all_errors is None:
                all_errors = np.linalg.norm(gt_flow - pred_flow, axis=1)
            errors = all_errors
        sums[i] = float(np.sum(errors))
        numbers[i] = errors.shape[0]
    return counts, sums, numbers


def mave(
    benchmark: Benchmark, rows: Sequence[tuple[np.ndarray, np.ndarray]]
) -> tuple[np.ndarray, float]:
    """Per flow class AVE and mAVE from the samples' rows in sample order: each class's
    sums added one sample at a time in float64 (the official ``ave[j][i] += ...``), divided
    by its ray count (NaN without any), ``nanmean`` over the flow classes."""
    assert benchmark.ray is not None
    f = len(benchmark.ray.flow_classes)
    total, count = np.zeros(f, dtype=np.float64), np.zeros(f, dtype=np.float64)
    for sums, numbers in rows:
        for i in range(f):
            if numbers[i]:
                total[i] += sums[i]
                count[i] += numbers[i]
    with np.errstate(divide="ignore", invalid="ignore"):
        ave = total / count
    finite = ~np.isnan(ave)
    return ave, float(np.nanmean(ave)) if finite.any() else math.nan


def occ_score(rayiou: float, mave_value: float) -> float:
    """OpenOcc v2's OccScore: ``0.9 RayIoU + 0.1 max(1 - mAVE, 0)`` (NaN with mAVE NaN)."""
    if math.isnan(mave_value):
        return math.nan
    return rayiou * 0.9 + max(1 - mave_value, 0.0) * 0.1


__all__ = [
    "cast_with_flow",
    "class_iou",
    "geometric_iou",
    "mave",
    "occ_score",
    "ray_flow_counts",
    "ray_reports",
    "ray_spec",
    "voxel_counts",
    "voxel_report",
]
