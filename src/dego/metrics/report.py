"""IoU summaries of occupancy predictions: per-class IoU, mIoU, geometric IoU, group means."""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Mapping, Sequence
from types import MappingProxyType

import numpy as np
import torch
from jaxtyping import Float, Integer
from torch import Tensor

from dego import _serialization, _units
from dego._typing import check_tensor_fields, typechecked

AVERAGING_RULES = ("nanmean", "mean", "sequential-mean")
"""How the per-class IoU of a class set becomes one number: ``"nanmean"`` skips NaN (the
Occ3D devkit); ``"mean"`` (``numpy.mean``) does not, so a NaN class makes the mean NaN
(SurroundOcc); ``"sequential-mean"`` is Python's ``sum(values) / len(values)``, added left
to right (OpenOccupancy), which can differ from numpy's pairwise sum in the last bit."""


@typechecked
def per_class_iou(confusion: Integer[Tensor, "C C"]) -> Float[Tensor, " C"]:
    """IoU ``tp / (tp + fp + fn)`` per class from a confusion matrix (rows gt), float64.

    ``confusion`` holds counts of any integer dtype (not labels); the result does not
    depend on the dtype.

    A class that is neither in gt nor predicted gets NaN (0/0), as in Occ3D; one that is
    predicted but absent from gt gets 0.
    """
    confusion = confusion.double()
    tp = confusion.diagonal()
    return tp / (confusion.sum(0) + confusion.sum(1) - tp)


def _nanmean(values: Tensor) -> float:
    """The mean of the non-NaN ``values`` as numpy's ``nanmean`` sums them (the Occ3D
    devkit's recipe): torch's ``mean`` can differ in the last bit, which flips a score
    rounded to 2 decimals at a tie (25.625 -> 25.63 against the devkit's 25.62)."""
    array = values.detach().double().cpu().numpy()
    return float(np.nanmean(array)) if (~np.isnan(array)).any() else math.nan


def average(values: Tensor, rule: str = "nanmean") -> float:
    """One of :data:`AVERAGING_RULES` over ``values`` (float64), summed as the official
    code sums them."""
    array = values.detach().double().cpu().numpy()
    if rule == "mean":
        return float(np.mean(array))
    if rule == "sequential-mean":
        return sum(float(v) for v in array) / len(array)
    return _nanmean(values)


_HEADINGS = {"iou": "IoU", "insm": "InsM", "scnm": "ScnM", "hcm": "HCM", "miou": "mIoU"}
_KEYS = {title: key for key, title in _HEADINGS.items()}  # what headline() was keyed by


def heading(key: str) -> str:
    """The column heading the tables print for a score key (``"miou"`` -> ``"mIoU"``);
    keys are lower case everywhere else (``as_dict()``, ``headline()``, loggers, JSON)."""
    return _HEADINGS.get(key, key)


class _Headline(dict[str, float]):
    """:meth:`OccupancyReport.headline`'s dict: its keys are the lower-case score keys;
    the headings it used before (``"IoU"``, ``"mIoU"``, ...) still read, with a warning."""

    def __missing__(self, key: str) -> float:
        current = _KEYS.get(key)
        if current is None or current not in self:
            raise KeyError(key)
        warnings.warn(
            f"headline()[{key!r}]: the keys are lower case now, like as_dict()'s: use "
            f"[{current!r}] (the heading {key!r} stops working in dego 0.3)",
            FutureWarning,
            stacklevel=2,
        )
        return self[current]


