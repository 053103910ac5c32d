"""Fit canonical Gaussians and a deformation network to a clip's pseudo labels."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import Literal

import torch
from jaxtyping import Float
from torch import Tensor

from dego._checks import check_int, check_positive
from dego.classes import CLASS_GROUPS
from dego.data.synthetic import SyntheticScene
from dego.deformation import DecoupledDeformation, DeformationLossWeights, deformation_loss
from dego.demo.balance import balance_deformation_gradients
from dego.demo.clip import DemoClip
from dego.demo.model import (
    MOVABLE_CLASSES,
    Allocation,
    GaussianSceneModel,
    LatentInit,
    check_initialisation,
)
from dego.demo.offsets import FrameOffsets, free_offsets, free_velocities, true_motion
from dego.gaussians import GaussianSet
from dego.losses import rendering_loss
from dego.splatting import SplatOutput, splat

Variant = Literal[
    "static",
    "rigid",
    "decoupled",
    "velocity",
    "single-frame",
    "free-offsets",
    "free-velocities",
    "true-motion",
]
VARIANTS: tuple[Variant, ...] = ("static", "rigid", "decoupled")
"""The fitted variants. ``static``: no deformation at all (the canonical Gaussians are used
at every frame; only the ego moves); ``rigid``: position offsets only (rigidity mask fixed
at 0, the GaussianFlowOcc-style baseline); ``decoupled``: DeGO's learned rigid / nonrigid
mask and full deformation."""

EXTENSION_VARIANTS: tuple[Variant, ...] = ("velocity",)
"""Ours, beyond the paper. ``velocity``: ``decoupled`` with a constant-velocity rigid branch
(:class:`~dego.DecoupledDeformation` ``rigid_motion="velocity"``: one velocity per Gaussian
from its features, offset ``t v``), the nonrigid branch as in the paper."""

REFERENCE_VARIANTS: tuple[Variant, ...] = (
    "single-frame",
    "free-offsets",
    "free-velocities",
    "true-motion",
)
"""Reference rows, not competitors. ``single-frame``: only the reference frame's views, as
many steps as a multi-frame fit gives that frame (what the other frames' labels add at
t = 0); ``free-offsets``: a position offset per (frame, Gaussian) optimised directly, no
network and no regulariser (what a per-Gaussian lookup table reaches);
``free-velocities``: one velocity per Gaussian, the offset at frame offset t being ``t *
v`` (same gating, no network, no ground truth: what a constant-velocity motion model
reaches when every frame pulls on the same parameters); ``true-motion``:
the agents' true motion from the synthetic scene held fixed (**uses the ground truth**: a
ceiling for position offsets)."""

ROW_NAMES: dict[str, str] = {
    "lifted-labels": "lifted labels (no learning)",
    "free-offsets": "free offsets",
    "free-velocities": "free velocities",
    "true-motion": "true motion (oracle)",
}
"""How the tables name a variant where it differs from its id."""


def row_name(variant: str) -> str:
    """How the tables name ``variant`` (:data:`ROW_NAMES`, else the id itself)."""
    return ROW_NAMES.get(variant, variant)


def most_likely_in(semantic_logits: Tensor, classes: tuple[int, ...]) -> Tensor:
    """``(N,)`` bool: the Gaussians whose most likely class (argmax of the detached
    ``(N, 17)`` logits) is one of ``classes``."""
    labels = semantic_logits.detach().argmax(-1)
    return torch.isin(labels, torch.tensor(classes, device=labels.device))


DeformClasses = Literal["all", "movable"]
OffsetGradients = Literal["raw", "balanced"]

LOSS_TERMS = ("total", "semantics", "depth", "deformation")


MAX_SEED = 2**32 - 1
"""The largest seed of a fit, a demo or a study: what every generator involved accepts
(``torch.manual_seed`` takes up to ``2**64 - 1``, numpy's legacy ``RandomState``
``2**32 - 1``)."""

_DEFAULT_LR = {
    "means": 0.01,
    "quats": 0.01,
    "log_scales": 0.01,
    "opacity_logits": 0.05,
    "semantic_logits": 0.03,
    "latent": 0.01,
    "deformation": 0.01,
    "offsets": 0.05,
}


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """Budget and settings of :func:`fit_scene` (the defaults are the demo's full run).

    Attributes:
        iterations: optimiser steps; each renders one frame's cameras.
        num_gaussians: canonical Gaussians. latent_dim: their latent feature channels.
        hidden_dim, depth, head_hidden: the deformation network's size (the paper uses
            256 / 6 / 256; the demo is smaller to run in minutes on a CPU).
        lr: Adam learning rates per parameter group (missing groups take the defaults;
            ``"offsets"``: the parameters of the ``free-offsets`` and ``free-velocities``
            references).
        depth_weight: weight of the L1 depth loss (per metre).
        deformation_weight: weight of ``deformation_loss(...).total`` (0.001; it was 0.1
            in dego 0.1.0: then ``L_reg``, a mean over *Gaussians*, cost ~0.08 at the
            agents' true motion against a best rendering gain of ~0.002, a mean over
            *pixels*, and the fit kept every agent still).
        seed: seeds the initialisation and the frame order, in ``[0, MAX_SEED]``.
        cameras_per_step: cameras of the frame rendered per step, a seeded random subset
            (``None``: all six). Fewer cameras make a step cheaper (3: half the cost).
        allocation, class_balance, semantic_prior, latent_init: the initialisation of
            :meth:`GaussianSceneModel.from_clip`.
        deform: which Gaussians the deformation may move. ``"movable"`` (default): those
            whose most likely class is movable (:data:`MOVABLE_CLASSES`, read from the
            fitted semantic logits, never the ground truth), the others keep their
            canonical parameters at every frame (:meth:`DeformationOutput.gated`);
            ``"all"``: every Gaussian, as in the paper.
        pos_scale: the network's position scale in metres (:class:`~dego.DecoupledDeformation`;
            4 m; ``None``: the network's default, 40 m): positions are divided by it before
            the encoding, so a smaller value tells nearby agents apart more sharply.
        offset_gradients: ``"raw"``, or ``"balanced"``: the position gradient that
            reaches the deformation is equalised over the deformable Gaussians
            (:func:`balance_deformation_gradients`); the free offsets and the oracle do
            not need it (and ignore it: their offsets have no shared network).
        regulariser: how ``L_reg`` is reduced (:func:`~dego.deformation_loss`'s
            ``reduction``): ``"mean"`` over every Gaussian (the paper's) or ``"sum"``.
        warmup: protection (off by default). The first ``warmup`` fraction of
            iterations, frames other than the reference train the deformation (and
            latent features) only: the canonical Gaussians get no gradient from them.
        freeze_movable: protection (off by default). At frames other than the
            reference, the canonical Gaussians whose most likely class is movable get no
            gradient for the whole fit. With it (and the warm-up) a moving agent cannot be
            explained away at t = 0 by the other frames, so every variant, ``static``
            included, keeps the same agents at t = 0 and the t = 0 effect of the
            deformation cannot show.
        mask_sparsity: weight of an optional prior ``mean(m)`` on the rigidity mask that
            prefers rigid unless shape change is needed (0: the paper's formulation,
            which has no such term). Only the ``decoupled`` variant has a mask.
    """

    iterations: int = 600
    num_gaussians: int = 8000
    latent_dim: int = 16
    hidden_dim: int = 64
    depth: int = 3
    head_hidden: int = 64
    lr: dict[str, float] = dataclasses.field(default_factory=lambda: dict(_DEFAULT_LR))
    depth_weight: float = 0.1
    deformation_weight: float = 0.001
    seed: int = 0
    cameras_per_step: int | None = 3
    allocation: Allocation = "class_balanced"
    class_balance: float = 0.3
    semantic_prior: float = 0.5
    latent_init: LatentInit = "segments"
    mask_sparsity: float = 0.0
    deform: DeformClasses = "movable"
    regulariser: str = "mean"
    pos_scale: float | None = 4.0
    offset_gradients: OffsetGradients = "balanced"
    warmup: float = 0.0
    freeze_movable: bool = False

    def __post_init__(self) -> None:
        check_int("iterations", self.iterations, 0)
        check_int("num_gaussians", self.num_gaussians, 1)
        for name in ("latent_dim", "hidden_dim", "depth", "head_hidden", "seed"):
            check_int(name, getattr(self, name), 0 if name in ("latent_dim", "seed") else 1)
        if self.seed > MAX_SEED:
            raise ValueError(f"seed: expected an int in [0, {MAX_SEED}], got {self.seed!r}")
        for name, value in self.lr.items():
            check_positive(f"lr[{name!r}]", value)
        unknown = sorted(set(self.lr) - set(_DEFAULT_LR))
        if unknown:
            raise ValueError(
                f"lr: unknown groups {unknown}; expected some of {sorted(_DEFAULT_LR)}"
            )
        object.__setattr__(self, "lr", {**_DEFAULT_LR, **self.lr})
        if self.cameras_per_step is not None:
            check_int("cameras_per_step", self.cameras_per_step, 1)
        check_initialisation(
            self.allocation,
            self.class_balance,
            self.semantic_prior,
            "class_balance",
            self.latent_init,
        )
        if self.pos_scale is not None:
            check_positive("pos_scale", self.pos_scale)
        if self.deform not in ("all", "movable"):
            raise ValueError(f"deform: expected 'all' or 'movable', got {self.deform!r}")
        if self.offset_gradients not in ("raw", "balanced"):
            raise ValueError(
                f"offset_gradients: expected 'raw' or 'balanced', got {self.offset_gradients!r}"
            )
        if self.regulariser not in ("mean", "sum"):
            raise ValueError(f"regulariser: expected 'mean' or 'sum', got {self.regulariser!r}")
        if not 0 <= self.warmup <= 1:
            raise ValueError(f"warmup: expected a fraction in [0, 1], got {self.warmup!r}")
        for name in ("depth_weight", "deformation_weight", "mask_sparsity"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name}: expected a finite weight >= 0, got {value!r}")


@dataclasses.dataclass
class FitResult:
    """What :func:`fit_scene` returns.

    Attributes:
        variant: the fitted variant (:data:`VARIANTS`, :data:`EXTENSION_VARIANTS`,
            :data:`REFERENCE_VARIANTS`).
        model: the fitted canonical Gaussians. deformation: the fitted network
            (``None`` for ``static``).
        history: per-iteration values of each term in :data:`LOSS_TERMS`.
        seconds: wall-clock time of the fit.
    """

    variant: Variant
    model: GaussianSceneModel
    deformation: DecoupledDeformation | FrameOffsets | None
    history: dict[str, list[float]]
    seconds: float


@torch.no_grad()
def rigidity_mask(result: FitResult) -> Float[Tensor, " N"]:
    """The fitted per-Gaussian mask m (1 = nonrigid; ``paper`` preset: time-independent;
    0 everywhere for ``static``)."""
    model = result.model
    if result.deformation is None:
        return model.means.new_zeros(model.num_gaussians)
    times = model.means.new_zeros(1)
    return result.deformation(model.gaussians(), model.latent[None], times).rigid_mask[0]


def mask_by_group(mask: Float[Tensor, " N"], model: GaussianSceneModel) -> dict[str, float]:
    """Mean mask over all Gaussians and over those whose most likely class is in each of
    the InsM / ScnM / HCM groups (NaN for an empty group)."""
    summary = {"all": float(mask.mean())}
    for name, ids in CLASS_GROUPS.items():
        members = most_likely_in(model.semantic_logits, ids)
        summary[name] = float(mask[members].mean()) if members.any() else float("nan")
    return summary


def build_deformation(
    variant: Variant,
    config: FitConfig,
    clip: DemoClip,
    *,
    means: Tensor | None = None,
    scene: SyntheticScene | None = None,
) -> DecoupledDeformation | FrameOffsets | None:
    """The deformation of ``variant``: the ``paper``-preset network (``rigid``:
    ``fixed_mask=0``; ``velocity``: ``rigid_motion="velocity"``),
    :func:`~dego.demo.offsets.free_offsets` (``free-offsets``),
    :func:`~dego.demo.offsets.free_velocities` (``free-velocities``), the
    oracle :func:`~dego.demo.offsets.true_motion` (``true-motion``: needs the canonical
    ``means`` and the clip's ``scene``), or ``None`` (``static``, ``single-frame``)."""
    known = VARIANTS + EXTENSION_VARIANTS + REFERENCE_VARIANTS
    if variant not in known:
        raise ValueError(f"variant: expected one of {known}, got {variant!r}")
    if variant in ("static", "single-frame"):
        return None
    if variant == "true-motion":
        if scene is None or means is None:
            raise ValueError(
                "scene: the true-motion oracle needs the SyntheticScene of the clip (and the "
                "canonical means); pass scene=..."
            )
        return true_motion(scene, clip, means)
    if variant in ("free-offsets", "free-velocities"):
        n = config.num_gaussians if means is None else means.shape[0]
        make = free_offsets if variant == "free-offsets" else free_velocities
        return make(clip, n)
    largest_offset = float(clip.times.abs().max().clamp_min(1))
    return DecoupledDeformation(
        config.latent_dim,
        hidden_dim=config.hidden_dim,
        depth=config.depth,
        head_hidden=config.head_hidden,
        time_scale=largest_offset,
        pos_scale=config.pos_scale,
        fixed_mask=0.0 if variant == "rigid" else None,
        rigid_motion="velocity" if variant == "velocity" else "time",
        loss_weights=DeformationLossWeights(reduction=config.regulariser),  # type: ignore[arg-type]
    )


def deformable(model: GaussianSceneModel | _FrozenCanonical) -> Tensor | None:
    """``(1, N)`` bool: the Gaussians ``model.deform_classes`` lets the deformation move
    (their most likely class is one of them), or ``None`` when every Gaussian may move."""
    if model.deform_classes is None:
        return None
    return most_likely_in(model.semantic_logits, model.deform_classes)[None]


def gaussians_at(
    model: GaussianSceneModel | _FrozenCanonical,
    deformation: DecoupledDeformation | FrameOffsets | None,
    clip: DemoClip,
    index: int,
    mask_sparsity: float = 0.0,
    offset_gradients: OffsetGradients = "raw",
) -> tuple[GaussianSet, dict[str, Tensor] | None]:
    """The ``(1, N)`` Gaussians at frame ``index`` (world coordinates) and their
    deformation losses.

    The reference frame is the canonical set itself (no deformation, no loss); every
    other frame deforms it to that frame's time offset (``deformation=None``: it does
    not, the ``static`` variant). Where ``model.deform_classes`` is set, only the
    Gaussians whose most likely class is one of them are deformed
    (:meth:`~dego.DeformationOutput.gated`; the losses see zero deltas elsewhere).
    ``mask_sparsity`` adds ``mask_sparsity * mean(m)`` to the loss ``total`` (also
    reported as ``"sparsity"``). ``offset_gradients="balanced"``: see
    :func:`balance_deformation_gradients` (values are unchanged, only gradients).
    """
    canonical = model.gaussians()
    if index == clip.reference or deformation is None:
        return canonical, None
    output = deformation(canonical, model.latent[None], clip.times[index : index + 1])
    keep = deformable(model)
    if keep is not None:
        output = output.gated(keep, canonical)
    losses = deformation_loss(output).to_dict()  # plus "sparsity" below
    if deformation.fixed_mask is None and mask_sparsity > 0:
        losses["sparsity"] = output.rigid_mask.mean()
        losses["total"] = losses["total"] + mask_sparsity * losses["sparsity"]
    deformed = output.at(0)
    if offset_gradients == "balanced" and deformed.means.requires_grad:
        deformed = balance_deformation_gradients(deformed, canonical, keep)
    return deformed, losses


def render(
    gaussians: GaussianSet, clip: DemoClip, index: int, cameras: Tensor | None = None
) -> SplatOutput:
    """Class probabilities and expected depth of ``gaussians`` in frame ``index``'s cameras
    (``cameras``: indices of a subset, default all)."""
    world_to_cam = clip.world_to_cam[index : index + 1]
    intrinsics = clip.intrinsics[index : index + 1]
    if cameras is not None:
        world_to_cam, intrinsics = world_to_cam[:, cameras], intrinsics[:, cameras]
    return splat(gaussians, world_to_cam, intrinsics, clip.image_size)


def fit_iterations(variant: Variant, config: FitConfig, clip: DemoClip) -> int:
    """Optimiser steps :func:`fit_scene` takes: ``config.iterations``, or for
    ``single-frame`` the reference frame's share of them, ``round(iterations / T)``."""
    if variant == "single-frame":
        return round(config.iterations / clip.num_frames)
    return config.iterations


def fit_scene(
    clip: DemoClip,
    variant: Variant,
    config: FitConfig | None = None,
    *,
    scene: SyntheticScene | None = None,
    progress: Callable[[int, dict[str, float]], None] | None = None,
) -> FitResult:
    """Fit canonical Gaussians + a ``variant`` deformation to ``clip`` with Adam.

    Each iteration renders one frame (a seeded shuffled cycle over the clip; only the
    reference frame for ``single-frame``, for ``round(iterations / T)`` steps) into its
    cameras and minimises ``semantics + depth_weight * depth + deformation_weight *
    deformation`` (the terms of :func:`~dego.losses.rendering_loss` against the frame's
    pseudo labels, :func:`~dego.deformation.deformation_loss`).
    ``scene``: the clip's :class:`~dego.data.SyntheticScene`, needed by the ``true-motion``
    oracle only. ``progress(iteration, losses)`` is called after every step.
    """
    config = config or FitConfig()
    generator = torch.Generator().manual_seed(config.seed)
    model = initial_model(clip, config, generator)
    torch.manual_seed(config.seed)  # the deformation network's initial weights
    deformation = build_deformation(variant, config, clip, means=model.means.detach(), scene=scene)
    if deformation is not None:
        deformation = deformation.to(clip.depth.device)
    free = variant in ("free-offsets", "free-velocities")
    networked = variant in ("rigid", "decoupled", *EXTENSION_VARIANTS)
    if (networked or free) and config.deform == "movable":
        model.deform_classes = MOVABLE_CLASSES
    groups = [
        {"params": [getattr(model, name)], "lr": config.lr[name]}
        for name in ("means", "quats", "log_scales", "opacity_logits", "semantic_logits")
    ]
    groups.append({"params": [model.latent], "lr": config.lr["latent"]})
    trainable = [] if deformation is None else list(deformation.parameters())
    if trainable:
        rate = config.lr["offsets" if free else "deformation"]
        groups.append({"params": trainable, "lr": rate})
    optimizer = torch.optim.Adam(groups)

    single = variant == "single-frame"
    iterations = fit_iterations(variant, config, clip)
    history: dict[str, list[float]] = {term: [] for term in LOSS_TERMS}
    order: list[int] = []
    start = time.perf_counter()
    for iteration in range(iterations):
        if not order:
            order = (
                [clip.reference]
                if single
                else torch.randperm(clip.num_frames, generator=generator).tolist()
            )
        index = order.pop()
        frozen = iteration < config.warmup * iterations
        losses = _frame_losses(model, deformation, clip, index, config, generator, frozen)
        losses["total"] = (
            losses["semantics"]
            + config.depth_weight * losses["depth"]
            + config.deformation_weight * losses["deformation"]
        )
        optimizer.zero_grad(set_to_none=True)
        if losses["total"].requires_grad:  # not so for static during the warm-up
            losses["total"].backward()
            optimizer.step()
        values = {term: losses[term].item() for term in LOSS_TERMS}
        for term in LOSS_TERMS:
            history[term].append(values[term])
        if progress is not None:
            progress(iteration, values)
    return FitResult(variant, model, deformation, history, time.perf_counter() - start)


def _frame_losses(
    model: GaussianSceneModel,
    deformation: DecoupledDeformation | FrameOffsets | None,
    clip: DemoClip,
    index: int,
    config: FitConfig,
    generator: torch.Generator,
    frozen: bool = False,
) -> dict[str, Tensor]:
    """Semantics, depth and deformation losses of frame ``index`` on a camera subset;
    ``frozen``: the canonical Gaussians get no gradient from this frame."""
    deformation_model: GaussianSceneModel | _FrozenCanonical = model
    if index != clip.reference and (frozen or config.freeze_movable):
        deformation_model = _FrozenCanonical(model, movable_only=not frozen)
    balance = config.offset_gradients if isinstance(deformation, DecoupledDeformation) else "raw"
    gaussians, deformation_terms = gaussians_at(
        deformation_model, deformation, clip, index, config.mask_sparsity, balance
    )
    num_cameras = clip.world_to_cam.shape[1]
    cameras = None
    if config.cameras_per_step is not None and config.cameras_per_step < num_cameras:
        cameras = torch.randperm(num_cameras, generator=generator)[: config.cameras_per_step]
    rendered = render(gaussians, clip, index, cameras)
    depth, semantics, supervised = (
        x[index][None] if cameras is None else x[index][cameras.to(x.device)][None]
        for x in (clip.depth, clip.semantics, clip.supervised)
    )
    assert rendered.depth is not None
    rendering = rendering_loss(
        rendered.features, rendered.alpha, rendered.depth, semantics, depth, supervised
    )
    losses = {"semantics": rendering.semantic, "depth": rendering.depth}
    losses["deformation"] = (
        deformation_terms["total"] if deformation_terms else losses["depth"].new_zeros(())
    )
    return losses


class _FrozenCanonical:
    """A model view whose canonical Gaussians are detached (the latent is not): all of
    them, or (``movable_only``) those whose most likely class is movable."""

    def __init__(self, model: GaussianSceneModel, movable_only: bool = False) -> None:
        self.latent, self.semantic_logits = model.latent, model.semantic_logits
        self.deform_classes = model.deform_classes
        self._model, self._movable_only = model, movable_only

    def gaussians(self) -> GaussianSet:
        gaussians = self._model.gaussians()
        if not self._movable_only:
            return gaussians.detach()
        movable = most_likely_in(self._model.semantic_logits, MOVABLE_CLASSES)

        def freeze(name: str, field: Tensor) -> Tensor:
            keep = movable[None] if name == "opacities" else movable[None, :, None]
            return torch.where(keep, field.detach(), field)

        return gaussians.map(freeze)


def initial_model(
    clip: DemoClip, config: FitConfig, generator: torch.Generator | None = None
) -> GaussianSceneModel:
    """The untrained model :func:`fit_scene` starts from (the same draw for the same
    ``generator`` state)."""
    return GaussianSceneModel.from_clip(
        clip,
        config.num_gaussians,
        latent_dim=config.latent_dim,
        allocation=config.allocation,
        balance=config.class_balance,
        semantic_prior=config.semantic_prior,
        latent_init=config.latent_init,
        generator=generator,
    )
