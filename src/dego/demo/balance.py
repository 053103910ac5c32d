"""Balanced offset gradients: each deformable Gaussian gets the same say in a shared network."""

from __future__ import annotations

import torch
from torch import Tensor

from dego.gaussians import GaussianSet


class _BalancedGradient(torch.autograd.Function):
    """Identity on the deformed means; in backward the part of the gradient that reaches
    the deformation is rescaled per Gaussian (see :func:`balance_deformation_gradients`),
    while the canonical parameters still get the unchanged gradient."""

    @staticmethod
    def forward(ctx, deformed: Tensor, canonical: Tensor, keep: Tensor) -> Tensor:
        ctx.save_for_backward(keep)
        return deformed.clone()

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, Tensor, None]:
        (keep,) = ctx.saved_tensors
        norm = grad.norm(dim=-1, keepdim=True)  # (1, N, 1)
        active = keep[..., None] & (norm > 0)
        # the mean norm over the active Gaussians (1 where none is), without a host sync:
        # a data-dependent branch would break a compiled backward's graph
        count = active.sum()
        total = torch.where(active, norm, 0).sum()
        scale = torch.where(count > 0, total / count.clamp_min(1), 1.0).to(norm.dtype)
        balanced = torch.where(active, grad / norm.clamp_min(1e-30) * scale, grad)
        return balanced, grad - balanced, None


def balance_deformation_gradients(
    deformed: GaussianSet, canonical: GaussianSet, keep: Tensor | None
) -> GaussianSet:
    """``deformed`` unchanged, except that the position gradient flowing back into the
    deformation is equalised over Gaussians: each Gaussian in ``keep`` (``(1, N)`` bool;
    ``None``: all) passes on its gradient direction at the mean gradient norm. The
    canonical parameters' gradient is exactly the raw one.

    Why: a shared network sums per-Gaussian gradients whose sizes differ by orders of
    magnitude (a Gaussian near a camera covers thousands of pixels, one on a pedestrian a
    few), so the few Gaussians of a small moving agent hardly move it; free per-Gaussian
    parameters do not have this problem because Adam normalises each one separately.
    """
    if keep is None:
        keep = torch.ones(deformed.means.shape[:-1], dtype=torch.bool, device=deformed.device)
    means = _BalancedGradient.apply(deformed.means, canonical.means, keep)
    return deformed.replace(means=means)
