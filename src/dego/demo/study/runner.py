"""``dego study``'s runs: the variants, the scores it keeps, its settings and the loop that
fits and scores every (seed, budget, variant).

For every seed a synthetic clip is rendered; for every total Gaussian budget each
variant (``static``, ``rigid``, ``decoupled``, ``decoupled`` with the optional mask
prior, and the reference rows ``single-frame``, ``free-offsets``, ``free-velocities``
and the ground-truth ``true-motion`` oracle) is fitted from the pseudo labels and scored
at every frame (:mod:`dego.demo`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import torch
from jaxtyping import Float
from torch import Tensor

from dego._checks import check_int
from dego.data.synthetic import SyntheticScene
from dego.demo.clip import DEMO_FRAME_DT, MAX_DEMO_FRAMES, DemoClip, max_gaussians
from dego.demo.evaluate import OFFSET_GROUPS, lifted_clip_labels, predict_clip, score_clip
from dego.demo.fit import FitConfig, FitResult, fit_scene, rigidity_mask
from dego.demo.offsets import agent_under
from dego.demo.stats import Interval, StudyRun, check_distinct, check_seeds, mean_interval

STUDY_VARIANTS = (
    "lifted-labels",
    "single-frame",
    "static",
    "rigid",
    "decoupled",
    "decoupled+prior",
    "velocity",
    "free-offsets",
    "free-velocities",
    "true-motion",
)
""":data:`~dego.demo.VARIANTS`, :data:`~dego.demo.EXTENSION_VARIANTS` (``velocity``, ours)
and :data:`~dego.demo.REFERENCE_VARIANTS`, the ``lifted-labels`` ceiling (no fit: each
frame's pseudo labels lifted to 3D), and
``decoupled+prior``: ``decoupled`` with :attr:`StudyConfig.mask_prior` as the weight of
the mask sparsity prior (:attr:`~dego.demo.FitConfig.mask_sparsity`). ``true-motion``
uses the ground truth (a ceiling, not a competitor)."""

DEFAULT_STUDY_VARIANTS = tuple(
    v for v in STUDY_VARIANTS if v not in ("decoupled+prior", "velocity")
)
"""What ``dego study`` fits unless told otherwise (``--variants``; ``velocity`` and
``decoupled+prior`` on request)."""

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


QUICK_STUDY = StudyConfig(
    seeds=(0, 1), budgets=(300,), frames=3, iterations=20, variants=STUDY_VARIANTS
)
"""``dego study --quick``: the tiny settings the tests run."""


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
