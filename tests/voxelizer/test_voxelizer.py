"""Gaussian-to-voxel voxelizer: dense-reference agreement, official cube rule, invariants,
closed forms, gradients, labels and errors."""

from __future__ import annotations

import math
from typing import Any

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

import dego
import dego.voxelizer
from dego import GaussianSet, GaussianVoxelizer, VoxelGrid, VoxelOutput, voxelize
from dego.deformation import quaternion_multiply
from tests.helpers.strategies import make_gaussian_set
from tests.reference.voxel import (
    cube_mask,
    dense_voxelize,
    ellipsoid_box_mask,
    gaussian_values,
    official_cube_voxelize,
)

GRID = VoxelGrid((-2.0, -2.0, -1.0), (2.0, 2.0, 1.0), 0.25)  # (16, 16, 8)
WIDE_GRID = VoxelGrid((-3.0, -3.0, -2.0), (3.0, 3.0, 2.0), 0.25)  # (24, 24, 16)
TINY_GRID = VoxelGrid((0.0, 0.0, 0.0), (1.0, 0.75, 0.5), 0.25)  # (4, 3, 2)
BOUNDARY_SLACK = 1e-9  # metres: voxel centres this close to a box edge are not compared
FIELDS = ("means", "quats", "scales", "opacities", "features")

# ---------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------


@st.composite
def scenes(
    draw: st.DrawFn,
    *,
    min_n: int = 0,
    max_n: int = 30,
    extent: float = 2.5,
    scale_range: tuple[float, float] = (0.05, 1.0),
    dtype: torch.dtype = torch.float64,
) -> GaussianSet:
    """(B, N) GaussianSets with B in {1, 2} around ``GRID``, some means outside it."""
    b = draw(st.integers(1, 2))
    n = draw(st.integers(min_n, max_n))
    c = draw(st.integers(1, 4))
    seed = draw(st.integers(0, 2**31 - 1))
    return make_gaussian_set(
        (b,), n, seed=seed, feature_dim=c, extent=extent, scale_range=scale_range, dtype=dtype
    )


def settled(gs: GaussianSet, grid: VoxelGrid, cutoff_sigma: float) -> Tensor:
    """``(B, X, Y, Z)``: voxels no Gaussian's ellipsoid box edge passes close to."""
    outer = ellipsoid_box_mask(cutoff_sigma, BOUNDARY_SLACK)(gs, grid)
    inner = ellipsoid_box_mask(cutoff_sigma, -BOUNDARY_SLACK)(gs, grid)
    return ~(outer & ~inner).any(dim=1)


def assert_close_where(
    actual: Tensor, expected: Tensor, where: Tensor, *, atol: float, rtol: float = 0.0
) -> None:
    torch.testing.assert_close(actual[where], expected[where], atol=atol, rtol=rtol)


def requiring_grad(gs: GaussianSet) -> GaussianSet:
    return gs.map(lambda _, t: t.detach().clone().requires_grad_(True))


def gradients(loss: Tensor, gs: GaussianSet) -> list[Tensor]:
    leaves = [getattr(gs, name) for name in FIELDS]
    if not loss.requires_grad:
        return [torch.zeros_like(t) for t in leaves]
    grads = torch.autograd.grad(loss, leaves, allow_unused=True)
    return [torch.zeros_like(t) if g is None else g for g, t in zip(grads, leaves, strict=True)]


def weighted_sum(density: Tensor, features: Tensor, seed: int = 0) -> Tensor:
    g = torch.Generator().manual_seed(seed)
    wd = torch.rand(density.shape, generator=g, dtype=density.dtype)
    wf = torch.rand(features.shape, generator=g, dtype=features.dtype)
    return (density * wd).sum() + (features * wf).sum()


def single_gaussian(
    mean: tuple[float, float, float],
    *,
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0),
    scales: tuple[float, float, float] = (0.3, 0.3, 0.3),
    opacity: float = 1.0,
    features: tuple[float, ...] | None = (1.0,),
    dtype: torch.dtype = torch.float64,
) -> GaussianSet:
    """A (1, 1) GaussianSet."""

    def t(values: Any) -> Tensor:
        return torch.tensor(values, dtype=dtype).reshape(1, 1, -1)

    return GaussianSet(
        means=t(mean),
        quats=t(quat),
        scales=t(scales),
        opacities=torch.tensor([[opacity]], dtype=dtype),
        features=None if features is None else t(features),
    )


def axis_quat(axis: int, degrees: float) -> Tensor:
    half = math.radians(degrees) / 2
    q = [math.cos(half), 0.0, 0.0, 0.0]
    q[1 + axis] = math.sin(half)
    return torch.tensor(q, dtype=torch.float64)