@dataclasses.dataclass(frozen=True, eq=False)
class OccupancyReport(_serialization.DictForm):
    """Scores of a set of occupancy predictions; every value is a fraction in [0, 1] (or NaN).

    Attributes:
        per_class: ``(C,)`` float64 IoU of every label (free included); NaN where a class
            has neither gt nor predictions among the evaluated voxels.
        miou: nanmean of ``per_class`` over ``evaluated_classes``.
        iou: geometric IoU of occupied (label != free) vs free, over the same voxels.
        group_means: nanmean of ``per_class`` over each group (``insm``, ``scnm``, ``hcm``
            by default), from the same pooled per-class vector.
        averaging: how ``miou`` and the group means average (:data:`AVERAGING_RULES`):
            ``"nanmean"`` (the default; the Occ3D devkit), ``"mean"`` or
            ``"sequential-mean"``.
        protocol: ``"occ3d"``, ``"weak"`` or ``"surroundocc"`` (or ``"custom"`` for
            hand-built reports).
        evaluated_classes: the classes averaged into ``miou``.
        groups: the class ids of each group.
        class_names: names of all C labels.
    """

    def __post_init__(self) -> None:
        check_tensor_fields(self)

    per_class: Tensor
    miou: float
    iou: float
    group_means: Mapping[str, float]
    protocol: str
    evaluated_classes: tuple[int, ...]
    groups: Mapping[str, tuple[int, ...]]
    class_names: tuple[str, ...]
    averaging: str = "nanmean"

    @classmethod
    @typechecked
    def from_per_class(
        cls,
        per_class: Tensor | Sequence[float],
        *,
        evaluated_classes: Sequence[int],
        groups: Mapping[str, Sequence[int]],
        class_names: Sequence[str],
        iou: float = math.nan,
        protocol: str = "custom",
        averaging: str = "nanmean",
    ) -> OccupancyReport:
        """Summarise a per-class IoU vector (fractions, NaN for absent classes).

        This is the single place where mIoU and the group means are computed; it also
        lets published per-class numbers be re-summarised (divide percentages by 100).
        ``averaging``: one of :data:`AVERAGING_RULES`.
        """
        if averaging not in AVERAGING_RULES:
            raise ValueError(
                f"averaging: expected one of {list(AVERAGING_RULES)}, got {averaging!r}"
            )
        per_class = torch.as_tensor(per_class, dtype=torch.float64).detach().cpu()
        if per_class.ndim != 1 or per_class.shape[0] != len(class_names):
            raise ValueError(
                f"per_class: expected shape ({len(class_names)},) to match class_names, "
                f"got {tuple(per_class.shape)}"
            )
        for name, ids in {"evaluated_classes": evaluated_classes, **groups}.items():
            if any(not 0 <= i < len(class_names) for i in ids):
                raise ValueError(
                    f"{name}: class ids {list(ids)} must lie in 0..{len(class_names) - 1}"
                )
        frozen_groups = MappingProxyType({k: tuple(int(i) for i in v) for k, v in groups.items()})
        return cls(
            per_class=per_class,
            miou=average(per_class[list(evaluated_classes)], averaging),
            iou=float(iou),
            group_means=MappingProxyType(
                {k: average(per_class[list(v)], averaging) for k, v in frozen_groups.items()}
            ),
            protocol=protocol,
            evaluated_classes=tuple(int(i) for i in evaluated_classes),
            groups=frozen_groups,
            class_names=tuple(class_names),
            averaging=averaging,
        )

    def _group(self, name: str) -> float:
        if name not in self.group_means:
            raise AttributeError(
                f"group {name!r} is not configured; groups are {list(self.groups)}"
            )
        return self.group_means[name]

    @property
    def insm(self) -> float:
        """Mean IoU over instance classes (barrier .. truck by default)."""
        return self._group("insm")

    @property
    def scnm(self) -> float:
        """Mean IoU over scene classes (driveable, sidewalk, terrain, manmade, vegetation)."""
        return self._group("scnm")

    @property
    def hcm(self) -> float:
        """Mean IoU over human-centric classes (bicycle, motorcycle, pedestrian)."""
        return self._group("hcm")

    def as_dict(self, *, percent: bool = False) -> dict[str, float]:
        """Flat ``{"iou", "miou", <group>, "iou/<class>"}`` for loggers, fractions (a key
        holds a fraction wherever dego gives one). Per-class entries cover
        ``evaluated_classes``. ``percent=True`` (deprecated) rounds percentages to 2
        decimals under the same keys: print :meth:`table` for the papers' numbers.
        """
        if percent:
            _units.warn_percent_keys("OccupancyReport.as_dict(percent=True)")

        def fmt(v: float) -> float:
            return round(_units.percent(v), 2) if percent else v

        out = {"iou": fmt(self.iou), "miou": fmt(self.miou)}
        out.update({name: fmt(value) for name, value in self.group_means.items()})
        for label in self.evaluated_classes:
            out[f"iou/{self.class_names[label]}"] = fmt(float(self.per_class[label]))
        return out

    def headline(self) -> dict[str, float]:
        """The summary row of the tables, in their order, keyed like :meth:`as_dict`:
        ``{"iou", "insm", "scnm", "hcm" (the configured groups), "miou"}``, fractions
        (:func:`heading` gives each column's printed heading)."""
        return _Headline({"iou": self.iou, **self.group_means, "miou": self.miou})

    def table(self) -> str:
        """A paper-style text table in percent with two decimals (the first line says so),
        '-' for absent classes."""
        summary = self.headline()
        lines = [
            f"protocol: {self.protocol}, mIoU over {len(self.evaluated_classes)} classes"
            + ("" if self.averaging == "nanmean" else f" ({self.averaging}, NaN kept)")
            + ", "
            "IoU in percent",
            "| " + " | ".join(f"{heading(k):>6}" for k in summary) + " |",
            "|" + "|".join("-" * 8 for _ in summary) + "|",
            "| " + " | ".join(f"{_units.percent_text(v):>6}" for v in summary.values()) + " |",
            "",
            f"| {'class':<22} | {'IoU':>6} | groups",
            f"|{'-' * 24}|{'-' * 8}|{'-' * 8}",
        ]
        for label in self.evaluated_classes:
            member_of = ", ".join(g for g, ids in self.groups.items() if label in ids)
            value = _units.percent_text(float(self.per_class[label]))
            lines.append(f"| {self.class_names[label]:<22} | {value:>6} | {member_of}".rstrip())
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.table()


__all__ = [
    "AVERAGING_RULES",
    "OccupancyReport",
    "average",
    "heading",
    "per_class_iou",
]
