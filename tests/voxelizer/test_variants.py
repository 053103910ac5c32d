"""GaussianFormer variants of the voxelizer: the ``scale_cube`` neighbourhood,
``feature_weight``, ``opacity_in_density``, ``empty_value`` / ``empty_threshold``."""

from __future__ import annotations

import math
from typing import Any

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from dego import GaussianSet, GaussianVoxelizer, VoxelGrid, voxelize
from dego.voxelizer import VoxelizerConfig
from tests.helpers.strategies import make_gaussian_set
from tests.reference.voxel import dense_voxelize, gaussian_values, scale_cube_mask

GRID = VoxelGrid((-2.0, -2.0, -1.0), (2.0, 2.0, 1.0), 0.25)  # (16, 16, 8)
ANISOTROPIC_GRID = VoxelGrid((-2.0, -2.0, -1.0), (2.0, 2.0, 1.0), (0.25, 0.5, 0.125))
TINY_GRID = VoxelGrid((0.0, 0.0, 0.0), (1.0, 0.75, 0.5), 0.25)  # (4, 3, 2)
FIELDS = ("means", "quats", "scales", "opacities", "features")


@st.composite
def scenes(draw: st.DrawFn, *, max_n: int = 12, extent: float = 2.8) -> GaussianSet:
    """(B, N) float64 GaussianSets, anisotropic and rotated, some means outside ``GRID``."""
    b = draw(st.integers(1, 2))
    n = draw(st.integers(0, max_n))
    seed = draw(st.integers(0, 2**31 - 1))
    return make_gaussian_set(
        (b,), n, seed=seed, feature_dim=3, extent=extent, scale_range=(0.03, 0.6)
    )


options = st.fixed_dictionaries(
    {
        "feature_weight": st.sampled_from([None, "kernel", "opacity_kernel"]),
        "opacity_in_density": st.booleans(),
        "empty_value": st.sampled_from([0.0, -1.5, 0.25]),
    }
)


def single_gaussian(
    mean: tuple[float, float, float],
    *,
    scales: tuple[float, float, float] = (0.3, 0.3, 0.3),
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0),
    opacity: float = 1.0,
    features: tuple[float, ...] = (1.0,),
    dtype: torch.dtype = torch.float64,
) -> GaussianSet:
    def t(values: Any) -> Tensor:
        return torch.tensor(values, dtype=dtype).reshape(1, 1, -1)

    return GaussianSet(
        t(mean), t(quat), t(scales), torch.tensor([[opacity]], dtype=dtype), t(features)
    )


def mixture_total(gs: GaussianSet, grid: VoxelGrid, mask: Tensor, with_opacity: bool) -> Tensor:
    normaliser = (2 * math.pi) ** -1.5 * torch.linalg.det(gs.precisions()).sqrt()
    p = normaliser * (gs.opacities if with_opacity else 1.0)
    return (p[:, :, None, None, None] * gaussian_values(gs, grid) * mask).sum(dim=1)


# ---------------------------------------------------------------------------------------
# scale_cube against the dense reference restricted to the cube
# ---------------------------------------------------------------------------------------


@settings(max_examples=25)
@given(
    scenes(),
    st.sampled_from([0.5, 1.0, 2.0, 3.0]),
    st.sampled_from(["additive", "probabilistic"]),
    options,
    st.sampled_from([GRID, ANISOTROPIC_GRID]),
)
def test_scale_cube_matches_the_cube_masked_dense_reference(
    gs: GaussianSet, k: float, mode: str, opts: dict[str, Any], grid: VoxelGrid
) -> None:
    out = voxelize(gs, grid, mode=mode, neighborhood="scale_cube", scale_multiplier=k, **opts)
    mask_fn = scale_cube_mask(k)
    density, features = dense_voxelize(gs, grid, mode=mode, mask_fn=mask_fn, **opts)
    torch.testing.assert_close(out.density, density, atol=1e-9, rtol=1e-9)
    if mode == "additive":
        torch.testing.assert_close(out.features, features, atol=1e-9, rtol=1e-9)
        return
    # the normalised mixture is compared where its weight is well above underflow
    with_opacity = opts["feature_weight"] != "kernel"
    total = mixture_total(gs, grid, mask_fn(gs, grid), with_opacity)
    well_defined = (total > 1e-12) | (total == 0)
    torch.testing.assert_close(
        out.features[well_defined], features[well_defined], atol=1e-7, rtol=1e-7
    )


