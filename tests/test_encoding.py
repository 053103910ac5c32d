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
