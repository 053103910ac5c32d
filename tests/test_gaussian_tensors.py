"""GaussianSet.from_tensors / to_tensors: other code bases' conventions in and out."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from jaxtyping import TypeCheckError

from dego import GaussianSet, quaternions_to_rotation_matrices
from tests.helpers.strategies import gaussian_sets, make_gaussian_set, random_quaternions

QUAT_ORDERS = ("wxyz", "xyzw")
ROTATIONS = ("R", "R^T")
SCALE_SPACES = ("std", "variance", "log")
OPACITY_SPACES = ("prob", "logit")
OPACITY_SHAPES = ("N", "N1")
COMBINATIONS = list(
    itertools.product(QUAT_ORDERS, ROTATIONS, SCALE_SPACES, OPACITY_SPACES, OPACITY_SHAPES)
)
DTYPES = {"float32": torch.float32, "float64": torch.float64}

# 48 option combinations x 2 dtypes x 2 directions: a few examples each keeps this file fast
# while the whole grid is still exercised on every run.
FEW = settings(max_examples=max(4, settings().max_examples // 5))


def options(combination: tuple[str, ...]) -> dict[str, str]:
    quat_order, rotation, scale_space, opacity_space, _ = combination
    return {
        "quat_order": quat_order,
        "rotation": rotation,
        "scale_space": scale_space,
        "opacity_space": opacity_space,
    }


def assert_field(actual: torch.Tensor, expected: torch.Tensor, *, exact: bool) -> None:
    assert actual.shape == expected.shape and actual.dtype == expected.dtype
    if exact:
        assert torch.equal(actual, expected)
    else:
        torch.testing.assert_close(actual, expected)


# ---------------------------------------------------------------------------------------
# round trips in every combination of options
# ---------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("dtype", DTYPES.values(), ids=DTYPES.keys())
@pytest.mark.parametrize("combination", COMBINATIONS, ids="-".join)
@FEW
@given(gs=gaussian_sets())
def test_set_to_tensors_and_back_round_trips(
    combination: tuple[str, ...], dtype: torch.dtype, gs: GaussianSet
) -> None:
    gs = gs.to(dtype)
    opts = options(combination)
    tensors = gs.to_tensors(**opts, opacity_shape=combination[-1])
    assert tensors[3].shape == (*gs.batch_shape, gs.num_gaussians) + (
        (1,) if combination[-1] == "N1" else ()
    )
    back = GaussianSet.from_tensors(*tensors, **opts)
    # An unbatched set's tensors look unbatched and come back with a batch axis of 1.
    expected = gs if gs.batch_shape else gs.reshape_batch(1)
    assert back.batch_shape == expected.batch_shape
    assert_field(back.means, expected.means, exact=True)
    assert_field(back.quats, expected.quats, exact=True)  # reorder / conjugation: bitwise
    assert_field(back.scales, expected.scales, exact=combination[2] == "std")
    assert_field(back.opacities, expected.opacities, exact=combination[3] == "prob")
    assert (back.features is None) == (expected.features is None)
    if expected.features is not None:
        assert_field(back.features, expected.features, exact=True)


@st.composite
def foreign_tensors(
    draw: st.DrawFn, combination: tuple[str, ...], dtype: torch.dtype
) -> tuple[torch.Tensor, ...]:
    """Tensors as another code base stores them (options in ``combination``)."""
    batch = draw(st.lists(st.integers(1, 3), min_size=0, max_size=2).map(tuple))
    n = draw(st.integers(0, 6))
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    shape = (*batch, n)
    log_std = torch.rand(*shape, 3, generator=g, dtype=dtype) * 6 - 4  # s in [e^-4, e^2]
    scales = {"std": log_std.exp(), "variance": (2 * log_std).exp(), "log": log_std}
    # Logits in [-4, 4]: sigmoid then logit is well conditioned in float32 there.
    logits = torch.rand(*shape, generator=g, dtype=dtype) * 8 - 4
    opacities = {"prob": torch.rand(*shape, generator=g, dtype=dtype), "logit": logits}
    opacity = opacities[combination[3]]
    if combination[4] == "N1":
        opacity = opacity.unsqueeze(-1)
    features = None
    if draw(st.booleans()):
        features = torch.randn(*shape, draw(st.integers(1, 4)), generator=g, dtype=dtype)
    return (
        torch.randn(*shape, 3, generator=g, dtype=dtype) * 10,
        random_quaternions(shape, g, dtype),
        scales[combination[2]],
        opacity,
        features,
    )


@pytest.mark.slow
@pytest.mark.parametrize("dtype", DTYPES.values(), ids=DTYPES.keys())
@pytest.mark.parametrize("combination", COMBINATIONS, ids="-".join)
@FEW
@given(data=st.data())
def test_tensors_to_set_and_back_round_trips(
    combination: tuple[str, ...], dtype: torch.dtype, data: st.DataObject
) -> None:
    tensors = data.draw(foreign_tensors(combination, dtype))
    opts = options(combination)
    gs = GaussianSet.from_tensors(*tensors, **opts)
    back = gs.to_tensors(**opts, opacity_shape=combination[-1])
    unbatched = tensors[0].ndim == 2
    exact = (True, True, combination[2] == "std", combination[3] == "prob", True)
    for name, original, returned, is_exact in zip(gs.FIELDS, tensors, back, exact, strict=True):
        if original is None:
            assert returned is None, name
            continue
        assert_field(returned, original.unsqueeze(0) if unbatched else original, exact=is_exact)


def test_logit_round_trip_keeps_zero_opacity_padding() -> None:
    """Padding (opacity 0) becomes a -inf logit and comes back as exactly 0."""
    stacked = GaussianSet.stack([make_gaussian_set((), 3), make_gaussian_set((), 1, seed=1)])
    tensors = stacked.to_tensors(opacity_space="logit")
    assert torch.isneginf(tensors[3][1, 1:]).all()
    back = GaussianSet.from_tensors(*tensors, opacity_space="logit")
    assert bool((back.opacities[1, 1:] == 0).all())
    torch.testing.assert_close(back.opacities, stacked.opacities)


# ---------------------------------------------------------------------------------------
# conventions
# ---------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("dtype", DTYPES.values(), ids=DTYPES.keys())
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 6))
def test_gaussianformer_rotation_gives_r_transpose_s2_r(
    dtype: torch.dtype, seed: int, n: int
) -> None:
    """GaussianFormer: Cov = (S R)^T (S R) = R^T diag(s^2) R with R from its quaternion."""
    g = torch.Generator().manual_seed(seed)
    quats = random_quaternions((2, n), g, dtype)
    scales = torch.rand(2, n, 3, generator=g, dtype=dtype) + 0.1
    means, opacities = torch.zeros(2, n, 3, dtype=dtype), torch.ones(2, n, dtype=dtype)
    rot = quaternions_to_rotation_matrices(quats)
    s_mat = torch.diag_embed(scales)
    gaussianformer = (s_mat @ rot).transpose(-1, -2) @ (s_mat @ rot)
    torch.testing.assert_close(gaussianformer, rot.transpose(-1, -2) @ s_mat.square() @ rot)

    gs = GaussianSet.from_tensors(means, quats, scales, opacities, rotation="R^T")
    torch.testing.assert_close(gs.covariances(), gaussianformer)
    torch.testing.assert_close(gs.rotation_matrices(), rot.transpose(-1, -2))
    gsplat = GaussianSet.from_tensors(means, quats, scales, opacities, rotation="R")
    torch.testing.assert_close(gsplat.covariances(), rot @ s_mat.square() @ rot.transpose(-1, -2))


@pytest.mark.parametrize("rotation", ROTATIONS)
def test_xyzw_quarter_turn_about_z(rotation: str, dtype: torch.dtype) -> None:
    half = math.sqrt(0.5)
    xyzw = torch.tensor([[0.0, 0.0, half, half]], dtype=dtype)  # 90 degrees about z
    quarter = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)
    gs = GaussianSet.from_tensors(
        torch.zeros(1, 3, dtype=dtype),
        xyzw,
        torch.tensor([[1.0, 2.0, 3.0]], dtype=dtype),
        torch.ones(1, dtype=dtype),
        quat_order="xyzw",
        rotation=rotation,
    )
    torch.testing.assert_close(gs.quats[0, 0, 0], torch.tensor(half, dtype=dtype))  # w first
    expected = quarter if rotation == "R" else quarter.T
    torch.testing.assert_close(gs.rotation_matrices()[0, 0], expected)
    # Either way the std-dev 1 along x and 2 along y are swapped by the quarter turn.
    torch.testing.assert_close(
        gs.covariances()[0, 0], torch.diag(torch.tensor([4.0, 1.0, 9.0], dtype=dtype))
    )


def test_log_scales_and_logit_opacities_are_decoded(dtype: torch.dtype) -> None:
    gs = make_gaussian_set((2,), 5, dtype=dtype)
    decoded = GaussianSet.from_tensors(
        gs.means,
        gs.quats,
        gs.scales.log(),
        torch.logit(gs.opacities),
        scale_space="log",
        opacity_space="logit",
    )
    torch.testing.assert_close(decoded.scales, gs.scales)
    torch.testing.assert_close(decoded.opacities, gs.opacities)
    variances = GaussianSet.from_tensors(
        gs.means, gs.quats, gs.scales.square(), gs.opacities, scale_space="variance"
    )
    torch.testing.assert_close(variances.scales, gs.scales)
    torch.testing.assert_close(variances.covariances(), gs.covariances())


def test_unbatched_input_gets_a_batch_axis_and_n1_opacities_are_squeezed() -> None:
    gs = make_gaussian_set((), 4, feature_dim=2, dtype=torch.float32)
    out = GaussianSet.from_tensors(
        gs.means, gs.quats, gs.scales, gs.opacities[:, None], gs.features
    )
    assert out.batch_shape == (1,) and out.opacities.shape == (1, 4)
    assert out.features is not None and out.features.shape == (1, 4, 2)
    assert torch.equal(out.opacities[0], gs.opacities)
    batched = make_gaussian_set((2, 3), 4, dtype=torch.float32)
    out = GaussianSet.from_tensors(*batched.to_tensors(opacity_shape="N1"))
    assert out.batch_shape == (2, 3) and out.opacities.shape == (2, 3, 4) and out.features is None
    # N = 1 with (N, 1) opacities: means.ndim decides that the input is unbatched.
    single = GaussianSet.from_tensors(gs.means[:1], gs.quats[:1], gs.scales[:1], torch.ones(1, 1))
    assert single.batch_shape == (1,) and single.opacities.shape == (1, 1)


def test_from_tensors_is_differentiable() -> None:
    gs = make_gaussian_set((2,), 3, seed=5, scale_range=(0.5, 2.0))
    quats = gs.quats.clone().requires_grad_()
    log_scales = gs.scales.log().requires_grad_()
    logits = torch.logit(gs.opacities).requires_grad_()

    def covariance_and_opacity(
        q: torch.Tensor, s: torch.Tensor, o: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        out = GaussianSet.from_tensors(
            gs.means, q, s, o, rotation="R^T", scale_space="log", opacity_space="logit"
        )
        return out.covariances(), out.opacities

    assert torch.autograd.gradcheck(covariance_and_opacity, (quats, log_scales, logits))


# ---------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------


def raw(n: int = 4, batch: tuple[int, ...] = (2,)) -> dict[str, torch.Tensor]:
    return {
        "means": torch.zeros(*batch, n, 3),
        "quats": torch.tensor([1.0, 0, 0, 0]).expand(*batch, n, 4),
        "scales": torch.ones(*batch, n, 3),
        "opacities": torch.full((*batch, n), 0.5),
    }


def test_all_logit_opacities_are_recognised() -> None:
    kwargs = raw()
    kwargs["opacities"] = torch.linspace(-6, -0.5, 8).reshape(2, 4)  # all outside [0, 1]
    with pytest.raises(ValueError, match=r"opacities: .* lie outside \[0, 1\].*logits") as info:
        GaussianSet.from_tensors(**kwargs)
    assert 'from_tensors(..., opacity_space="logit")' in str(info.value)
    with pytest.raises(ValueError, match="looks like logits"):
        GaussianSet(**kwargs).check_values()
    assert GaussianSet.from_tensors(**kwargs, opacity_space="logit").opacities.max() < 0.5


def test_all_negative_scales_are_recognised() -> None:
    kwargs = raw()
    kwargs["scales"] = torch.full((2, 4, 3), -2.5)
    with pytest.raises(ValueError, match=r"scales: .* not positive.*log-scales") as info:
        GaussianSet.from_tensors(**kwargs)
    assert 'from_tensors(..., scale_space="log")' in str(info.value)
    with pytest.raises(ValueError, match="looks like log-scales"):
        GaussianSet(**kwargs).check_values()
    torch.testing.assert_close(
        GaussianSet.from_tensors(**kwargs, scale_space="log").scales,
        torch.full((2, 4, 3), math.exp(-2.5)),
    )


@pytest.mark.parametrize(
    ("field", "values"),
    [
        ("opacities", [1.5, 0.5]),  # partly outside [0, 1]
        ("opacities", [-0.1, 0.0]),  # 0 is a valid opacity
        ("scales", [-1.0, 1.0]),  # partly negative
        ("scales", [-1.0, 0.0]),  # zero is not negative: not all negative
    ],
)
def test_partial_violations_keep_the_plain_message(field: str, values: list[float]) -> None:
    kwargs = raw(n=2, batch=())
    kwargs[field] = kwargs[field].clone()
    kwargs[field][0], kwargs[field][1] = values
    expected = (
        r"opacities: .* outside \[0, 1\]" if field == "opacities" else "scales: .* not positive"
    )
    with pytest.raises(ValueError, match=expected) as info:
        GaussianSet.from_tensors(**kwargs)
    message = str(info.value)
    assert "looks like" not in message and "from_tensors" not in message


def test_negative_variances_are_named() -> None:
    kwargs = raw()
    kwargs["scales"] = kwargs["scales"].clone()
    kwargs["scales"][0, 0, 0] = -1.0
    with pytest.raises(ValueError, match="scales: expected non-negative variances"):
        GaussianSet.from_tensors(**kwargs, scale_space="variance")


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("quat_order", "xyz"),
        ("quat_order", "WXYZ"),
        ("rotation", "RT"),
        ("scale_space", "logs"),
        ("opacity_space", "sigmoid"),
    ],
)
def test_bad_options_are_named(option: str, value: str) -> None:
    with pytest.raises(ValueError, match=rf"{option}: expected one of '.*', got '{value}'"):
        GaussianSet.from_tensors(**raw(), **{option: value})
    with pytest.raises(ValueError, match=rf"{option}: expected one of"):
        make_gaussian_set((2,), 3).to_tensors(**{option: value})


def test_bad_opacity_shape_and_shapes_are_named() -> None:
    gs = make_gaussian_set((2,), 3)
    with pytest.raises(ValueError, match=r"opacity_shape: expected one of 'N', 'N1', got 'N,1'"):
        gs.to_tensors(opacity_shape="N,1")
    kwargs = raw()
    kwargs["opacities"] = torch.ones(2, 4, 2)
    with pytest.raises(TypeCheckError, match="parameter 'opacities'"):
        GaussianSet.from_tensors(**kwargs)
    kwargs = raw()
    kwargs["quats"] = torch.ones(2, 4, 3)
    with pytest.raises(TypeCheckError, match="parameter 'quats'"):
        GaussianSet.from_tensors(**kwargs)
    kwargs = raw()
    kwargs["scales"] = kwargs["scales"].double()
    with pytest.raises(TypeError, match=r"scales: dtype torch\.float64 differs"):
        GaussianSet.from_tensors(**kwargs)
