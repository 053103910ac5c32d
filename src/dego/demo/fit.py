"""Fit canonical Gaussians and a deformation network to a clip's pseudo labels."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import Literal

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from dego._checks import check_int, check_positive
from dego.classes import CLASS_GROUPS
from dego.deformation import DecoupledDeformation, deformation_loss
from dego.demo.clip import DemoClip
from dego.demo.model import GaussianSceneModel
from dego.gaussians import GaussianSet
from dego.splatting import SplatOutput, splat

Variant = Literal["rigid", "decoupled"]
VARIANTS: tuple[Variant, ...] = ("rigid", "decoupled")
"""``rigid``: position offsets only (rigidity mask fixed at 0, the GaussianFlowOcc-style
baseline); ``decoupled``: DeGO's learned rigid / nonrigid mask and full deformation."""

LOSS_TERMS = ("total", "semantics", "depth", "deformation")


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """Budget and settings of :func:`fit_scene` (the defaults are the demo's full run).

    Attributes:
        iterations: optimiser steps; each renders one frame's cameras.
        num_gaussians: canonical Gaussians. latent_dim: their latent feature channels.
        hidden_dim, depth, head_hidden: the deformation network's size (the paper uses
            256 / 6 / 256; the demo is smaller to run in minutes on a CPU).
        lr: Adam learning rates per parameter group.
        depth_weight: weight of the L1 depth loss (per metre).
        deformation_weight: weight of ``deformation_loss(...)["total"]``.
        seed: seeds the initialisation and the frame order.
    """

    iterations: int = 600
    num_gaussians: int = 8000
    latent_dim: int = 16
    hidden_dim: int = 64
    depth: int = 3
    head_hidden: int = 64
    lr: dict[str, float] = dataclasses.field(
        default_factory=lambda: {
            "means": 0.01,
            "quats": 0.01,
            "log_scales": 0.01,
            "opacity_logits": 0.05,
            "semantic_logits": 0.1,
            "latent": 0.01,
            "deformation": 0.002,
        }
    )
    depth_weight: float = 0.1
    deformation_weight: float = 0.1
    seed: int = 0

    def __post_init__(self) -> None:
        check_int("iterations", self.iterations, 0)
        check_int("num_gaussians", self.num_gaussians, 1)
        for name in ("latent_dim", "hidden_dim", "depth", "head_hidden", "seed"):
            check_int(name, getattr(self, name), 0 if name in ("latent_dim", "seed") else 1)
        for name, value in self.lr.items():
            check_positive(f"lr[{name!r}]", value)
        for name in ("depth_weight", "deformation_weight"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name}: expected a finite weight >= 0, got {value!r}")


@dataclasses.dataclass
class FitResult:
    """What :func:`fit_scene` returns.

    Attributes:
        variant: ``"rigid"`` or ``"decoupled"``.
        model: the fitted canonical Gaussians. deformation: the fitted network.
        history: per-iteration values of each term in :data:`LOSS_TERMS`.
        seconds: wall-clock time of the fit.
    """

    variant: Variant
    model: GaussianSceneModel
    deformation: DecoupledDeformation
    history: dict[str, list[float]]
    seconds: float


@torch.no_grad()
def rigidity_mask(result: FitResult) -> Float[Tensor, " N"]:
    """The fitted per-Gaussian mask m (1 = nonrigid; ``paper`` preset: time-independent)."""
    model = result.model
    times = model.means.new_zeros(1)
    return result.deformation(model.gaussians(), model.latent[None], times).rigid_mask[0]


def mask_by_group(mask: Float[Tensor, " N"], model: GaussianSceneModel) -> dict[str, float]:
    """Mean mask over all Gaussians and over those whose most likely class is in each of
    the InsM / ScnM / HCM groups (NaN for an empty group)."""
    labels = model.semantic_logits.argmax(-1)
    summary = {"all": float(mask.mean())}
    for name, ids in CLASS_GROUPS.items():
        members = torch.isin(labels, torch.tensor(ids, device=labels.device))
        summary[name] = float(mask[members].mean()) if members.any() else float("nan")
    return summary


def build_deformation(variant: Variant, config: FitConfig, clip: DemoClip) -> DecoupledDeformation:
    """The ``paper``-preset network of ``variant`` (``rigid``: ``fixed_mask=0``)."""
    if variant not in VARIANTS:
        raise ValueError(f"variant: expected one of {VARIANTS}, got {variant!r}")
    largest_offset = float(clip.times.abs().max().clamp_min(1))
    return DecoupledDeformation(
        config.latent_dim,
        hidden_dim=config.hidden_dim,
        depth=config.depth,
        head_hidden=config.head_hidden,
        time_scale=largest_offset,
        fixed_mask=0.0 if variant == "rigid" else None,
    )


