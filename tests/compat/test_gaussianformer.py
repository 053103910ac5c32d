"""dego.compat.gaussianformer: GaussianFormer's aggregation heads (GF-1 ``localagg``, GF-2
``localagg_prob`` with ``combine_geosem``) against plain re-statements of their maths,
analytic single-Gaussian cases, layouts, conventions and errors."""

from __future__ import annotations

import math
from typing import Any

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from dego import GaussianSet, VoxelGrid
from dego.compat.gaussianformer import EMPTY_MEAN, EMPTY_SCALE, aggregate_gf1, aggregate_gf2
from tests.reference.voxel import scale_cube_mask

GRID = VoxelGrid((-2.0, -2.0, -1.0), (2.0, 2.0, 1.0), 0.5)  # (8, 8, 4): GaussianFormer's 0.5 m


# ---------------------------------------------------------------------------------------
# reference: GaussianFormer's heads written from the maths, dense over a small grid
# ---------------------------------------------------------------------------------------


def hamilton_rotation(q: Tensor) -> Tensor:
    """The rotation matrix of wxyz quaternions ``(..., 4)`` (normalised first)."""
    w, x, y, z = (q / q.norm(dim=-1, keepdim=True)).unbind(-1)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def gf_terms(
    means: Tensor, scales: Tensor, rotations: Tensor, grid: VoxelGrid, k: float
) -> tuple[Tensor, Tensor]:
    """``(g, normaliser)``: ``(B, P, X*Y*Z)`` kernels inside each cube (0 outside) with
    GaussianFormer's covariance ``(S R)^T (S R)``, and ``(B, P)`` ``sqrt(det Sigma^-1) /
    (2 pi)^1.5``."""
    m = torch.diag_embed(scales) @ hamilton_rotation(rotations)  # S R
    precision = torch.linalg.inv(m.transpose(-1, -2) @ m)
    centres = grid.centers(dtype=means.dtype).reshape(-1, 3)  # x-major flattening
    d = means[:, :, None, :] - centres  # (B, P, V, 3)
    g = torch.exp(-0.5 * torch.einsum("bpvi,bpij,bpvj->bpv", d, precision, d))
    cube = GaussianSet(means, rotations, scales, torch.ones_like(means[..., 0]))
    inside = scale_cube_mask(k)(cube, grid).flatten(2)
    normaliser = torch.linalg.det(precision).sqrt() / (2 * math.pi) ** 1.5
    return g * inside, normaliser


def gf1_reference(means, scales, rotations, opacities, semantics, grid, k=3.0) -> Tensor:
    g, _ = gf_terms(means, scales, rotations, grid, k)
    return torch.einsum("bpv,bp,bpc->bcv", g, opacities, semantics)  # (B, C, V)


def gf2_reference(means, scales, rotations, opacities, semantics, grid, k=4.0) -> Tensor:
    g, normaliser = gf_terms(means, scales, rotations, grid, k)
    c = semantics.shape[-1]
    alpha = 1 - torch.prod(1 - g, dim=1)  # (B, V)
    p = (opacities * normaliser)[:, :, None] * g  # (B, P, V)
    total = p.sum(dim=1)
    mixed = (
        torch.einsum("bpv,bpc->bcv", p, semantics.softmax(-1)) / total.clamp_min(1e-300)[:, None]
    )
    e = torch.where((total > 1e-9)[:, None], mixed, torch.full_like(mixed, 1 / c))
    return torch.cat([e * alpha[:, None], (1 - alpha)[:, None]], dim=1)  # (B, C + 1, V)


def prediction(b: int, p: int, c: int, seed: int, *, extent: float = 2.2) -> dict[str, Tensor]:
    g = torch.Generator().manual_seed(seed)
    f64 = {"dtype": torch.float64, "generator": g}
    return {
        "means": (torch.rand(b, p, 3, **f64) * 2 - 1) * torch.tensor([extent, extent, 1.1]),
        "scales": torch.rand(b, p, 3, **f64) * 0.5 + 0.08,
        "rotations": torch.randn(b, p, 4, **f64),
        "opacities": torch.rand(b, p, 1, **f64),
        "semantics": torch.randn(b, p, c, **f64),
    }


# ---------------------------------------------------------------------------------------
# the SurroundOcc grid
# ---------------------------------------------------------------------------------------


