"""The input policy shared by every entry point: memory guard, dtype rule, finite checks.

- **Memory guard.** Before a large allocation an entry point estimates the bytes it needs
  and calls :func:`check_memory`, which raises ``ValueError`` naming the sizes and the
  estimate when it exceeds the limit (default 64 GiB). Change the limit with
  :func:`dego.set_memory_limit` (``None``: no limit) or temporarily with
  :func:`dego.memory_limit`.
- **dtypes.** Floating inputs of one call share one dtype (``TypeError`` naming the
  argument otherwise: nothing is promoted silently). float16 and bfloat16 inputs are
  computed in float32 and the results returned in the input dtype (:func:`compute_dtype`).
- **Non-finite values** in geometric inputs raise ``ValueError`` naming the argument and
  the count (:func:`check_finite`).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Sequence

import torch
from torch import Tensor

_DEFAULT_LIMIT = 64 * 2**30
_limit: int | None = _DEFAULT_LIMIT

HALF_DTYPES = (torch.float16, torch.bfloat16)


def get_memory_limit() -> int | None:
    """The current per-call memory limit in bytes (``None``: no limit)."""
    return _limit


def set_memory_limit(nbytes: int | None) -> int | None:
    """Set the per-call memory limit (bytes, or ``None`` for no limit); returns the old one.

    Entry points estimate what a call will allocate (images, grids, pair buffers) and raise
    a ``ValueError`` before allocating when the estimate exceeds the limit (default 64 GiB).
    """
    global _limit
    if nbytes is not None and (
        isinstance(nbytes, bool) or not isinstance(nbytes, int) or nbytes <= 0
    ):
        raise ValueError(f"nbytes: expected a positive int or None, got {nbytes!r}")
    previous, _limit = _limit, nbytes
    return previous


@contextlib.contextmanager
def memory_limit(nbytes: int | None) -> Iterator[None]:
    """Context manager: the memory limit is ``nbytes`` inside the block."""
    previous = set_memory_limit(nbytes)
    try:
        yield
    finally:
        set_memory_limit(previous)


def _gib(nbytes: float) -> str:
    return f"{nbytes / 2**30:.3g} GiB"


def check_memory(what: str, nbytes: float, sizes: str) -> None:
    """Raise ``ValueError`` when ``nbytes`` (an estimate) exceeds the limit.

    ``what`` names the call (e.g. ``"splat"``), ``sizes`` the sizes behind the estimate
    (e.g. ``"B*V = 6 images of 256 x 704 x 49 channels, float32"``).
    """
    limit = _limit
    if limit is not None and (not math.isfinite(nbytes) or nbytes > limit):
        raise ValueError(
            f"{what}: would need about {_gib(nbytes)} ({sizes}), above dego's memory "
            f"limit of {_gib(limit)}; reduce the sizes, or raise the limit with "
            "dego.set_memory_limit(nbytes) (None: no limit)"
        )


def compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype to compute in: float32 for float16 / bfloat16, else ``dtype`` itself."""
    return torch.float32 if dtype in HALF_DTYPES else dtype


def check_dtype(name: str, tensor: Tensor, expected: torch.dtype, owner: str) -> None:
    """``TypeError`` unless ``tensor`` has the ``expected`` dtype of ``owner``."""
    if tensor.dtype != expected:
        raise TypeError(
            f"{name}: dtype {tensor.dtype} differs from {owner}'s {expected}; inputs of one "
            f"call share one floating dtype (convert with .to({expected}))"
        )


def check_finite(name: str, tensor: Tensor) -> None:
    """``ValueError`` naming ``name`` when ``tensor`` holds NaN or infinite values."""
    bad = ~torch.isfinite(tensor)
    if bool(bad.any()):
        raise ValueError(f"{name}: {int(bad.sum())} of {tensor.numel()} values are not finite")


def check_finite_with(named: Sequence[tuple[str, Tensor]], *flags: Tensor) -> list[int]:
    """:func:`check_finite` on every ``(name, tensor)`` plus the values of other scalar
    checks ``flags`` (bool or integer tensors), with one host sync for all of them.

    Raises for the first non-finite tensor; returns the flags' values as ints.
    """
    values = [torch.isfinite(t).all() for _, t in named] + list(flags)
    results = torch.stack([v.to(torch.int64) for v in values]).tolist() if values else []
    for (name, tensor), ok in zip(named, results, strict=False):
        if not ok:
            check_finite(name, tensor)
    return results[len(named) :]


__all__ = [
    "HALF_DTYPES",
    "check_dtype",
    "check_finite",
    "check_finite_with",
    "check_memory",
    "compute_dtype",
    "get_memory_limit",
    "memory_limit",
    "set_memory_limit",
]
