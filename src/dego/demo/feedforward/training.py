"""Train the feed-forward network on many scenes' pseudo labels, with or without deformation.

Every step takes one training scene, predicts its Gaussians from the reference frame's
images (their depth along the rays anchored on the reference frame's pseudo depth unless
``depth="learned"``), and renders them into a random subset of cameras at the reference
frame and (all but ``single-frame``) at one other frame, drawn at random: there the
Gaussians are ``static`` (as predicted), moved by the deformation network on the network's
latents (``rigid``: position offsets only; ``decoupled``: DeGO's rigid / nonrigid mask;
``velocity``: the same with one velocity per Gaussian as the rigid branch), or moved with
the ground-truth agent they sit on (``true-motion``, an oracle for analysis). The loss is
:func:`~dego.losses.rendering_loss` (semantics + ``depth_weight *`` depth) against each
rendered frame's pseudo labels, averaged over the frames, plus the deformation's
regulariser.

The ``paired`` recipe (default) trains one network on the reference frame's labels
(:func:`warm_up`, shared by the variants of a seed) and fine-tunes a copy of it per variant
(:func:`fine_tune`) on the same scenes, frames and cameras in the same order; ``scratch``
trains each variant from the initial weights for as many steps in all.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import Literal

import torch
from torch import Tensor

from dego._checks import check_int, check_positive
from dego.classes import FREE_LABEL
from dego.deformation import DecoupledDeformation, deformation_loss
from dego.demo.feedforward.data import SceneRecord
from dego.demo.feedforward.network import SCALE_FLOOR, GaussianPredictor, Prediction
from dego.demo.fit import MAX_SEED, most_likely_in
from dego.demo.model import MOVABLE_CLASSES
from dego.demo.offsets import agent_offsets, agent_under
from dego.gaussians import GaussianSet
from dego.losses import RenderingLossWeights, rendering_loss
from dego.splatting import splat

FeedForwardVariant = Literal[
    "single-frame", "static", "rigid", "decoupled", "velocity", "true-motion"
]
FEEDFORWARD_VARIANTS: tuple[FeedForwardVariant, ...] = (
    "single-frame",
    "static",
    "rigid",
    "decoupled",
    "velocity",
    "true-motion",
)
"""``single-frame``: the reference frame's labels only; ``static``: every frame's labels, no
deformation; ``rigid``: position offsets from the deformation network (mask fixed at 0);
``decoupled``: DeGO's deformation with its learned rigid / nonrigid mask; ``velocity``: the
same with a constant-velocity rigid branch (``rigid_motion="velocity"``, ours, beyond the
paper); ``true-motion``: the Gaussians on a ground-truth agent move with it (**uses the
ground truth**: a ceiling for position offsets, analysis only)."""

DEFORMED_VARIANTS: tuple[FeedForwardVariant, ...] = ("rigid", "decoupled", "velocity")
"""The variants with a :class:`~dego.DecoupledDeformation`."""

DepthSource = Literal["anchored", "learned"]
DEPTH_SOURCES: tuple[DepthSource, ...] = ("anchored", "learned")
"""Where a predicted Gaussian's distance along its ray comes from: ``anchored``: the
reference frame's pseudo depth at its pixel (the network's depth where there is none);
``learned``: the network's own prediction (the paper's; it learns depth from Metric3D
labels over 30 epochs of nuScenes)."""

Recipe = Literal["paired", "scratch"]
RECIPES: tuple[Recipe, ...] = ("paired", "scratch")
"""``paired``: one shared single-frame warm-up per seed, then each variant fine-tuned from
it; ``scratch``: each variant trained from the initial weights."""


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Settings of :func:`train` (the defaults are ``dego train``'s CPU default).

    Attributes:
        steps: each variant's own optimiser steps, one training scene each (after the
            warm-up under ``recipe="paired"``).
        warmup_steps: steps of the shared single-frame warm-up (``paired``); under
            ``scratch`` each variant trains ``warmup_steps + steps`` steps from scratch.
        recipe: ``"paired"`` or ``"scratch"`` (:data:`RECIPES`).
        lr: Adam learning rate of the image network (the warm-up, and ``scratch``).
        finetune_lr: the image network's learning rate when fine-tuning (``paired``).
        deformation_lr: the deformation network's learning rate.
        cosine: cosine-decay each phase's learning rates to 0 (else constant).
        clip_norm: clip the gradient's global norm to it (0: no clipping).
        class_weights: weight the cross-entropy by median-frequency class weights of the
            training scenes' pseudo labels (:func:`median_frequency_weights`).
        depth_source: ``"anchored"`` or ``"learned"`` (:data:`DEPTH_SOURCES`).
        scale_floor: the smallest predicted scale in metres (:data:`SCALE_FLOOR`).
        cameras_per_step: cameras rendered per frame and step (a seeded random subset).
        depth_weight, deformation_weight: loss weights (as :class:`~dego.demo.FitConfig`).
        block, width, latent_dim: :class:`GaussianPredictor`'s size.
        hidden_dim, depth, head_hidden, pos_scale: the deformation network's size and
            position scale (as :class:`~dego.demo.FitConfig`).
        deform: ``"movable"``: only Gaussians whose predicted class is movable are
            deformed (:class:`~dego.demo.FitConfig`'s default); ``"all"``: every one.
        seed: the networks' initial weights and the scene / frame / camera order.
    """

    steps: int = 100
    warmup_steps: int = 400
    recipe: Recipe = "paired"
    lr: float = 2e-3
    finetune_lr: float = 1e-3
    deformation_lr: float = 1e-2
    cosine: bool = False
    clip_norm: float = 0.0
    class_weights: bool = False
    depth_source: DepthSource = "anchored"
    scale_floor: float = SCALE_FLOOR
    cameras_per_step: int = 3
    depth_weight: float = 0.1
    deformation_weight: float = 0.001
    block: int = 4
    width: int = 32
    latent_dim: int = 16
    hidden_dim: int = 64
    depth: int = 3
    head_hidden: int = 64
    pos_scale: float = 4.0
    deform: Literal["movable", "all"] = "movable"
    seed: int = 0

    def __post_init__(self) -> None:
        check_int("steps", self.steps, 0)
        check_int("warmup_steps", self.warmup_steps, 0)
        for name in ("lr", "finetune_lr", "deformation_lr", "pos_scale"):
            check_positive(name, getattr(self, name))
        for name in ("cameras_per_step", "width", "hidden_dim", "depth", "head_hidden"):
            check_int(name, getattr(self, name), 1)
        check_int("latent_dim", self.latent_dim, 0)
        check_int("seed", self.seed, 0)
        if self.seed > MAX_SEED:
            raise ValueError(f"seed: expected an int in [0, {MAX_SEED}], got {self.seed!r}")
        for name in ("depth_weight", "deformation_weight", "clip_norm"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name}: expected a finite number >= 0, got {value!r}")
        if self.deform not in ("movable", "all"):
            raise ValueError(f"deform: expected 'movable' or 'all', got {self.deform!r}")
        if self.recipe not in RECIPES:
            raise ValueError(f"recipe: expected one of {RECIPES}, got {self.recipe!r}")
        if self.depth_source not in DEPTH_SOURCES:
            raise ValueError(
                f"depth_source: expected one of {DEPTH_SOURCES}, got {self.depth_source!r}"
            )
        check_positive("scale_floor", self.scale_floor)
        if self.scale_floor >= 1.0:
            raise ValueError(
                f"scale_floor: expected < 1 m (the largest scale), got {self.scale_floor}"
            )
        GaussianPredictor(block=self.block, width=1, latent_dim=0)  # checks block

    @property
    def total_steps(self) -> int:
        """Steps behind each variant's network: ``warmup_steps + steps``."""
        return self.warmup_steps + self.steps


