"""Hypothesis strategies shared by the test-suite (GaussianSets of any batch shape and N).

Shapes and a seed are drawn by hypothesis; tensor values come from a seeded torch
generator, which keeps examples fast to build while staying reproducible and shrinkable
in their structure (batch shape, N, feature size).
"""

from __future__ import annotations

import math

import torch
from hypothesis import strategies as st

from dego import GaussianSet

batch_shapes = st.lists(st.integers(1, 3), min_size=0, max_size=2).map(tuple)
"""Batch shapes with up to two axes of size 1-3 (including the unbatched ``()``)."""


def random_quaternions(
    shape: tuple[int, ...], generator: torch.Generator, dtype: torch.dtype
) -> torch.Tensor:
    """Random, deliberately unnormalised wxyz quaternions ``(*shape, 4)`` with norm >= 0.1."""
    quats = torch.randn(*shape, 4, generator=generator, dtype=dtype)
    tiny = torch.linalg.vector_norm(quats, dim=-1, keepdim=True) < 0.1
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype)
    norms = torch.rand(*shape, 1, generator=generator, dtype=dtype) * 3 + 0.1
    return torch.where(tiny, identity, quats) * norms


def make_gaussian_set(
    batch: tuple[int, ...],
    n: int,
    *,
    seed: int = 0,
    feature_dim: int | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
    scale_range: tuple[float, float] = (1e-2, 10.0),
    extent: float = 50.0,
) -> GaussianSet:
    """A random valid GaussianSet with log-uniform scales in ``scale_range``."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = math.log(scale_range[0]), math.log(scale_range[1])
    features = None
    if feature_dim is not None:
        features = torch.randn(*batch, n, feature_dim, generator=g, dtype=dtype)
    gs = GaussianSet(
        means=(torch.rand(*batch, n, 3, generator=g, dtype=dtype) * 2 - 1) * extent,
        quats=random_quaternions((*batch, n), g, dtype),
        scales=torch.exp(torch.rand(*batch, n, 3, generator=g, dtype=dtype) * (hi - lo) + lo),
        opacities=torch.rand(*batch, n, generator=g, dtype=dtype),
        features=features,
    )
    return gs.to(device)


@st.composite
def gaussian_sets(
    draw: st.DrawFn,
    *,
    batch: st.SearchStrategy[tuple[int, ...]] = batch_shapes,
    min_n: int = 0,
    max_n: int = 8,
    with_features: bool | None = None,
    max_feature_dim: int = 5,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
    scale_range: tuple[float, float] = (1e-2, 10.0),
) -> GaussianSet:
    """Random valid GaussianSets: any batch shape, N in [min_n, max_n] (0 and 1 included)."""
    shape = draw(batch)
    n = draw(st.integers(min_n, max_n))
    has_features = draw(st.booleans()) if with_features is None else with_features
    feature_dim = draw(st.integers(1, max_feature_dim)) if has_features else None
    seed = draw(st.integers(0, 2**31 - 1))
    return make_gaussian_set(
        shape,
        n,
        seed=seed,
        feature_dim=feature_dim,
        dtype=dtype,
        device=device,
        scale_range=scale_range,
    )
