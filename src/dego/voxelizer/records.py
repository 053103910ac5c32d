"""The records passed between the voxelizer's stages (internal, not exported).

:class:`FlatGaussians`: the checked inputs, flattened to ``M = B * N`` Gaussians, once,
instead of a list of tensors handed from stage to stage. :class:`VoxelSums`: the three
per-voxel sums (density, weighted features, feature weights) every neighbourhood reduces
its (Gaussian, voxel) pairs into, and their conversion to a :class:`VoxelOutput`.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from dego.voxelizer.kernels import Kernel
from dego.voxelizer.output import VoxelOutput
from dego.voxelizer.types import VoxelizerConfig


@dataclasses.dataclass(frozen=True)
class FlatGaussians:
    """``(B, N)`` Gaussians as ``M = B * N`` rows in the compute dtype, values checked.

    ``scales`` are floored at the kernel's smallest scale; ``log_normaliser`` is the clamped
    log of ``(2 pi)^(-3/2) sqrt(det P)``; ``out_dtype`` is the Gaussians' own dtype (the
    result is cast back to it).
    """

    batch_size: int  # B
    num_gaussians: int  # N
    means: Tensor  # (M, 3)
    quats: Tensor  # (M, 4)
    scales: Tensor  # (M, 3)
    opacities: Tensor  # (M,)
    features: Tensor  # (M, C)
    log_normaliser: Tensor  # (M,)
    out_dtype: torch.dtype

    @property
    def dtype(self) -> torch.dtype:
        """The compute dtype (float16 / bfloat16 inputs: float32)."""
        return self.means.dtype

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def channels(self) -> int:
        return self.features.shape[-1]


def requiring_grad(*inputs: Tensor) -> tuple[Tensor, ...]:
    """The inputs that require grad, none when grad mode is off."""
    if not torch.is_grad_enabled():
        return ()
    return tuple(t for t in inputs if t.requires_grad)


@dataclasses.dataclass
class VoxelSums:
    """Running per-voxel sums over ``B * X * Y * Z`` flattened voxels: the density term
    (additive: ``sum o g``; probabilistic: ``sum log(1 - o g)``), the weighted features
    ``sum w f`` and the feature weights ``W = sum w``."""

    density: Tensor  # (V,)
    features: Tensor  # (V, C)
    weights: Tensor  # (V,)

    @classmethod
    def zeros(
        cls, num_voxels: int, channels: int, dtype: torch.dtype, device: torch.device
    ) -> VoxelSums:
        return cls(
            torch.zeros(num_voxels, dtype=dtype, device=device),
            torch.zeros(num_voxels, channels, dtype=dtype, device=device),
            torch.zeros(num_voxels, dtype=dtype, device=device),
        )

    def add(self, voxel: Tensor, terms: tuple[Tensor, Tensor, Tensor]) -> None:
        """Reduce one chunk's per-pair ``(density, feature, weight)`` terms into ``voxel``."""
        self.density.index_add_(0, voxel, terms[0])
        self.features.index_add_(0, voxel, terms[1])
        self.weights.index_add_(0, voxel, terms[2])

    def finish(
        self,
        kernel: Kernel,
        config: VoxelizerConfig,
        shape: tuple[int, ...],
        differentiable: tuple[Tensor, ...],  # the inputs requiring grad (empty: no link)
    ) -> VoxelOutput:
        """Density from its sum; features ``empty_value`` where ``W <= empty_threshold``,
        else ``sum w f`` (additive) or ``sum w f / W`` (probabilistic).

        An output that no pair reached (no Gaussians, no (Gaussian, voxel) pair, B = 0) is
        still linked to every input in ``differentiable``, by an exact zero: it requires
        grad whenever an input does, and backward gives zero gradients.
        """
        density, accumulated, weights = self.density, self.features, self.weights
        reached = (weights > config.empty_threshold).unsqueeze(-1)
        if kernel.probabilistic:
            density = -torch.expm1(density)  # 1 - prod(1 - x), accurate for small densities
            # the divisor is 1 where unused, so the discarded branch's gradient stays finite
            accumulated = accumulated / torch.where(reached, weights.unsqueeze(-1), 1.0)
        else:
            density = density.clamp(0, 1)
        accumulated = torch.where(reached, accumulated, float(config.empty_value))
        if differentiable and not (density.requires_grad and accumulated.requires_grad):
            # a sum over no element: exactly 0 (whatever the values), zero gradient to each input
            zero = sum((t.flatten()[:0].sum() for t in differentiable), density.new_zeros(()))
            density = density if density.requires_grad else density + zero
            accumulated = accumulated if accumulated.requires_grad else accumulated + zero
        return VoxelOutput(
            density=density.view(*shape),
            features=accumulated.view(*shape, accumulated.shape[-1]),
        )