def overlap(shift: int, size: int) -> tuple[slice, slice]:
    """Source and destination slices of an axis shifted by ``shift`` voxels."""
    src = slice(max(0, -shift), size - max(0, shift))
    dst = slice(max(0, shift), size - max(0, -shift))
    return src, dst


CONFIGS = [
    {"mode": "additive"},
    {"mode": "probabilistic"},
    {"mode": "additive", "neighborhood": "cube", "nbh": 1},
    {"mode": "probabilistic", "neighborhood": "cube", "nbh": 2},
    {"mode": "additive", "cutoff_sigma": 1.5},
]
CONFIG_IDS = ["additive", "probabilistic", "cube1", "prob-cube2", "additive-k1.5"]

# ---------------------------------------------------------------------------------------
# agreement with the dense reference (ellipsoid neighbourhood)
# ---------------------------------------------------------------------------------------


@settings(max_examples=15)
@given(scenes(), st.sampled_from([1.0, 2.0, 3.0]))
def test_ellipsoid_additive_matches_box_masked_dense_reference(
    gs: GaussianSet, cutoff_sigma: float
) -> None:
    gs = requiring_grad(gs)
    out = voxelize(gs, GRID, cutoff_sigma=cutoff_sigma)
    density, features = dense_voxelize(
        gs, GRID, mode="additive", mask_fn=ellipsoid_box_mask(cutoff_sigma)
    )
    b = gs.means.shape[0]
    assert out.density.shape == (b, *GRID.shape)
    assert out.features.shape == (b, *GRID.shape, gs.features.shape[-1])
    ok = settled(gs, GRID, cutoff_sigma)
    assert_close_where(out.density, density, ok, atol=1e-6)
    assert_close_where(out.features, features, ok, atol=1e-6)
    if bool(ok.all()):  # no box edge near a voxel centre: gradients agree too
        actual = gradients(weighted_sum(out.density, out.features), gs)
        expected = gradients(weighted_sum(density, features), gs)
        for name, a, e in zip(FIELDS, actual, expected, strict=True):
            torch.testing.assert_close(a, e, atol=1e-6, rtol=1e-6, msg=name)


@settings(max_examples=15)
@given(scenes(), st.sampled_from([1.0, 2.0, 3.0]))
def test_ellipsoid_truncation_error_is_bounded_by_the_cutoff(
    gs: GaussianSet, cutoff_sigma: float
) -> None:
    out = voxelize(gs, GRID, cutoff_sigma=cutoff_sigma)
    density, features = dense_voxelize(gs, GRID, mode="additive")
    # Every voxel left out of a Gaussian's box lies beyond Mahalanobis distance k.
    tail = math.exp(-0.5 * cutoff_sigma**2)
    density_bound = tail * gs.opacities.sum(dim=1)[:, None, None, None] + 1e-9
    feature_bound = tail * gs.features.abs().sum(dim=1)[:, None, None, None, :] + 1e-9
    assert bool(((out.density - density).abs() <= density_bound).all())
    assert bool(((out.features - features).abs() <= feature_bound).all())
    # ... and the truncation only ever removes (non-negative) density.
    assert bool((out.density <= density + 1e-9).all())


@settings(max_examples=10)
@given(scenes(), st.sampled_from(["additive", "probabilistic"]))
def test_large_cutoff_equals_the_untruncated_dense_reference(gs: GaussianSet, mode: str) -> None:
    out = voxelize(gs, GRID, mode=mode, cutoff_sigma=8.0)
    density, features = dense_voxelize(gs, GRID, mode=mode)
    torch.testing.assert_close(out.density, density, atol=1e-6, rtol=0)
    if mode == "additive":
        torch.testing.assert_close(out.features, features, atol=1e-6, rtol=0)


@settings(max_examples=15)
@given(scenes(), st.sampled_from([2.0, 3.0]))
def test_ellipsoid_probabilistic_matches_box_masked_dense_reference(
    gs: GaussianSet, cutoff_sigma: float
) -> None:
    out = voxelize(gs, GRID, mode="probabilistic", cutoff_sigma=cutoff_sigma)
    mask_fn = ellipsoid_box_mask(cutoff_sigma)
    density, features = dense_voxelize(gs, GRID, mode="probabilistic", mask_fn=mask_fn)
    ok = settled(gs, GRID, cutoff_sigma)
    assert bool(((out.density >= 0) & (out.density <= 1)).all())
    assert_close_where(out.density, density, ok, atol=1e-6)
    # mixture weights, to know where the feature average is well defined
    mask = mask_fn(gs, GRID)
    normaliser = (2 * math.pi) ** -1.5 * torch.linalg.det(gs.precisions()).sqrt()
    p = gs.opacities * normaliser
    total = (p[:, :, None, None, None] * gaussian_values(gs, GRID) * mask).sum(dim=1)
    assert_close_where(out.features, features, ok & (total > 1e-12), atol=1e-6, rtol=1e-6)
    # voxels no Gaussian reaches are empty
    unreached = ok & ~mask.any(dim=1)
    assert bool((out.density[unreached] == 0).all())
    assert bool((out.features[unreached] == 0).all())


