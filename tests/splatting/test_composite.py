"""The hand-written backward of the chunk compositor equals autograd through the same maths."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dego.splatting.composite import (
    CompositeRules,
    _alphas,
    _chunk_backward,
    _chunk_forward,
    _transmittances,
)


class _Chunk(torch.autograd.Function):
    """One chunk as an autograd node around the library's closed-form backward."""

    @staticmethod
    def forward(ctx, transmittance, finished, mean, conic, opacity, color, origins, rules):
        ctx.save_for_backward(transmittance, finished, mean, conic, opacity, color, origins)
        ctx.rules = rules
        return _chunk_forward(transmittance, finished, mean, conic, opacity, color, origins, rules)[
            :2
        ]

    @staticmethod
    def backward(ctx, grad_contribution, grad_transmittance):
        grads = _chunk_backward(
            *ctx.saved_tensors, ctx.rules, grad_contribution, grad_transmittance
        )
        grad_in, grad_mean, grad_conic, grad_opacity, grad_color = grads
        return grad_in, None, grad_mean, grad_conic, grad_opacity, grad_color, None, None


def composite_chunk(*args):
    return _Chunk.apply(*args)


def autograd_chunk(transmittance, finished, mean, conic, opacity, color, origins, rules):
    """Front-to-back compositing written with plain differentiable torch ops."""
    size = transmittance.shape[-1]
    alpha = _alphas(mean, conic, opacity, origins, size, rules)[0]
    start = transmittance.masked_fill(finished, 0.0)
    relative_before, after = _transmittances(start, alpha)
    weights = torch.where(
        after <= rules.transmittance_min, 0.0, start.unsqueeze(1) * relative_before * alpha
    )
    contribution = torch.bmm(weights.flatten(2).transpose(1, 2), color)
    return contribution, torch.where(finished, transmittance, start - weights.sum(1))


def random_chunk(seed: int, groups: int = 3, k: int = 6, size: int = 4, channels: int = 5):
    g = torch.Generator().manual_seed(seed)
    dt = torch.float64
    factor = torch.randn(groups, k, 2, 2, generator=g, dtype=dt)
    precision = torch.linalg.inv(factor @ factor.transpose(-1, -2) * 2 + torch.eye(2, dtype=dt))
    opacity = torch.rand(groups, k, generator=g, dtype=dt) * 0.95 + 0.02
    opacity[0, 2] = 0.0  # padding / zero opacity
    opacity[1, 0] = 0.9999  # clamped to max_alpha
    return (
        torch.rand(groups, size, size, generator=g, dtype=dt) * 0.9 + 0.1,
        torch.rand(groups, size, size, generator=g) < 0.2,
        torch.rand(groups, k, 2, generator=g, dtype=dt) * size,
        torch.stack([precision[..., 0, 0], precision[..., 0, 1], precision[..., 1, 1]], -1),
        opacity,
        torch.randn(groups, k, channels, generator=g, dtype=dt),
        torch.full((groups, 2), 0.5, dtype=dt),
    )


@settings(max_examples=20)
@given(st.integers(0, 10_000), st.sampled_from([1e-4, 0.3]))
def test_custom_backward_equals_autograd(seed: int, transmittance_min: float) -> None:
    rules = CompositeRules(0.999, 1 / 255, transmittance_min)
    t, fin, mean, conic, opacity, color, origins = random_chunk(seed)
    inputs = [x.clone().requires_grad_() for x in (t, mean, conic, opacity, color)]
    ours = composite_chunk(inputs[0], fin, *inputs[1:], origins, rules)
    reference = autograd_chunk(inputs[0], fin, *inputs[1:], origins, rules)
    for a, b in zip(ours, reference, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    weights = [torch.randn_like(o) for o in ours]
    grads = torch.autograd.grad(
        sum((o * w).sum() for o, w in zip(ours, weights, strict=True)), inputs
    )
    expected = torch.autograd.grad(
        sum((o * w).sum() for o, w in zip(reference, weights, strict=True)), inputs
    )
    for name, a, b in zip(
        ["transmittance", "mean", "conic", "opacity", "color"], grads, expected, strict=True
    ):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10, msg=name)


@pytest.mark.slow
def test_gradcheck_chunk() -> None:
    rules = CompositeRules(0.999, 1 / 255, 1e-4)
    t, fin, mean, conic, opacity, color, origins = random_chunk(7)
    inputs = tuple(x.clone().requires_grad_() for x in (t, mean, conic, opacity, color))

    def fn(t, mean, conic, opacity, color):
        return composite_chunk(t, fin, mean, conic, opacity, color, origins, rules)

    assert torch.autograd.gradcheck(fn, inputs)
