"""``dego study``'s report: means with 95% intervals per budget and variant, paired
differences, plain sentences that follow from them, and the files ``study.md``,
``study.json`` and ``study.png``."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path

from dego._atomic import write_files
from dego._units import UNIT
from dego.demo.evaluate import OFFSET_GROUPS
from dego.demo.fit import row_name
from dego.demo.stats import (
    MIN_INTERVAL_SEEDS,
    Interval,
    StudyRun,
    json_safe,
    paired_differences,
)
from dego.demo.study.runner import HEADLINE, MASK_METRICS, METRICS, StudyConfig, summarise

COMPARISONS = (
    ("decoupled", "static"),
    ("rigid", "static"),
    ("decoupled", "rigid"),
    ("decoupled+prior", "decoupled"),
    ("velocity", "static"),
    ("velocity", "decoupled"),
    ("free-offsets", "static"),
    ("free-velocities", "static"),
    ("true-motion", "static"),
    ("static", "single-frame"),
    ("decoupled", "single-frame"),
)
"""Paired differences the report gives (first - second, same seed and budget).
``static - single-frame`` is what the other frames' labels do to t = 0 without any
motion model; ``decoupled - single-frame`` the same with the deformation."""

PAIRED_METRICS = (
    *(f"{m} {scope}" for m in ("articulated", "vehicles") for scope in OFFSET_GROUPS),
    "HCM t=0",
    "mIoU t=0",
)
"""The metrics of the paired-difference table."""


def study_report(runs: Sequence[StudyRun], config: StudyConfig) -> tuple[str, dict]:
    """The Markdown report and its JSON payload."""
    summary = summarise(runs)
    lines = [
        "# dego study: when does decoupling pay off?",
        "",
        f"Seeds {list(config.seeds)}, budgets {list(config.budgets)} Gaussians, "
        f"{config.frames} frames, {config.iterations} iterations per fit, mask prior weight "
        f"{config.mask_prior}. Percent, mean [95% t-interval over seeds].",
    ]
    if len(config.seeds) < MIN_INTERVAL_SEEDS:
        lines += [
            "",
            f"With {len(config.seeds)} seed(s) no interval is given (`n/a`): a 95% t-interval "
            f"needs at least {MIN_INTERVAL_SEEDS} seeds to say anything (with 2 its half-width is "
            "12.7 standard errors, past the range of a bounded quantity such as the mask AUC); "
            "the means are single draws, not comparisons.",
        ]
    payload: dict = {
        "units": {"scores": UNIT, "mask": "mask values and ROC-AUC in [0, 1]"},
        "settings": dataclasses.asdict(config),
        "runs": [dataclasses.asdict(r) for r in runs],
        "summary": {},
        "paired": {},
    }
    for budget, variants in summary.items():
        lines += ["", f"## {budget} Gaussians", ""]
        lines += _interval_table(variants, METRICS)
        lines += [
            "",
            "Rigidity mask (1 = nonrigid) on the Gaussians of each kind of agent: mask means "
            "and ROC-AUC in [0, 1], not percent:",
            "",
        ]
        masked = {v: s for v, s in variants.items() if v.startswith("decoupled") or v == "velocity"}
        if masked:
            lines += _interval_table(masked, (*MASK_METRICS, "Gaussians per articulated agent"))
        payload["summary"][budget] = {
            v: {m: dataclasses.asdict(i) for m, i in s.items()} for v, s in variants.items()
        }
    lines += ["", "## Paired differences (first - second, same seed), points", ""]
    lines += [
        "A `*` marks an interval that excludes 0 (the sign is resolved).",
        "",
        "| difference | budget | n | " + " | ".join(PAIRED_METRICS) + " |",
        "|---|---:|---:|" + "---|" * len(PAIRED_METRICS),
    ]
    present = {r.variant for r in runs}
    for first, second in COMPARISONS:
        if first not in present or second not in present:
            continue
        by_metric = {m: paired_differences(runs, m, first, second) for m in PAIRED_METRICS}
        for budget in by_metric[PAIRED_METRICS[0]]:
            cells = []
            for metric in PAIRED_METRICS:
                interval = by_metric[metric][budget]
                cells.append(f"{interval}{' *' if interval.excludes_zero() else ''}")
                key = f"{first} - {second} @ {budget}: {metric}"
                payload["paired"][key] = dataclasses.asdict(interval)
            n = by_metric[PAIRED_METRICS[0]][budget].n
            lines.append(
                f"| {row_name(first)} - {row_name(second)} | {budget} | {n} | "
                + " | ".join(cells)
                + " |"
            )
    lines += ["", "## Reading", "", *_reading(runs, summary)]
    return "\n".join(lines) + "\n", payload


def _interval_table(variants: dict[str, dict[str, Interval]], metrics: Sequence[str]) -> list[str]:
    head = "| variant | " + " | ".join(metrics) + " |"
    rows = [head, "|---|" + "---|" * len(metrics)]
    for variant, values in variants.items():
        cells = [str(values[m]) for m in metrics]
        rows.append(f"| {row_name(variant)} | " + " | ".join(cells) + " |")
    return rows


def _reading(runs: Sequence[StudyRun], summary: dict) -> list[str]:
    """Plain sentences that follow from the numbers (no judgement beyond them)."""
    out = []
    present = {r.variant for r in runs}
    for first, second, metric in (
        ("decoupled", "static", HEADLINE),
        ("decoupled", "static", f"vehicles {OFFSET_GROUPS[0]}"),
        ("decoupled", "static", "HCM t=0"),
        ("decoupled", "rigid", HEADLINE),
    ):
        if not {first, second} <= present:
            continue
        for budget, interval in paired_differences(runs, metric, first, second).items():
            if interval.n < 2:
                verdict = "one seed only: no interval"
            elif interval.n < MIN_INTERVAL_SEEDS:
                verdict = f"{interval.n} seeds only: no interval (at least {MIN_INTERVAL_SEEDS})"
            elif interval.excludes_zero():
                better = "better" if interval.mean > 0 else "worse"
                verdict = f"the interval excludes 0: {first} is {better} than {second} here"
            else:
                verdict = "the interval includes 0: the sign is not resolved at this budget"
            out.append(
                f"- {budget} Gaussians: {first} - {second} on {metric} is {interval} points; "
                f"{verdict}."
            )
    for variant, what in (
        ("true-motion", "the ground-truth motion (oracle)"),
        ("free-velocities", "one free velocity per Gaussian (no network, no ground truth)"),
    ):
        if {variant, "static"} <= present:
            for budget, interval in paired_differences(runs, HEADLINE, variant, "static").items():
                out.append(
                    f"- {budget} Gaussians: {what} gains {interval} points on {HEADLINE} over "
                    "static"
                    + (": the room a motion model has here." if variant == "true-motion" else ".")
                )
    for variant in ("decoupled", "decoupled+prior"):
        if variant not in present:
            continue
        for budget, variants in summary.items():
            values = variants[variant]
            out.append(
                f"- {variant}, {budget} Gaussians: mean mask {values['mask articulated']} on "
                f"articulated agents vs {values['mask vehicles']} on vehicles, ROC-AUC "
                f"{values['mask AUC']} (0.5: no separation)."
            )
    return out


def study_outputs(out: Path, *, pictures: bool = True) -> list[Path]:
    """Every file :func:`write_study` writes to ``out`` (``study.png`` whether or not
    matplotlib is here), checked before the study starts."""
    return [out / "study.md", out / "study.json", *([out / "study.png"] if pictures else [])]


def write_study(
    runs: Sequence[StudyRun], config: StudyConfig, out: Path, *, pictures: bool = True
) -> tuple[str, list[Path]]:
    """Write ``study.md``, ``study.json`` and (with matplotlib) ``study.png`` to ``out``,
    all or nothing (:func:`dego._atomic.write_files`: a failure leaves the previous files
    as they were); return the Markdown report and the paths."""
    text, payload = study_report(runs, config)
    files: dict[Path, str | bytes] = {
        out / "study.md": text,
        out / "study.json": json.dumps(json_safe(payload), indent=1) + "\n",
    }
    if pictures:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            pass
        else:
            from dego.demo.study.picture import study_png

            files[out / "study.png"] = study_png(runs)
    return text, write_files(files)