@settings(max_examples=10)
@given(scenes(), st.sampled_from(["additive", "probabilistic"]), options)
def test_scale_cube_chunked_equals_unchunked(
    gs: GaussianSet, mode: str, opts: dict[str, Any]
) -> None:
    kw = {"mode": mode, "neighborhood": "scale_cube", "scale_multiplier": 3, **opts}
    whole = voxelize(gs, GRID, **kw)
    for chunk in (97, 1000):
        part = voxelize(gs, GRID, chunk_size=chunk, **kw)
        torch.testing.assert_close(part.density, whole.density, atol=1e-12, rtol=1e-12)
        torch.testing.assert_close(part.features, whole.features, atol=1e-12, rtol=1e-12)


@pytest.mark.parametrize("mode", ["additive", "probabilistic"])
def test_infinite_multiplier_is_the_whole_grid(mode: str) -> None:
    gs = make_gaussian_set((2,), 6, seed=1, feature_dim=2, extent=3.0, scale_range=(0.05, 0.5))
    out = voxelize(gs, GRID, mode=mode, neighborhood="scale_cube", scale_multiplier=math.inf)
    density, features = dense_voxelize(gs, GRID, mode=mode)
    full = voxelize(gs, GRID, mode=mode, cutoff_sigma=math.inf)
    torch.testing.assert_close(out.density, density, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(out.density, full.density, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(out.features, full.features, atol=1e-12, rtol=1e-12)
    if mode == "additive":
        torch.testing.assert_close(out.features, features, atol=1e-9, rtol=1e-9)


@pytest.mark.parametrize("scale", [1e3, 1e30, 1e300])
def test_huge_scales_or_multiplier_cover_the_whole_grid_without_overflow(scale: float) -> None:
    gs = single_gaussian((0.1, 0.0, 0.0), scales=(scale, 0.5, 0.5))
    out = voxelize(gs, GRID, neighborhood="scale_cube", scale_multiplier=3)
    assert bool((out.density > 0).all())  # every voxel is in the cube
    big_k = voxelize(single_gaussian((0.1, 0, 0)), GRID, neighborhood="scale_cube",
                     scale_multiplier=1e300)  # fmt: skip
    assert bool((big_k.density > 0).all())


def test_cube_radius_and_support() -> None:
    # s = 0.3 m, k = 3, 0.25 m voxels: r = ceil(3.6) = 4 voxels around the mean's voxel
    gs = single_gaussian((0.1, -0.6, 0.3), scales=(0.3, 0.1, 0.05))
    out = voxelize(gs, GRID, neighborhood="scale_cube", scale_multiplier=3)
    home = GRID.world_to_index(gs.means[0, 0])
    reached = (out.density[0] > 0).nonzero()
    assert torch.equal(reached.min(0).values, (home - 4).clamp_min(0))
    assert torch.equal(reached.max(0).values, torch.minimum(home + 4, torch.tensor([15, 15, 7])))
    # radius at least one voxel: k s / v = 0.2 -> r = 1, though the kernel is still
    # 1.9e-22 (> 0) two voxels away
    small = voxelize(
        single_gaussian((0.125, 0.125, 0.125), scales=(0.05,) * 3),
        GRID,
        neighborhood="scale_cube",
        scale_multiplier=1,
    )
    reached = (small.density[0] > 0).nonzero()
    assert (reached.max(0).values - reached.min(0).values).tolist() == [2, 2, 2]


def test_anisotropic_voxels_use_each_axis_size() -> None:
    # voxel sizes (0.25, 0.5, 0.125), s = 0.3, k = 1: r = (ceil(1.2), ceil(0.6), ceil(2.4))
    gs = single_gaussian((0.1, 0.1, 0.1), scales=(0.3, 0.3, 0.3))
    out = voxelize(gs, ANISOTROPIC_GRID, neighborhood="scale_cube", scale_multiplier=1)
    reached = (out.density[0] > 0).nonzero()
    extent = reached.max(0).values - reached.min(0).values + 1
    assert extent.tolist() == [2 * 2 + 1, 2 * 1 + 1, 2 * 3 + 1]


def test_means_outside_the_grid_give_partial_coverage() -> None:
    # mean 0.1 m below the grid's x face: its cube (r = 4) still reaches x index 0..3
    gs = single_gaussian((-2.1, 0.0, 0.0), scales=(0.3, 0.3, 0.3))
    out = voxelize(gs, GRID, neighborhood="scale_cube", scale_multiplier=3)
    density, _ = dense_voxelize(gs, GRID, mask_fn=scale_cube_mask(3))
    torch.testing.assert_close(out.density, density, atol=1e-12, rtol=0)
    reached = (out.density[0] > 0).nonzero()
    assert reached[:, 0].max() == 3  # home x index -1, radius 4
    # far outside: nothing, and no error
    far = voxelize(single_gaussian((1e9, -1e12, 0.0)), GRID, neighborhood="scale_cube",
                   scale_multiplier=3)  # fmt: skip
    assert bool((far.density == 0).all()) and bool((far.features == 0).all())


def test_rotation_does_not_change_the_cube_only_the_kernel() -> None:
    # a needle rotated 45 degrees: the cube is the same, the values follow the rotation
    half = math.radians(45) / 2
    q = (math.cos(half), 0.0, 0.0, math.sin(half))
    gs = single_gaussian((0.125, 0.125, 0.125), scales=(0.6, 0.05, 0.05), quat=q)
    out = voxelize(gs, GRID, neighborhood="scale_cube", scale_multiplier=2)
    density, _ = dense_voxelize(gs, GRID, mask_fn=scale_cube_mask(2))
    torch.testing.assert_close(out.density, density, atol=1e-12, rtol=0)
    home = GRID.world_to_index(gs.means[0, 0])
    i, j, k = home.tolist()
    assert out.density[0, i + 2, j + 2, k] > out.density[0, i + 2, j - 2, k]


# ---------------------------------------------------------------------------------------
# feature_weight, opacity_in_density
# ---------------------------------------------------------------------------------------


def test_feature_weight_additive_multiplies_by_the_opacity() -> None:
    gs = make_gaussian_set((2,), 8, seed=2, feature_dim=3, extent=2.0, scale_range=(0.1, 0.5))
    plain = voxelize(gs, GRID)
    assert torch.equal(voxelize(gs, GRID, feature_weight="kernel").features, plain.features)
    weighted = voxelize(gs, GRID, feature_weight="opacity_kernel")
    scaled = gs.replace(features=gs.features * gs.opacities.unsqueeze(-1))
    torch.testing.assert_close(weighted.features, voxelize(scaled, GRID).features)
    torch.testing.assert_close(weighted.density, plain.density)


def test_feature_weight_probabilistic_default_is_the_opacity_mixture() -> None:
    gs = make_gaussian_set((1,), 8, seed=3, feature_dim=2, extent=2.0, scale_range=(0.1, 0.5))
    default = voxelize(gs, GRID, mode="probabilistic")
    explicit = voxelize(gs, GRID, mode="probabilistic", feature_weight="opacity_kernel")
    assert torch.equal(default.features, explicit.features)
    # "kernel": the equal-weight mixture, i.e. the opacity-weighted one with opacities 1
    equal = voxelize(gs, GRID, mode="probabilistic", feature_weight="kernel")
    ones = voxelize(gs.replace(opacities=torch.ones_like(gs.opacities)), GRID, mode="probabilistic")
    torch.testing.assert_close(equal.features, ones.features)
    torch.testing.assert_close(equal.density, default.density)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_probabilistic_without_opacity_is_exactly_one_at_the_mean(dtype: torch.dtype) -> None:
    centre = (0.125, -0.375, 0.125)  # a voxel centre of GRID
    gs = single_gaussian(centre, opacity=0.3, features=(2.0, -1.0), dtype=dtype)
    kw = {"mode": "probabilistic", "neighborhood": "scale_cube", "scale_multiplier": 4}
    out = voxelize(gs, GRID, opacity_in_density=False, **kw)
    i, j, k = GRID.world_to_index(gs.means[0, 0]).tolist()
    assert out.density[0, i, j, k].item() == 1.0
    with_opacity = voxelize(gs, GRID, **kw)
    torch.testing.assert_close(with_opacity.density[0, i, j, k], torch.tensor(0.3, dtype=dtype))
    # one Gaussian: the mixture is its own features wherever it reaches
    reached = out.density[0] > 0
    expected = torch.tensor([2.0, -1.0], dtype=dtype).expand(int(reached.sum()), 2)
    torch.testing.assert_close(out.features[0][reached], expected)
    # elsewhere 1 - (1 - g): the kernel itself
    g = gaussian_values(gs, GRID)[0, 0] * scale_cube_mask(4)(gs, GRID)[0, 0]
    torch.testing.assert_close(out.density[0], g, atol=1e-6, rtol=1e-5)


def test_additive_without_opacity_is_the_clamped_kernel_sum() -> None:
    gs = make_gaussian_set((1,), 6, seed=4, feature_dim=1, extent=2.0, scale_range=(0.1, 0.5))
    out = voxelize(gs, GRID, opacity_in_density=False, cutoff_sigma=math.inf)
    expected = gaussian_values(gs, GRID).sum(dim=1).clamp(0, 1)
    torch.testing.assert_close(out.density, expected)
    ones = voxelize(
        gs.replace(opacities=torch.ones_like(gs.opacities)), GRID, cutoff_sigma=math.inf
    )
    torch.testing.assert_close(out.density, ones.density)


def test_zero_opacity_counts_only_where_the_options_say_so() -> None:
    gs = single_gaussian((0.125, 0.125, 0.125), opacity=0.0, features=(1.0,))
    neutral = voxelize(gs, GRID, mode="probabilistic")
    assert bool((neutral.density == 0).all()) and bool((neutral.features == 0).all())
    geometry = voxelize(gs, GRID, mode="probabilistic", opacity_in_density=False)
    assert geometry.density.max().item() == 1.0
    assert bool((geometry.features == 0).all())  # zero mixture weight: empty_value
    semantics = voxelize(gs, GRID, mode="probabilistic", feature_weight="kernel")
    assert bool((semantics.density == 0).all()) and semantics.features.max().item() == 1.0


# ---------------------------------------------------------------------------------------
# empty_value / empty_threshold
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["additive", "probabilistic"])
@pytest.mark.parametrize("neighborhood", [{}, {"neighborhood": "cube", "nbh": 1},
                                          {"neighborhood": "scale_cube", "scale_multiplier": 2}])  # fmt: skip
def test_empty_value_fills_every_channel_of_unreached_voxels(
    mode: str, neighborhood: dict[str, Any]
) -> None:
    gs = single_gaussian((0.125, 0.125, 0.125), scales=(0.2, 0.2, 0.2), features=(3.0, -2.0))
    base = voxelize(gs, GRID, mode=mode, **neighborhood)
    out = voxelize(gs, GRID, mode=mode, empty_value=0.5, **neighborhood)
    unreached = base.features.eq(0).all(-1)  # single Gaussian: zero weight <=> zero features
    assert 0 < int(unreached.sum()) < unreached.numel()
    assert bool((out.features[unreached] == 0.5).all())
    assert torch.equal(out.features[~unreached], base.features[~unreached])
    assert torch.equal(out.density, base.density)


def test_empty_threshold_marks_negligible_mixture_weights_empty() -> None:
    # opacity 1e-12: mixture weight <= 1e-9 everywhere, yet the geometry (no opacity) is full
    gs = single_gaussian((0.125, 0.125, 0.125), opacity=1e-12, features=(1.0, 0.0))
    kw = {"mode": "probabilistic", "opacity_in_density": False, "empty_value": 0.5}
    out = voxelize(gs, GRID, empty_threshold=1e-9, **kw)
    reached = out.density > 0
    assert bool((out.features[reached] == 0.5).all())
    default = voxelize(gs, GRID, **kw)  # 1e-30: the weights still count
    torch.testing.assert_close(default.features[reached][:, 0], torch.ones(int(reached.sum()),
                               dtype=torch.float64))  # fmt: skip


def test_empty_value_matches_the_dense_reference() -> None:
    gs = make_gaussian_set((2,), 5, seed=5, feature_dim=2, extent=2.5, scale_range=(0.05, 0.3))
    for mode in ("additive", "probabilistic"):
        kw = {"mode": mode, "empty_value": -3.0, "empty_threshold": 1e-6}
        out = voxelize(gs, GRID, neighborhood="scale_cube", scale_multiplier=3, **kw)
        _, features = dense_voxelize(gs, GRID, mask_fn=scale_cube_mask(3), **kw)
        torch.testing.assert_close(out.features, features, atol=1e-9, rtol=1e-9)


# ---------------------------------------------------------------------------------------
# options, module, gradients, devices
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"neighborhood": "scale_cube"}, "scale_multiplier"),
        ({"neighborhood": "scale_cube", "scale_multiplier": 0}, "scale_multiplier"),
        ({"neighborhood": "scale_cube", "scale_multiplier": -1.0}, "scale_multiplier"),
        ({"neighborhood": "scale_cube", "scale_multiplier": math.nan}, "scale_multiplier"),
        ({"neighborhood": "scale_cube", "scale_multiplier": True}, "scale_multiplier"),
        ({"scale_multiplier": 3.0}, "scale_multiplier"),
        ({"neighborhood": "cube", "nbh": 2, "scale_multiplier": 3.0}, "scale_multiplier"),
        ({"feature_weight": "opacity"}, "feature_weight"),
        ({"opacity_in_density": 1}, "opacity_in_density"),
        ({"empty_value": math.nan}, "empty_value"),
        ({"empty_value": math.inf}, "empty_value"),
        ({"empty_value": "0"}, "empty_value"),
        ({"empty_threshold": -1e-9}, "empty_threshold"),
        ({"empty_threshold": math.inf}, "empty_threshold"),
        ({"neighborhood": "box"}, "neighborhood"),
    ],
)
def test_bad_options_raise_naming_the_argument(kwargs: dict[str, Any], name: str) -> None:
    with pytest.raises(ValueError, match=f"^{name}"):
        VoxelizerConfig(**kwargs)
    with pytest.raises(ValueError, match=f"^{name}"):
        GaussianVoxelizer(GRID, **kwargs)
    gs = single_gaussian((0.0, 0.0, 0.0))
    with pytest.raises((ValueError, TypeError), match=name):  # beartype may answer first
        voxelize(gs, GRID, **kwargs)