def test_surroundocc_grid() -> None:
    grid = VoxelGrid.surroundocc()
    assert grid.shape == (200, 200, 16)
    assert grid.lower == (-50.0, -50.0, -5.0) and grid.upper == (50.0, 50.0, 3.0)
    assert grid.voxel_size == (0.5, 0.5, 0.5)
    first = grid.index_to_world(torch.tensor([0, 0, 0]), dtype=torch.float64)
    assert first.tolist() == [-49.75, -49.75, -4.75]


# ---------------------------------------------------------------------------------------
# agreement with the reference
# ---------------------------------------------------------------------------------------


@settings(max_examples=12)
@given(st.integers(1, 2), st.integers(0, 8), st.integers(1, 5), st.integers(0, 2**31 - 1))
def test_gf1_matches_the_reference(b: int, p: int, c: int, seed: int) -> None:
    x = prediction(b, p, c, seed)
    out = aggregate_gf1(**x, grid=GRID)
    assert out.shape == (b, c, GRID.num_voxels)
    expected = gf1_reference(**{**x, "opacities": x["opacities"][..., 0]}, grid=GRID)
    torch.testing.assert_close(out, expected, atol=1e-9, rtol=1e-9)
    grid_layout = aggregate_gf1(**x, grid=GRID, layout="grid")
    assert grid_layout.shape == (b, *GRID.shape, c)
    torch.testing.assert_close(grid_layout.reshape(b, -1, c).transpose(1, 2), out)


@settings(max_examples=12)
@given(st.integers(1, 2), st.integers(0, 8), st.integers(1, 5), st.integers(0, 2**31 - 1))
def test_gf2_matches_the_reference(b: int, p: int, c: int, seed: int) -> None:
    x = prediction(b, p, c, seed)
    out = aggregate_gf2(**x, grid=GRID)
    assert out.shape == (b, c + 1, GRID.num_voxels)
    expected = gf2_reference(**{**x, "opacities": x["opacities"][..., 0]}, grid=GRID)
    torch.testing.assert_close(out, expected, atol=1e-9, rtol=1e-7)


def test_batches_are_independent() -> None:
    x = prediction(3, 6, 4, seed=11)
    for aggregate in (aggregate_gf1, aggregate_gf2):
        whole = aggregate(**x, grid=GRID)
        for i in range(3):
            single = aggregate(**{k: v[i : i + 1] for k, v in x.items()}, grid=GRID)
            torch.testing.assert_close(whole[i : i + 1], single, atol=1e-12, rtol=1e-12)


def test_means_outside_the_grid_give_partial_coverage() -> None:
    x = prediction(1, 6, 3, seed=12, extent=2.6)  # some means beyond the 2 m faces
    assert bool((x["means"].abs() > 2.0).any())
    out = aggregate_gf2(**x, grid=GRID)
    expected = gf2_reference(**{**x, "opacities": x["opacities"][..., 0]}, grid=GRID)
    torch.testing.assert_close(out, expected, atol=1e-9, rtol=1e-7)


# ---------------------------------------------------------------------------------------
# analytic single-Gaussian cases and conventions
# ---------------------------------------------------------------------------------------


