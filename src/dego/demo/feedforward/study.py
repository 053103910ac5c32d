"""``dego train``: the feed-forward variants over seeds, scored on held-out scenes at t = 0.

For every seed: its own training and held-out scenes (:func:`scene_seeds`), then (the
``paired`` recipe) one single-frame warm-up and every variant fine-tuned from it on the same
scenes, frames and cameras in the same order (``scratch``: from the same initial weights),
and scored on the held-out scenes. The report gives means with 95% t-intervals over seeds and
paired differences (same seed), as ``dego study`` does.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import Tensor

from dego._atomic import write_files
from dego._units import UNIT
from dego.demo.feedforward.data import (
    HELDOUT_SPLIT,
    TRAIN_SPLIT,
    DataConfig,
    SceneRecord,
    load_scenes,
    scene_seeds,
)
from dego.demo.feedforward.evaluate import SCORES, predict_scene, score_scenes
from dego.demo.feedforward.training import (
    FEEDFORWARD_VARIANTS,
    TrainConfig,
    predict,
    train,
    warm_up,
)
from dego.demo.fit import row_name
from dego.demo.stats import (
    MIN_INTERVAL_SEEDS,
    Interval,
    StudyRun,
    check_distinct,
    check_seeds,
    json_safe,
    mean_interval,
    paired_differences,
)


@dataclasses.dataclass(frozen=True)
class FeedForwardStudyConfig:
    """What :func:`run_feedforward_study` runs.

    Attributes:
        seeds: run seeds (each: its own scenes, initial weights and order), each once.
        variants: some of :data:`~dego.demo.feedforward.FEEDFORWARD_VARIANTS`, each once.
        data: the scenes. train: the training settings (its ``seed`` is each run's seed).
    """

    seeds: tuple[int, ...] = (0,)
    variants: tuple[str, ...] = FEEDFORWARD_VARIANTS
    data: DataConfig = dataclasses.field(default_factory=DataConfig)
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        for name in ("seeds", "variants"):
            check_distinct(name, getattr(self, name))
        check_seeds(self.seeds)
        unknown = sorted(set(self.variants) - set(FEEDFORWARD_VARIANTS))
        if unknown:
            raise ValueError(
                f"variants: unknown {unknown}; expected some of {FEEDFORWARD_VARIANTS}"
            )


PRESETS: dict[str, FeedForwardStudyConfig] = {
    "quick": FeedForwardStudyConfig(
        seeds=(0,),
        data=DataConfig(train_scenes=2, heldout_scenes=1, image_size=(32, 88)),
        train=TrainConfig(steps=3, warmup_steps=3, block=8, width=8, hidden_dim=16, head_hidden=16),
    ),
    "cpu": FeedForwardStudyConfig(),
    "full": FeedForwardStudyConfig(seeds=(0, 1, 2, 3, 4)),
}
"""``dego train --quick`` (the wiring only: a few steps on two tiny scenes), the default
(one seed, sized for a CPU) and ``--full`` (seeds 0-4, the study with intervals)."""

COMPARISONS = (
    ("static", "single-frame"),
    ("true-motion", "static"),
    ("decoupled", "static"),
    ("velocity", "static"),
    ("rigid", "static"),
    ("velocity", "decoupled"),
    ("decoupled", "rigid"),
    ("decoupled", "single-frame"),
    ("velocity", "single-frame"),
)
"""Paired differences of the report (first - second, same seed). ``static -
single-frame``: what the other frames' labels do to t = 0 without a motion model (the harm
the paper's deformation removes); ``true-motion - static``: what ground-truth motion wins
back; ``decoupled - static`` / ``velocity - static``: what DeGO's deformation and our
constant-velocity one win back."""

PAIRED_SCORES = (
    "HCM",
    "mIoU",
    "people voxels",
    "people blocks",
    "articulated",
    "vehicles",
    "IoU",
    "RayIoU",
)
"""The scores of the paired-difference table."""

PER_SEED_SCORES = ("mIoU", "HCM", "people voxels", "articulated")
"""The scores of the per-seed table."""

PICTURED_SCENE = 0
"""Which held-out scene (of the first seed) the pictures show."""


@dataclasses.dataclass
class FeedForwardRuns:
    """What :func:`run_feedforward_study` returns: one :class:`~dego.demo.stats.StudyRun` per
    (seed, variant), its ``budget`` the Gaussians per scene, and the first seed's labels of
    the pictured held-out scene per variant (with that scene) for pictures; the seconds
    spent on scenes and on the shared warm-ups."""

    runs: list[StudyRun]
    pictured_labels: dict[str, Tensor]
    pictured_scene: SceneRecord | None
    data_seconds: float
    warmup_seconds: float = 0.0


def run_feedforward_study(
    config: FeedForwardStudyConfig,
    *,
    cache: Path | None,
    device: str | torch.device = "cpu",
    progress: Callable[[str, int, int, float], None] | None = None,
    note: Callable[[str], None] | None = None,
) -> FeedForwardRuns:
    """Train and score every (seed, variant) of ``config`` on ``device``.

    ``progress(label, step, steps, loss)`` is called after every training step (and after
    every scene rendered or read, with ``loss`` NaN), ``note`` with one line per finished
    stage (scenes loaded, a variant scored)."""
    device = torch.device(device)
    runs: list[StudyRun] = []
    pictured: dict[str, Tensor] = {}
    pictured_scene = None
    data_seconds = warmup_seconds = 0.0
    for seed in config.seeds:
        start = time.perf_counter()
        data = config.data
        seeds = scene_seeds(seed, TRAIN_SPLIT, data.train_scenes)
        seeds += scene_seeds(seed, HELDOUT_SPLIT, data.heldout_scenes)

        def loaded(done: int, total: int, label: str = f"{seed}/scenes") -> None:
            if progress is not None:
                progress(label, done - 1, total, math.nan)

        scenes = load_scenes(seeds, data, cache, progress=loaded)
        train_set, heldout = scenes[: data.train_scenes], scenes[data.train_scenes :]
        train_set = [r.to(device) for r in train_set]
        heldout = [r.to(device) for r in heldout]
        data_seconds += time.perf_counter() - start
        if note is not None:
            note(
                f"seed {seed}: {len(train_set)} training + {len(heldout)} held-out scenes "
                f"ready ({time.perf_counter() - start:.1f} s)"
            )
        settings = dataclasses.replace(config.train, seed=seed)
        start_network = None
        if settings.recipe == "paired":

            def warm_step(
                index: int,
                loss: float,
                label: str = f"{seed}/warm-up",
                total: int = settings.warmup_steps,
            ) -> None:
                if progress is not None:
                    progress(label, index, total, loss)

            warm = warm_up(train_set, settings, progress=warm_step)
            start_network, warmup_seconds = warm.network, warmup_seconds + warm.seconds
            if note is not None:
                note(
                    f"seed {seed}: single-frame warm-up, {settings.warmup_steps} steps "
                    f"({warm.seconds:.0f} s)"
                )
        steps = settings.steps if settings.recipe == "paired" else settings.total_steps
        for variant in config.variants:
            label = f"{seed}/{variant}"

            def step(index: int, loss: float, label: str = label, total: int = steps) -> None:
                if progress is not None:
                    progress(label, index, total, loss)

            result = train(
                train_set,
                variant,  # type: ignore[arg-type]
                settings,
                start=start_network,
                progress=step,
            )
            predicted = [predict_scene(result.network, r, settings.depth_source) for r in heldout]
            labels = [grid for grid, _ in predicted]
            scores = score_scenes(labels, heldout, [people for _, people in predicted])
            with torch.no_grad():
                prediction = predict(result.network, heldout[0], settings.depth_source)
                gaussians = prediction.gaussians.num_gaussians
            runs.append(StudyRun(seed, gaussians, variant, scores, {}, math.nan, result.seconds))
            if seed == config.seeds[0]:
                pictured[variant] = labels[PICTURED_SCENE].cpu()
                pictured_scene = heldout[PICTURED_SCENE]
            if note is not None:
                note(
                    f"seed {seed} {row_name(variant)}: mIoU {scores['mIoU']:.1f}, HCM "
                    f"{scores['HCM']:.1f}, people voxels {scores['people voxels']:.0f}%, "
                    f"articulated {scores['articulated']:.1f} ({result.seconds:.0f} s)"
                )
    return FeedForwardRuns(runs, pictured, pictured_scene, data_seconds, warmup_seconds)


def summarise(runs: Sequence[StudyRun]) -> dict[str, dict[str, Interval]]:
    """``{variant: {score: Interval}}`` over seeds."""
    variants = [v for v in FEEDFORWARD_VARIANTS if any(r.variant == v for r in runs)]
    return {
        v: {s: mean_interval([r.scores[s] for r in runs if r.variant == v]) for s in SCORES}
        for v in variants
    }


def paired(runs: Sequence[StudyRun]) -> dict[tuple[str, str], dict[str, Interval]]:
    """``{(first, second): {score: Interval}}`` of :data:`COMPARISONS` present in ``runs``."""
    present = {r.variant for r in runs}
    out = {}
    for first, second in COMPARISONS:
        if {first, second} <= present:
            out[first, second] = {
                s: next(iter(paired_differences(runs, s, first, second).values()))
                for s in PAIRED_SCORES
            }
    return out


def feedforward_report(
    result: FeedForwardRuns, config: FeedForwardStudyConfig, *, wall_seconds: float, device: str
) -> tuple[str, dict]:
    """The Markdown report and its JSON payload."""
    runs = result.runs
    summary, differences = summarise(runs), paired(runs)
    data, training = config.data, config.train
    gaussians = runs[0].budget if runs else 0
    lines = [
        "# dego train: a feed-forward Gaussian occupancy network, with and without deformation",
        "",
        f"Seeds {list(config.seeds)}; per seed {data.train_scenes} training and "
        f"{data.heldout_scenes} held-out synthetic scenes of {data.frames} frames "
        f"({data.frame_dt} s apart, {data.image_size[0]}x{data.image_size[1]} pixels, six "
        f"cameras{_noise(data.depth_noise)}); {_recipe(training)}; {gaussians} Gaussians per "
        f"scene, depth {_depth(training)}; {device}, {wall_seconds:.0f} s wall in all. "
        "Held-out scenes at t = 0 (inference: one frame of images), weak protocol inside the "
        "camera mask, percent, mean [95% t-interval over seeds].",
    ]
    if len(config.seeds) < MIN_INTERVAL_SEEDS:
        lines += [
            "",
            f"With {len(config.seeds)} seed(s) there are no intervals (at least "
            f"{MIN_INTERVAL_SEEDS} are needed): every value is a single draw, not a comparison.",
        ]
    lines += ["", "| variant | " + " | ".join(SCORES) + " |", "|---|" + "---|" * len(SCORES)]
    for variant, values in summary.items():
        lines.append(
            f"| {row_name(variant)} | " + " | ".join(str(values[s]) for s in SCORES) + " |"
        )
    lines += [
        "",
        "Paired differences (first - second, same seed and data), points; `*`: the interval "
        "excludes 0:",
        "",
        "| difference | n | " + " | ".join(PAIRED_SCORES) + " |",
        "|---|---:|" + "---|" * len(PAIRED_SCORES),
    ]
    for (first, second), values in differences.items():
        cells = [f"{values[s]}{' *' if values[s].excludes_zero() else ''}" for s in PAIRED_SCORES]
        n = values[PAIRED_SCORES[0]].n
        lines.append(
            f"| {row_name(first)} - {row_name(second)} | {n} | " + " | ".join(cells) + " |"
        )
    variants = list(summary)
    lines += [
        "",
        f"Per seed, {' / '.join(PER_SEED_SCORES)}:",
        "",
        "| seed | " + " | ".join(row_name(v) for v in variants) + " |",
        "|---:|" + "---|" * len(variants),
    ]
    by_key = {(r.seed, r.variant): r.scores for r in runs}
    for seed in config.seeds:
        cells = [
            " / ".join(f"{by_key[seed, v][s]:.1f}" for s in PER_SEED_SCORES)
            if (seed, v) in by_key
            else "-"
            for v in variants
        ]
        lines.append(f"| {seed} | " + " | ".join(cells) + " |")
    lines += ["", "## Reading", "", *_reading(differences), *_won_back(runs)]
    payload = {
        "units": UNIT,
        "settings": {
            "seeds": list(config.seeds),
            "variants": list(config.variants),
            "data": dataclasses.asdict(data),
            "train": dataclasses.asdict(training),
            "device": device,
            "wall_seconds": wall_seconds,
            "data_seconds": result.data_seconds,
            "warmup_seconds": result.warmup_seconds,
        },
        "runs": [dataclasses.asdict(r) for r in runs],
        "summary": {
            v: {s: dataclasses.asdict(i) for s, i in d.items()} for v, d in summary.items()
        },
        "paired": {
            f"{a} - {b}: {s}": dataclasses.asdict(i)
            for (a, b), d in differences.items()
            for s, i in d.items()
        },
        "won_back": {
            v: {"share": share, "at_least_half": dataclasses.asdict(half)}
            for v in RECOVERING
            if (found := won_back(runs, v)) is not None
            for share, half in [found]
        },
    }
    return "\n".join(lines) + "\n", payload


def _noise(depth_noise: float) -> str:
    return f", pseudo depth noise {depth_noise:g}" if depth_noise else ""


def _depth(training: TrainConfig) -> str:
    if training.depth_source == "anchored":
        return "anchored on the t = 0 pseudo depth"
    return "learned"


def _recipe(training: TrainConfig) -> str:
    if training.recipe == "paired":
        return (
            f"a shared single-frame warm-up of {training.warmup_steps} steps, then "
            f"{training.steps} steps per variant from it"
        )
    return f"{training.total_steps} steps per variant from the initial weights"


QUESTIONS = (
    ("static", "single-frame", "HCM", "do the other frames' labels harm t = 0 without motion?"),
    ("true-motion", "static", "HCM", "does the true motion win it back?"),
    ("decoupled", "static", "HCM", "does DeGO's deformation win it back?"),
    ("velocity", "static", "HCM", "does the constant-velocity deformation win it back?"),
    ("decoupled", "static", "mIoU", "and DeGO's on mIoU?"),
    ("velocity", "decoupled", "HCM", "velocity or DeGO's time-conditioned rigid branch?"),
)
"""The questions the reading answers, one paired difference each."""

RECOVERING = ("true-motion", "decoupled", "velocity", "rigid")
"""The variants whose share of the harm won back the reading gives (:func:`won_back`)."""

WON_BACK_SCORE = "HCM"
"""The score of :func:`won_back`."""


def won_back(
    runs: Sequence[StudyRun], variant: str, score: str = WON_BACK_SCORE
) -> tuple[float, Interval] | None:
    """How much of the harm ``static - single-frame`` ``variant`` wins back on ``score``.

    Returns ``(share, half)``: ``share = mean(variant - static) / mean(single-frame -
    static)`` (1: all of it; NaN where the mean harm is not negative) and the interval over
    seeds of ``(variant - static) - (single-frame - static) / 2`` per seed: above 0 means at
    least half of the harm is won back. ``None`` without the three variants.
    """
    table = {(r.seed, r.variant): r.scores[score] for r in runs}
    needed = (variant, "static", "single-frame")
    seeds = sorted({s for s, _ in table if all((s, v) in table for v in needed)})
    if not seeds:
        return None
    gains = [table[s, variant] - table[s, "static"] for s in seeds]
    harms = [table[s, "single-frame"] - table[s, "static"] for s in seeds]
    harm = sum(harms) / len(harms)
    share = (sum(gains) / len(gains)) / harm if harm > 0 else math.nan
    half = mean_interval([g - h / 2 for g, h in zip(gains, harms, strict=True)])
    return share, half


def _won_back(runs: Sequence[StudyRun]) -> list[str]:
    out = []
    for variant in RECOVERING:
        found = won_back(runs, variant)
        if found is None:
            continue
        share, half = found
        if math.isnan(share):
            out.append(
                f"- {row_name(variant)}: static did not score below single-frame on "
                f"{WON_BACK_SCORE}, so there is no harm to win back."
            )
            continue
        if half.n < MIN_INTERVAL_SEEDS:
            verdict = "too few seeds for an interval"
        elif half.excludes_zero():
            least = "at least" if half.mean > 0 else "less than"
            verdict = f"{least} half, the interval excludes 0"
        else:
            verdict = "whether it is at least half is not resolved"
        out.append(
            f"- {row_name(variant)} wins back {share:.0%} of the harm on {WON_BACK_SCORE} "
            f"(gain minus half the harm, per seed: {half} points; {verdict})."
        )
    return out


def _reading(differences: dict[tuple[str, str], dict[str, Interval]]) -> list[str]:
    out = []
    for first, second, score, question in QUESTIONS:
        if (first, second) not in differences:
            continue
        interval = differences[first, second][score]
        if interval.n < MIN_INTERVAL_SEEDS:
            verdict = f"{interval.n} seed(s): no interval, the sign is not resolved"
        elif interval.excludes_zero():
            verdict = f"the interval excludes 0 ({'positive' if interval.mean > 0 else 'negative'})"
        else:
            verdict = "the interval includes 0: the sign is not resolved"
        out.append(
            f"- {question} {row_name(first)} - {row_name(second)} on {score} at t = 0: "
            f"{interval} points; {verdict}."
        )
    return out


def feedforward_outputs(out: Path, variants: Sequence[str], *, pictures: bool = True) -> list[Path]:
    """Every file :func:`write_feedforward_study` writes to ``out`` for ``variants`` (the
    pictures' names whether or not matplotlib is here), checked before the run starts."""
    names = ["train.md", "train.json"]
    if pictures:
        names += [f"heldout_{variant}.png" for variant in variants]
    return [out / name for name in names]


def write_feedforward_study(
    result: FeedForwardRuns,
    config: FeedForwardStudyConfig,
    out: Path,
    *,
    wall_seconds: float,
    device: str,
    pictures: bool = True,
) -> tuple[str, list[Path]]:
    """Write ``train.md``, ``train.json`` and (with matplotlib) ``heldout_<variant>.png``
    to ``out``, all or nothing; return the report and the paths."""
    text, payload = feedforward_report(result, config, wall_seconds=wall_seconds, device=device)
    files: dict[Path, str | bytes] = {
        out / "train.md": text,
        out / "train.json": json.dumps(json_safe(payload), indent=1) + "\n",
    }
    if pictures and result.pictured_scene is not None:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            pass
        else:
            from dego.demo.pictures import bev_figure
            from dego.viz import png_bytes

            clip = result.pictured_scene.reference_clip()
            for variant, labels in result.pictured_labels.items():
                figure = bev_figure(labels, clip, f"{row_name(variant)} (held-out scene)")
                files[out / f"heldout_{variant}.png"] = png_bytes(figure)
    return text, write_files(files)