@dataclasses.dataclass
class TrainResult:
    """What :func:`train` returns: the trained ``network``, its ``deformation`` (``None``
    for ``single-frame``, ``static`` and ``true-motion``), the loss per step of this
    variant's own training and its wall time (a shared warm-up's are not included)."""

    variant: FeedForwardVariant
    network: GaussianPredictor
    deformation: DecoupledDeformation | None
    history: list[float]
    seconds: float


def build_network(config: TrainConfig) -> GaussianPredictor:
    """The untrained image network of ``config``."""
    return GaussianPredictor(
        block=config.block,
        width=config.width,
        latent_dim=config.latent_dim,
        scale_range=(config.scale_floor, 1.0),
    )


def build_deformation(
    variant: FeedForwardVariant, config: TrainConfig, times: Tensor
) -> DecoupledDeformation | None:
    """The ``paper``-preset deformation network of :data:`DEFORMED_VARIANTS` (times in
    frames, scaled by the largest offset of ``times``), else ``None``."""
    if variant not in FEEDFORWARD_VARIANTS:
        raise ValueError(f"variant: expected one of {FEEDFORWARD_VARIANTS}, got {variant!r}")
    if variant not in DEFORMED_VARIANTS:
        return None
    return DecoupledDeformation(
        config.latent_dim,
        hidden_dim=config.hidden_dim,
        depth=config.depth,
        head_hidden=config.head_hidden,
        time_scale=float(times.abs().max().clamp_min(1)),
        pos_scale=config.pos_scale,
        fixed_mask=0.0 if variant == "rigid" else None,
        rigid_motion="velocity" if variant == "velocity" else "time",
    )