def one(
    mean=(0.25, -0.25, 0.25), scales=(0.3, 0.3, 0.3), rotation=(1.0, 0, 0, 0), opacity=0.3,
    semantics=(1.0, 2.0, 3.0), dtype=torch.float64,
) -> dict[str, Tensor]:  # fmt: skip
    def t(values: Any) -> Tensor:
        return torch.tensor(values, dtype=dtype).reshape(1, 1, -1)

    return {
        "means": t(mean),
        "scales": t(scales),
        "rotations": t(rotation),
        "opacities": t(opacity),
        "semantics": t(semantics),
    }


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gf1_single_gaussian(dtype: torch.dtype) -> None:
    x = one(dtype=dtype)
    out = aggregate_gf1(**x, grid=GRID, layout="grid")[0]
    assert out.dtype == dtype
    i, j, k = GRID.world_to_index(x["means"][0, 0]).tolist()  # the mean is a voxel centre
    torch.testing.assert_close(out[i, j, k], 0.3 * x["semantics"][0, 0])
    # one voxel along x: o exp(-0.5 (0.5 / 0.3)^2) s
    g = math.exp(-0.5 * (0.5 / 0.3) ** 2)
    torch.testing.assert_close(out[i + 1, j, k], 0.3 * g * x["semantics"][0, 0])
    # r = ceil(3 * 0.3 / 0.5) = 2: nothing three voxels away, though the kernel is not 0 there
    assert bool((out[i + 3] == 0).all()) and bool((out[i + 2, j, k] != 0).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gf2_single_gaussian_is_occupied_at_its_mean_whatever_its_opacity(
    dtype: torch.dtype,
) -> None:
    x = one(dtype=dtype)
    out = aggregate_gf2(**x, grid=GRID, layout="grid")[0]  # (X, Y, Z, 4)
    i, j, k = GRID.world_to_index(x["means"][0, 0]).tolist()
    probabilities = x["semantics"][0, 0].softmax(-1)
    assert out[i, j, k, -1].item() == 0.0  # 1 - alpha with alpha exactly 1 (opacity 0.3)
    torch.testing.assert_close(out[i, j, k, :3], probabilities)
    # a neighbour: alpha = g, semantics the Gaussian's own probabilities
    g = math.exp(-0.5 * (0.5 / 0.3) ** 2)
    expected = torch.cat([probabilities * g, torch.tensor([1 - g], dtype=dtype)])
    torch.testing.assert_close(out[i, j + 1, k], expected)
    # a voxel no Gaussian reaches (r = ceil(4 * 0.3 / 0.5) = 3): alpha = 0 -> [0, 0, 0, 1]
    assert out[i, j + 4, k].tolist() == [0.0, 0.0, 0.0, 1.0]
    assert out[i, j + 3, k, -1].item() < 1.0


def test_gf2_uniform_fallback_where_the_mixture_weight_is_negligible() -> None:
    # opacity 1e-12: the mixture weight is <= 1e-9 everywhere, the geometry is not
    x = one(opacity=1e-12)
    out = aggregate_gf2(**x, grid=GRID, layout="grid")[0]
    alpha = 1 - out[..., -1]
    reached = alpha > 0
    assert int(reached.sum()) > 1
    expected = (alpha[reached] / 3).unsqueeze(-1).expand(-1, 3)
    torch.testing.assert_close(out[reached][:, :3], expected)


def test_gf1_empty_gaussian() -> None:
    x = one(opacity=0.5, semantics=(0.2, 0.7))  # two non-empty classes
    logit = torch.tensor(10.0, dtype=torch.float64, requires_grad=True)
    out = aggregate_gf1(**x, grid=GRID, empty_logit=logit, layout="grid")[0]  # (X, Y, Z, 3)
    assert out.shape == (*GRID.shape, 3)
    centres = GRID.centers(dtype=torch.float64)
    d = (centres - torch.tensor(EMPTY_MEAN, dtype=torch.float64)) / torch.tensor(
        EMPTY_SCALE, dtype=torch.float64
    )
    empty = 10.0 * torch.exp(-0.5 * d.square().sum(-1))
    torch.testing.assert_close(out[..., 2], empty)  # everywhere: its cube covers the grid
    assert bool((out.argmax(-1) == 2).all())  # the empty class wins where the one is weak
    without = aggregate_gf1(**x, grid=GRID, layout="grid")[0]
    torch.testing.assert_close(out[..., :2], without)
    out[..., 2].sum().backward()
    assert logit.grad is not None and logit.grad.item() > 0
    # a Python float works too
    torch.testing.assert_close(aggregate_gf1(**x, grid=GRID, empty_logit=10.0, layout="grid")[0],
                               out.detach())  # fmt: skip


def test_rotation_convention_is_gaussianformers_transpose() -> None:
    # a needle along x, rotated by +45 degrees about z in GaussianFormer's (S R)^T (S R):
    # its long axis is R^T e_x = (1, -1, 0) / sqrt(2), not (1, 1, 0) / sqrt(2)
    half = math.radians(45) / 2
    x = one(scales=(0.6, 0.1, 0.1), rotation=(math.cos(half), 0.0, 0.0, math.sin(half)))
    out = aggregate_gf1(**x, grid=GRID, layout="grid")[0, ..., 0]
    i, j, k = GRID.world_to_index(x["means"][0, 0]).tolist()
    assert out[i + 1, j - 1, k] > 100 * out[i + 1, j + 1, k]
    torch.testing.assert_close(
        aggregate_gf1(**x, grid=GRID).flatten(),
        gf1_reference(**{**x, "opacities": x["opacities"][..., 0]}, grid=GRID).flatten(),
    )


def test_opacity_layouts() -> None:
    x = prediction(2, 5, 3, seed=13)
    base = aggregate_gf1(**x, grid=GRID)
    flat = aggregate_gf1(**{**x, "opacities": x["opacities"][..., 0]}, grid=GRID)
    assert torch.equal(base, flat)
    ones = {**x, "opacities": torch.ones_like(x["opacities"])}
    for missing in (None, x["opacities"][..., :0]):
        for aggregate in (aggregate_gf1, aggregate_gf2):
            torch.testing.assert_close(
                aggregate(**{**x, "opacities": missing}, grid=GRID), aggregate(**ones, grid=GRID)
            )


def test_default_grid_is_surroundocc() -> None:
    x = one(mean=(0.25, 0.25, -0.75), dtype=torch.float32)
    out = aggregate_gf2(**x)
    assert out.shape == (1, 4, 200 * 200 * 16)
    index = VoxelGrid.surroundocc().world_to_index(x["means"][0, 0]).tolist()
    flat = (index[0] * 200 + index[1]) * 16 + index[2]
    assert out[0, -1, flat].item() == 0.0


# ---------------------------------------------------------------------------------------
# errors, gradients, devices
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("change", "name", "error"),
    [
        ({"means": torch.zeros(1, 2, 3, dtype=torch.float64)}, "semantics", TypeError),
        ({"rotations": torch.zeros(1, 1, 3, dtype=torch.float64)}, "rotations", TypeError),
        ({"opacities": torch.zeros(1, 1, 2, dtype=torch.float64)}, "opacities", TypeError),
        ({"semantics": torch.zeros(1, 1, 3)}, "semantics", TypeError),  # float32
        ({"rotations": torch.zeros(1, 1, 4, dtype=torch.float64)}, "rotations", ValueError),
        ({"scales": -torch.ones(1, 1, 3, dtype=torch.float64)}, "scales", ValueError),
        ({"opacities": torch.full((1, 1), 2.0, dtype=torch.float64)}, "opacities", ValueError),
        ({"semantics": torch.full((1, 1, 3), math.nan, dtype=torch.float64)}, "semantics",
         ValueError),
        ({"means": torch.full((1, 1, 3), math.inf, dtype=torch.float64)}, "means", ValueError),
        ({"semantics": torch.zeros(1, 1, 0, dtype=torch.float64)}, "semantics", ValueError),
    ],
)  # fmt: skip
def test_bad_inputs_name_the_argument(change: dict[str, Tensor], name: str, error: type) -> None:
    x = {**one(), **change}
    for aggregate in (aggregate_gf1, aggregate_gf2):
        with pytest.raises(error, match=name):
            aggregate(**x, grid=GRID)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"scale_multiplier": 0}, "scale_multiplier"),
        ({"scale_multiplier": math.nan}, "scale_multiplier"),
        ({"layout": "flat"}, "layout"),
        ({"empty_logit": math.nan}, "empty_logit"),
        ({"empty_logit": torch.zeros(2, dtype=torch.float64)}, "empty_logit"),
    ],
)
def test_bad_options_name_the_argument(kwargs: dict[str, Any], name: str) -> None:
    with pytest.raises((ValueError, TypeError), match=name):
        aggregate_gf1(**one(), grid=GRID, **kwargs)


