"""OccupancyMetrics: dataset-level voxel IoU / mIoU under the Occ3D and weak protocols."""

from __future__ import annotations

import dataclasses
import enum
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from dego._typing import typechecked
from dego.classes import CLASS_GROUPS, FREE_LABEL, NUM_CLASSES, PROTOCOL_CLASSES
from dego.metrics.confusion import (
    binary_occupancy_confusion,
    check_ignore_label,
    confusion_matrix,
)
from dego.metrics.counts import CountingMetric, class_names
from dego.metrics.report import OccupancyReport, per_class_iou

WEAK_REMOVED_CLASSES = (0, 12)
"""GT classes whose voxels the weakly supervised protocol removes (others, other_flat)."""
SURROUNDOCC_REMOVED_CLASSES = (0,)
"""GT classes whose voxels the SurroundOcc protocol removes (0: noise)."""
_REMOVED_CLASSES = {"weak": WEAK_REMOVED_CLASSES, "surroundocc": SURROUNDOCC_REMOVED_CLASSES}
CAMERA_MASK_PROTOCOLS = ("occ3d", "weak")
"""Protocols scored inside the camera mask (Occ3D's ``mask_camera``): their ``update`` needs
``mask`` (the camera mask, or ``mask=None`` explicitly to score every voxel)."""


class Omitted(enum.Enum):
    """The default of ``update``'s ``mask``: not passed (``None`` is an explicit choice)."""

    MASK = "omitted"

    def __repr__(self) -> str:
        return "<omitted>"


OMITTED = Omitted.MASK


