"""GaussianFlowOcc's temporal module and class gating, on dego's deformation outputs.

- :class:`TemporalOffsetNetwork`: GaussianFlowOcc's ``TemporalFeedForwardNetwork``
  (a learned embedding per time index, one 3-D offset per Gaussian and time step), with the
  original's parameter names, so its checkpoints load with ``load_state_dict``.
- :func:`gate_by_class`: only Gaussians whose argmax class is dynamic move.

The same semantics on DeGO's architecture: ``gate_by_class(DecoupledDeformation(...,
fixed_mask=0.0)(canonical, features, times), logits, canonical)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

import torch
from jaxtyping import Float, Int
from torch import Tensor, nn

from dego._checks import check_int
from dego._typing import typechecked
from dego.deformation import (
    DeformationDeltas,
    DeformationLossWeights,
    DeformationOutput,
    canonical_batch,
    check_like_gaussians,
)
from dego.gaussians import GaussianSet

GAUSSIANFLOWOCC_CHECKPOINT_PREFIX = "temporal_module."
"""Where GaussianFlowOcc's detector keeps its ``TemporalFeedForwardNetwork``."""

GAUSSIANFLOWOCC_DYNAMIC_CLASSES: tuple[int, ...] = (2, 3, 4, 5, 6, 7, 9, 10)
"""Occ3D labels whose Gaussians GaussianFlowOcc lets move: bicycle, bus, car, construction
vehicle, motorcycle, pedestrian, trailer, truck (:class:`dego.classes.Occ3DLabel` values)."""


@typechecked
def gate_by_class(
    output: DeformationOutput,
    logits: Float[Tensor, "B N K"],
    canonical: GaussianSet,
    dynamic_classes: Sequence[int] = GAUSSIANFLOWOCC_DYNAMIC_CLASSES,
    *,
    first_label: int = 1,
) -> DeformationOutput:
    """GaussianFlowOcc's class gating: only Gaussians whose argmax class is dynamic deform.

    A Gaussian's label is ``argmax(logits) + first_label``; where it is not in
    ``dynamic_classes`` the Gaussian keeps its canonical parameters at every time step
    (:meth:`DeformationOutput.gated`). The gate is a hard, non-differentiable choice, as in
    GaussianFlowOcc (no gradient reaches ``logits``).

    Args:
        output: a deformation of ``canonical``.
        logits: ``(B, N, K)`` per-Gaussian class scores for labels ``first_label`` ..
            ``first_label + K - 1``.
        canonical: the canonical set, batch shape ``(B,)``.
        dynamic_classes: the labels that may move (default GaussianFlowOcc's
            :data:`GAUSSIANFLOWOCC_DYNAMIC_CLASSES`).
        first_label: the label of logit channel 0: 1 for GaussianFlowOcc's 16 logits
            (labels 1..16, no ``others``), 0 for logits over every Occ3D label.
    """
    return output.gated(_dynamic_mask(logits, dynamic_classes, first_label), canonical)


def _dynamic_mask(logits: Tensor, dynamic_classes: Sequence[int], first_label: int) -> Tensor:
    check_int("first_label", first_label)
    classes = list(dynamic_classes)
    for c in classes:
        check_int("dynamic_classes", c)
    if not bool(torch.isfinite(logits).all()):
        raise ValueError("logits: expected finite values, got NaN or inf")
    if logits.shape[-1] == 0:
        raise ValueError("logits: expected at least one class channel, got K = 0")
    labels = logits.argmax(-1) + first_label
    return torch.isin(labels, torch.tensor(classes, dtype=labels.dtype, device=labels.device))