def predict(
    network: GaussianPredictor, record: SceneRecord, depth_source: DepthSource = "anchored"
) -> Prediction:
    """The network's ``(1, N)`` Gaussians of ``record`` from its reference-frame images
    (``depth_source="anchored"``: on the reference frame's pseudo depth)."""
    if depth_source not in DEPTH_SOURCES:
        raise ValueError(f"depth_source: expected one of {DEPTH_SOURCES}, got {depth_source!r}")
    ref = record.reference
    anchor = record.depth[ref][None] if depth_source == "anchored" else None
    return network(
        record.images[None],
        record.world_to_cam[ref][None],
        record.intrinsics[ref][None],
        anchor_depth=anchor,
    )


def gaussians_at_frame(
    prediction: Prediction,
    variant: FeedForwardVariant,
    deformation: DecoupledDeformation | None,
    record: SceneRecord,
    index: int,
    deform: Literal["movable", "all"] = "movable",
) -> tuple[GaussianSet, Tensor]:
    """The ``(1, N)`` predicted Gaussians carried to frame ``index`` of ``record`` by
    ``variant``, and the deformation's regulariser (0 where there is none)."""
    canonical = prediction.gaussians
    zero = canonical.means.new_zeros(())
    if index == record.reference or variant in ("static", "single-frame"):
        return canonical, zero
    if variant == "true-motion":
        agent = agent_under(canonical.means[0], record.reference_clip())
        offsets = agent_offsets(record.agent_translations, agent)[index]  # (N, 3)
        return canonical.replace(means=canonical.means + offsets[None]), zero
    assert deformation is not None
    times = record.times[index : index + 1]
    output = deformation(canonical, prediction.latent, times)
    if deform == "movable":
        output = output.gated(
            most_likely_in(prediction.logits[0], MOVABLE_CLASSES)[None], canonical
        )
    return output.at(0), deformation_loss(output).total


def median_frequency_weights(records: Sequence[SceneRecord]) -> Tensor:
    """``(18,)`` median-frequency weights of the pseudo labels of ``records`` (every frame,
    supervised pixels): ``median(f) / f_c`` over the labels present (free space included),
    1 for a label never seen."""
    counts = sum(
        torch.bincount(r.semantics[r.supervised].flatten().cpu(), minlength=FREE_LABEL + 1)
        for r in records
    )
    assert isinstance(counts, Tensor)
    frequency = counts.double() / counts.sum().clamp_min(1)
    seen = counts > 0
    if not seen.any():
        return torch.ones(FREE_LABEL + 1)
    weights = torch.where(seen, frequency[seen].median() / frequency.clamp_min(1e-12), 1.0)
    return weights.float()