@dataclasses.dataclass(frozen=True, eq=False)
class OccupancySpec:
    """A validated occupancy configuration and its two steps, shared by
    :class:`OccupancyMetrics` and ``dego.compat.torchmetrics.OccupancyMetric``: counting one
    batch (:meth:`counts`) and summarising pooled counts (:meth:`report`)."""

    protocol: str
    num_classes: int
    free_label: int
    ignore_label: int | None
    groups: Mapping[str, tuple[int, ...]]
    evaluated_classes: tuple[int, ...]
    removed_classes: tuple[int, ...]

    @classmethod
    def make(
        cls,
        protocol: str,
        num_classes: int,
        free_label: int,
        ignore_label: int | None,
        groups: Mapping[str, Sequence[int]] | None,
    ) -> OccupancySpec:
        """Check the arguments of :class:`OccupancyMetrics` (errors name them)."""
        if protocol not in PROTOCOL_CLASSES:
            raise ValueError(
                f"protocol: expected one of {sorted(PROTOCOL_CLASSES)}, got {protocol!r}"
            )
        if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 2:
            raise ValueError(f"num_classes: expected an int >= 2, got {num_classes!r}")
        if not 0 <= free_label < num_classes:
            raise ValueError(f"free_label: {free_label} must lie in 0..{num_classes - 1}")
        ignore_label = check_ignore_label(ignore_label, num_classes)
        if protocol != "occ3d" and (num_classes, free_label) != (NUM_CLASSES, FREE_LABEL):
            raise ValueError(
                f"protocol: {protocol!r} is defined on 18 labels "
                f"(num_classes=18, free_label=17), got num_classes={num_classes}, "
                f"free_label={free_label}"
            )
        if groups is None:
            groups = CLASS_GROUPS if num_classes == NUM_CLASSES else {}
        for name, ids in groups.items():
            if any(not 0 <= int(i) < num_classes for i in ids):
                raise ValueError(
                    f"groups: group {name!r} has ids {list(ids)} outside 0..{num_classes - 1}"
                )
        if protocol in _REMOVED_CLASSES:
            evaluated = PROTOCOL_CLASSES[protocol]
            removed: tuple[int, ...] = _REMOVED_CLASSES[protocol]
        else:
            evaluated = tuple(c for c in range(num_classes) if c != free_label)
            removed = ()
        return cls(
            protocol=protocol,
            num_classes=num_classes,
            free_label=free_label,
            ignore_label=ignore_label,
            groups={name: tuple(int(i) for i in ids) for name, ids in groups.items()},
            evaluated_classes=tuple(evaluated),
            removed_classes=removed,
        )

    @property
    def class_names(self) -> tuple[str, ...]:
        return class_names(self.num_classes)

    def config(self) -> dict[str, Any]:
        """The configuration as plain data (compared by merge / load_state_dict, saved)."""
        return {
            "protocol": self.protocol,
            "num_classes": self.num_classes,
            "free_label": self.free_label,
            "ignore_label": self.ignore_label,
            "groups": {k: list(v) for k, v in self.groups.items()},
        }

    def count_shapes(self) -> dict[str, tuple[int, ...]]:
        """The shapes of the int64 counts, by name (the state of both metric classes)."""
        return {"confusion": (self.num_classes, self.num_classes), "geometric": (2, 2)}

    def counts(
        self,
        pred: Tensor | np.ndarray,
        gt: Tensor | np.ndarray,
        mask: Tensor | np.ndarray | Omitted | None,
    ) -> tuple[Tensor, Tensor]:
        """The ``(C, C)`` confusion and ``(2, 2)`` occupied/free counts of one batch, on
        ``gt``'s device (the checks and errors of :meth:`OccupancyMetrics.update`)."""
        if isinstance(gt, Tensor | np.ndarray) and gt.ndim < 3:
            raise ValueError(
                f"gt: expected a label grid (X, Y, Z) or (B, X, Y, Z), got shape {tuple(gt.shape)}"
            )
        if mask is OMITTED:
            if self.protocol in CAMERA_MASK_PROTOCOLS:
                raise ValueError(
                    f"mask: the {self.protocol!r} protocol is scored inside the camera mask, "
                    "and none was passed; pass the camera mask (Occ3D's mask_camera, bool, "
                    "same shape as gt), or mask=None explicitly to score every voxel"
                )
            mask = None
        confusion = confusion_matrix(
            pred,
            gt,
            mask,
            num_classes=self.num_classes,
            ignore_label=self.ignore_label,
            removed_classes=self.removed_classes,
        )
        return confusion, binary_occupancy_confusion(confusion, self.free_label)

    def report(
        self, confusion: Tensor, geometric: Tensor, *, stacklevel: int = 2
    ) -> OccupancyReport:
        """The :class:`OccupancyReport` of pooled counts (``stacklevel``: of the warning,
        counted from the caller of this method)."""
        if int(confusion.sum()) == 0:
            raise RuntimeError("compute: no voxel has been evaluated yet; call update() first")
        if int(geometric[:, 1].sum()) == 0 and int(geometric[1].sum()) > 0:
            warnings.warn(
                f"no voxel was predicted free (label {self.free_label}) while the ground truth "
                "has free voxels: were the predictions overlaid with free space? "
                "dego.compat.dego.occupancy_to_labels (or VoxelOutput.labels) turns density and "
                "semantics into labels with it",
                UserWarning,
                stacklevel=stacklevel + 1,
            )
        occupied_iou = per_class_iou(geometric)[0]
        return OccupancyReport.from_per_class(
            per_class_iou(confusion),
            evaluated_classes=self.evaluated_classes,
            groups=self.groups,
            class_names=self.class_names,
            iou=float(occupied_iou),
            protocol=self.protocol,
        )