@pytest.mark.slow
def test_gradcheck_float64() -> None:
    x = prediction(1, 2, 2, seed=14, extent=1.0)
    x["opacities"] = x["opacities"] * 0.8 + 0.1
    names = list(x)
    grid = VoxelGrid((-1.0, -1.0, -0.5), (1.0, 0.5, 0.5), 0.5)  # (4, 3, 2)

    def run(aggregate, *tensors: Tensor) -> Tensor:
        return aggregate(**dict(zip(names, tensors, strict=True)), grid=grid, scale_multiplier=1)

    inputs = tuple(t.clone().requires_grad_(True) for t in x.values())
    for aggregate in (aggregate_gf1, aggregate_gf2):
        assert torch.autograd.gradcheck(
            lambda *t, a=aggregate: run(a, *t), inputs, eps=1e-6, atol=1e-5, rtol=1e-4
        )


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
def test_cuda_matches_cpu() -> None:
    x = prediction(2, 30, 17, seed=15)
    for aggregate in (aggregate_gf1, aggregate_gf2):
        expected = aggregate(**x, grid=GRID)
        out = aggregate(**{k: v.cuda() for k, v in x.items()}, grid=GRID)
        assert out.device.type == "cuda"
        torch.testing.assert_close(out.cpu(), expected, atol=1e-9, rtol=1e-9)