def step_loss(
    network: GaussianPredictor,
    deformation: DecoupledDeformation | None,
    record: SceneRecord,
    variant: FeedForwardVariant,
    config: TrainConfig,
    generator: torch.Generator,
    class_weights: Tensor | None = None,
) -> Tensor:
    """One step's loss on ``record`` (see the module docstring). Every variant draws the
    same numbers from ``generator`` (``single-frame`` draws the other frame too and does not
    render it), so variants that share a generator state see the same frames and cameras."""
    prediction = predict(network, record, config.depth_source)
    frames = [record.reference]
    others = [i for i in range(record.num_frames) if i != record.reference]
    other = others[int(torch.randint(len(others), (), generator=generator))] if others else None
    if variant != "single-frame" and other is not None:
        frames.append(other)
    weights = RenderingLossWeights(semantic=1.0, depth=config.depth_weight)
    views = record.world_to_cam.shape[1]
    draws = [torch.randperm(views, generator=generator) for _ in range(2)]
    total = prediction.gaussians.means.new_zeros(())
    for index, drawn in zip(frames, draws, strict=False):
        gaussians, regulariser = gaussians_at_frame(
            prediction, variant, deformation, record, index, config.deform
        )
        cameras = drawn[: config.cameras_per_step].to(record.depth.device)
        rendered = splat(
            gaussians,
            record.world_to_cam[index][cameras][None],
            record.intrinsics[index][cameras][None],
            record.image_size,
        )
        assert rendered.depth is not None
        rendering = rendering_loss(
            rendered.features,
            rendered.alpha,
            rendered.depth,
            record.semantics[index][cameras][None],
            record.depth[index][cameras][None],
            record.supervised[index][cameras][None],
            weights=weights,
            class_weights=class_weights,
        )
        total = total + (rendering.total + config.deformation_weight * regulariser)
    return total / len(frames)


def _optimise(
    network: GaussianPredictor,
    deformation: DecoupledDeformation | None,
    records: Sequence[SceneRecord],
    variant: FeedForwardVariant,
    config: TrainConfig,
    *,
    steps: int,
    lr: float,
    stream: int,
    progress: Callable[[int, float], None] | None,
) -> list[float]:
    """``steps`` Adam steps (fresh state) of ``network`` (and ``deformation``) on
    ``records``; the scene order and the frames / cameras come from two generators seeded
    by ``(config.seed, stream)``, so every call with the same seed and stream sees the same
    scenes, frames and cameras."""
    groups: list[dict] = [{"params": list(network.parameters()), "lr": lr}]
    if deformation is not None:
        groups.append({"params": list(deformation.parameters()), "lr": config.deformation_lr})
    optimizer = torch.optim.Adam(groups)
    schedule = None
    if config.cosine and steps:
        schedule = torch.optim.lr_scheduler.LambdaLR(
            optimizer, lambda step: 0.5 * (1 + math.cos(math.pi * step / steps))
        )
    parameters = [p for group in groups for p in group["params"]]
    weights = None
    if config.class_weights:
        weights = median_frequency_weights(records).to(records[0].depth.device)
    seeds = torch.Generator().manual_seed(config.seed * 1_000_003 + stream)
    order_generator = torch.Generator().manual_seed(int(torch.randint(2**62, (), generator=seeds)))
    generator = torch.Generator().manual_seed(int(torch.randint(2**62, (), generator=seeds)))
    order: list[int] = []
    history = []
    network.train()
    for step in range(steps):
        if not order:
            order = torch.randperm(len(records), generator=order_generator).tolist()
        record = records[order.pop()]
        loss = step_loss(network, deformation, record, variant, config, generator, weights)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if config.clip_norm > 0:
            torch.nn.utils.clip_grad_norm_(parameters, config.clip_norm)
        optimizer.step()
        if schedule is not None:
            schedule.step()
        history.append(float(loss.detach()))
        if progress is not None:
            progress(step, history[-1])
    network.eval()
    return history


_WARMUP_STREAM, _VARIANT_STREAM = 0, 1


def _check_inputs(records: Sequence[SceneRecord], variant: str) -> torch.device:
    if not records:
        raise ValueError("records: expected at least one training scene")
    if variant not in FEEDFORWARD_VARIANTS:
        raise ValueError(f"variant: expected one of {FEEDFORWARD_VARIANTS}, got {variant!r}")
    return records[0].depth.device