class OccupancyMetrics(CountingMetric):
    """Pooled voxel IoU metrics with a torchmetrics-style ``update / compute / reset / sync``.

    Args:
        protocol: ``"weak"`` (GaussianFlowOcc / DeGO: voxels whose gt is others (0) or
            other_flat (12) are removed from the mask; mIoU over the 15 classes
            1..11, 13..16), ``"occ3d"`` (the Occ3D benchmark: mIoU over every class
            but free, 0..16 for Occ3D-nuScenes) or ``"surroundocc"`` (SurroundOcc's
            labels as GaussianFormer scores them: voxels whose gt is 0, noise, are
            removed; mIoU over 1..16).
        num_classes: C, the number of labels including free (18 for Occ3D-nuScenes).
            ``"weak"`` and ``"surroundocc"`` are defined on 18 labels with free 17.
        free_label: the empty-space label (17).
        ignore_label: gt value whose voxels are skipped (255), or ``None``; any int
            outside ``0..C-1`` (e.g. -1).
        groups: class groups averaged into ``report.group_means``; defaults to the paper's
            InsM / ScnM / HCM for Occ3D-nuScenes labels, none otherwise.
        device: where the state lives (inputs on other devices are reduced where they are
            and only the small count matrices are moved).

    State (int64 buffers): ``confusion`` ``(C, C)`` (rows gt, columns pred) and
    ``geometric`` ``(2, 2)`` (0 occupied, 1 free), pooled over every voxel seen, never
    averaged per sample. They stay out of ``state_dict`` unless :meth:`persistent` is
    called. ``dego.compat.torchmetrics.OccupancyMetric`` is the same metric as a
    ``torchmetrics.Metric``.
    """

    COUNTS = ("confusion", "geometric")
    confusion: Tensor
    geometric: Tensor

    def __init__(
        self,
        protocol: str = "weak",
        num_classes: int = NUM_CLASSES,
        free_label: int = FREE_LABEL,
        ignore_label: int | None = 255,
        groups: Mapping[str, Sequence[int]] | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self._spec = OccupancySpec.make(protocol, num_classes, free_label, ignore_label, groups)
        for name, shape in self._spec.count_shapes().items():
            self._add_count(name, torch.zeros(shape, dtype=torch.int64, device=device))

    # the configuration, read-only
    protocol = property(lambda self: self._spec.protocol, doc="The protocol.")
    num_classes = property(lambda self: self._spec.num_classes, doc="C, labels including free.")
    free_label = property(lambda self: self._spec.free_label, doc="The empty-space label.")
    ignore_label = property(lambda self: self._spec.ignore_label, doc="The skipped gt value.")
    groups = property(lambda self: self._spec.groups, doc="Class ids of each group.")
    evaluated_classes = property(
        lambda self: self._spec.evaluated_classes, doc="The classes averaged into mIoU."
    )
    removed_classes = property(
        lambda self: self._spec.removed_classes, doc="GT classes whose voxels are skipped."
    )

    # -- accumulation -----------------------------------------------------------------
    @typechecked
    def update(
        self,
        pred: Tensor | np.ndarray,
        gt: Tensor | np.ndarray,
        mask: Tensor | np.ndarray | Omitted | None = OMITTED,
    ) -> None:
        """Add one batch of label grids ``(X, Y, Z)`` or ``(B, X, Y, Z)`` to the state.

        Args:
            pred: predicted labels in ``0..C-1``, any integer dtype (uint8 as Occ3D ships
                them, int8 ... int64: the counts do not depend on it), torch or numpy.
                An empty batch ``(0, X, Y, Z)`` adds nothing.
            gt: ground-truth labels in ``0..C-1`` or ``ignore_label``, same shape.
            mask: the camera mask, bool (or uint8 holding only 0/1), same shape; False
                voxels are skipped. ``"occ3d"`` and ``"weak"`` are defined inside the
                camera mask, so for them it must be passed: the mask, or ``mask=None``
                explicitly to score every voxel. ``"surroundocc"`` has none (omitted
                means ``None``).

        Raises:
            TypeError: bool, floating or non-array labels.
            ValueError: a label out of range (naming ``pred`` or ``gt`` and the value), a
                bad mask, no ``mask`` under ``"occ3d"`` or ``"weak"``, shape or device
                mismatches.
        """
        confusion, geometric = self._spec.counts(pred, gt, mask)
        self.confusion += confusion.to(self.confusion.device)
        self.geometric += geometric.to(self.geometric.device)
        self._changed()

    # -- results ----------------------------------------------------------------------
    def compute(self) -> OccupancyReport:
        """IoU, per-class IoU, mIoU and group means of everything seen (synced if ``sync``-ed)."""
        return self._spec.report(*self._totals(), stacklevel=2)

    # -- (de)serialisation ------------------------------------------------------------
    def _config(self) -> dict[str, Any]:
        return self._spec.config()

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v!r}" for k, v in self._config().items() if k != "groups")


__all__ = [
    "CAMERA_MASK_PROTOCOLS",
    "SURROUNDOCC_REMOVED_CLASSES",
    "WEAK_REMOVED_CLASSES",
    "OccupancyMetrics",
]
