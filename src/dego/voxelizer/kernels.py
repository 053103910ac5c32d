"""Per-(Gaussian, voxel) pair terms: the Mahalanobis quadratic, the kernel and its weights.

Shared by the box neighbourhoods (:mod:`dego.voxelizer.boxes`) and the official cube
(:mod:`dego.voxelizer.cube`); everything here is elementwise over pairs.
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from dego.voxelizer.types import VoxelizerConfig

# log(1 - x) used for a saturated pair (x = 1: the voxel is certainly occupied); exp of it
# is exactly 0 in float32 and float64, and sums of it stay finite.
_SATURATED_LOG = -1e4
# Additive cube mode skips (Gaussian, voxel) pairs with exp(-q/2) < 1e-10, i.e. q > 2 * 23.03;
# the skipped total per voxel is below (2 nbh + 1)^3 * 1e-10 (1.3e-7 for nbh = 5) times the
# largest |opacity| or |feature|.
NEGLIGIBLE_QUADRATIC = 2 * 23.026


def scale_floor(dtype: torch.dtype) -> float:
    """Smallest scale used in the kernel: ``finfo.tiny ** 0.25`` (1.1e-10 m in float32,
    1.2e-77 m in float64), so ``1/s^2`` and its products with offsets stay finite."""
    return torch.finfo(dtype).tiny ** 0.25


def log_normaliser_bound(dtype: torch.dtype) -> float:
    """``|log|`` bound of the mixture normaliser: ``0.5 log(finfo.max)`` (44.4 in float32,
    354.9 in float64), so probabilistic weights and their sums never overflow."""
    return 0.5 * math.log(torch.finfo(dtype).max)


@dataclasses.dataclass(frozen=True)
class Kernel:
    """Which per-pair terms are summed: the mode and where the opacity enters."""

    probabilistic: bool
    opacity_features: bool  # feature weight o g / o N (else g / N)
    opacity_density: bool  # density from o g (else g)

    @classmethod
    def of(cls, config: VoxelizerConfig) -> Kernel:
        return cls(
            config.mode == "probabilistic",
            config.opacity_weights_features,
            config.opacity_in_density,
        )


def _pair_quadratic(
    means: Tensor,  # (M, 3)
    whitening: Tensor,  # (M, 9): diag(1/s) R^T, row-major
    owner: Tensor,  # (P,) Gaussian of each pair
    centres: Tensor,  # (P, 3) voxel centre of each pair
) -> Tensor:
    """Per-pair Mahalanobis quadratic ``|diag(1/s) R^T d|^2`` ``(P,)``.

    A sum of squares: non-negative and free of the cancellation of ``d^T P d`` for
    needle-like Gaussians. Whitened offsets are clamped to ``+-sqrt(max) / 2`` (NaN from
    overflowing products counts as far), so the quadratic (then g = 0) and every gradient
    stay finite, whatever the scales and means.
    """
    d = centres - means[owner]
    u = (whitening[owner].view(-1, 3, 3) * d.unsqueeze(-2)).sum(-1)  # (P, 3)
    far = math.sqrt(torch.finfo(u.dtype).max) / 2  # 3 far^2 and 2 far stay finite
    u = torch.nan_to_num(u, nan=far).clamp(-far, far)
    return u.square().sum(-1)


def kernel_terms(
    quadratic: Tensor,  # (P,)
    opacity: Tensor,  # (P,) opacity of each pair's Gaussian
    features: Tensor,  # (P, C) features of each pair's Gaussian
    log_normaliser: Tensor,  # (P,) clamped log of (2 pi)^(-3/2) sqrt(det P) of each pair
    kernel: Kernel,
) -> tuple[Tensor, Tensor, Tensor]:
    """Per-pair density term, feature term and feature weight (additive: ``g`` or ``o g``;
    probabilistic: the mixture weight ``N`` or ``o N``)."""
    # d^T P d >= 0: rounding below 0 is clamped, NaN (inf - inf: a far pair) counts as far
    quadratic = torch.where(quadratic.isnan(), math.inf, quadratic.clamp_min(0))
    g = torch.exp(-0.5 * quadratic)
    occupancy = opacity * g if kernel.opacity_density else g
    if not kernel.probabilistic:
        weight = opacity * g if kernel.opacity_features else g
        return occupancy, weight.unsqueeze(-1) * features, weight
    # log(1 - x): kept finite (and its gradient) where x nears 1; x = 1 exactly (o = 1 or
    # opacity unused, at the mean) saturates the voxel: occupancy exactly 1
    survival = torch.log1p(-occupancy.clamp(max=1 - torch.finfo(g.dtype).eps))
    survival = torch.where(occupancy >= 1, _SATURATED_LOG, survival)
    weight = torch.exp(log_normaliser - 0.5 * quadratic)
    if kernel.opacity_features:
        weight = opacity * weight
    return survival, weight.unsqueeze(-1) * features, weight


def pair_terms(
    means: Tensor,
    whitening: Tensor,
    opacities: Tensor,  # (M,)
    features: Tensor,  # (M, C)
    owner: Tensor,
    centres: Tensor,
    log_normaliser: Tensor,  # (M,)
    kernel: Kernel,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`kernel_terms` of the (Gaussian ``owner``, voxel centre) pairs."""
    quadratic = _pair_quadratic(means, whitening, owner, centres)
    return kernel_terms(quadratic, opacities[owner], features[owner], log_normaliser[owner], kernel)