def warm_up(
    records: Sequence[SceneRecord],
    config: TrainConfig | None = None,
    *,
    progress: Callable[[int, float], None] | None = None,
) -> TrainResult:
    """The shared start of the ``paired`` recipe: a fresh network (from ``config.seed``)
    trained ``config.warmup_steps`` steps on the reference frames' labels at ``config.lr``.
    :func:`fine_tune` (or :func:`train` with ``start=``) copies it for each variant."""
    config = config or TrainConfig()
    device = _check_inputs(records, "single-frame")
    torch.manual_seed(config.seed)
    network = build_network(config).to(device)
    start = time.perf_counter()
    history = _optimise(
        network,
        None,
        records,
        "single-frame",
        config,
        steps=config.warmup_steps,
        lr=config.lr,
        stream=_WARMUP_STREAM,
        progress=progress,
    )
    return TrainResult("single-frame", network, None, history, time.perf_counter() - start)


def fine_tune(
    start: GaussianPredictor,
    records: Sequence[SceneRecord],
    variant: FeedForwardVariant,
    config: TrainConfig | None = None,
    *,
    progress: Callable[[int, float], None] | None = None,
) -> TrainResult:
    """A copy of ``start`` (``start`` itself is not changed) and a fresh deformation (from
    ``config.seed``) trained ``config.steps`` steps as ``variant`` with a fresh Adam at
    ``config.finetune_lr`` (the deformation at ``config.deformation_lr``). Every variant
    of one seed sees the same scenes, frames and cameras in the same order."""
    config = config or TrainConfig()
    device = _check_inputs(records, variant)
    return _fit(
        copy.deepcopy(start).to(device),
        records,
        variant,
        config,
        steps=config.steps,
        lr=config.finetune_lr,
        progress=progress,
    )


def _fit(
    network: GaussianPredictor,
    records: Sequence[SceneRecord],
    variant: FeedForwardVariant,
    config: TrainConfig,
    *,
    steps: int,
    lr: float,
    progress: Callable[[int, float], None] | None,
) -> TrainResult:
    """``network`` and a fresh deformation of ``variant`` (from ``config.seed``) trained
    ``steps`` steps on the variants' shared stream of scenes, frames and cameras."""
    torch.manual_seed(config.seed)
    deformation = build_deformation(variant, config, records[0].times)
    if deformation is not None:
        deformation = deformation.to(records[0].depth.device)
    begin = time.perf_counter()
    history = _optimise(
        network,
        deformation,
        records,
        variant,
        config,
        steps=steps,
        lr=lr,
        stream=_VARIANT_STREAM,
        progress=progress,
    )
    return TrainResult(variant, network, deformation, history, time.perf_counter() - begin)


def train(
    records: Sequence[SceneRecord],
    variant: FeedForwardVariant,
    config: TrainConfig | None = None,
    *,
    start: GaussianPredictor | None = None,
    progress: Callable[[int, float], None] | None = None,
) -> TrainResult:
    """Train a :class:`GaussianPredictor` (and deformation) on ``records`` as ``variant``.

    ``recipe="paired"``: fine-tune ``start`` (a :func:`warm_up` network; ``None``: the warm
    up runs here first and its time counts); ``"scratch"``: a fresh network trained
    ``config.total_steps`` steps as ``variant`` at ``config.lr`` (``start`` must be
    ``None``). The networks start from ``config.seed`` and live on the records' device;
    ``progress(step, loss)`` is called after every step of the variant's own training.
    """
    config = config or TrainConfig()
    device = _check_inputs(records, variant)
    if config.recipe == "paired":
        warm_seconds = 0.0
        if start is None:
            warm = warm_up(records, config)
            start, warm_seconds = warm.network, warm.seconds
        result = fine_tune(start, records, variant, config, progress=progress)
        result.seconds += warm_seconds
        return result
    if start is not None:
        raise ValueError("start: the 'scratch' recipe trains from the initial weights; pass None")
    torch.manual_seed(config.seed)
    network = build_network(config).to(device)
    return _fit(
        network,
        records,
        variant,
        config,
        steps=config.total_steps,
        lr=config.lr,
        progress=progress,
    )