# ---------------------------------------------------------------------------------------
# official fixed-cube neighbourhood
# ---------------------------------------------------------------------------------------


@settings(max_examples=15)
@given(scenes(extent=3.0), st.sampled_from([0, 1, 2]))
def test_cube_matches_the_official_algorithm(gs: GaussianSet, nbh: int) -> None:
    out = voxelize(gs, GRID, neighborhood="cube", nbh=nbh)
    density, features = official_cube_voxelize(gs, GRID, None, nbh)
    torch.testing.assert_close(out.density, density, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(out.features, features, atol=1e-9, rtol=1e-9)
    # the two references agree with each other
    dense = dense_voxelize(gs, GRID, mode="additive", mask_fn=cube_mask(nbh))
    torch.testing.assert_close(dense[0], density, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(dense[1], features, atol=1e-12, rtol=1e-12)


@settings(max_examples=10)
@given(scenes(extent=3.0, max_n=60, dtype=torch.float32), st.sampled_from([1, 2, 3]))
def test_cube_float32_matches_the_official_float32_algorithm(gs: GaussianSet, nbh: int) -> None:
    # Same candidate voxels (the float32 home voxel) as the official float32 code, but our
    # centre-minus-mean offsets and precisions are float64, so the difference is about the
    # official code's own float32 error (tests/voxelizer/test_faults.py pins ours below it):
    # at most 2.4e-6 / 3.8e-6 (density / features) over 300 draws of this strategy.
    out = voxelize(gs, GRID, neighborhood="cube", nbh=nbh)
    density, features = official_cube_voxelize(gs, GRID, None, nbh)
    torch.testing.assert_close(out.density, density, atol=1e-5, rtol=0)
    scale = max(1.0, float(features.abs().max()))
    torch.testing.assert_close(out.features, features, atol=1e-5 * scale, rtol=0)


@pytest.mark.parametrize("mode", ["additive", "probabilistic"])
def test_cube_values_do_not_depend_on_grad_mode(mode: str) -> None:
    gs = make_gaussian_set((2,), 40, seed=3, feature_dim=3, extent=2.5, dtype=torch.float32)
    with torch.no_grad():
        plain = voxelize(gs, GRID, mode=mode, neighborhood="cube", nbh=2)
    tracked = voxelize(requiring_grad(gs), GRID, mode=mode, neighborhood="cube", nbh=2)
    assert tracked.density.requires_grad
    assert torch.equal(tracked.density.detach(), plain.density)
    assert torch.equal(tracked.features.detach(), plain.features)


@settings(max_examples=10)
@given(scenes(extent=3.0), st.sampled_from([0, 1, 2]))
def test_cube_probabilistic_matches_cube_masked_dense_reference(gs: GaussianSet, nbh: int) -> None:
    out = voxelize(gs, GRID, mode="probabilistic", neighborhood="cube", nbh=nbh)
    mask_fn = cube_mask(nbh)
    density, features = dense_voxelize(gs, GRID, mode="probabilistic", mask_fn=mask_fn)
    torch.testing.assert_close(out.density, density, atol=1e-6, rtol=0)
    normaliser = (2 * math.pi) ** -1.5 * torch.linalg.det(gs.precisions()).sqrt()
    p = (gs.opacities * normaliser)[:, :, None, None, None]
    total = (p * gaussian_values(gs, GRID) * mask_fn(gs, GRID)).sum(dim=1)
    # Every pair of the cube counts, however small its g: the mixture is normalised, so a
    # tiny but sharply peaked Gaussian can dominate a voxel's weighted mean.
    assert_close_where(out.features, features, total > 1e-12, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize(
    "neighborhood",
    [{"neighborhood": "cube", "nbh": 2}, {"neighborhood": "ellipsoid", "cutoff_sigma": 8.0}],
    ids=["cube2", "ellipsoid-k8"],
)
def test_probabilistic_features_of_one_gaussian_are_its_features_wherever_it_reaches(
    neighborhood: dict[str, Any],
) -> None:
    # p = o N(x) > 0 at every reached voxel, however small g is (a 2-voxel diagonal step is
    # Mahalanobis distance 8.7 here: g ~ 4e-17, p ~ 5e-15, far above the 1e-30 floor).
    gs = single_gaussian(
        (0.125, 0.125, 0.125), scales=(0.1, 0.1, 0.1), opacity=0.9, features=(2.0, -3.0)
    )
    out = voxelize(gs, GRID, mode="probabilistic", **neighborhood)
    reached = cube_mask(2)(gs, GRID)[0, 0]
    expected = torch.tensor([2.0, -3.0], dtype=torch.float64).expand(int(reached.sum()), 2)
    torch.testing.assert_close(out.features[0][reached], expected, atol=1e-9, rtol=1e-9)


@pytest.mark.parametrize("nbh", [0, 1, 2])
def test_cube_of_a_gaussian_outside_the_grid_reaches_only_its_in_grid_part(nbh: int) -> None:
    # Home voxel (-1, 5, 3): one voxel beyond the low-x face of GRID.
    gs = single_gaussian((-2.1, -0.6, -0.2), scales=(0.5, 0.5, 0.5))
    out = voxelize(gs, GRID, neighborhood="cube", nbh=nbh)
    reached = out.density[0] > 0
    expected = torch.zeros(GRID.shape, dtype=torch.bool)
    expected[: max(0, nbh), 5 - nbh : 6 + nbh, 3 - nbh : 4 + nbh] = True
    assert torch.equal(reached, expected)
    density, _ = official_cube_voxelize(gs, GRID, None, nbh)
    torch.testing.assert_close(out.density, density, atol=1e-12, rtol=0)


def test_cube_home_voxel_uses_floor_of_the_mean() -> None:
    # Mean just below the upper face of voxel 7 on x: floor gives 7, not round's 8.
    gs = single_gaussian((-0.001, 0.1, 0.1), scales=(5.0, 5.0, 5.0))
    out = voxelize(gs, GRID, neighborhood="cube", nbh=0)
    nonzero = out.density[0].nonzero().tolist()
    assert nonzero == [[7, 8, 4]]


# ---------------------------------------------------------------------------------------
# invariants
# ---------------------------------------------------------------------------------------


@settings(max_examples=15)
@given(scenes(min_n=1), st.sampled_from(range(len(CONFIGS))), st.integers(0, 2**31 - 1))
def test_permuting_gaussians_changes_nothing(gs: GaussianSet, which: int, seed: int) -> None:
    config = CONFIGS[which]
    perm = torch.randperm(gs.num_gaussians, generator=torch.Generator().manual_seed(seed))
    permuted = gs.map(lambda _, t: t[:, perm])
    a, b = voxelize(gs, GRID, **config), voxelize(permuted, GRID, **config)
    torch.testing.assert_close(a.density, b.density, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(a.features, b.features, atol=1e-10, rtol=1e-10)


@settings(max_examples=15)
@given(
    scenes(min_n=1, extent=3.5),
    st.sampled_from(range(len(CONFIGS))),
    st.tuples(st.integers(-3, 3), st.integers(-3, 3), st.integers(-3, 3)),
)
def test_whole_voxel_translation_shifts_the_output(
    gs: GaussianSet, which: int, shift: tuple[int, int, int]
) -> None:
    config = CONFIGS[which]
    offset = torch.tensor(shift, dtype=gs.dtype) * torch.tensor(WIDE_GRID.voxel_size)
    moved = gs.replace(means=gs.means + offset)
    a, b = voxelize(gs, WIDE_GRID, **config), voxelize(moved, WIDE_GRID, **config)
    (sx, dx), (sy, dy), (sz, dz) = (
        overlap(s, n) for s, n in zip(shift, WIDE_GRID.shape, strict=True)
    )
    torch.testing.assert_close(
        b.density[:, dx, dy, dz], a.density[:, sx, sy, sz], atol=1e-9, rtol=1e-9
    )
    torch.testing.assert_close(
        b.features[:, dx, dy, dz], a.features[:, sx, sy, sz], atol=1e-8, rtol=1e-8
    )


@pytest.mark.slow
@settings(max_examples=10)
@given(scenes(), st.sampled_from(range(len(CONFIGS))))
def test_chunk_size_does_not_change_the_result(gs: GaussianSet, which: int) -> None:
    config = CONFIGS[which]
    reference = voxelize(gs, GRID, **config)
    for chunk_size in (1, 7, 500, 10**9):
        out = voxelize(gs, GRID, chunk_size=chunk_size, **config)
        torch.testing.assert_close(out.density, reference.density, atol=1e-12, rtol=0)
        torch.testing.assert_close(out.features, reference.features, atol=1e-12, rtol=0)


@settings(max_examples=10)
@given(
    scenes(), st.integers(1, 10), st.integers(0, 2**31 - 1), st.sampled_from(["ellipsoid", "cube"])
)
def test_zero_opacity_gaussians_change_neither_density_nor_probabilistic_features(
    gs: GaussianSet, extra: int, seed: int, neighborhood: str
) -> None:
    ghosts = make_gaussian_set(
        (gs.means.shape[0],), extra, seed=seed, feature_dim=gs.features.shape[-1], extent=2.5,
        scale_range=(0.05, 1.0),
    )  # fmt: skip
    ghosts = ghosts.replace(opacities=torch.zeros_like(ghosts.opacities))
    both = GaussianSet.cat([ghosts, gs])
    nbh = 1 if neighborhood == "cube" else None
    for mode in ("additive", "probabilistic"):
        a = voxelize(gs, GRID, mode=mode, neighborhood=neighborhood, nbh=nbh)
        b = voxelize(both, GRID, mode=mode, neighborhood=neighborhood, nbh=nbh)
        torch.testing.assert_close(b.density, a.density, atol=1e-12, rtol=0)
        if mode == "probabilistic":
            torch.testing.assert_close(b.features, a.features, atol=1e-12, rtol=1e-12)


@settings(max_examples=10)
@given(scenes(), scenes(min_n=1), st.sampled_from(["ellipsoid", "cube"]))
def test_adding_gaussians_never_lowers_probabilistic_density(
    gs: GaussianSet, extra: GaussianSet, neighborhood: str
) -> None:
    b = gs.means.shape[0]
    extra = extra.map(lambda _, t: t[:1].expand(b, *t.shape[1:]))
    extra = extra.replace(
        features=torch.zeros(b, extra.num_gaussians, gs.features.shape[-1], dtype=gs.dtype)
    )
    nbh = 2 if neighborhood == "cube" else None
    a = voxelize(gs, GRID, mode="probabilistic", neighborhood=neighborhood, nbh=nbh)
    both = voxelize(
        GaussianSet.cat([gs, extra]), GRID, mode="probabilistic", neighborhood=neighborhood, nbh=nbh
    )
    assert bool((both.density >= a.density - 1e-12).all())
    assert bool((both.density <= 1).all())


# ---------------------------------------------------------------------------------------
# closed forms
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["additive", "probabilistic"])
@pytest.mark.parametrize("neighborhood", ["ellipsoid", "cube"])
@pytest.mark.parametrize("opacity", [0.0, 0.3, 0.8, 1.0])
def test_single_gaussian_at_a_voxel_centre_gives_its_opacity_there(
    mode: str, neighborhood: str, opacity: float
) -> None:
    # centre of voxel (9, 6, 5) of GRID; a rotated anisotropic Gaussian
    quat = tuple(quaternion_multiply(axis_quat(2, 30.0), axis_quat(0, 70.0)).tolist())
    gs = single_gaussian(
        (0.375, -0.375, 0.375), quat=quat, scales=(0.2, 0.5, 0.1), opacity=opacity,
        features=(0.5, -2.0, 3.0),
    )  # fmt: skip
    nbh = 1 if neighborhood == "cube" else None
    out = voxelize(gs, GRID, mode=mode, neighborhood=neighborhood, nbh=nbh)
    torch.testing.assert_close(
        out.density[0, 9, 6, 5], torch.tensor(opacity, dtype=torch.float64), atol=1e-12, rtol=0
    )
    if mode == "additive" or opacity > 0:
        # additive: g = 1 times f; probabilistic: a single Gaussian's weighted mean is f
        torch.testing.assert_close(
            out.features[0, 9, 6, 5], gs.features[0, 0], atol=1e-12, rtol=1e-12
        )
    assert bool((out.density <= opacity + 1e-12).all())


@settings(max_examples=10)
@given(
    scenes(min_n=1),
    st.integers(0, 3),
    st.integers(0, 5),
    st.floats(0.01, 0.9),
    st.sampled_from(["additive", "probabilistic"]),
)
def test_one_class_features_label_every_occupied_voxel_with_that_class(
    gs: GaussianSet, cls_seed: int, label_offset: int, threshold: float, mode: str
) -> None:
    b, n, c = gs.features.shape
    cls = cls_seed % c
    one_hot = torch.nn.functional.one_hot(torch.full((b, n), cls), c).to(gs.dtype)
    out = voxelize(gs.replace(features=one_hot), GRID, mode=mode)
    labels = out.labels(threshold=threshold, free_label=99, label_offset=label_offset)
    assert labels.dtype == torch.long and labels.shape == out.density.shape
    occupied = out.density >= threshold
    assert bool((labels[occupied] == cls + label_offset).all())
    assert bool((labels[~occupied] == 99).all())


@pytest.mark.parametrize("cutoff_sigma", [2.0, 3.0])
def test_rotated_needle_reaches_every_voxel_inside_its_cutoff_ellipsoid(
    cutoff_sigma: float,
) -> None:
    grid = VoxelGrid((-2.0, -2.0, -2.0), (2.0, 2.0, 2.0), 0.125)  # (32, 32, 32)
    quat = quaternion_multiply(axis_quat(2, 45.0), axis_quat(0, 45.0))
    gs = single_gaussian(
        (0.03, -0.02, 0.05), quat=tuple(quat.tolist()), scales=(0.05, 0.05, 2.0), opacity=1.0
    )
    out = voxelize(gs, grid, cutoff_sigma=cutoff_sigma)
    g = gaussian_values(gs, grid)[0, 0]
    inside = g > math.exp(-0.5 * cutoff_sigma**2) * (1 + 1e-9)
    assert int(inside.sum()) >= 20  # the needle crosses many voxel centres
    torch.testing.assert_close(out.density[0][inside], g[inside], atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(out.features[0, ..., 0][inside], g[inside], atol=1e-12, rtol=1e-12)
    # nothing outside the axis-aligned box of the ellipsoid
    box = ellipsoid_box_mask(cutoff_sigma, BOUNDARY_SLACK)(gs, grid)[0, 0]
    assert bool((out.density[0][~box] == 0).all())


# ---------------------------------------------------------------------------------------
# gradients
# ---------------------------------------------------------------------------------------


def _tiny_inputs(seed: int) -> tuple[Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(1, 2, 3, generator=g, dtype=torch.float64) * torch.tensor(
        [1.0, 0.75, 0.5], dtype=torch.float64
    )
    quats = torch.randn(1, 2, 4, generator=g, dtype=torch.float64)
    scales = torch.rand(1, 2, 3, generator=g, dtype=torch.float64) * 0.3 + 0.2
    opacities = torch.rand(1, 2, generator=g, dtype=torch.float64) * 0.7 + 0.2
    features = torch.randn(1, 2, 2, generator=g, dtype=torch.float64)
    return tuple(t.requires_grad_(True) for t in (means, quats, scales, opacities, features))


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["additive", "probabilistic"])
@pytest.mark.parametrize(
    "neighborhood",
    [
        {"neighborhood": "ellipsoid", "cutoff_sigma": 8.0},
        {"neighborhood": "ellipsoid"},
        {"neighborhood": "cube", "nbh": 1},
    ],
    ids=["k8", "k3", "cube1"],
)
def test_gradcheck_float64(mode: str, neighborhood: dict[str, Any]) -> None:
    def fn(*tensors: Tensor) -> tuple[Tensor, Tensor]:
        gs = GaussianSet(*tensors)
        out = voxelize(gs, TINY_GRID, mode=mode, **neighborhood)
        return out.density, out.features

    assert torch.autograd.gradcheck(fn, _tiny_inputs(3), eps=1e-6, atol=1e-5, rtol=1e-4)


@settings(max_examples=10)
@given(scenes(min_n=1, extent=3.0), st.sampled_from(range(len(CONFIGS))))
def test_gradients_are_finite_and_reach_every_field(gs: GaussianSet, which: int) -> None:
    # add a saturating Gaussian: opacity 1 exactly at a voxel centre (o g = 1)
    b = gs.means.shape[0]
    sat = single_gaussian((0.125, 0.125, 0.125), opacity=1.0, features=None)
    sat = sat.map(lambda _, t: t.expand(b, *t.shape[1:]))
    sat = sat.replace(features=torch.ones(b, 1, gs.features.shape[-1], dtype=gs.dtype))
    gs = requiring_grad(GaussianSet.cat([gs, sat]))
    out = voxelize(gs, GRID, **CONFIGS[which])
    loss = weighted_sum(out.density, out.features)
    grads = torch.autograd.grad(loss, [getattr(gs, name) for name in FIELDS])
    for name, grad in zip(FIELDS, grads, strict=True):
        assert grad is not None and bool(torch.isfinite(grad).all()), name
    assert bool(torch.isfinite(out.density).all() and torch.isfinite(out.features).all())


# ---------------------------------------------------------------------------------------
# labels
# ---------------------------------------------------------------------------------------


def _label_output() -> VoxelOutput:
    # one batch, a (1, 2, 4) grid: densities and 3-channel features per voxel
    density = torch.tensor([[[[0.0, 0.02, 0.1, 0.5], [0.9, 0.04, 0.3, 1.0]]]])
    features = torch.tensor(
        [[[
            [[1, 0, 0], [0, 2, 0], [0, 0, 3], [5, 1, 1]],
            [[0, 1, 0], [1, 2, 3], [3, 2, 1], [0, 0, 9]],
        ]]],
        dtype=torch.float32,
    )  # fmt: skip
    return VoxelOutput(density=density, features=features)


def test_labels_defaults_argmax_plus_one_and_free_below_threshold() -> None:
    labels = _label_output().labels()
    expected = torch.tensor([[[[17, 17, 3, 1], [2, 17, 1, 3]]]])
    assert labels.dtype == torch.long
    assert torch.equal(labels, expected)
    assert int(dego.FREE_LABEL) == 17


def test_labels_options() -> None:
    out = _label_output()
    assert torch.equal(
        out.labels(threshold=0.2, free_label=255, label_offset=0),
        torch.tensor([[[[255, 255, 255, 0], [1, 255, 0, 2]]]]),
    )
    # density below min_density is zeroed first: 0.1 and 0.3 become free at threshold 0.05
    assert torch.equal(
        out.labels(min_density=0.35),
        torch.tensor([[[[17, 17, 17, 1], [2, 17, 17, 3]]]]),
    )
    # min_density below threshold changes nothing
    assert torch.equal(out.labels(min_density=0.01), out.labels())
    # z indices >= max_z_index are free
    assert torch.equal(
        out.labels(max_z_index=2),
        torch.tensor([[[[17, 17, 17, 17], [2, 17, 17, 17]]]]),
    )
    assert torch.equal(out.labels(max_z_index=4), out.labels())
    assert torch.equal(out.labels(max_z_index=0), torch.full((1, 1, 2, 4), 17))
    assert torch.equal(out.labels(threshold=0.0), torch.tensor([[[[1, 2, 3, 1], [2, 3, 1, 3]]]]))


def test_voxel_output_is_frozen() -> None:
    out = _label_output()
    with pytest.raises((AttributeError, TypeError)):
        out.density = out.density * 2  # type: ignore[misc]


# ---------------------------------------------------------------------------------------
# API: module, features argument, empty and outside sets, errors, device, dtype
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
def test_module_equals_functional(config: dict[str, Any]) -> None:
    gs = make_gaussian_set((2,), 12, seed=5, feature_dim=3, extent=2.5, scale_range=(0.05, 1.0))
    module = GaussianVoxelizer(GRID, **config)
    assert isinstance(module, torch.nn.Module)
    expected = voxelize(gs, GRID, **config)
    out = module(gs)
    assert isinstance(out, VoxelOutput)
    torch.testing.assert_close(out.density, expected.density, atol=0, rtol=0)
    torch.testing.assert_close(out.features, expected.features, atol=0, rtol=0)
    other = torch.randn(2, 12, 5, dtype=torch.float64)
    torch.testing.assert_close(
        module(gs, other).features, voxelize(gs, GRID, features=other, **config).features
    )
    assert dego.voxelizer.voxelize is voxelize
    assert dego.voxelizer.GaussianVoxelizer is GaussianVoxelizer


def test_module_default_grid_is_occ3d() -> None:
    module = GaussianVoxelizer()
    assert module.grid == VoxelGrid.occ3d()
    gs = make_gaussian_set((1,), 3, seed=1, feature_dim=2, extent=10.0, scale_range=(0.1, 0.5))
    out = module(gs)
    assert out.density.shape == (1, 200, 200, 16)
    assert out.features.shape == (1, 200, 200, 16, 2)


def test_features_argument_overrides_and_defaults() -> None:
    gs = make_gaussian_set((2,), 6, seed=2, feature_dim=3, extent=2.0, scale_range=(0.1, 1.0))
    other = torch.randn(2, 6, 4, dtype=torch.float64)
    for mode in ("additive", "probabilistic"):
        default = voxelize(gs, GRID, mode=mode)
        _, expected = dense_voxelize(gs, GRID, mode=mode, mask_fn=ellipsoid_box_mask(3.0))
        torch.testing.assert_close(default.features, expected, atol=1e-6, rtol=1e-6)
        given_features = voxelize(gs, GRID, mode=mode, features=other)
        assert given_features.features.shape == (2, *GRID.shape, 4)
        _, expected = dense_voxelize(gs, GRID, other, mode=mode, mask_fn=ellipsoid_box_mask(3.0))
        torch.testing.assert_close(given_features.features, expected, atol=1e-6, rtol=1e-6)
        torch.testing.assert_close(given_features.density, default.density, atol=0, rtol=0)


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
def test_without_features_there_are_zero_channels(config: dict[str, Any]) -> None:
    gs = make_gaussian_set((2,), 6, seed=2, feature_dim=3, extent=2.0, scale_range=(0.1, 1.0))
    bare = voxelize(gs.replace(features=None), GRID, **config)
    assert bare.features.shape == (2, *GRID.shape, 0)
    torch.testing.assert_close(bare.density, voxelize(gs, GRID, **config).density, atol=0, rtol=0)
    module = GaussianVoxelizer(GRID, **config)(gs.replace(features=None))
    assert module.features.shape == (2, *GRID.shape, 0)


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
@pytest.mark.parametrize("channels", [None, 3])
def test_no_gaussians_give_empty_grids(config: dict[str, Any], channels: int | None) -> None:
    gs = make_gaussian_set((2,), 0, feature_dim=channels)
    out = voxelize(gs, GRID, **config)
    c = channels or 0
    assert out.density.shape == (2, *GRID.shape) and out.features.shape == (2, *GRID.shape, c)
    assert bool((out.density == 0).all()) and bool((out.features == 0).all())


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
def test_gaussians_far_outside_or_transparent_give_empty_density(config: dict[str, Any]) -> None:
    far = make_gaussian_set((1,), 5, seed=4, feature_dim=2, scale_range=(0.05, 0.2))
    far = far.replace(means=far.means + torch.tensor([40.0, -30.0, 25.0], dtype=torch.float64))
    out = voxelize(far, GRID, **config)
    assert bool((out.density == 0).all()) and bool((out.features == 0).all())
    clear = make_gaussian_set((1,), 5, seed=4, feature_dim=2, extent=1.0, scale_range=(0.2, 0.5))
    clear = clear.replace(opacities=torch.zeros_like(clear.opacities))
    out = voxelize(clear, GRID, **config)
    assert bool((out.density == 0).all())
    if config["mode"] == "probabilistic":  # p_i = 0 everywhere: features 0
        assert bool((out.features == 0).all())


@pytest.mark.parametrize(
    "kwargs",
    [
        {"features": torch.zeros(2, 5, 3, dtype=torch.float64)},  # wrong N
        {"features": torch.zeros(3, 4, 3, dtype=torch.float64)},  # wrong B
        {"features": torch.zeros(4, 3, dtype=torch.float64)},  # missing batch axis
        {"neighborhood": "cube"},  # cube without nbh
        {"neighborhood": "cube", "nbh": -1},
        {"mode": "max"},
        {"neighborhood": "sphere"},
        {"features": torch.zeros(2, 4, 3, dtype=torch.float32)},  # dtype differs
        {"cutoff_sigma": float("nan")},
        {"cutoff_sigma": 0.0},
        {"cutoff_sigma": -1.0},
        {"chunk_size": 0},
    ],
    ids=[
        "features-n",
        "features-b",
        "features-2d",
        "cube-no-nbh",
        "negative-nbh",
        "bad-mode",
        "bad-neighborhood",
        "features-dtype",
        "cutoff-nan",
        "cutoff-zero",
        "cutoff-negative",
        "chunk-zero",
    ],
)
def test_bad_inputs_raise(kwargs: dict[str, Any]) -> None:
    gs = make_gaussian_set((2,), 4, seed=0, feature_dim=3, extent=1.0, scale_range=(0.1, 0.5))
    with pytest.raises((ValueError, TypeError)):
        voxelize(gs, GRID, **kwargs)
    config = {k: v for k, v in kwargs.items() if k != "features"}
    if "features" in kwargs:
        with pytest.raises((ValueError, TypeError)):
            GaussianVoxelizer(GRID)(gs, kwargs["features"])
    else:
        with pytest.raises((ValueError, TypeError)):
            GaussianVoxelizer(GRID, **config)(gs)


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
def test_runs_on_device(device: torch.device, config: dict[str, Any]) -> None:
    gs = make_gaussian_set((2,), 10, seed=6, feature_dim=3, extent=2.5, scale_range=(0.05, 1.0))
    expected = voxelize(gs, GRID, **config)
    out = voxelize(gs.to(device), GRID, **config)
    assert out.density.device.type == device.type and out.features.device.type == device.type
    torch.testing.assert_close(out.density.cpu(), expected.density, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(out.features.cpu(), expected.features, atol=1e-9, rtol=1e-9)


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
def test_output_keeps_the_input_dtype(dtype: torch.dtype, config: dict[str, Any]) -> None:
    gs64 = make_gaussian_set((1,), 10, seed=7, feature_dim=2, extent=2.0, scale_range=(0.1, 1.0))
    out = voxelize(gs64.to(dtype), GRID, **config)
    assert out.density.dtype == dtype and out.features.dtype == dtype
    reference = voxelize(gs64, GRID, **config)
    torch.testing.assert_close(out.density.double(), reference.density, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(out.features.double(), reference.features, atol=1e-3, rtol=1e-3)
