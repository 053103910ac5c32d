"""Input validation and numerical policy of ``voxelize`` / ``GaussianVoxelizer`` (issue 17).

Non-finite values and degenerate Gaussians raise ``ValueError`` naming the field; finite
but extreme parameters (tiny / huge scales, huge or infinite ``cutoff_sigma``, far means)
give finite results with densities in [0, 1] and never make a Gaussian vanish; empty
batches give empty grids; the memory guard trips before allocating; float16 / bfloat16
are computed in float32 and returned in their own dtype.
"""

from __future__ import annotations

import math
from typing import Any

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

import dego
from dego import GaussianSet, GaussianVoxelizer, VoxelGrid, voxelize
from dego.gaussians import QUATERNION_EPS
from dego.voxelizer import VoxelizerConfig
from tests.helpers.strategies import make_gaussian_set
from tests.reference.voxel import dense_voxelize

GRID = VoxelGrid((-2.0, -2.0, -1.0), (2.0, 2.0, 1.0), 0.25)  # (16, 16, 8)
FIELDS = ("means", "quats", "scales", "opacities", "features")
CONFIGS = [
    {"mode": "additive"},
    {"mode": "probabilistic"},
    {"mode": "additive", "neighborhood": "cube", "nbh": 1},
    {"mode": "probabilistic", "neighborhood": "cube", "nbh": 2},
]
CONFIG_IDS = ["additive", "probabilistic", "cube", "prob-cube"]
configs = st.sampled_from(CONFIGS)
float_dtypes = st.sampled_from([torch.float32, torch.float64])


def scene(seed: int, b: int = 1, n: int = 5, dtype: torch.dtype = torch.float64) -> GaussianSet:
    return make_gaussian_set(
        (b,), n, seed=seed, feature_dim=3, extent=2.0, scale_range=(0.1, 0.8), dtype=dtype
    )


def voxel_centre(index: tuple[int, int, int], dtype: torch.dtype) -> Tensor:
    """The centre of voxel ``index`` of ``GRID``, computed as the voxelizer computes it."""
    lower = torch.tensor(GRID.lower, dtype=dtype)
    size = torch.tensor(GRID.voxel_size, dtype=dtype)
    return lower + (torch.tensor(index, dtype=dtype) + 0.5) * size


def one_gaussian(
    mean: Tensor, quat: Tensor, scales: Tensor, opacity: float, dtype: torch.dtype
) -> GaussianSet:
    return GaussianSet(
        means=mean.to(dtype).reshape(1, 1, 3),
        quats=quat.to(dtype).reshape(1, 1, 4),
        scales=scales.to(dtype).reshape(1, 1, 3),
        opacities=torch.tensor([[opacity]], dtype=dtype),
        features=torch.tensor([[[1.0, -2.0]]], dtype=dtype),
    )


def assert_valid_output(density: Tensor, features: Tensor) -> None:
    assert bool(torch.isfinite(density).all()), "density has NaN/inf"
    assert bool(torch.isfinite(features).all()), "features have NaN/inf"
    assert bool(((density >= 0) & (density <= 1)).all()), "density outside [0, 1]"


# ---------------------------------------------------------------------------------------
# non-finite values
# ---------------------------------------------------------------------------------------


@settings(max_examples=40)
@given(
    st.integers(0, 2**31 - 1),
    st.sampled_from(FIELDS),
    st.sampled_from([math.nan, math.inf, -math.inf]),
    st.data(),
    configs,
    st.booleans(),
)
def test_one_poisoned_value_raises_naming_the_field(
    seed: int, field: str, value: float, data: st.DataObject, config: dict[str, Any], module: bool
) -> None:
    gs = scene(seed, b=2, n=4)
    poisoned = getattr(gs, field).clone()
    poisoned.view(-1)[data.draw(st.integers(0, poisoned.numel() - 1))] = value
    match = rf"^{field}: 1 of {poisoned.numel()} values are not finite"
    with pytest.raises(ValueError, match=match):
        if module:
            GaussianVoxelizer(GRID, **config)(gs.replace(**{field: poisoned}))
        else:
            voxelize(gs.replace(**{field: poisoned}), GRID, **config)
    if field == "features":  # features passed as an argument are checked the same way
        with pytest.raises(ValueError, match=match):
            voxelize(gs.replace(features=None), GRID, features=poisoned, **config)


