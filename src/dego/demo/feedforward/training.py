"""Train the feed-forward network on many scenes' pseudo labels, with or without deformation.

Every step takes one training scene, predicts its Gaussians from the reference frame's
images, and renders them into a random subset of cameras at the reference frame and (all
but ``single-frame``) at one other frame, drawn at random: there the Gaussians are
``static`` (as predicted), moved by the deformation network on the network's latents
(``rigid``: position offsets only; ``decoupled``: DeGO's rigid / nonrigid mask), or moved
with the ground-truth agent they sit on (``true-motion``, an oracle for analysis). The loss
is :func:`~dego.losses.rendering_loss` (semantics + ``depth_weight *`` depth) against each
rendered frame's pseudo labels, averaged over the frames, plus the deformation's
regulariser.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import Literal

import torch
from torch import Tensor

from dego._checks import check_int, check_positive
from dego.deformation import DecoupledDeformation, deformation_loss
from dego.demo.feedforward.data import SceneRecord
from dego.demo.feedforward.network import GaussianPredictor, Prediction
from dego.demo.fit import MAX_SEED, most_likely_in
from dego.demo.model import MOVABLE_CLASSES
from dego.demo.offsets import agent_offsets, agent_under
from dego.gaussians import GaussianSet
from dego.losses import RenderingLossWeights, rendering_loss
from dego.splatting import splat

FeedForwardVariant = Literal["single-frame", "static", "rigid", "decoupled", "true-motion"]
FEEDFORWARD_VARIANTS: tuple[FeedForwardVariant, ...] = (
    "single-frame",
    "static",
    "rigid",
    "decoupled",
    "true-motion",
)
"""``single-frame``: the reference frame's labels only; ``static``: every frame's labels, no
deformation; ``rigid``: position offsets from the deformation network (mask fixed at 0);
``decoupled``: DeGO's deformation with its learned rigid / nonrigid mask; ``true-motion``:
the Gaussians on a ground-truth agent move with it (**uses the ground truth**: a ceiling for
position offsets, analysis only)."""


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Settings of :func:`train` (the defaults are ``dego train``'s CPU default).

    Attributes:
        steps: optimiser steps, one training scene each.
        lr, deformation_lr: Adam learning rates of the image network and the deformation.
        cameras_per_step: cameras rendered per frame and step (a seeded random subset).
        depth_weight, deformation_weight: loss weights (as :class:`~dego.demo.FitConfig`).
        block, width, latent_dim: :class:`GaussianPredictor`'s size.
        hidden_dim, depth, head_hidden, pos_scale: the deformation network's size and
            position scale (as :class:`~dego.demo.FitConfig`).
        deform: ``"movable"``: only Gaussians whose predicted class is movable are
            deformed (:class:`~dego.demo.FitConfig`'s default); ``"all"``: every one.
        seed: the networks' initial weights and the scene / frame / camera order.
    """

    steps: int = 800
    lr: float = 2e-3
    deformation_lr: float = 1e-3
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
        for name in ("lr", "deformation_lr", "pos_scale"):
            check_positive(name, getattr(self, name))
        for name in ("cameras_per_step", "width", "hidden_dim", "depth", "head_hidden"):
            check_int(name, getattr(self, name), 1)
        check_int("latent_dim", self.latent_dim, 0)
        check_int("seed", self.seed, 0)
        if self.seed > MAX_SEED:
            raise ValueError(f"seed: expected an int in [0, {MAX_SEED}], got {self.seed!r}")
        for name in ("depth_weight", "deformation_weight"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name}: expected a finite weight >= 0, got {value!r}")
        if self.deform not in ("movable", "all"):
            raise ValueError(f"deform: expected 'movable' or 'all', got {self.deform!r}")
        GaussianPredictor(block=self.block, width=1, latent_dim=0)  # checks block


@dataclasses.dataclass
class TrainResult:
    """What :func:`train` returns: the trained ``network``, its ``deformation`` (``None``
    for ``single-frame``, ``static`` and ``true-motion``), the loss per step and the wall
    time."""

    variant: FeedForwardVariant
    network: GaussianPredictor
    deformation: DecoupledDeformation | None
    history: list[float]
    seconds: float


