"""GaussianSet and the quaternion / covariance helpers."""

from __future__ import annotations

import math

import pytest
import torch
import torch.utils._pytree as pytree
from hypothesis import given
from hypothesis import strategies as st

from dego import (
    GaussianSet,
    build_covariances,
    build_precisions,
    normalize_quaternions,
    quaternions_to_rotation_matrices,
)
from tests.helpers.strategies import batch_shapes, gaussian_sets, make_gaussian_set

# ---------------------------------------------------------------------------------------
# analytic cases
# ---------------------------------------------------------------------------------------


def test_quarter_turn_about_z_is_exact() -> None:
    half = math.sqrt(0.5)
    quat = torch.tensor([half, 0.0, 0.0, half], dtype=torch.float64)
    expected = torch.tensor(
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64
    )
    torch.testing.assert_close(quaternions_to_rotation_matrices(quat), expected)
    # A std-dev of 1 along x and 2 along y: rotated 90 degrees, y gets variance 1 and x 4.
    cov = build_covariances(quat, torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    torch.testing.assert_close(cov, torch.diag(torch.tensor([4.0, 1.0, 9.0], dtype=torch.float64)))
    prec = build_precisions(quat, torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    torch.testing.assert_close(
        prec, torch.diag(torch.tensor([1 / 4, 1.0, 1 / 9], dtype=torch.float64))
    )


def test_identity_quaternion_gives_diagonal_covariance(
    dtype: torch.dtype, device: torch.device
) -> None:
    gs = GaussianSet(
        means=torch.zeros(2, 3, dtype=dtype, device=device),
        quats=torch.tensor([[1.0, 0, 0, 0], [5.0, 0, 0, 0]], dtype=dtype, device=device),
        scales=torch.tensor([[0.5, 1.0, 2.0], [3.0, 3.0, 3.0]], dtype=dtype, device=device),
        opacities=torch.ones(2, dtype=dtype, device=device),
    )
    torch.testing.assert_close(gs.covariances(), torch.diag_embed(gs.scales**2))
    torch.testing.assert_close(gs.precisions(), torch.diag_embed(gs.scales**-2))
    assert gs.covariances().dtype == dtype and gs.covariances().device.type == device.type


# ---------------------------------------------------------------------------------------
# properties
# ---------------------------------------------------------------------------------------


@given(gaussian_sets(min_n=1))
def test_rotation_matrices_are_proper_rotations(gs: GaussianSet) -> None:
    rot = gs.rotation_matrices()
    eye = torch.eye(3, dtype=rot.dtype).expand_as(rot)
    torch.testing.assert_close(rot @ rot.transpose(-1, -2), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(rot.shape[:-2], dtype=rot.dtype))


@given(gaussian_sets(min_n=1))
def test_covariance_is_symmetric_positive_definite_with_eigenvalues_s_squared(
    gs: GaussianSet,
) -> None:
    cov = gs.covariances()
    assert cov.shape == (*gs.batch_shape, gs.num_gaussians, 3, 3)
    torch.testing.assert_close(cov, cov.transpose(-1, -2), rtol=0, atol=0)
    eigenvalues = torch.linalg.eigvalsh(cov)
    assert bool((eigenvalues > 0).all())
    expected = (gs.scales**2).sort(dim=-1).values
    torch.testing.assert_close(eigenvalues, expected, rtol=1e-9, atol=1e-9 * float(expected.max()))


@given(gaussian_sets(min_n=1))
def test_covariance_equals_the_one_from_normalised_quaternions(gs: GaussianSet) -> None:
    unit = normalize_quaternions(gs.quats)
    torch.testing.assert_close(
        torch.linalg.vector_norm(unit, dim=-1), torch.ones(unit.shape[:-1], dtype=unit.dtype)
    )
    rot = quaternions_to_rotation_matrices(unit)
    explicit = rot @ torch.diag_embed(gs.scales**2) @ rot.transpose(-1, -2)
    torch.testing.assert_close(gs.covariances(), explicit)
    torch.testing.assert_close(gs.covariances(), build_covariances(unit, gs.scales))


@given(gaussian_sets(min_n=1))
def test_precision_times_covariance_is_identity(gs: GaussianSet) -> None:
    product = gs.precisions() @ gs.covariances()
    # Error grows with the condition number (s_max / s_min)^2 of the covariance.
    condition = (gs.scales.amax(-1) / gs.scales.amin(-1)) ** 2
    eye = torch.eye(3, dtype=product.dtype).expand_as(product)
    error = (product - eye).abs().amax(dim=(-1, -2))
    assert bool((error <= 1e-13 * condition + 1e-13).all()), float((error / condition).max())


@given(
    gaussian_sets(min_n=1),
    st.floats(1e-3, 1e3) | st.floats(-1e3, -1e-3),
)
def test_quaternion_sign_and_scale_do_not_change_the_covariance(
    gs: GaussianSet, factor: float
) -> None:
    cov = gs.covariances()
    torch.testing.assert_close(gs.replace(quats=-gs.quats).covariances(), cov)
    torch.testing.assert_close(gs.replace(quats=factor * gs.quats).covariances(), cov)
    torch.testing.assert_close(gs.replace(quats=factor * gs.quats).precisions(), gs.precisions())


@given(gaussian_sets(min_n=1), st.integers(0, 2**31 - 1))
def test_isotropic_scales_make_rotation_irrelevant(gs: GaussianSet, seed: int) -> None:
    iso = gs.replace(scales=gs.scales[..., :1].expand_as(gs.scales).contiguous())
    other_rotation = make_gaussian_set(tuple(gs.batch_shape), gs.num_gaussians, seed=seed).quats
    expected = torch.diag_embed(iso.scales**2)
    torch.testing.assert_close(iso.covariances(), expected)
    torch.testing.assert_close(iso.replace(quats=other_rotation).covariances(), expected)


@st.composite
def two_compatible_sets(draw: st.DrawFn) -> tuple[GaussianSet, GaussianSet]:
    batch = draw(batch_shapes)
    features = draw(st.none() | st.integers(1, 4))
    a, b = (
        make_gaussian_set(
            batch, draw(st.integers(0, 6)), seed=draw(st.integers(0, 999)), feature_dim=features
        )
        for _ in range(2)
    )
    return a, b


def assert_sets_equal(x: GaussianSet, y: GaussianSet) -> None:
    assert x.feature_dim == y.feature_dim
    for name in GaussianSet.FIELDS:
        if getattr(x, name) is not None:
            torch.testing.assert_close(getattr(x, name), getattr(y, name), rtol=0, atol=0)


@given(two_compatible_sets())
def test_cat_then_select_round_trips(pair: tuple[GaussianSet, GaussianSet]) -> None:
    a, b = pair
    joined = GaussianSet.cat([a, b])
    assert joined.num_gaussians == a.num_gaussians + b.num_gaussians
    assert joined.batch_shape == a.batch_shape
    assert_sets_equal(joined.select(slice(0, a.num_gaussians)), a)
    assert_sets_equal(joined.select(slice(a.num_gaussians, None)), b)
    assert_sets_equal(joined.select(torch.arange(a.num_gaussians, joined.num_gaussians)), b)
    mask = torch.zeros(joined.num_gaussians, dtype=torch.bool)
    mask[: a.num_gaussians] = True
    assert_sets_equal(joined.select(mask), a)


@given(gaussian_sets())
def test_pytree_flatten_unflatten_round_trips(gs: GaussianSet) -> None:
    leaves, spec = pytree.tree_flatten(gs)
    assert len(leaves) == (5 if gs.features is not None else 4)
    assert all(isinstance(leaf, torch.Tensor) for leaf in leaves)
    rebuilt = pytree.tree_unflatten(leaves, spec)
    assert isinstance(rebuilt, GaussianSet)
    assert_sets_equal(rebuilt, gs)
    as_float32 = pytree.tree_map(lambda t: t.float(), {"scene": [gs]})["scene"][0]
    assert isinstance(as_float32, GaussianSet) and as_float32.dtype == torch.float32


@given(gaussian_sets())
def test_flatten_batch_and_reshape_batch(gs: GaussianSet) -> None:
    flat = gs.flatten_batch()
    assert flat.batch_shape == (math.prod(gs.batch_shape),)
    assert flat.num_gaussians == gs.num_gaussians
    assert_sets_equal(flat.reshape_batch(*gs.batch_shape), gs)


@given(gaussian_sets(batch=st.just((2, 3)), min_n=1), st.data())
def test_batched_select_picks_per_item(gs: GaussianSet, data: st.DataObject) -> None:
    k = data.draw(st.integers(0, 4))
    n = gs.num_gaussians
    seed = data.draw(st.integers(0, 999))
    index = torch.randint(-n, n, (2, 3, k), generator=torch.Generator().manual_seed(seed))
    picked = gs.select(index)
    assert picked.batch_shape == (2, 3) and picked.num_gaussians == k
    for i in range(2):
        for j in range(3):
            rows = index[i, j] % n
            torch.testing.assert_close(picked.means[i, j], gs.means[i, j, rows])
            torch.testing.assert_close(picked.opacities[i, j], gs.opacities[i, j, rows])
            if gs.features is not None:
                torch.testing.assert_close(picked.features[i, j], gs.features[i, j, rows])


# ---------------------------------------------------------------------------------------
# select / cat / stack / replace / to details
# ---------------------------------------------------------------------------------------


def test_select_accepts_negative_indices_and_lists() -> None:
    gs = make_gaussian_set((), 5, feature_dim=2)
    assert_sets_equal(gs.select([-1, 0]), gs.select(torch.tensor([4, 0])))
    with pytest.raises(IndexError, match="index: value 5"):
        gs.select([5])
    with pytest.raises(IndexError, match="index"):
        gs.select(torch.tensor([-6]))
    with pytest.raises(ValueError, match="bool mask has length 3"):
        gs.select(torch.tensor([True, False, True]))
    with pytest.raises(TypeError):
        gs.select(2)  # an int would drop the N axis


def test_select_batched_index_must_match_batch() -> None:
    gs = make_gaussian_set((2, 3), 4)
    with pytest.raises(ValueError, match="batched index"):
        gs.select(torch.zeros(3, 2, 1, dtype=torch.long))


def test_stack_pads_with_zero_opacity_gaussians() -> None:
    a, b = (
        make_gaussian_set((), 3, feature_dim=2, seed=1),
        make_gaussian_set((), 5, feature_dim=2, seed=2),
    )
    stacked = GaussianSet.stack([a, b])
    assert stacked.batch_shape == (2,) and stacked.num_gaussians == 5
    first = stacked.select(slice(0, 3))
    torch.testing.assert_close(first.means[0], a.means)
    torch.testing.assert_close(first.features[0], a.features)
    torch.testing.assert_close(stacked.quats[1], b.quats)
    assert bool((stacked.opacities[0, 3:] == 0).all())
    stacked.check_values()
    with pytest.raises(ValueError, match="unbatched"):
        GaussianSet.stack([stacked])


def test_cat_rejects_incompatible_sets() -> None:
    a = make_gaussian_set((2,), 3, feature_dim=2)
    with pytest.raises(ValueError, match=r"sets\[1\]: batch shape"):
        GaussianSet.cat([a, make_gaussian_set((3,), 3, feature_dim=2)])
    with pytest.raises(ValueError, match=r"sets\[1\]: feature_dim"):
        GaussianSet.cat([a, make_gaussian_set((2,), 3)])
    with pytest.raises(ValueError, match=r"sets\[1\]: torch.float32"):
        GaussianSet.cat([a, make_gaussian_set((2,), 3, feature_dim=2, dtype=torch.float32)])
    with pytest.raises(ValueError, match="at least one"):
        GaussianSet.cat([])


def test_replace_to_detach_and_properties() -> None:
    gs = make_gaussian_set((2,), 4, feature_dim=3)
    assert gs.batch_shape == (2,) and gs.num_gaussians == 4 and gs.feature_dim == 3
    assert gs.replace(features=None).feature_dim is None
    with pytest.raises(TypeError, match="unknown field"):
        gs.replace(colors=gs.means)
    with pytest.raises(TypeError, match="means: is required"):
        gs.replace(means=None)
    with pytest.raises(ValueError, match="scales"):
        gs.replace(scales=gs.scales[..., :2])
    half = gs.to(torch.float32)
    assert half.dtype == torch.float32 and half.features.dtype == torch.float32
    with pytest.raises(TypeError, match="means: expected a floating-point tensor"):
        gs.to(torch.int64)
    leaf = gs.means.clone().requires_grad_()
    assert not gs.replace(means=leaf).detach().means.requires_grad
    assert "num_gaussians=4" in repr(gs) and "feature_dim=3" in repr(gs)
    with pytest.raises(dataclass_error()):
        gs.means = gs.means  # frozen


def dataclass_error() -> type[Exception]:
    import dataclasses

    return dataclasses.FrozenInstanceError


# ---------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------


def fields(
    n: int = 4, batch: tuple[int, ...] = (2,), dtype: torch.dtype = torch.float32
) -> dict[str, torch.Tensor]:
    return {
        "means": torch.zeros(*batch, n, 3, dtype=dtype),
        "quats": torch.tensor([1.0, 0, 0, 0], dtype=dtype).expand(*batch, n, 4),
        "scales": torch.ones(*batch, n, 3, dtype=dtype),
        "opacities": torch.ones(*batch, n, dtype=dtype),
        "features": torch.zeros(*batch, n, 8, dtype=dtype),
    }


@pytest.mark.parametrize(
    ("field", "bad_shape", "expected"),
    [
        ("means", (2, 4, 2), r"means: expected shape \(\*batch, N, 3\), got \(2, 4, 2\)"),
        ("means", (4,), r"means: expected shape \(\*batch, N, 3\), got \(4,\)"),
        (
            "quats",
            (2, 4, 3),
            r"quats: expected shape \(\*batch, N, 4\) = \(2, 4, 4\), got \(2, 4, 3\)",
        ),
        (
            "scales",
            (2, 5, 3),
            r"scales: expected shape \(\*batch, N, 3\) = \(2, 4, 3\), got \(2, 5, 3\)",
        ),
        (
            "opacities",
            (2, 4, 1),
            r"opacities: expected shape \(\*batch, N\) = \(2, 4\), got \(2, 4, 1\)",
        ),
        ("opacities", (3, 4), r"opacities: .*got \(3, 4\)"),
        (
            "features",
            (2, 3, 8),
            r"features: expected shape \(\*batch, N, C\) = \(2, 4, C\), got \(2, 3, 8\)",
        ),
        ("features", (2, 4), r"features: .*got \(2, 4\)"),
    ],
)
def test_wrong_shapes_name_the_field(field: str, bad_shape: tuple[int, ...], expected: str) -> None:
    kwargs = fields()
    kwargs[field] = torch.zeros(bad_shape)
    with pytest.raises(ValueError, match=expected):
        GaussianSet(**kwargs)


@pytest.mark.parametrize("field", ["means", "quats", "scales", "opacities", "features"])
def test_integer_and_non_tensor_fields_are_rejected(field: str) -> None:
    kwargs = fields()
    kwargs[field] = kwargs[field].long()
    with pytest.raises(
        TypeError, match=f"{field}: expected a floating-point tensor, got torch.int64"
    ):
        GaussianSet(**kwargs)
    kwargs[field] = kwargs[field].tolist()
    with pytest.raises(TypeError, match=f"{field}: expected a torch.Tensor"):
        GaussianSet(**kwargs)


@pytest.mark.parametrize("field", ["quats", "scales", "opacities", "features"])
def test_mismatched_dtype_and_device_name_the_field(field: str) -> None:
    kwargs = fields()
    kwargs[field] = kwargs[field].double()
    with pytest.raises(TypeError, match=f"{field}: dtype torch.float64 differs"):
        GaussianSet(**kwargs)
    kwargs = fields()
    kwargs[field] = kwargs[field].to("meta")  # a second device that exists on any machine
    with pytest.raises(ValueError, match=f"{field}: on device meta"):
        GaussianSet(**kwargs)


@pytest.mark.parametrize(
    ("field", "value", "expected"),
    [
        ("means", float("nan"), "means: 1 of 24 values are not finite"),
        ("features", float("inf"), "features: 1 of 64 values are not finite"),
        ("scales", 0.0, "scales: 1 of 24 values are not positive"),
        ("scales", -1.0, "scales: 1 of 24 values are not positive"),
        ("opacities", 1.5, r"opacities: 1 of 8 values lie outside \[0, 1\]"),
        ("opacities", -0.1, r"opacities: 1 of 8 values lie outside \[0, 1\]"),
    ],
)
def test_check_values_rejects_invalid_values(field: str, value: float, expected: str) -> None:
    kwargs = {k: v.clone() for k, v in fields().items()}
    kwargs[field].view(-1)[0] = value
    gs = GaussianSet(**kwargs)  # construction checks structure only
    with pytest.raises(ValueError, match=expected):
        gs.check_values()


def test_check_values_rejects_zero_quaternion_and_passes_valid_sets() -> None:
    kwargs = {k: v.clone() for k, v in fields().items()}
    assert GaussianSet(**kwargs).check_values() is not None
    kwargs["quats"][1, 2] = 0.0
    with pytest.raises(ValueError, match="quats: 1 of 8 quaternions have zero norm"):
        GaussianSet(**kwargs).check_values()


# ---------------------------------------------------------------------------------------
# degenerate inputs of the helpers: zero quaternions, huge quaternions, zero scales
# ---------------------------------------------------------------------------------------


def test_zero_quaternion_stays_finite_through_the_eps_clamp(dtype: torch.dtype) -> None:
    # Without the eps clamp these are 0 / 0 = NaN.
    zero = torch.zeros(3, 4, dtype=dtype, requires_grad=True)
    unit = normalize_quaternions(zero)
    assert bool(torch.isfinite(unit).all()) and bool((unit == 0).all())
    rotation = quaternions_to_rotation_matrices(zero)
    torch.testing.assert_close(rotation, torch.eye(3, dtype=dtype).expand(3, 3, 3))
    for out in (unit, rotation):
        (grad,) = torch.autograd.grad(out.sum(), zero)
        assert bool(torch.isfinite(grad).all())
    # below eps the norm is clamped: q / eps, not a unit quaternion
    tiny = torch.tensor([1e-13, 0.0, 0.0, 0.0], dtype=dtype)
    torch.testing.assert_close(normalize_quaternions(tiny), tiny / 1e-12)
    assert bool(torch.isfinite(normalize_quaternions(tiny, eps=0.0)).all())


@given(
    st.integers(0, 2**31 - 1), st.floats(-11, 30), st.sampled_from([torch.float32, torch.float64])
)
def test_quaternions_of_any_magnitude_normalise_to_the_same_rotation(
    seed: int, exponent: float, dtype: torch.dtype
) -> None:
    # taken directly, a float32 |q| overflows to inf past 1.8e19 (and q / |q| gives 0)
    q = torch.randn(5, 4, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    scaled = (q * 10.0**exponent).to(dtype)
    tolerance = {"atol": 1e-6, "rtol": 1e-6} if dtype == torch.float32 else {}
    torch.testing.assert_close(normalize_quaternions(scaled), q.to(dtype), **tolerance)
    torch.testing.assert_close(
        quaternions_to_rotation_matrices(scaled),
        quaternions_to_rotation_matrices(q).to(dtype),
        **tolerance,
    )


@pytest.mark.parametrize("bad", [0.0, -0.5, float("nan")])
def test_precisions_of_a_non_positive_scale_raise_naming_scales(bad: float) -> None:
    gs = make_gaussian_set((2,), 3, seed=4, scale_range=(0.5, 2.0))
    scales = gs.scales.clone()
    scales[1, 2, 0] = bad
    with pytest.raises(ValueError, match=r"^scales: 1 of 18 values are not positive"):
        build_precisions(gs.quats, scales)
    with pytest.raises(ValueError, match=r"^scales: 1 of 18 values are not positive"):
        GaussianSet(gs.means, gs.quats, scales, gs.opacities).precisions()
    # covariances stay defined (s^2) and are not checked
    assert bool(torch.isfinite(build_covariances(gs.quats, scales.nan_to_num(1.0))).all())


@pytest.mark.slow
def test_precisions_compile_without_a_graph_break() -> None:
    gs = make_gaussian_set((2,), 5, dtype=torch.float32, scale_range=(0.5, 2.0))
    compiled = torch.compile(lambda g: g.precisions(), backend="eager", fullgraph=True)
    torch.testing.assert_close(compiled(gs), gs.precisions())


# ---------------------------------------------------------------------------------------
# differentiability and compilation
# ---------------------------------------------------------------------------------------


@pytest.mark.slow
def test_gradcheck_covariances_and_precisions() -> None:
    gs = make_gaussian_set((2,), 3, seed=3, scale_range=(0.5, 2.0))
    quats = gs.quats.clone().requires_grad_()
    scales = gs.scales.clone().requires_grad_()
    assert torch.autograd.gradcheck(build_covariances, (quats, scales))
    assert torch.autograd.gradcheck(build_precisions, (quats, scales))
    assert torch.autograd.gradgradcheck(build_covariances, (quats, scales))

    def through_set(q: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        return gs.replace(quats=q, scales=s).precisions()

    assert torch.autograd.gradcheck(through_set, (quats, scales))


def test_methods_run_on_the_device_and_dtype(device: torch.device, dtype: torch.dtype) -> None:
    gs = make_gaussian_set((2,), 6, feature_dim=3, dtype=dtype, device=device)
    for out in (gs.covariances(), gs.precisions(), gs.rotation_matrices()):
        assert out.device.type == device.type and out.dtype == dtype
    picked = gs.select(torch.tensor([0, 5]))
    assert picked.device.type == device.type and picked.num_gaussians == 2


def test_torch_compile_traces_through_gaussian_sets() -> None:
    gs = make_gaussian_set((2,), 5, feature_dim=3, dtype=torch.float32)

    def weighted_volume(g: GaussianSet) -> GaussianSet:
        det = torch.linalg.det(g.covariances())
        return g.replace(opacities=g.opacities * det / (1 + det))

    compiled = torch.compile(weighted_volume, backend="eager", fullgraph=True)
    out = compiled(gs)
    assert isinstance(out, GaussianSet)
    torch.testing.assert_close(out.opacities, weighted_volume(gs).opacities)


def test_helpers_check_shapes_and_name_the_argument() -> None:
    from jaxtyping import TypeCheckError

    with pytest.raises(TypeCheckError, match="parameter 'scales'"):
        build_covariances(torch.ones(5, 4), torch.ones(4, 3))
    with pytest.raises(TypeCheckError, match="parameter 'quats'"):
        quaternions_to_rotation_matrices(torch.ones(5, 3))
    with pytest.raises(TypeCheckError, match="parameter 'quats'"):
        normalize_quaternions(torch.ones(5, 4, dtype=torch.long))