def test_a_nan_opacity_no_longer_propagates() -> None:
    gs = scene(0)
    opacities = gs.opacities.clone()
    opacities[0, 1] = math.nan
    with pytest.raises(ValueError, match=r"^opacities: 1 of 5 values are not finite"):
        voxelize(gs.replace(opacities=opacities), GRID)


# ---------------------------------------------------------------------------------------
# degenerate Gaussians: raise, or finite output with density in [0, 1]
# ---------------------------------------------------------------------------------------

SCALE_VALUES = [0.0, -0.3, -1e-30, 1e-30, 1e-12, 1e-6, 0.05, 0.3, 1e6, 1e30]
QUAT_NORMS = [0.0, 1e-13, 1e-6, 1.0, 1e20]
OPACITY_VALUES = [-1.0, -1e-9, 0.0, 1e-30, 0.5, 1.0, 1.5]


@st.composite
def degenerate_sets(draw: st.DrawFn) -> GaussianSet:
    """(1, N) sets whose values mix valid, extreme and invalid scales / quats / opacities."""
    dtype = draw(float_dtypes)
    n = draw(st.integers(1, 4))
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    means = (torch.rand(1, n, 3, generator=g, dtype=torch.float64) * 2 - 1) * 2.5
    directions = torch.randn(1, n, 4, generator=g, dtype=torch.float64)
    directions = directions / torch.linalg.vector_norm(directions, dim=-1, keepdim=True)
    norms = [draw(st.sampled_from(QUAT_NORMS)) for _ in range(n)]
    quats = directions * torch.tensor(norms, dtype=torch.float64)[None, :, None]
    scales = [[draw(st.sampled_from(SCALE_VALUES)) for _ in range(3)] for _ in range(n)]
    opacities = [draw(st.sampled_from(OPACITY_VALUES)) for _ in range(n)]
    return GaussianSet(
        means=means.to(dtype),
        quats=quats.to(dtype),
        scales=torch.tensor([scales], dtype=dtype),
        opacities=torch.tensor([opacities], dtype=dtype),
        features=torch.randn(1, n, 2, generator=g, dtype=torch.float64).to(dtype),
    )


def expected_rejection(gs: GaussianSet) -> str | None:
    """The field voxelize must name, in its order of checks, or None when all is valid."""
    if bool((gs.scales <= 0).any()):
        return "scales"
    if bool((torch.linalg.vector_norm(gs.quats, dim=-1) <= QUATERNION_EPS).any()):
        return "quats"
    if bool(((gs.opacities < 0) | (gs.opacities > 1)).any()):
        return "opacities"
    return None


@settings(max_examples=60)
@given(degenerate_sets(), configs, st.sampled_from([1.0, 3.0, math.inf]))
def test_degenerate_gaussians_raise_or_give_finite_densities_in_unit_interval(
    gs: GaussianSet, config: dict[str, Any], cutoff_sigma: float
) -> None:
    field = expected_rejection(gs)
    if field is not None:
        with pytest.raises(ValueError, match=rf"^{field}: "):
            voxelize(gs, GRID, cutoff_sigma=cutoff_sigma, **config)
        return
    out = voxelize(gs, GRID, cutoff_sigma=cutoff_sigma, **config)
    assert_valid_output(out.density, out.features)


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
@pytest.mark.parametrize(
    ("field", "index", "value"),
    [
        ("scales", (0, 2, 1), -0.2),  # probabilistic mode zeroed its neighbours' features
        ("scales", (0, 0, 0), 0.0),  # cube mode gave a NaN density
        ("opacities", (0, 4), -1.0),  # a negative density
        ("quats", (0, 3), 0.0),  # the whole quaternion: no rotation
    ],
    ids=["negative-scale", "zero-scale", "negative-opacity", "zero-quat"],
)
def test_the_issue_cases_are_rejected(
    config: dict[str, Any], field: str, index: tuple[int, ...], value: float
) -> None:
    gs = scene(3)
    edited = getattr(gs, field).clone()
    edited[index] = value
    with pytest.raises(ValueError, match=rf"^{field}: 1 of "):
        voxelize(gs.replace(**{field: edited}), GRID, **config)


def test_messages_hint_at_logits_and_log_scales() -> None:
    gs = scene(4)
    with pytest.raises(ValueError, match=r'opacity_space="logit"'):
        voxelize(gs.replace(opacities=torch.logit(gs.opacities) + 10), GRID)
    with pytest.raises(ValueError, match=r"^opacities: 1 of 5 values lie outside \[0, 1\]") as info:
        voxelize(gs.replace(opacities=gs.opacities.index_fill(1, torch.tensor([2]), 1.5)), GRID)
    assert "logit" not in str(info.value)  # only when every value is outside
    with pytest.raises(ValueError, match=r'^scales: 15 of 15 .*scale_space="log"'):
        voxelize(gs.replace(scales=-gs.scales), GRID)


