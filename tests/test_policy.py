"""The input policy: the memory limit's scopes (process-wide and per-thread blocks) and the
no-silent-promotion rule of the helpers outside the big entry points."""

from __future__ import annotations

import threading
from collections.abc import Callable

import pytest
import torch

import dego
from dego._policy import check_memory
from dego.gaussians import build_covariances, build_precisions

DEFAULT = 64 * 2**30


def _in_thread(fn: Callable[[], None]) -> threading.Thread:
    errors: list[BaseException] = []

    def run() -> None:
        try:
            fn()
        except BaseException as exc:  # reported by the main thread
            errors.append(exc)

    thread = threading.Thread(target=run)
    thread.errors = errors  # type: ignore[attr-defined]
    thread.start()
    return thread


def _join(*threads: threading.Thread) -> None:
    for thread in threads:
        thread.join(timeout=30)
        assert not thread.is_alive()
        if thread.errors:  # type: ignore[attr-defined]
            raise thread.errors[0]  # type: ignore[attr-defined]


def test_interleaved_blocks_of_two_threads_restore_the_default() -> None:
    """A enters memory_limit(1), B enters memory_limit(None), A exits, B exits: the issue's
    sequence left the whole process at 1 byte."""
    a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event()
    seen: dict[str, object] = {}

    def a() -> None:
        with dego.memory_limit(1):
            a_in.set()
            assert b_in.wait(10)
            seen["a"] = dego.get_memory_limit()
        a_out.set()

    def b() -> None:
        assert a_in.wait(10)
        with dego.memory_limit(None):
            b_in.set()
            assert a_out.wait(10)
            seen["b"] = dego.get_memory_limit()
            check_memory("b", 2**70, "huge")  # no limit in B's block
        seen["b after"] = dego.get_memory_limit()

    _join(_in_thread(a), _in_thread(b))
    assert seen == {"a": 1, "b": None, "b after": DEFAULT}
    assert dego.get_memory_limit() == DEFAULT


def test_a_block_binds_only_its_own_thread() -> None:
    seen: list[int | None] = []
    with dego.memory_limit(1000):
        _join(_in_thread(lambda: seen.append(dego.get_memory_limit())))
        assert dego.get_memory_limit() == 1000
        with pytest.raises(ValueError, match="memory limit"):
            check_memory("here", 1001, "1001 bytes")
    assert seen == [DEFAULT]


def test_blocks_nest_and_restore_on_error() -> None:
    with dego.memory_limit(10):
        with pytest.raises(RuntimeError), dego.memory_limit(None):
            assert dego.get_memory_limit() is None
            raise RuntimeError
        assert dego.get_memory_limit() == 10
    assert dego.get_memory_limit() == DEFAULT


def test_set_memory_limit_is_process_wide_and_a_block_wins_in_its_thread() -> None:
    seen: list[int | None] = []
    previous = dego.set_memory_limit(5000)
    try:
        assert previous == DEFAULT
        with dego.memory_limit(7):
            assert dego.set_memory_limit(6000) == 5000
            assert dego.get_memory_limit() == 7
            _join(_in_thread(lambda: seen.append(dego.get_memory_limit())))
        assert dego.get_memory_limit() == 6000
    finally:
        dego.set_memory_limit(previous)
    assert seen == [6000]
    assert dego.get_memory_limit() == DEFAULT


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "1"])
def test_a_bad_limit_is_refused_before_the_block(bad: object) -> None:
    with pytest.raises(ValueError, match="nbytes"), dego.memory_limit(bad):  # type: ignore[arg-type]
        pass
    with pytest.raises(ValueError, match="nbytes"):
        dego.set_memory_limit(bad)  # type: ignore[arg-type]
    assert dego.get_memory_limit() == DEFAULT


def test_a_block_holds_inside_compiled_code() -> None:
    def guarded(x: torch.Tensor) -> torch.Tensor:
        check_memory("guarded", x.numel() * x.element_size(), "x")
        return x * 2

    compiled = torch.compile(guarded, backend="eager")
    x = torch.ones(8)
    assert torch.equal(compiled(x), x * 2)
    with dego.memory_limit(16), pytest.raises(ValueError, match="memory limit"):
        compiled(x)
    assert torch.equal(compiled(x), x * 2)


@pytest.mark.parametrize("fn", [build_covariances, build_precisions])
@pytest.mark.parametrize(
    ("quats_dtype", "scales_dtype"),
    [(torch.float64, torch.float32), (torch.float32, torch.float64)],
)
def test_covariance_helpers_do_not_promote_mixed_dtypes(
    fn: Callable[..., torch.Tensor], quats_dtype: torch.dtype, scales_dtype: torch.dtype
) -> None:
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=quats_dtype)
    scales = torch.ones(1, 3, dtype=scales_dtype)
    with pytest.raises(TypeError, match="scales: dtype"):
        fn(quats, scales)
    assert fn(quats, scales.to(quats_dtype)).dtype == quats_dtype


@pytest.mark.parametrize("argument", ["post_rot", "post_tran"])
def test_image_augmentation_does_not_promote_mixed_dtypes(argument: str) -> None:
    inputs = {
        "intrinsics": torch.eye(3, dtype=torch.float64),
        "post_rot": torch.eye(2, dtype=torch.float64),
        "post_tran": torch.zeros(2, dtype=torch.float64),
    }
    inputs[argument] = inputs[argument].float()
    with pytest.raises(TypeError, match=f"{argument}: dtype torch.float32 differs"):
        dego.apply_image_aug(**inputs)
    inputs[argument] = inputs[argument].double()
    assert dego.apply_image_aug(**inputs).dtype == torch.float64