def build_network(config: TrainConfig) -> GaussianPredictor:
    """The untrained image network of ``config``."""
    return GaussianPredictor(block=config.block, width=config.width, latent_dim=config.latent_dim)


def build_deformation(
    variant: FeedForwardVariant, config: TrainConfig, times: Tensor
) -> DecoupledDeformation | None:
    """The ``paper``-preset deformation network of ``rigid`` / ``decoupled`` (times in
    frames, scaled by the largest offset of ``times``), else ``None``."""
    if variant not in FEEDFORWARD_VARIANTS:
        raise ValueError(f"variant: expected one of {FEEDFORWARD_VARIANTS}, got {variant!r}")
    if variant not in ("rigid", "decoupled"):
        return None
    return DecoupledDeformation(
        config.latent_dim,
        hidden_dim=config.hidden_dim,
        depth=config.depth,
        head_hidden=config.head_hidden,
        time_scale=float(times.abs().max().clamp_min(1)),
        pos_scale=config.pos_scale,
        fixed_mask=0.0 if variant == "rigid" else None,
    )


def predict(network: GaussianPredictor, record: SceneRecord) -> Prediction:
    """The network's ``(1, N)`` Gaussians of ``record`` from its reference-frame images."""
    ref = record.reference
    return network(
        record.images[None], record.world_to_cam[ref][None], record.intrinsics[ref][None]
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


def step_loss(
    network: GaussianPredictor,
    deformation: DecoupledDeformation | None,
    record: SceneRecord,
    variant: FeedForwardVariant,
    config: TrainConfig,
    generator: torch.Generator,
) -> Tensor:
    """One step's loss on ``record`` (see the module docstring)."""
    prediction = predict(network, record)
    frames = [record.reference]
    if variant != "single-frame" and record.num_frames > 1:
        others = [i for i in range(record.num_frames) if i != record.reference]
        frames.append(others[int(torch.randint(len(others), (), generator=generator))])
    weights = RenderingLossWeights(semantic=1.0, depth=config.depth_weight)
    total = prediction.gaussians.means.new_zeros(())
    for index in frames:
        gaussians, regulariser = gaussians_at_frame(
            prediction, variant, deformation, record, index, config.deform
        )
        views = record.world_to_cam.shape[1]
        cameras = torch.randperm(views, generator=generator)[: config.cameras_per_step]
        cameras = cameras.to(record.depth.device)
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
        )
        total = total + (rendering.total + config.deformation_weight * regulariser)
    return total / len(frames)


def train(
    records: Sequence[SceneRecord],
    variant: FeedForwardVariant,
    config: TrainConfig | None = None,
    *,
    progress: Callable[[int, float], None] | None = None,
) -> TrainResult:
    """Train a fresh :class:`GaussianPredictor` (and deformation) on ``records`` with Adam.

    The networks start from ``config.seed`` and the scenes come in a seeded shuffled cycle,
    so every variant of one seed sees the same initial weights and the same scenes in the
    same order. The networks live on the records' device. ``progress(step, loss)`` is called
    after every step.
    """
    config = config or TrainConfig()
    if not records:
        raise ValueError("records: expected at least one training scene")
    if variant not in FEEDFORWARD_VARIANTS:
        raise ValueError(f"variant: expected one of {FEEDFORWARD_VARIANTS}, got {variant!r}")
    device = records[0].depth.device
    torch.manual_seed(config.seed)
    network = build_network(config).to(device)
    deformation = build_deformation(variant, config, records[0].times)
    groups: list[dict] = [{"params": list(network.parameters()), "lr": config.lr}]
    if deformation is not None:
        deformation = deformation.to(device)
        groups.append({"params": list(deformation.parameters()), "lr": config.deformation_lr})
    optimizer = torch.optim.Adam(groups)
    generator = torch.Generator().manual_seed(config.seed)
    order: list[int] = []
    history = []
    start = time.perf_counter()
    for step in range(config.steps):
        if not order:
            order = torch.randperm(len(records), generator=generator).tolist()
        loss = step_loss(network, deformation, records[order.pop()], variant, config, generator)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        history.append(float(loss.detach()))
        if progress is not None:
            progress(step, history[-1])
    network.eval()
    return TrainResult(variant, network, deformation, history, time.perf_counter() - start)