# ---------------------------------------------------------------------------------------
# extreme but finite parameters never make a Gaussian vanish
# ---------------------------------------------------------------------------------------

EXTREME_SCALES = [1e-30, 1e-12, 1e-6, 1e-3, 0.3, 1e3, 1e6, 1e12, 1e30]
CUTOFFS = [0.5, 3.0, 1e3, 1e30, 1e300, math.inf]


@pytest.mark.slow
@settings(max_examples=60)
@given(
    float_dtypes,
    configs,
    st.tuples(*(st.sampled_from(EXTREME_SCALES) for _ in range(3))),
    st.sampled_from(CUTOFFS),
    st.floats(1e-30, 1.0),
    st.tuples(st.integers(0, 15), st.integers(0, 15), st.integers(0, 7)),
    st.integers(0, 2**31 - 1),
)
def test_a_gaussian_on_a_voxel_centre_keeps_its_opacity_there_whatever_its_size(
    dtype: torch.dtype,
    config: dict[str, Any],
    scales: tuple[float, float, float],
    cutoff_sigma: float,
    opacity: float,
    index: tuple[int, int, int],
    seed: int,
) -> None:
    quat = torch.randn(4, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    gs = requiring_grad(
        one_gaussian(voxel_centre(index, dtype), quat, torch.tensor(scales), opacity, dtype=dtype)
    )
    out = voxelize(gs, GRID, cutoff_sigma=cutoff_sigma, **config)
    assert_valid_output(out.density, out.features)
    expected = torch.tensor(opacity, dtype=dtype)
    torch.testing.assert_close(out.density[(0, *index)], expected, rtol=1e-6, atol=0)
    assert float(out.density[(0, *index)].detach()) > 0
    assert_finite_gradients(out.density.sum() + out.features.sum(), gs)


@settings(max_examples=40)
@given(
    float_dtypes,
    configs,
    st.tuples(*(st.sampled_from([0.05, 0.5, 1e3, 1e12, 1e30]) for _ in range(3))),
    st.sampled_from([5.0, 1e3, 1e30, math.inf]),
    st.floats(1e-6, 1.0),
    st.integers(0, 2**31 - 1),
)
def test_an_in_grid_gaussian_never_vanishes_from_its_own_voxel(
    dtype: torch.dtype,
    config: dict[str, Any],
    scales: tuple[float, float, float],
    cutoff_sigma: float,
    opacity: float,
    seed: int,
) -> None:
    # any mean in the grid; scales >= 0.05 m put the own voxel centre within 4.4 sigma
    g = torch.Generator().manual_seed(seed)
    lower, upper = torch.tensor(GRID.lower), torch.tensor(GRID.upper)
    mean = lower + torch.rand(3, generator=g, dtype=torch.float64) * (upper - lower) * 0.999
    quat = torch.randn(4, generator=g, dtype=torch.float64)
    gs = one_gaussian(mean, quat, torch.tensor(scales), opacity, dtype=dtype)
    out = voxelize(gs, GRID, cutoff_sigma=cutoff_sigma, **config)
    assert_valid_output(out.density, out.features)
    position = (gs.means[0, 0].double() - lower) / torch.tensor(GRID.voxel_size)
    own = position.floor().long().tolist()
    assert float(out.density[(0, *own)]) > 0


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_infinite_cutoff_is_the_whole_grid(config: dict[str, Any], dtype: torch.dtype) -> None:
    gs = scene(5, b=2, n=4, dtype=dtype)
    whole = voxelize(gs, GRID, cutoff_sigma=math.inf, **config)
    assert_valid_output(whole.density, whole.features)
    if config.get("neighborhood") == "cube":  # cutoff_sigma does not apply to the cube
        same = voxelize(gs, GRID, **config)
        torch.testing.assert_close(whole.density, same.density, atol=0, rtol=0)
        return
    torch.testing.assert_close(
        whole.density, voxelize(gs, GRID, cutoff_sigma=1e300, **config).density, atol=0, rtol=0
    )
    if dtype == torch.float64:  # untruncated: the dense evaluation of every pair
        density, features = dense_voxelize(gs, GRID, mode=config["mode"])
        torch.testing.assert_close(whole.density, density, atol=1e-9, rtol=0)
        if config["mode"] == "additive":
            torch.testing.assert_close(whole.features, features, atol=1e-9, rtol=0)


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cutoff_sigma", [3.0, math.inf])
def test_far_tiny_and_huge_gaussians_do_not_overflow(
    config: dict[str, Any], dtype: torch.dtype, cutoff_sigma: float
) -> None:
    far = 1e30 if dtype == torch.float32 else 1e250
    gs = scene(6, n=4, dtype=dtype)
    means, scales = gs.means.clone(), gs.scales.clone()
    means[0, 0] = far  # beyond int64 in voxel units
    means[0, 1] = -far
    scales[0, 1] = 1e-30  # far and tiny: |d| / s overflows
    scales[0, 2] = far  # a Gaussian bigger than the grid, centred in it: g ~ 1 everywhere
    gs = requiring_grad(gs.replace(means=means, scales=scales))
    out = voxelize(gs, GRID, cutoff_sigma=cutoff_sigma, **config)
    assert_valid_output(out.density, out.features)
    if config.get("neighborhood") != "cube":  # the cube is fixed-size: it cannot see it all
        assert bool((out.density > 0).all())
    assert_finite_gradients(out.density.sum() + out.features.sum(), gs)


@settings(max_examples=20)
@given(st.integers(0, 2**31 - 1), configs)
def test_float32_needles_stay_bounded(seed: int, config: dict[str, Any]) -> None:
    # A 1e-6 m thin axis makes d^T P d cancel in float32 (the cube's precision entries
    # are ~1e12): rounding below zero must not turn into g > 1 or an infinite exp.
    g = torch.Generator().manual_seed(seed)
    n = 8
    gs = GaussianSet(
        means=torch.rand(1, n, 3, generator=g) * 2 - 1,
        quats=torch.randn(1, n, 4, generator=g),
        scales=torch.tensor([1.0, 1.0, 1e-6]).expand(1, n, 3).clone(),
        opacities=torch.full((1, n), 0.5),
        features=torch.ones(1, n, 1),
    )
    out = voxelize(gs, GRID, **config)
    assert_valid_output(out.density, out.features)
    assert bool((out.features <= n).all())  # each g <= 1 (a weighted mean <= 1 too)


def test_tiny_gaussians_do_not_overflow_the_mixture_weights() -> None:
    # four 1e-30 m Gaussians on one voxel centre, large features, float32: their
    # normalised densities (~1e88) are clamped so that the weighted sums stay finite
    index = (5, 9, 3)
    centre = voxel_centre(index, torch.float32)
    gs = GaussianSet(
        means=centre.expand(1, 4, 3).clone(),
        quats=torch.randn(1, 4, 4, generator=torch.Generator().manual_seed(0)),
        scales=torch.full((1, 4, 3), 1e-30),
        opacities=torch.tensor([[0.2, 0.4, 0.6, 0.8]]),
        features=torch.tensor([[[1e12], [2e12], [3e12], [4e12]]]),
    )
    for config in CONFIGS:
        out = voxelize(gs, GRID, **config)
        assert_valid_output(out.density, out.features)
        if config["mode"] == "probabilistic":  # equal kernels: the opacity-weighted mean
            expected = torch.tensor([3e12])
            torch.testing.assert_close(out.features[(0, *index)], expected, rtol=1e-5, atol=0)


@pytest.mark.parametrize("cutoff_sigma", [math.nan, 0.0, -3.0, True])
def test_cutoff_sigma_must_be_positive(cutoff_sigma: Any) -> None:
    with pytest.raises(ValueError, match=r"^cutoff_sigma: expected a positive number"):
        VoxelizerConfig(cutoff_sigma=cutoff_sigma)
    if not isinstance(cutoff_sigma, bool):
        with pytest.raises(ValueError, match=r"^cutoff_sigma"):
            voxelize(scene(0), GRID, cutoff_sigma=cutoff_sigma)


# ---------------------------------------------------------------------------------------
# empty batches
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
@pytest.mark.parametrize("bn", [(0, 0), (0, 3), (2, 0)], ids=["B0N0", "B0N3", "B2N0"])
@pytest.mark.parametrize("channels", [None, 3])
def test_empty_batches_give_empty_grids(
    config: dict[str, Any], bn: tuple[int, int], channels: int | None, dtype: torch.dtype
) -> None:
    b, n = bn
    gs = make_gaussian_set((b,), n, feature_dim=channels, dtype=dtype)
    for out in (voxelize(gs, GRID, **config), GaussianVoxelizer(GRID, **config)(gs)):
        assert out.density.shape == (b, *GRID.shape)
        assert out.features.shape == (b, *GRID.shape, channels or 0)
        assert out.density.dtype == dtype and out.features.dtype == dtype
        assert bool((out.density == 0).all()) and bool((out.features == 0).all())


# ---------------------------------------------------------------------------------------
# memory guard
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
def test_memory_guard_trips_with_a_tiny_limit(config: dict[str, Any]) -> None:
    gs = scene(7)
    before = dego.get_memory_limit()
    with dego.memory_limit(1000), pytest.raises(ValueError, match="memory limit") as info:
        voxelize(gs, GRID, **config)
    assert str(info.value).startswith("voxelize: would need about")
    assert "16 x 16 x 8 voxels" in str(info.value)
    assert dego.get_memory_limit() == before
    with dego.memory_limit(64 * 2**20):  # a realistic limit passes
        voxelize(gs, GRID, **config)


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
def test_memory_guard_trips_before_allocating_a_huge_grid(config: dict[str, Any]) -> None:
    # 4096^3 voxels x 5 channels in float64: ~2.7 TB. Allocating first would fail (or
    # swap) with a RuntimeError; the guard must raise its ValueError at once.
    huge = VoxelGrid((0.0, 0.0, 0.0), (4096.0, 4096.0, 4096.0), 1.0)
    with pytest.raises(ValueError, match="memory limit"):
        voxelize(scene(8, n=2), huge, **config)


# ---------------------------------------------------------------------------------------
# dtypes
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16], ids=["float16", "bfloat16"])
def test_half_inputs_are_computed_in_float32_and_returned_in_their_dtype(
    config: dict[str, Any], half: torch.dtype
) -> None:
    gs32 = scene(9, b=2, n=6, dtype=torch.float32)
    gs = requiring_grad(gs32.to(half))
    out = voxelize(gs, GRID, **config)
    assert out.density.dtype == half and out.features.dtype == half
    # exactly the float32 computation on the half values, rounded once at the end
    reference = voxelize(gs.detach().to(torch.float32), GRID, **config)
    torch.testing.assert_close(out.density, reference.density.to(half), atol=0, rtol=0)
    torch.testing.assert_close(out.features, reference.features.to(half), atol=0, rtol=0)
    # ... and close to the float32 result of the unrounded inputs
    full = voxelize(gs32, GRID, **config)
    tolerance = 2e-2 if half == torch.float16 else 8e-2
    torch.testing.assert_close(out.density.float(), full.density, atol=tolerance, rtol=0)
    # (probabilistic features are a normalised mixture: only where the density is not a
    # mere tail does rounding the inputs move them by a matching amount)
    where = full.density > 0.05 if config["mode"] == "probabilistic" else ...
    scale = float(full.features.abs().max())
    torch.testing.assert_close(
        out.features.float()[where], full.features[where], atol=tolerance * scale, rtol=0
    )
    # gradients flow back through the casts, in the input dtype
    grads = torch.autograd.grad(
        out.density.float().sum() + out.features.float().sum(),
        [gs.means, gs.scales, gs.opacities, gs.features],
    )
    for grad in grads:
        assert grad.dtype == half and bool(torch.isfinite(grad).all())
    assert any(bool((grad != 0).any()) for grad in grads)


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
def test_features_of_another_dtype_raise_type_error(config: dict[str, Any]) -> None:
    gs = scene(10)
    with pytest.raises(TypeError, match=r"^features: dtype torch.float32 differs"):
        voxelize(gs, GRID, features=gs.features.float(), **config)
    with pytest.raises(TypeError, match=r"^features: dtype torch.float16 differs"):
        GaussianVoxelizer(GRID, **config)(gs, gs.features.half())


# ---------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------


def requiring_grad(gs: GaussianSet) -> GaussianSet:
    return gs.map(lambda _, t: t.detach().clone().requires_grad_(True))


def assert_finite_gradients(loss: Tensor, gs: GaussianSet) -> None:
    leaves = [getattr(gs, name) for name in FIELDS]
    for name, grad in zip(
        FIELDS, torch.autograd.grad(loss, leaves, allow_unused=True), strict=True
    ):
        assert grad is None or bool(torch.isfinite(grad).all()), f"{name}: non-finite gradient"
