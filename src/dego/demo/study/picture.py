"""``dego study``'s picture: articulated-agent IoU per variant and budget, and each
variant's paired gain over ``static``, with 95% intervals (needs matplotlib)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dego._atomic import write_files
from dego.demo.evaluate import OFFSET_GROUPS
from dego.demo.fit import row_name
from dego.demo.stats import MIN_INTERVAL_SEEDS, StudyRun, paired_differences
from dego.demo.study.runner import HEADLINE, STUDY_VARIANTS, summarise

PICTURED_GAINS = (
    "rigid",
    "decoupled",
    "velocity",
    "free-offsets",
    "free-velocities",
    "true-motion",
)
"""The variants whose paired gain over ``static`` the study picture shows."""


def study_picture(runs: Sequence[StudyRun], path: Path) -> Path:
    """Write :func:`study_figure` to ``path`` (PNG, atomically; needs matplotlib)."""
    return write_files({path: study_png(runs)})[0]


def study_png(runs: Sequence[StudyRun]) -> bytes:
    """:func:`study_figure` encoded as PNG (``study.png``; needs matplotlib)."""
    from dego.viz import png_bytes

    return png_bytes(study_figure(runs), dpi=90)


def study_figure(runs: Sequence[StudyRun]) -> Any:
    """Articulated-agent IoU one frame from the reference per variant and budget, and each
    variant's paired gain over ``static``, with 95% intervals: a matplotlib Figure (needs
    matplotlib)."""
    from dego.viz import new_figure

    summary = summarise(runs)
    figure = new_figure((10.0, 3.6))
    left, right = figure.subplots(1, 2)
    budgets = list(summary)
    variants = [v for v in STUDY_VARIANTS if any(r.variant == v for r in runs)]

    def bars(axis, intervals_of, names) -> bool:
        """Draw the bars; an error bar only where the report gives an interval (at least
        MIN_INTERVAL_SEEDS seeds). Returns whether any was drawn."""
        width = 0.8 / max(len(names), 1)
        drawn = False
        for k, variant in enumerate(names):
            intervals = [intervals_of(b, variant) for b in budgets]
            xs = [i + (k - (len(names) - 1) / 2) * width for i in range(len(budgets))]
            shown = [iv.n >= MIN_INTERVAL_SEEDS for iv in intervals]  # as the report
            errors = [
                [iv.mean - iv.low if ok else 0 for iv, ok in zip(intervals, shown, strict=True)],
                [iv.high - iv.mean if ok else 0 for iv, ok in zip(intervals, shown, strict=True)],
            ]
            axis.bar(
                xs,
                [iv.mean for iv in intervals],
                width,
                yerr=errors if any(shown) else None,
                capsize=3 if any(shown) else 0,
                label=row_name(variant),
                color=f"C{STUDY_VARIANTS.index(variant) % 10}",  # one colour per variant
            )
            drawn |= any(shown)
        axis.set_xticks(range(len(budgets)), [f"{b} G" for b in budgets])
        return drawn

    with_intervals = bars(left, lambda b, v: summary[b][v][HEADLINE], variants)
    left.set_ylabel(f"articulated IoU, {OFFSET_GROUPS[0]} (%)")
    left.legend(fontsize=6)
    gains = [v for v in PICTURED_GAINS if v in variants] if "static" in variants else []
    paired = {v: paired_differences(runs, HEADLINE, v, "static") for v in gains}
    with_intervals |= bars(right, lambda b, v: paired[v][b], gains)
    right.axhline(0, color="grey", linewidth=0.8)
    right.set_ylabel("gain over static (points)")
    if gains:
        right.legend(fontsize=6)
    seeds = len({r.seed for r in runs})
    if with_intervals:
        right.set_title(f"{HEADLINE}, paired by seed, 95% CI", fontsize=9)
    else:  # as the report: no interval below MIN_INTERVAL_SEEDS seeds, so none is drawn
        # two lines: on one it ran past the figure's right edge (issue 51)
        right.set_title(
            f"{HEADLINE}, paired by seed;\nmeans of {seeds} seed(s), no interval "
            f"(needs {MIN_INTERVAL_SEEDS}+)",
            fontsize=9,
        )
    return figure