class TemporalOffsetNetwork(nn.Module):
    """GaussianFlowOcc's temporal module (``TemporalFeedForwardNetwork``), faithfully.

    A learned embedding ``e_k`` (``feature_dim`` wide) per time index k, concatenated with
    each Gaussian's feature and fed to an MLP that outputs one 3-D offset per Gaussian
    per target time: Linear(2C, 3C), LeakyReLU, ``num_layers`` x [Linear(3C, 3C),
    LeakyReLU], Linear(3C, 3) (LeakyReLU slope 0.01). No positional encoding of the means;
    only the means move. PyTorch's default initialisation, as the original.

    The parameter names are the original's (``time_embed.weight``, ``ffn.{i}.weight`` /
    ``bias``), so a GaussianFlowOcc checkpoint loads with ``load_state_dict`` once the
    :data:`GAUSSIANFLOWOCC_CHECKPOINT_PREFIX` (``"temporal_module."``) is removed.

    Args:
        feature_dim: C, the Gaussian feature width (GaussianFlowOcc: 256).
        num_timesteps: size of the embedding table (GaussianFlowOcc: 13, the frame
            offsets -6..+6, index = offset + 6).
        num_layers: hidden 3C x 3C layers (GaussianFlowOcc: 3).
    """

    def __init__(self, feature_dim: int = 256, *, num_timesteps: int = 13, num_layers: int = 3):
        super().__init__()
        check_int("feature_dim", feature_dim, 1)
        check_int("num_timesteps", num_timesteps, 1)
        check_int("num_layers", num_layers, 0)
        self.feature_dim, self.num_timesteps = feature_dim, num_timesteps
        width = 3 * feature_dim
        layers: list[nn.Module] = [nn.Linear(2 * feature_dim, width), nn.LeakyReLU()]
        for _ in range(num_layers):
            layers += [nn.Linear(width, width), nn.LeakyReLU()]
        layers.append(nn.Linear(width, 3))
        self.time_embed = nn.Embedding(num_timesteps, feature_dim)
        self.ffn = nn.Sequential(*layers)

    @typechecked
    def offsets(
        self, features: Float[Tensor, "B N C"], time_indices: Int[Tensor, "B T"]
    ) -> Float[Tensor, "B T N 3"]:
        """The raw offsets, ``(B, T, N, 3)``, for validated inputs (see :meth:`forward`)."""
        first = cast(nn.Linear, self.ffn[0])
        c = self.feature_dim
        # ffn on [f, e_t] with the first layer split, so [f] is projected once for all T
        per_gaussian = nn.functional.linear(features, first.weight[:, :c], first.bias)
        per_time = nn.functional.linear(self.time_embed(time_indices), first.weight[:, c:])
        return self.ffn[1:](per_gaussian[:, None] + per_time[:, :, None])

    @typechecked
    def forward(
        self,
        gaussians: GaussianSet,
        features: Float[Tensor, "B N C"],
        time_indices: Int[Tensor, " T"] | Int[Tensor, "B T"],
        logits: Float[Tensor, "B N K"] | None = None,
        *,
        dynamic_classes: Sequence[int] = GAUSSIANFLOWOCC_DYNAMIC_CLASSES,
        first_label: int = 1,
    ) -> DeformationOutput:
        """Move the canonical ``(B, N)`` means to every time index; gate by class if asked.

        Args:
            gaussians: canonical Gaussians, batch shape ``(B,)``.
            features: ``(B, N, C)`` per-Gaussian features.
            time_indices: ``(T,)`` or ``(B, T)`` integer indices into the embedding table
                in [0, num_timesteps) (GaussianFlowOcc: frame offset + 6).
            logits: ``(B, N, K)`` class scores; given, only Gaussians whose argmax class is
                in ``dynamic_classes`` move (:func:`gate_by_class`, GaussianFlowOcc's
                ``move_gaussians_temporal_module``). ``None``: every Gaussian moves.
            dynamic_classes: see :func:`gate_by_class`.
            first_label: see :func:`gate_by_class`.

        Returns:
            :class:`DeformationOutput` shaped like a ``paper`` preset output with mask
            ``m = 0`` ``(B, N)``: ``gaussians`` ``(B, T)`` with only the means changed
            (``deltas.means`` and both raw offsets are the offsets; the other deltas are 0).
            Append the canonical frame with :meth:`DeformationOutput.with_canonical`.
        """
        b, n = canonical_batch(gaussians)
        if tuple(features.shape) != (b, n, self.feature_dim):
            raise ValueError(
                f"features: expected shape ({b}, {n}, {self.feature_dim}), got "
                f"{tuple(features.shape)}"
            )
        check_like_gaussians(gaussians, cast(nn.Linear, self.ffn[0]).weight, features)
        if time_indices.device != gaussians.device:
            raise ValueError(
                f"time_indices: expected on {gaussians.device} like gaussians, got "
                f"{time_indices.device}"
            )
        if time_indices.ndim == 1:
            time_indices = time_indices.expand(b, -1)
        elif time_indices.shape[0] != b:
            raise ValueError(
                f"time_indices: expected shape (T,) or (B, T) with B = {b}, got "
                f"{tuple(time_indices.shape)}"
            )
        if time_indices.shape[1] == 0:
            raise ValueError("time_indices: expected at least one time step, got T = 0")
        if bool(((time_indices < 0) | (time_indices >= self.num_timesteps)).any()):
            raise ValueError(
                f"time_indices: expected indices in [0, {self.num_timesteps}), got values from "
                f"{int(time_indices.min())} to {int(time_indices.max())}"
            )
        offsets = self.offsets(features, time_indices)
        t = offsets.shape[1]

        def fixed(value: Tensor) -> Tensor:
            return value[:, None].expand(-1, t, *value.shape[1:])

        deformed = {name: fixed(value) for name, value in gaussians.items()}
        deformed["means"] = gaussians.means[:, None] + offsets
        zeros = offsets.new_zeros(())
        output = DeformationOutput(
            gaussians=GaussianSet(**deformed),
            rigid_mask=offsets.new_zeros(b, n),
            deltas=DeformationDeltas(
                offsets,
                zeros.expand(b, t, n, 4),
                zeros.expand(b, t, n, 3),
                zeros.expand(b, t, n),
            ),
            rigid_offsets=offsets,
            nonrigid_offsets=offsets,
            preset="paper",
            loss_weights=DeformationLossWeights(),
        )
        if logits is None:
            return output
        if tuple(logits.shape[:2]) != (b, n):
            raise ValueError(f"logits: expected shape ({b}, {n}, K), got {tuple(logits.shape)}")
        return gate_by_class(output, logits, gaussians, dynamic_classes, first_label=first_label)

    def extra_repr(self) -> str:
        return f"feature_dim={self.feature_dim}, num_timesteps={self.num_timesteps}"


__all__ = [
    "GAUSSIANFLOWOCC_CHECKPOINT_PREFIX",
    "GAUSSIANFLOWOCC_DYNAMIC_CLASSES",
    "TemporalOffsetNetwork",
    "gate_by_class",
]
