"""GaussianSet as a tensor-like container: len, iteration, indexing over the batch and
Gaussian axes, and .cpu() / .cuda() / .float() / .double() / .half() / .bfloat16()."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from dego import GaussianSet

B, N, C = 3, 11, 4


def batched(seed: int = 0, dtype: torch.dtype = torch.float32) -> GaussianSet:
    g = torch.Generator().manual_seed(seed)
    return GaussianSet(
        means=torch.randn(B, N, 3, generator=g, dtype=dtype),
        quats=torch.randn(B, N, 4, generator=g, dtype=dtype),
        scales=torch.rand(B, N, 3, generator=g, dtype=dtype) + 0.1,
        opacities=torch.rand(B, N, generator=g, dtype=dtype),
        features=torch.randn(B, N, C, generator=g, dtype=dtype),
    )


def assert_fields(out: GaussianSet, index) -> None:  # type: ignore[no-untyped-def]
    """Every field of ``out`` is the reference set's field indexed by ``index(name, t)``."""
    for name, value in batched().items():
        torch.testing.assert_close(getattr(out, name), index(name, value), rtol=0, atol=0)


def test_len_and_iteration_follow_the_first_batch_axis() -> None:
    gs = batched()
    assert len(gs) == B
    items = list(gs)
    assert len(items) == B and all(item.batch_shape == () for item in items)
    assert_fields(items[1], lambda _, t: t[1])
    with pytest.raises(TypeError, match=r"unbatched GaussianSet.*num_gaussians"):
        len(items[0])


@given(st.integers(-B, B - 1), st.integers(0, N), st.integers(0, N))
def test_batch_then_gaussian_slices_index_like_tensors(b: int, start: int, stop: int) -> None:
    gs = batched()
    assert_fields(gs[b], lambda _, t: t[b])
    assert_fields(gs[b, start:stop], lambda _, t: t[b, start:stop])
    assert_fields(gs[:, start:stop], lambda _, t: t[:, start:stop])
    assert_fields(gs[..., start:stop], lambda _, t: t[:, start:stop])
    assert_fields(gs[1:], lambda _, t: t[1:])


def test_tensor_and_mask_indices() -> None:
    gs = batched()
    mask = torch.arange(N) % 3 == 0
    assert_fields(gs[:, mask], lambda _, t: t[:, mask])
    picks = torch.tensor([4, 0, 4])
    assert_fields(gs[0, picks], lambda _, t: t[0, picks])
    assert_fields(gs[torch.tensor([2, 0])], lambda _, t: t[torch.tensor([2, 0])])
    unbatched = gs[0]
    assert_fields(unbatched[2:5], lambda _, t: t[0, 2:5])  # unbatched: the index is on N


def assert_same_set(got: GaussianSet, expected: GaussianSet) -> None:
    assert [n for n, _ in got.items()] == [n for n, _ in expected.items()]
    for name, value in expected.items():
        torch.testing.assert_close(getattr(got, name), value, rtol=0, atol=0)


def test_numpy_index_arrays_index_as_the_same_tensors() -> None:
    gs = batched()
    picks = np.array([4, 0, 4, -1])
    mask = np.arange(N) % 3 == 0
    per_item = np.tile(picks, (B, 1))
    cases = [
        ((slice(None), picks), (slice(None), torch.as_tensor(picks))),
        ((0, picks), (0, torch.as_tensor(picks))),
        ((slice(None), mask), (slice(None), torch.as_tensor(mask))),
        ((Ellipsis, mask), (Ellipsis, torch.as_tensor(mask))),
        ((slice(None), per_item), (slice(None), torch.as_tensor(per_item))),
        ((slice(None), np.array([4, 0], np.uint8)), (slice(None), torch.tensor([4, 0]))),
        (np.array([2, 0]), torch.tensor([2, 0])),  # the batch axis
        (np.array([True, False, True]), torch.tensor([True, False, True])),
        ((np.int64(1), slice(2, 5)), (1, slice(2, 5))),
    ]
    for key, same in cases:
        assert_same_set(gs[key], gs[same])
    assert_fields(gs[:, mask], lambda _, t: t[:, torch.as_tensor(mask)])
    assert_same_set(gs.select(picks), gs.select(torch.as_tensor(picks)))
    with pytest.raises(IndexError, match="int on the Gaussian axis"):
        gs[0, np.int64(3)]


@pytest.mark.parametrize(
    ("index", "got"),
    [
        ("abc", "got str"),
        (1.5, "got float"),
        (torch.tensor([0.0, 1.0]), "got a torch.float32 tensor"),
        (np.array([0.0, 1.0]), "got a numpy ndarray of dtype float64"),
        ([0, "1"], "got a sequence that holds other values than ints"),
        ({0, 1}, "got set"),
    ],
)
def test_other_gaussian_axis_indices_are_one_line_type_errors(index: object, got: str) -> None:
    with pytest.raises(TypeError) as caught:
        batched()[:, index]
    message = str(caught.value)
    assert "\n" not in message and message.endswith(got), message
    assert message.startswith(
        "GaussianSet index: the Gaussian axis N takes a slice, a sequence of ints, or an "
        "integer or bool torch.Tensor / numpy.ndarray"
    )


def test_indices_that_would_drop_the_gaussian_axis_are_refused() -> None:
    gs = batched()
    with pytest.raises(IndexError, match="int on the Gaussian axis"):
        gs[0, 3]
    with pytest.raises(IndexError, match="int on the Gaussian axis"):
        gs[0][3]
    with pytest.raises(IndexError, match="int on the Gaussian axis"):
        gs[..., torch.tensor(2)]
    with pytest.raises(IndexError, match="at most 2"):
        gs[0, 1, 2]
    with pytest.raises(IndexError, match=r"only allowed as gs\[\.\.\., n\]"):
        gs[..., 0, 1:2]
    with pytest.raises(IndexError):
        gs[B]  # out of range, as for a tensor


def test_dtype_and_device_helpers() -> None:
    gs = batched()
    doubled = gs.double()
    assert doubled.dtype == torch.float64 and all(
        t.dtype == torch.float64 for _, t in doubled.items()
    )
    assert_fields(doubled.float(), lambda _, t: t)
    assert gs.cpu().device == torch.device("cpu")


@pytest.mark.parametrize(
    ("method", "dtype"),
    [
        ("half", torch.float16),
        ("bfloat16", torch.bfloat16),
        ("float", torch.float32),
        ("double", torch.float64),
    ],
)
def test_half_bfloat16_float_double_cast_every_field(method: str, dtype: torch.dtype) -> None:
    gs = batched(dtype=torch.float64)
    cast = getattr(gs, method)()
    assert isinstance(cast, GaussianSet) and cast.dtype == dtype
    assert [name for name, _ in cast.items()] == list(GaussianSet.FIELDS)  # none dropped
    for name, value in cast.items():
        assert value.dtype == dtype, name
        assert value.shape == getattr(gs, name).shape, name
        torch.testing.assert_close(value, getattr(gs, name).to(dtype), rtol=0, atol=0)
    assert getattr(gs.replace(features=None), method)().features is None
    assert gs.dtype == torch.float64  # the original set is unchanged


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
def test_cuda_moves_every_field() -> None:
    moved = batched().cuda()
    assert all(t.is_cuda for _, t in moved.items())
    assert_fields(moved.cpu(), lambda _, t: t)
