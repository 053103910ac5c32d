"""PositionalEncoding: exact values, layouts, shapes, dtypes and errors."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from jaxtyping import TypeCheckError

from dego import PositionalEncoding, positional_encoding


def test_hand_computed_values_coord_major() -> None:
    x = torch.tensor([0.5, -1.0], dtype=torch.float64)
    out = PositionalEncoding(2)(x)
    a, b = 0.5, -1.0
    expected = [
        a,
        b,
        math.sin(a),
        math.sin(2 * a),
        math.sin(b),
        math.sin(2 * b),
        math.cos(a),
        math.cos(2 * a),
        math.cos(b),
        math.cos(2 * b),
    ]
    torch.testing.assert_close(out, torch.tensor(expected, dtype=torch.float64), rtol=0, atol=1e-15)


def test_hand_computed_values_freq_interleaved_and_no_input() -> None:
    x = torch.tensor([[0.5, -1.0]], dtype=torch.float64)
    out = PositionalEncoding(2, include_input=False, layout="freq_interleaved")(x)
    a, b = 0.5, -1.0
    expected = [
        [
            math.sin(a),
            math.sin(b),
            math.cos(a),
            math.cos(b),
            math.sin(2 * a),
            math.sin(2 * b),
            math.cos(2 * a),
            math.cos(2 * b),
        ]
    ]
    torch.testing.assert_close(out, torch.tensor(expected, dtype=torch.float64), rtol=0, atol=1e-15)


def test_paper_dimensions() -> None:
    assert PositionalEncoding(6).out_dim(3) == 39
    assert PositionalEncoding(4).out_dim(1) == 9
    assert PositionalEncoding(6)(torch.zeros(2, 3)).shape == (2, 39)
    assert PositionalEncoding(4)(torch.zeros(7, 1)).shape == (7, 9)
    assert PositionalEncoding(4, include_input=False).out_dim(1) == 8
    assert PositionalEncoding(0).out_dim(3) == 3


@given(
    st.integers(0, 6),
    st.booleans(),
    st.sampled_from(["coord_major", "freq_interleaved"]),
    st.lists(st.integers(1, 3), max_size=3),
    st.integers(1, 4),
)
def test_shape_matches_out_dim_for_any_leading_shape(
    levels: int, include_input: bool, layout: str, batch: list[int], dim: int
) -> None:
    if levels == 0 and not include_input:
        return
    pe = PositionalEncoding(levels, include_input, layout=layout)
    x = torch.randn(*batch, dim, dtype=torch.float64)
    out = pe(x)
    assert out.shape == (*batch, pe.out_dim(dim))
    if include_input:
        torch.testing.assert_close(out[..., :dim], x, rtol=0, atol=0)


@given(st.integers(1, 6), st.integers(1, 4))
def test_layouts_are_permutations_of_each_other(levels: int, dim: int) -> None:
    x = torch.randn(5, dim, dtype=torch.float64)
    coord = PositionalEncoding(levels, layout="coord_major")(x)
    interleaved = PositionalEncoding(levels, layout="freq_interleaved")(x)
    torch.testing.assert_close(
        coord.sort(dim=-1).values, interleaved.sort(dim=-1).values, rtol=0, atol=0
    )


def test_dtype_device_and_gradients(dtype: torch.dtype, device: torch.device) -> None:
    x = torch.randn(4, 3, dtype=dtype, device=device)
    out = PositionalEncoding(6)(x)
    assert out.dtype == dtype and out.device.type == device.type


def test_gradcheck() -> None:
    x = torch.randn(3, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: positional_encoding(t, 4), (x,))
    assert torch.autograd.gradcheck(
        lambda t: positional_encoding(t, 3, layout="freq_interleaved"), (x,)
    )


def test_is_stateless() -> None:
    assert len(PositionalEncoding(6).state_dict()) == 0
    assert "num_levels=6" in repr(PositionalEncoding(6))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"num_levels": -1}, "num_levels: expected an int >= 0"),
        ({"num_levels": 2.0}, "num_levels: expected an int >= 0"),
        ({"num_levels": True}, "num_levels: expected an int >= 0"),
        ({"num_levels": 0, "include_input": False}, "would encode nothing"),
        ({"num_levels": 2, "layout": "interleaved"}, "layout: expected"),
    ],
)
def test_bad_configuration(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        PositionalEncoding(**kwargs)


def test_bad_input() -> None:
    pe = PositionalEncoding(4)
    with pytest.raises(TypeCheckError, match="parameter 'x'"):
        pe(torch.zeros(3, 2, dtype=torch.long))
    with pytest.raises(TypeCheckError, match="parameter 'x'"):
        pe(torch.tensor(1.0))
    with pytest.raises(ValueError, match="in_dim"):
        pe.out_dim(0)


# -- level limits, dtypes, empty inputs (issue 17) ------------------------------------
_MANTISSA = {torch.float16: 11, torch.bfloat16: 8, torch.float32: 24, torch.float64: 53}


@given(
    st.sampled_from(list(_MANTISSA)),
    st.integers(-20, 40),
    st.floats(0.5, 1.0, exclude_max=True),
    st.integers(0, 70),
    st.sampled_from(["coord_major", "freq_interleaved"]),
)
def test_levels_are_limited_by_the_input_resolution(
    dtype: torch.dtype, exponent: int, mantissa: float, levels: int, layout: str
) -> None:
    # |x| = mantissa 2^exponent, so 2^(L-1) |x| < 2^p exactly when L - 1 <= p - exponent.
    peak = math.ldexp(mantissa, exponent)
    x = torch.tensor([[0.0, -peak], [peak / 3, 0.25]], dtype=torch.float64).to(dtype)
    peak = float(x.abs().max())
    if not math.isfinite(peak) or peak == 0:
        return
    p = _MANTISSA[dtype]
    allowed = p - math.frexp(peak)[1] + 1
    if levels > allowed and levels > 0:
        with pytest.raises(ValueError, match=rf"^num_levels: {levels} levels are too many") as e:
            positional_encoding(x, levels, layout=layout)
        assert f"num_levels <= {max(allowed, 0)}" in str(e.value)
        assert 2.0 ** (levels - 1) * peak >= 2.0**p
    else:
        out = positional_encoding(x, levels, layout=layout)
        assert out.dtype == dtype and torch.isfinite(out).all()
        assert levels == 0 or 2.0 ** (levels - 1) * peak < 2.0**p


@pytest.mark.parametrize(
    ("dtype", "limit"), [(torch.float32, 128), (torch.float16, 128), (torch.float64, 1024)]
)
def test_frequencies_must_be_representable_even_for_zero_inputs(
    dtype: torch.dtype, limit: int
) -> None:
    x = torch.zeros(2, 3, dtype=dtype)
    assert torch.isfinite(positional_encoding(x, limit)).all()
    with pytest.raises(ValueError, match=rf"num_levels: .* at most {limit}"):
        positional_encoding(x, limit + 1)
    with pytest.raises(ValueError, match="num_levels"):
        PositionalEncoding(limit + 1)(x)


def test_paper_levels_work_for_float32_metres_and_frames() -> None:
    # L = 6 for positions within +-50 m, L = 4 for times up to 10^5 frames.
    assert torch.isfinite(positional_encoding(torch.full((4, 3), -50.0), 6)).all()
    assert torch.isfinite(positional_encoding(torch.full((4, 1), 1e5), 4)).all()
    assert positional_encoding(torch.full((1, 3), 50.0), 19).shape == (1, 117)
    with pytest.raises(ValueError, match="num_levels <= 19"):
        positional_encoding(torch.full((1, 3), 50.0), 20)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_inputs_are_rejected(bad: float) -> None:
    x = torch.zeros(3, 2)
    x[1, 0] = bad
    with pytest.raises(ValueError, match="x: 1 of 6 values are not finite"):
        positional_encoding(x, 4)
    assert positional_encoding(x, 0).shape == (3, 2)  # L = 0: x itself, nothing to check


@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
def test_half_inputs_are_computed_in_float32(half: torch.dtype) -> None:
    x = (torch.rand(5, 3, generator=torch.Generator().manual_seed(0)) - 0.5).to(half)
    out = positional_encoding(x, 3, layout="freq_interleaved")
    assert out.dtype == half
    expected = positional_encoding(x.float(), 3, layout="freq_interleaved").to(half)
    torch.testing.assert_close(out, expected, rtol=0, atol=0)


@given(st.lists(st.integers(0, 3), max_size=3), st.integers(1, 3), st.integers(0, 128))
def test_empty_inputs_give_empty_outputs(batch: list[int], dim: int, levels: int) -> None:
    x = torch.zeros(*batch, 0, dim)
    out = positional_encoding(x, levels)
    assert out.shape == (*batch, 0, dim * (2 * levels + 1))
