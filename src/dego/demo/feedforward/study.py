"""``dego train``: the feed-forward variants over seeds, scored on held-out scenes at t = 0.

For every seed: its own training and held-out scenes (:func:`scene_seeds`), then every
variant trained from the same initial weights on the same scenes in the same order, and
scored on the held-out scenes. The report gives means with 95% t-intervals over seeds and
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
from dego.demo.feedforward.evaluate import SCORES, predict_scene_labels, score_scenes
from dego.demo.feedforward.training import FEEDFORWARD_VARIANTS, TrainConfig, predict, train
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
        train=TrainConfig(steps=3, block=8, width=8, hidden_dim=16, head_hidden=16),
    ),
    "cpu": FeedForwardStudyConfig(),
    "full": FeedForwardStudyConfig(seeds=(0, 1, 2)),
}
"""``dego train --quick`` (the wiring only: a few steps on two tiny scenes), the default
(one seed, sized for a CPU) and ``--full`` (three seeds, the study with intervals)."""

COMPARISONS = (
    ("static", "single-frame"),
    ("decoupled", "static"),
    ("rigid", "static"),
    ("decoupled", "rigid"),
    ("true-motion", "static"),
    ("decoupled", "single-frame"),
)
"""Paired differences of the report (first - second, same seed). ``static -
single-frame``: what the other frames' labels do to t = 0 without a motion model (the harm
the paper's deformation removes); ``decoupled - static``: whether the deformation wins it
back; ``true-motion - static``: what ground-truth motion would have bought."""

PAIRED_SCORES = ("HCM", "mIoU", "articulated", "vehicles", "IoU", "RayIoU")
"""The scores of the paired-difference table."""

PER_SEED_SCORES = ("mIoU", "HCM", "vehicles", "articulated")
"""The scores of the per-seed table."""

PICTURED_SCENE = 0
"""Which held-out scene (of the first seed) the pictures show."""


@dataclasses.dataclass
class FeedForwardRuns:
    """What :func:`run_feedforward_study` returns: one :class:`~dego.demo.stats.StudyRun` per
    (seed, variant), its ``budget`` the Gaussians per scene, and the first seed's labels of
    the pictured held-out scene per variant (with that scene) for pictures."""

    runs: list[StudyRun]
    pictured_labels: dict[str, Tensor]
    pictured_scene: SceneRecord | None
    data_seconds: float


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
    data_seconds = 0.0
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
        for variant in config.variants:
            label = f"{seed}/{variant}"

            def step(
                index: int, loss: float, label: str = label, steps: int = settings.steps
            ) -> None:
                if progress is not None:
                    progress(label, index, steps, loss)

            result = train(train_set, variant, settings, progress=step)  # type: ignore[arg-type]
            labels = [predict_scene_labels(result.network, r) for r in heldout]
            scores = score_scenes(labels, heldout)
            with torch.no_grad():
                gaussians = predict(result.network, heldout[0]).gaussians.num_gaussians
            runs.append(StudyRun(seed, gaussians, variant, scores, {}, math.nan, result.seconds))
            if seed == config.seeds[0]:
                pictured[variant] = labels[PICTURED_SCENE].cpu()
                pictured_scene = heldout[PICTURED_SCENE]
            if note is not None:
                note(
                    f"seed {seed} {row_name(variant)}: mIoU {scores['mIoU']:.1f}, HCM "
                    f"{scores['HCM']:.1f}, articulated {scores['articulated']:.1f} "
                    f"({result.seconds:.0f} s)"
                )
    return FeedForwardRuns(runs, pictured, pictured_scene, data_seconds)


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
        f"cameras); {training.steps} steps per variant, {gaussians} Gaussians per scene; "
        f"{device}, {wall_seconds:.0f} s wall in all. Held-out scenes at t = 0 (inference: "
        "one frame of images), weak protocol inside the camera mask, percent, mean [95% "
        "t-interval over seeds].",
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
    lines += ["", "## Reading", "", *_reading(differences)]
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
    }
    return "\n".join(lines) + "\n", payload


QUESTIONS = (
    ("static", "single-frame", "HCM", "do the other frames' labels harm t = 0 without motion?"),
    ("decoupled", "static", "HCM", "does DeGO's deformation win it back?"),
    ("decoupled", "static", "mIoU", "and on mIoU?"),
    ("true-motion", "static", "HCM", "what would ground-truth motion have bought?"),
)
"""The questions the reading answers, one paired difference each."""


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
