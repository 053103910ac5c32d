"""``dego study``: when does decoupling pay off? Variants x seeds x Gaussian budgets.

For every seed a synthetic clip is rendered; for every total Gaussian budget each
variant (``static``, ``rigid``, ``decoupled``, ``decoupled`` with the optional mask
prior, and the reference rows ``single-frame``, ``free-offsets``, ``free-velocities``
and the ground-truth
``true-motion`` oracle) is fitted from the pseudo labels and scored at every frame
(:mod:`dego.demo`). The report gives per-variant means with 95% confidence intervals
over seeds, paired differences (e.g. decoupled - static on moving agents at the
non-reference frames and on HCM at the reference frame), and how well the learned
rigidity mask separates articulated agents from vehicles.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from jaxtyping import Float
from torch import Tensor

from dego._atomic import write_files
from dego._checks import check_int
from dego._units import UNIT
from dego.data.synthetic import SyntheticScene
from dego.demo.clip import DEMO_FRAME_DT, MAX_DEMO_FRAMES, DemoClip, max_gaussians
from dego.demo.evaluate import OFFSET_GROUPS, lifted_clip_labels, predict_clip, score_clip
from dego.demo.fit import MAX_SEED, FitConfig, FitResult, fit_scene, rigidity_mask, row_name
from dego.demo.offsets import agent_under

STUDY_VARIANTS = (
    "lifted-labels",
    "single-frame",
    "static",
    "rigid",
    "decoupled",
    "decoupled+prior",
    "free-offsets",
    "free-velocities",
    "true-motion",
)
""":data:`~dego.demo.VARIANTS` and :data:`~dego.demo.REFERENCE_VARIANTS`, the
``lifted-labels`` ceiling (no fit: each frame's pseudo labels lifted to 3D), and
``decoupled+prior``: ``decoupled`` with :attr:`StudyConfig.mask_prior` as the weight of
the mask sparsity prior (:attr:`~dego.demo.FitConfig.mask_sparsity`). ``true-motion``
uses the ground truth (a ceiling, not a competitor)."""

DEFAULT_STUDY_VARIANTS = tuple(v for v in STUDY_VARIANTS if v != "decoupled+prior")
"""What ``dego study`` fits unless told otherwise (``--variants``)."""

METRICS = (
    "IoU t=0",
    "mIoU t=0",
    "HCM t=0",
    "RayIoU t=0",
    *(f"{m} {scope}" for m in ("mIoU", "HCM") for scope in OFFSET_GROUPS),
    *(f"{m} {scope}" for m in ("vehicles", "articulated") for scope in OFFSET_GROUPS),
)
"""Per-run scores (percent) the report summarises; see :class:`dego.demo.ClipScore`
(``t=±1`` / ``t=±2+``: the frames one / two or more frames from the reference)."""

HEADLINE = f"articulated {OFFSET_GROUPS[0]}"
"""The study's headline score: IoU on moving pedestrians and cyclists one frame from the
reference, where a motion model has the most to win."""

MASK_METRICS = ("mask articulated", "mask vehicles", "mask static", "mask AUC")
"""Mean fitted mask on Gaussians of articulated agents / of vehicles / elsewhere, and
the ROC-AUC of the mask for telling articulated-agent Gaussians from vehicle ones."""


@dataclasses.dataclass(frozen=True)
class StudyConfig:
    """What :func:`run_study` runs (the defaults are ``dego study`` without ``--quick``).

    Attributes:
        seeds: scene and fitting seeds, in ``[0, MAX_SEED]``, each once.
        budgets: total numbers of canonical Gaussians, one sweep point each (each once,
            at most :func:`~dego.demo.clip.max_gaussians` of ``frames``).
        frames: frames per clip (offsets ``-(frames // 2) ..``), 2 to
            :data:`~dego.demo.clip.MAX_DEMO_FRAMES`.
        iterations: optimiser steps per fit.
        variants: a subset of :data:`STUDY_VARIANTS`, each once.
        mask_prior: the mask sparsity weight of ``decoupled+prior``.
    """

    seeds: tuple[int, ...] = tuple(range(10))
    budgets: tuple[int, ...] = (500, 2000)
    frames: int = 5
    iterations: int = 100
    variants: tuple[str, ...] = DEFAULT_STUDY_VARIANTS
    mask_prior: float = 0.1

    def __post_init__(self) -> None:
        for name in ("seeds", "budgets", "variants"):
            check_distinct(name, getattr(self, name))
        check_seeds(self.seeds)
        check_int("frames", self.frames, 2)
        if self.frames > MAX_DEMO_FRAMES:
            raise ValueError(
                f"frames: expected an int in [2, {MAX_DEMO_FRAMES}], got {self.frames!r}"
            )
        most = max_gaussians(self.frames)
        for budget in self.budgets:
            if check_int("budgets", budget, 1) > most:
                raise ValueError(
                    f"budgets: expected ints in [1, {most}] (a {self.frames}-frame clip has "
                    f"{most} camera pixels, one Gaussian each at most), got {budget!r}"
                )
        check_int("iterations", self.iterations, 0)
        unknown = sorted(set(self.variants) - set(STUDY_VARIANTS))
        if unknown:
            raise ValueError(f"variants: unknown {unknown}; expected some of {STUDY_VARIANTS}")
        if not (math.isfinite(self.mask_prior) and self.mask_prior >= 0):
            raise ValueError(f"mask_prior: expected a finite weight >= 0, got {self.mask_prior!r}")


def check_distinct(name: str, values: tuple) -> None:
    """``values`` of the config field ``name`` is not empty and names each value once."""
    if not values:
        raise ValueError(f"{name}: expected at least one value, got {values!r}")
    repeated = sorted({v for v in values if values.count(v) > 1}, key=values.index)
    if repeated:
        raise ValueError(f"{name}: {', '.join(map(str, repeated))} repeated; each value runs once")


def check_seeds(seeds: tuple[int, ...]) -> None:
    """Every one of ``seeds`` is an int in ``[0, MAX_SEED]``."""
    for seed in seeds:
        if check_int("seeds", seed, 0) > MAX_SEED:
            raise ValueError(f"seeds: expected ints in [0, {MAX_SEED}], got {seed!r}")


QUICK_STUDY = StudyConfig(
    seeds=(0, 1), budgets=(300,), frames=3, iterations=20, variants=STUDY_VARIANTS
)
"""``dego study --quick``: the tiny settings the tests run."""


@dataclasses.dataclass(frozen=True)
class StudyRun:
    """One fit: its settings, scores (percent) and mask statistics."""

    seed: int
    budget: int
    variant: str
    scores: dict[str, float]
    mask: dict[str, float]
    per_articulated_agent: float
    seconds: float


def roc_auc(positive: Float[Tensor, " P"], negative: Float[Tensor, " Q"]) -> float:
    """Probability that a random positive scores above a random negative (ties count
    half): the area under the ROC curve. NaN when either side is empty."""
    if positive.numel() == 0 or negative.numel() == 0:
        return math.nan
    total = 0.0
    for chunk in positive.split(4096):
        greater = (chunk[:, None] > negative[None]).sum()
        equal = (chunk[:, None] == negative[None]).sum()
        total += float(greater) + 0.5 * float(equal)
    return total / (positive.numel() * negative.numel())


def mask_statistics(result: FitResult, clip: DemoClip) -> tuple[dict[str, float], float]:
    """:data:`MASK_METRICS` of a fit, and its mean Gaussians per articulated agent."""
    mask = rigidity_mask(result).cpu()
    agent = agent_under(result.model.means, clip).cpu()
    index = (agent - 1).clamp_min(0)
    articulated = (agent > 0) & clip.agent_articulated.cpu()[index]
    vehicles = (agent > 0) & ~clip.agent_articulated.cpu()[index]
    elsewhere = agent == 0

    def mean(selected: Tensor) -> float:
        return float(mask[selected].mean()) if selected.any() else math.nan

    stats = {
        "mask articulated": mean(articulated),
        "mask vehicles": mean(vehicles),
        "mask static": mean(elsewhere),
        "mask AUC": roc_auc(mask[articulated], mask[vehicles]),
    }
    agents = agent[articulated].unique().numel()
    return stats, (float(articulated.sum()) / agents if agents else 0.0)


def run_study(
    config: StudyConfig,
    *,
    progress: Callable[[str], None] | None = None,
    device: str | torch.device = "cpu",
) -> list[StudyRun]:
    """Fit and score every (seed, budget, variant) of ``config`` on ``device`` (the clip
    and the fits live there, as with ``dego demo --device``).
    ``lifted-labels`` is not fitted: each frame's pseudo labels lifted to 3D (the same
    for every budget). ``progress`` gets one line per run, ``lifted-labels`` included."""
    runs = []
    for seed in config.seeds:
        scene = SyntheticScene(seed, num_frames=config.frames, frame_dt=DEMO_FRAME_DT)
        clip = DemoClip.from_scene(scene).to(torch.device(device))
        lifted = None
        for budget in config.budgets:
            for variant in config.variants:
                if variant == "lifted-labels":
                    if lifted is None:
                        lifted = score_clip(lifted_clip_labels(clip), clip).row()
                    scores = _study_scores(lifted)
                    empty = dict.fromkeys(MASK_METRICS, math.nan)
                    runs.append(StudyRun(seed, budget, variant, scores, empty, math.nan, 0.0))
                    if progress is not None:
                        progress(
                            f"seed {seed} budget {budget} {variant} (no fit): {HEADLINE} "
                            f"{scores[HEADLINE]:.1f}"
                        )
                    continue
                fit_config = FitConfig(
                    iterations=config.iterations,
                    num_gaussians=budget,
                    seed=seed,
                    mask_sparsity=config.mask_prior if variant == "decoupled+prior" else 0.0,
                )
                name = variant.split("+")[0]
                result = fit_scene(clip, name, fit_config, scene=scene)  # type: ignore[arg-type]
                row = score_clip(predict_clip(result.model, result.deformation, clip), clip).row()
                scores = _study_scores(row)
                mask, per_agent = mask_statistics(result, clip)
                run = StudyRun(seed, budget, variant, scores, mask, per_agent, result.seconds)
                runs.append(run)
                if progress is not None:
                    progress(
                        f"seed {seed} budget {budget} {variant}: {HEADLINE} "
                        f"{scores[HEADLINE]:.1f}, {result.seconds:.0f} s"
                    )
    return runs


def _study_scores(row: dict[str, float]) -> dict[str, float]:
    """:data:`METRICS` from a :meth:`~dego.demo.ClipScore.row` (``X t=0`` is its ``X``)."""
    return {name: row[name.removesuffix(" t=0")] for name in METRICS}


# Two-sided 95% quantiles of Student's t for 1..30 degrees of freedom.
_T975 = (
    12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228,
    2.201, 2.179, 2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086,
    2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042,
)  # fmt: skip


MIN_INTERVAL_SEEDS = 3
"""The fewest values whose interval the report prints. With 2 the t quantile is 12.7 and
the interval is wider than the range of a bounded quantity (``mask AUC 0.70 [-0.86,
2.27]``): the report prints ``n/a (2 seeds)`` instead and marks no sign as resolved; the
JSON keeps the plain t-interval with its ``n``."""


@dataclasses.dataclass(frozen=True)
class Interval:
    """A mean with its 95% Student-t confidence interval over ``n`` values."""

    mean: float
    low: float
    high: float
    n: int

    def excludes_zero(self) -> bool:
        """Whether the interval resolves the sign: it excludes 0 and rests on at least
        :data:`MIN_INTERVAL_SEEDS` values."""
        return self.n >= MIN_INTERVAL_SEEDS and (self.low > 0 or self.high < 0)

    def __str__(self) -> str:
        if math.isnan(self.mean):
            return "nan"
        if self.n < 2:
            return f"{self.mean:.2f}"
        if self.n < MIN_INTERVAL_SEEDS:
            return f"{self.mean:.2f} [n/a ({self.n} seeds)]"
        return f"{self.mean:.2f} [{self.low:.2f}, {self.high:.2f}]"


def mean_interval(values: Sequence[float]) -> Interval:
    """Mean and 95% t-interval of the finite ``values`` (NaNs are dropped)."""
    finite = [v for v in values if not math.isnan(v)]
    n = len(finite)
    if n == 0:
        return Interval(math.nan, math.nan, math.nan, 0)
    mean = sum(finite) / n
    if n == 1:
        return Interval(mean, math.nan, math.nan, 1)
    sd = math.sqrt(sum((v - mean) ** 2 for v in finite) / (n - 1))
    t = _T975[n - 2] if n - 1 <= len(_T975) else 1.96
    half = t * sd / math.sqrt(n)
    return Interval(mean, mean - half, mean + half, n)


def paired_differences(
    runs: Sequence[StudyRun], metric: str, first: str, second: str
) -> dict[int, Interval]:
    """Per budget: ``first - second`` on ``metric``, paired by seed, with its interval."""
    table = {(r.seed, r.budget, r.variant): r for r in runs}
    out = {}
    for budget in sorted({r.budget for r in runs}):
        differences = [
            table[seed, budget, first].scores[metric] - table[seed, budget, second].scores[metric]
            for seed in sorted({r.seed for r in runs})
            if (seed, budget, first) in table and (seed, budget, second) in table
        ]
        out[budget] = mean_interval(differences)
    return out


def summarise(runs: Sequence[StudyRun]) -> dict[int, dict[str, dict[str, Interval]]]:
    """``{budget: {variant: {metric: Interval}}}`` over seeds, scores and mask metrics."""
    out: dict[int, dict[str, dict[str, Interval]]] = {}
    for budget in sorted({r.budget for r in runs}):
        out[budget] = {}
        variants = [v for v in STUDY_VARIANTS if any(r.variant == v for r in runs)]
        for variant in variants:
            chosen = [r for r in runs if r.budget == budget and r.variant == variant]
            values = {name: mean_interval([r.scores[name] for r in chosen]) for name in METRICS}
            values.update(
                {name: mean_interval([r.mask[name] for r in chosen]) for name in MASK_METRICS}
            )
            values["Gaussians per articulated agent"] = mean_interval(
                [r.per_articulated_agent for r in chosen]
            )
            out[budget][variant] = values
    return out


COMPARISONS = (
    ("decoupled", "static"),
    ("rigid", "static"),
    ("decoupled", "rigid"),
    ("decoupled+prior", "decoupled"),
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
        masked = {v: s for v, s in variants.items() if v.startswith("decoupled")}
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


PICTURED_GAINS = ("rigid", "decoupled", "free-offsets", "free-velocities", "true-motion")
"""The variants whose paired gain over ``static`` the study picture shows."""


def study_picture(runs: Sequence[StudyRun], path: Path) -> Path:
    """Write :func:`study_figure` to ``path`` (PNG, atomically; needs matplotlib)."""
    from dego.demo.pictures import png_bytes

    return write_files({path: png_bytes(study_figure(runs), dpi=90)})[0]


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
        right.set_title(
            f"{HEADLINE}, paired by seed; means of {seeds} seed(s), no interval "
            f"(needs {MIN_INTERVAL_SEEDS}+)",
            fontsize=9,
        )
    return figure


def write_study(
    runs: Sequence[StudyRun], config: StudyConfig, out: Path, *, pictures: bool = True
) -> tuple[str, list[Path]]:
    """Write ``study.md``, ``study.json`` and (with matplotlib) ``study.png`` to ``out``,
    all or nothing (:func:`dego._atomic.write_files`: a failure leaves the previous files
    as they were); return the Markdown report and the paths."""
    import json

    text, payload = study_report(runs, config)
    files: dict[Path, str | bytes] = {
        out / "study.md": text,
        out / "study.json": json.dumps(_json_safe(payload), indent=1) + "\n",
    }
    if pictures:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            pass
        else:
            from dego.demo.pictures import png_bytes

            files[out / "study.png"] = png_bytes(study_figure(runs), dpi=90)
    return text, write_files(files)


def _json_safe(value: object) -> object:
    """NaN -> None, recursively (JSON has no NaN)."""
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value
