"""Helpers of tests/deformation/test_deformation.py, also used by

- tests/deformation/test_reduction.py
- tests/deformation/test_presets.py
"""

from __future__ import annotations

import torch
from torch import Tensor

from dego import GaussianSet, normalize_quaternions
from dego.deformation import (
    DecoupledDeformation,
    DeformationDeltas,
    DeformationLossWeights,
    DeformationOutput,
)
from tests.helpers.strategies import make_gaussian_set

PRESETS = ["paper", "official"]
SMALL = {
    "hidden_dim": 16,
    "head_hidden": 16,
    "depth": 2,
    "time_dim": 8,
    "pos_levels": 2,
    "time_levels": 2,
}


FEATURES = 4
TIMES = [0.0, 0.5, -1.0, 3.0]


def make_module(
    preset: str = "paper",
    *,
    feature_dim: int = FEATURES,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
    **kwargs: object,
) -> DecoupledDeformation:
    """A small module initialised from ``seed`` without touching the global RNG."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        module = DecoupledDeformation(feature_dim, preset=preset, **{**SMALL, **kwargs})  # type: ignore[arg-type]
    return module.to(device=device, dtype=dtype)


def make_inputs(
    b: int,
    n: int,
    *,
    feature_dim: int = FEATURES,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
    unit: bool = True,
) -> tuple[GaussianSet, Tensor]:
    """A canonical ``(b,)`` set (with its own 3 feature channels) and ``(b, n, C_g)`` latents."""
    canonical = make_gaussian_set((b,), n, seed=seed, feature_dim=3, extent=30.0)  # float64
    if unit:
        canonical = canonical.replace(quats=normalize_quaternions(canonical.quats))
    g = torch.Generator().manual_seed(seed + 1)
    features = torch.randn(b, n, feature_dim, generator=g, dtype=torch.float64)
    return canonical.to(device=device, dtype=dtype), features.to(device=device, dtype=dtype)


def times_tensor(
    values: list[float] | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
) -> Tensor:
    return torch.tensor(TIMES if values is None else values, dtype=dtype, device=device)


def randomize_last_layers(
    module: DecoupledDeformation, *, std: float = 0.5, seed: int = 0, mask: bool = True
) -> None:
    """Random weights and biases for the last layer of every delta head (and the mask head)."""
    g = torch.Generator().manual_seed(seed)
    heads = [*module.heads.values(), *([module.mask_head] if mask else [])]
    with torch.no_grad():
        for head in heads:
            for param in (head[-1].weight, head[-1].bias):
                param.copy_(torch.randn(param.shape, generator=g, dtype=torch.float64) * std)


def literal_output(preset: str) -> DeformationOutput:
    """``(B, T, N) = (1, 2, 1)`` deltas with hand-computable losses."""
    f64 = torch.float64
    deltas = DeformationDeltas(
        means=torch.tensor([[[[1.0, 2.0, 2.0]], [[0.0, 0.0, 0.0]]]], dtype=f64),
        quats=torch.tensor([[[[0.0, 0.0, 0.0, 0.0]], [[1.0, 0.0, 0.0, 0.0]]]], dtype=f64),
        scales=torch.tensor([[[[1.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]]]], dtype=f64),
        opacities=torch.tensor([[[2.0], [0.0]]], dtype=f64),
    )
    mask = torch.tensor([[0.25]], dtype=f64)
    if preset == "official":  # time dependent; only the last step enters L_mask
        mask = torch.tensor([[[0.5], [0.25]]], dtype=f64)
    gaussians = make_gaussian_set((1, 2), 1)
    return DeformationOutput(
        gaussians=gaussians,
        rigid_mask=mask,
        deltas=deltas,
        rigid_offsets=deltas.means,
        nonrigid_offsets=deltas.means,
        preset=preset,  # type: ignore[arg-type]
        loss_weights=DeformationLossWeights(),
    )
