"""EvaluationReport: the scores of one ``dego eval`` run and everything needed to trust them
(protocols, origin source, sample and ray counts, dego version, missing/failed samples).

Units: every score a report shows or writes is in percent (mIoU, IoU, group means,
RayIoU): :meth:`EvaluationReport.tables` and :meth:`~EvaluationReport.to_markdown` print
two decimals; :meth:`~EvaluationReport.to_dict` / :meth:`~EvaluationReport.to_json` hold
unrounded percentages (``null`` for NaN, i.e. a class absent from ground truth and
predictions) and say so with ``"units": "percent"``. The attributes of the
:class:`~dego.OccupancyReport` / :class:`~dego.RayIoUReport` inside stay fractions.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from typing import Any

from torch import Tensor

from dego._typing import check_tensor_fields
from dego._units import UNIT, percent_or_none, percent_text
from dego.evaluation.errors import SampleFailure
from dego.metrics.rayiou import RayIoUReport
from dego.metrics.report import OccupancyReport, heading


@dataclasses.dataclass(frozen=True, eq=False)
class EvaluationReport:
    """The result of :func:`dego.evaluate` (its metric reports hold fractions; its tables,
    Markdown and JSON show percent).

    Attributes:
        protocols: the :class:`~dego.OccupancyReport` of each voxel protocol scored
            (``"occ3d"``, ``"weak"``), summarised over ``classes`` when given; empty when
            no sample could be scored.
        rayiou: the :class:`~dego.RayIoUReport`, or ``None`` (``--no-rayiou``, or no
            scored sample / ray).
        counts: the pooled int64 counts behind the scores, by metric then count name.
        classes: the classes averaged into mIoU and RayIoU when not the protocol's
            default (``--classes``), else ``None``.
        gt, pred: the ground-truth root and the predictions folder.
        origin_source: ``"infos: <file>"``, ``"nuscenes: <root> (<version>)"``,
            ``"origins: <dir>"``, or ``None`` without RayIoU; ``ignored_sources``: those
            given but not used.
        samples_total: the samples selected (GT tree or infos order);
            ``samples_scored``: those scored successfully.
        origins_total: ray origins over all scored samples (K per sample);
            ``rays_per_origin``: rays per origin (14,040); ``rays_cast``: rays cast per
            grid (sum of K x 14,040; prediction and GT each get these);
            ``rays_scored``: rays whose GT hit is not free (RayIoU's gt counts summed).
        missing_policy: ``"error"``, ``"free"`` or ``"skip"``; ``missing_tokens``: the
            samples without a prediction (scored as all free, or skipped).
        failed: samples that could not be read or validated (the run is incomplete).
        world_size: processes that shared the samples; ``seconds``: wall time;
        version: the dego version.
        traversal: how the rays were cast: ``"numba"`` (the compiled CPU kernel) or
            ``"torch"``, with identical hits.
        benchmark: the benchmark scored; ``rules``: its rules, one line each (the
            header of every report: grid, frame, labels, masks, class sets, averaging).
        rayiou_sets: RayIoU over each class set the benchmark names (``rayiou`` is the
            first), e.g. Occ3D-nuScenes' 17 classes beside the 15 of the weak set.
        flow: OpenOcc v2's flow scores: ``variant``, ``ave`` (per class, m/s), ``mave``
            and ``occ_score`` (fractions), or ``None``.
    """

    def __post_init__(self) -> None:
        check_tensor_fields(self)

    protocols: Mapping[str, OccupancyReport]
    rayiou: RayIoUReport | None
    counts: Mapping[str, Mapping[str, Tensor]]
    classes: tuple[int, ...] | None
    gt: str
    pred: str
    origin_source: str | None
    ignored_sources: tuple[str, ...]
    samples_total: int
    samples_scored: int
    origins_total: int
    rays_per_origin: int
    rays_cast: int
    rays_scored: int
    missing_policy: str
    missing_tokens: tuple[str, ...]
    failed: tuple[SampleFailure, ...]
    world_size: int
    seconds: float
    version: str
    traversal: str = "torch"
    benchmark: str = "occ3d-nuscenes"
    rules: tuple[str, ...] = ()
    rayiou_sets: Mapping[str, RayIoUReport] = dataclasses.field(default_factory=dict)
    flow: Mapping[str, Any] | None = None

    @property
    def complete(self) -> bool:
        """Every selected sample was scored (no failures; skipped samples aside)."""
        return not self.failed

    @property
    def skipped(self) -> tuple[str, ...]:
        """Tokens left out for want of a prediction (``missing="skip"``)."""
        return self.missing_tokens if self.missing_policy == "skip" else ()

    @property
    def scored_as_free(self) -> tuple[str, ...]:
        """Tokens without a prediction scored as all free (``missing="free"``)."""
        return self.missing_tokens if self.missing_policy == "free" else ()

    # -- plain data ---------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready data; scores in percent, unrounded (``None`` for NaN); counts raw."""
        out: dict[str, Any] = {
            "dego_version": self.version,
            "units": UNIT,
            "benchmark": self.benchmark,
            "rules": list(self.rules),
            "complete": self.complete,
            "gt": self.gt,
            "pred": self.pred,
            "protocols": list(self.protocols),
            "classes": None if self.classes is None else list(self.classes),
            "samples": self.samples_scored,
            "samples_total": self.samples_total,
            "missing": {"policy": self.missing_policy, "tokens": list(self.missing_tokens)},
            "skipped": list(self.skipped),
            "scored_as_free": list(self.scored_as_free),
            "failed": [f.as_dict() for f in self.failed],
            "origins": {
                "source": self.origin_source,
                "ignored": list(self.ignored_sources),
                "total": self.origins_total,
            },
            "rays": {
                "per_origin": self.rays_per_origin,
                "cast": self.rays_cast,
                "scored": self.rays_scored,
                "traversal": self.traversal,
            },
            "world_size": self.world_size,
            "seconds": round(self.seconds, 3),
        }
        for name, report in self.protocols.items():
            out[name] = _occupancy_dict(report)
        out["rayiou"] = None if self.rayiou is None else _rayiou_dict(self.rayiou)
        out["rayiou_sets"] = {name: _rayiou_dict(r) for name, r in self.rayiou_sets.items()}
        if self.flow is not None:
            out["flow"] = {
                "variant": self.flow["variant"],
                "ave_m_per_s": {k: _finite(v) for k, v in self.flow["ave"].items()},
                "mave_m_per_s": _finite(self.flow["mave"]),
                "occ_score": percent_or_none(self.flow["occ_score"]),
            }
        out["counts"] = {
            metric: {name: count.tolist() for name, count in counts.items()}
            for metric, counts in self.counts.items()
        }
        return out

    def to_json(self) -> str:
        """:meth:`to_dict` as indented JSON (percent, ``"units": "percent"``)."""
        return json.dumps(self.to_dict(), indent=2) + "\n"

    # -- text -----------------------------------------------------------------------------
    def _summary_lines(self) -> list[str]:
        lines = [*self.rules]
        lines += [
            f"dego {self.version} eval: {self.samples_scored} of {self.samples_total} samples "
            f"scored ({self.world_size} process(es), {self.seconds:.1f} s)",
            f"gt: {self.gt}",
            f"pred: {self.pred}",
            f"protocols: {', '.join(self.protocols) or 'none scored'}",
        ]
        if self.classes is not None:
            lines.append(
                f"classes averaged (--classes): {', '.join(map(str, self.classes))} "
                "(instead of the protocols' defaults)"
            )
        if self.origin_source is not None:
            lines.append(f"RayIoU origins: {self.origin_source}")
            lines.append(
                f"rays: {self.origins_total} origins x {self.rays_per_origin:,} = "
                f"{self.rays_cast:,} rays cast per grid, {self.rays_scored:,} scored "
                f"(GT hit not free); traversal: {self.traversal}"
            )
        else:
            lines.append("RayIoU: not computed")
        for source in self.ignored_sources:
            lines.append(f"ignored origin source: {source}")
        lines.append(f"missing predictions: policy {self.missing_policy}, {self._missing_text()}")
        return lines

    def _missing_text(self) -> str:
        if not self.missing_tokens:
            return "none"
        what = "skipped" if self.missing_policy == "skip" else "scored as all free"
        return f"{len(self.missing_tokens)} {what}: {', '.join(self.missing_tokens)}"

    def _incomplete_line(self) -> str:
        return (
            f"INCOMPLETE: {len(self.failed)} of {self.samples_total} samples failed; the "
            f"scores are over the {self.samples_scored} samples that were read"
        )

    def tables(self) -> str:
        """The text shown on stdout: every score in percent with two decimals."""
        lines = []
        if not self.complete:
            lines += [self._incomplete_line(), ""]
        lines += self._summary_lines()
        lines += ["", "All scores below are percentages with 2 decimals."]
        for name, report in self.protocols.items():
            lines += ["", f"== voxel IoU, {name} protocol (percent) ==", report.table()]
        if self.rayiou is not None:
            for i, (name, ray) in enumerate((self.rayiou_sets or {"": self.rayiou}).items()):
                title = f"RayIoU (percent){', ' + name if i else ''}"
                lines += ["", f"== {title}, origins {self.origin_source} =="]
                lines += [ray.table()]
        if self.flow is not None:
            lines += ["", *self._flow_lines()]
        elif self.origin_source is not None:
            lines += ["", "RayIoU: no ray was scored"]
        if not self.protocols and self.rayiou is None:
            lines += ["", "no sample was scored"]
        if self.failed:
            lines += ["", f"failed samples ({len(self.failed)}):"]
            lines += [f"  {f.token}: {f.message}" for f in self.failed]
            lines += [self._incomplete_line()]
        return "\n".join(lines)

    def to_markdown(self) -> str:
        """A Markdown report (percent with two decimals, like :meth:`tables`)."""
        title = "# dego eval" + ("" if self.complete else " (INCOMPLETE)")
        lines = [title, ""]
        if not self.complete:
            lines += [f"**{self._incomplete_line()}**", ""]
        lines += [f"- {line}" for line in self._summary_lines()]
        lines += ["", "All scores are percentages with 2 decimals."]
        for name, report in self.protocols.items():
            summary = report.headline()
            lines += [
                "",
                f"## Voxel IoU (percent), {name} protocol "
                f"(mIoU over {len(report.evaluated_classes)} classes)",
                "",
                "| " + " | ".join(heading(k) for k in summary) + " |",
                "|" + "|".join("---:" for _ in summary) + "|",
                "| " + " | ".join(percent_text(v) for v in summary.values()) + " |",
                "",
                "| class | IoU |",
                "|---|---:|",
            ]
            lines += [
                f"| {report.class_names[c]} | {percent_text(float(report.per_class[c]))} |"
                for c in report.evaluated_classes
            ]
        ray_sets = self.rayiou_sets or ({"": self.rayiou} if self.rayiou else {})
        for i, (name, ray) in enumerate(ray_sets.items()):
            heads = [f"@{t:g} m" for t in ray.thresholds]
            lines += [
                "",
                f"## RayIoU (percent){', ' + name if i else ''}, origins {self.origin_source}",
                "",
                f"RayIoU **{percent_text(ray.rayiou)}** (mean over {len(ray.class_ids)} classes)",
                "",
                "| class | " + " | ".join(heads) + " |",
                "|---|" + "|".join("---:" for _ in heads) + "|",
            ]
            for c in ray.class_ids:
                cells = [percent_text(float(ray.per_class[i, c])) for i in range(len(heads))]
                lines.append(f"| {ray.class_names[c]} | " + " | ".join(cells) + " |")
            lines.append("| **mean** | " + " | ".join(percent_text(v) for v in ray.at) + " |")
        if self.flow is not None:
            lines += ["", "## Flow (OpenOcc v2)", "", *(f"- {line}" for line in self._flow_lines())]
        if self.failed:
            lines += ["", f"## Failed samples ({len(self.failed)})", ""]
            lines += [f"- `{f.token}` ({f.file}): {f.message}" for f in self.failed]
        if self.missing_tokens:
            lines += ["", f"## Samples without a prediction ({self.missing_policy})", ""]
            lines += [f"- `{t}`" for t in self.missing_tokens]
        return "\n".join(lines) + "\n"

    def _flow_lines(self) -> list[str]:
        assert self.flow is not None
        flow = self.flow
        ave = ", ".join(f"{k} {_num(v)}" for k, v in flow["ave"].items())
        return [
            f"mAVE ({flow['variant']} script): {_num(flow['mave'])} m/s; AVE per class: {ave}",
            f"OccScore: {percent_text(flow['occ_score'])} (percent)",
        ]

    def __str__(self) -> str:
        return self.tables()


def _num(value: float) -> str:
    return "-" if value != value else f"{value:.4f}"


def _finite(value: float) -> float | None:
    return None if value != value else float(value)


def _occupancy_dict(report: OccupancyReport) -> dict[str, Any]:
    return {
        "protocol": report.protocol,
        "averaging": report.averaging,
        "miou": percent_or_none(report.miou),
        "iou": percent_or_none(report.iou),
        **{name: percent_or_none(value) for name, value in report.group_means.items()},
        "evaluated_classes": list(report.evaluated_classes),
        "per_class": {
            report.class_names[c]: percent_or_none(float(report.per_class[c]))
            for c in report.evaluated_classes
        },
    }


def _rayiou_dict(report: RayIoUReport) -> dict[str, Any]:
    return {
        "rayiou": percent_or_none(report.rayiou),
        "at": {
            f"{t:g}": percent_or_none(v) for t, v in zip(report.thresholds, report.at, strict=True)
        },
        "class_ids": list(report.class_ids),
        "per_class": {
            report.class_names[c]: {
                f"{t:g}": percent_or_none(float(report.per_class[i, c]))
                for i, t in enumerate(report.thresholds)
            }
            for c in report.class_ids
        },
    }


__all__ = ["EvaluationReport"]