def gaussians_at(
    model: GaussianSceneModel, deformation: DecoupledDeformation, clip: DemoClip, index: int
) -> tuple[GaussianSet, dict[str, Tensor] | None]:
    """The ``(1, N)`` Gaussians at frame ``index`` and their deformation losses.

    The reference frame is the canonical set itself (no deformation, no loss); every
    other frame deforms it to that frame's time offset.
    """
    canonical = model.gaussians()
    if index == clip.reference:
        return canonical, None
    output = deformation(canonical, model.latent[None], clip.times[index : index + 1])
    return output.at(0), deformation_loss(output)


def render(gaussians: GaussianSet, clip: DemoClip, index: int) -> SplatOutput:
    """Class probabilities and expected depth of ``gaussians`` in frame ``index``'s cameras."""
    return splat(
        gaussians,
        clip.world_to_cam[index : index + 1],
        clip.intrinsics[index : index + 1],
        clip.image_size,
    )


def weak_losses(
    rendered: SplatOutput,
    depth: Float[Tensor, "V H W"],
    semantics: Int[Tensor, "V H W"],
    supervised: Bool[Tensor, "V H W"],
) -> dict[str, Tensor]:
    """Cross-entropy on semantics and L1 on depth against one frame's pseudo labels.

    The rendered class probabilities sum to the pixel's alpha; the transparency
    ``1 - alpha`` is the probability of free space (label 17), so the 18 values are a
    distribution and sky pixels teach the Gaussians to stay out of the way. Depth (the
    alpha-normalised expected depth) is compared where the pseudo depth is positive.
    """
    probabilities = torch.cat(
        [rendered.features[0], (1 - rendered.alpha[0])[:, None]], 1
    )  # (V, 18, H, W)
    picked = probabilities.gather(1, semantics[:, None]).squeeze(1)
    semantic = -picked.clamp_min(1e-6).log()[supervised].mean()
    with_depth = supervised & (depth > 0)
    assert rendered.depth is not None
    depth_error = (rendered.depth[0] - depth).abs()[with_depth]
    return {
        "semantics": semantic,
        "depth": depth_error.mean() if depth_error.numel() else depth.new_zeros(()),
    }


def fit_scene(
    clip: DemoClip,
    variant: Variant,
    config: FitConfig | None = None,
    *,
    progress: Callable[[int, dict[str, float]], None] | None = None,
) -> FitResult:
    """Fit canonical Gaussians + a ``variant`` deformation network to ``clip`` with Adam.

    Each iteration renders one frame (a seeded shuffled cycle over the clip) into its
    cameras and minimises ``semantics + depth_weight * depth + deformation_weight *
    deformation``. ``progress(iteration, losses)`` is called after every step.
    """
    config = config or FitConfig()
    generator = torch.Generator().manual_seed(config.seed)
    model = GaussianSceneModel.from_clip(
        clip, config.num_gaussians, latent_dim=config.latent_dim, generator=generator
    )
    torch.manual_seed(config.seed)  # the deformation network's initial weights
    deformation = build_deformation(variant, config, clip).to(clip.depth.device)
    groups = [
        {"params": [getattr(model, name)], "lr": config.lr[name]}
        for name in ("means", "quats", "log_scales", "opacity_logits", "semantic_logits")
    ]
    groups.append({"params": [model.latent], "lr": config.lr["latent"]})
    groups.append({"params": list(deformation.parameters()), "lr": config.lr["deformation"]})
    optimizer = torch.optim.Adam(groups)

    history: dict[str, list[float]] = {term: [] for term in LOSS_TERMS}
    order: list[int] = []
    start = time.perf_counter()
    for iteration in range(config.iterations):
        if not order:
            order = torch.randperm(clip.num_frames, generator=generator).tolist()
        index = order.pop()
        gaussians, deformation_terms = gaussians_at(model, deformation, clip, index)
        losses = weak_losses(
            render(gaussians, clip, index),
            clip.depth[index],
            clip.semantics[index],
            clip.supervised[index],
        )
        losses["deformation"] = (
            deformation_terms["total"] if deformation_terms else losses["depth"].new_zeros(())
        )
        losses["total"] = (
            losses["semantics"]
            + config.depth_weight * losses["depth"]
            + config.deformation_weight * losses["deformation"]
        )
        optimizer.zero_grad(set_to_none=True)
        losses["total"].backward()
        optimizer.step()
        values = {term: losses[term].item() for term in LOSS_TERMS}
        for term in LOSS_TERMS:
            history[term].append(values[term])
        if progress is not None:
            progress(iteration, values)
    return FitResult(variant, model, deformation, history, time.perf_counter() - start)