def test_module_holds_the_new_options() -> None:
    config = {
        "mode": "probabilistic",
        "neighborhood": "scale_cube",
        "scale_multiplier": 4,
        "opacity_in_density": False,
        "empty_value": 0.25,
        "empty_threshold": 1e-9,
    }
    module = GaussianVoxelizer(GRID, **config)
    assert "scale_multiplier=4" in repr(module)
    gs = make_gaussian_set((1,), 5, seed=6, feature_dim=2, extent=2.0, scale_range=(0.1, 0.4))
    a, b = module(gs), voxelize(gs, GRID, **config)
    assert torch.equal(a.density, b.density) and torch.equal(a.features, b.features)


def _tiny_inputs(seed: int) -> tuple[Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    extent = torch.tensor([1.0, 0.75, 0.5], dtype=torch.float64)
    means = torch.rand(1, 2, 3, generator=g, dtype=torch.float64) * extent
    quats = torch.randn(1, 2, 4, generator=g, dtype=torch.float64)
    scales = torch.rand(1, 2, 3, generator=g, dtype=torch.float64) * 0.2 + 0.1
    opacities = torch.rand(1, 2, generator=g, dtype=torch.float64) * 0.7 + 0.2
    features = torch.randn(1, 2, 2, generator=g, dtype=torch.float64)
    return tuple(t.requires_grad_(True) for t in (means, quats, scales, opacities, features))


@pytest.mark.slow
@pytest.mark.parametrize(
    "options",
    [
        {"mode": "additive", "feature_weight": "opacity_kernel", "empty_value": 0.5},
        {"mode": "additive", "opacity_in_density": False},
        {"mode": "probabilistic", "opacity_in_density": False, "empty_value": 0.1},
        {"mode": "probabilistic", "feature_weight": "kernel"},
    ],
    ids=["gf1", "add-no-opacity", "gf2", "prob-kernel"],
)
def test_gradcheck_float64(options: dict[str, Any]) -> None:
    def fn(*tensors: Tensor) -> tuple[Tensor, Tensor]:
        out = voxelize(
            GaussianSet(*tensors),
            TINY_GRID,
            neighborhood="scale_cube",
            scale_multiplier=1,
            **options,
        )
        return out.density, out.features

    assert torch.autograd.gradcheck(fn, _tiny_inputs(3), eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("mode", ["additive", "probabilistic"])
def test_scale_cube_on_device_and_in_float32(device: torch.device, mode: str) -> None:
    gs = make_gaussian_set((2,), 10, seed=7, feature_dim=3, extent=2.5, scale_range=(0.05, 0.8))
    kw = {"mode": mode, "neighborhood": "scale_cube", "scale_multiplier": 3, "empty_value": 0.2}
    expected = voxelize(gs, GRID, opacity_in_density=False, **kw)
    out = voxelize(gs.to(device), GRID, opacity_in_density=False, **kw)
    assert out.density.device.type == device.type
    torch.testing.assert_close(out.density.cpu(), expected.density, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(out.features.cpu(), expected.features, atol=1e-9, rtol=1e-9)
    single = voxelize(gs.to(device, torch.float32), GRID, opacity_in_density=False, **kw)
    assert single.density.dtype == torch.float32
    torch.testing.assert_close(single.density.cpu().double(), expected.density, atol=1e-5, rtol=0)
