"""The input policy shared by every entry point: memory guard, dtype rule, finite checks.

- **Memory guard.** Before a large allocation an entry point estimates the bytes it needs
  and calls :func:`check_memory`, which raises ``ValueError`` naming the sizes and the
  estimate when it exceeds the limit (default 64 GiB). Change the process-wide limit with
  :func:`dego.set_memory_limit` (``None``: no limit), or the calling thread's limit for a
  block with :func:`dego.memory_limit` (other threads keep theirs).
- **dtypes.** Floating inputs of one call share one dtype (``TypeError`` naming the
  argument otherwise: nothing is promoted silently). float16 and bfloat16 inputs are
  computed in float32 and the results returned in the input dtype (:func:`compute_dtype`).
- **Autocast.** Under ``torch.autocast`` the geometric ops are on autocast's float32
  list (:func:`float32_under_autocast`): float16 / bfloat16 inputs are cast to float32,
  the op runs with autocast off and returns float32.
- **Non-finite values** in geometric inputs raise ``ValueError`` naming the argument and
  the count (:func:`check_finite`). Value checks go through :func:`run_checks`: one host
  sync per call in eager mode; under ``torch.compile`` in-graph asserts (no sync, no graph
  break) that raise ``RuntimeError`` naming the argument.
"""

from __future__ import annotations

import contextlib
import functools
import math
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

import torch
from torch import Tensor
from torch.utils._pytree import tree_leaves, tree_map

from dego._geometry import QUATERNION_EPS
from dego._typing import _is_compiling

_DEFAULT_LIMIT = 64 * 2**30
_limit: int | None = _DEFAULT_LIMIT
"""The process-wide limit (:func:`set_memory_limit`)."""
_thread = threading.local()
"""Per-thread override of ``memory_limit`` blocks: attribute ``limit`` while inside one.
A ``threading.local`` rather than a ``ContextVar``: dynamo traces the former, not the latter."""

HALF_DTYPES = (torch.float16, torch.bfloat16)
F = TypeVar("F", bound=Callable[..., Any])


def get_memory_limit() -> int | None:
    """The calling thread's per-call memory limit in bytes (``None``: no limit): that of
    the innermost :func:`memory_limit` block it is in, else the process-wide one."""
    return getattr(_thread, "limit", _limit)


def _check_limit(nbytes: int | None) -> None:
    if nbytes is not None and (
        isinstance(nbytes, bool) or not isinstance(nbytes, int) or nbytes <= 0
    ):
        raise ValueError(f"nbytes: expected a positive int or None, got {nbytes!r}")


def set_memory_limit(nbytes: int | None) -> int | None:
    """Set the process-wide per-call memory limit (bytes, or ``None`` for no limit); returns
    the old one.

    Entry points estimate what a call will allocate (images, grids, pair buffers) and raise
    a ``ValueError`` before allocating when the estimate exceeds the limit (default 64 GiB).
    Threads inside a :func:`memory_limit` block keep the block's limit until they leave it.
    """
    global _limit
    _check_limit(nbytes)
    previous, _limit = _limit, nbytes
    return previous


@contextlib.contextmanager
def memory_limit(nbytes: int | None) -> Iterator[None]:
    """Context manager: the calling thread's memory limit is ``nbytes`` inside the block.

    Thread-local: other threads keep their own limit, and leaving the block restores this
    thread's previous one (blocks nest), whatever other threads enter or leave meanwhile.
    """
    _check_limit(nbytes)
    missing = object()
    previous = getattr(_thread, "limit", missing)
    _thread.limit = nbytes
    try:
        yield
    finally:
        if previous is missing:
            del _thread.limit
        else:
            _thread.limit = previous


def _gib(nbytes: float) -> str:
    return f"{nbytes / 2**30:.3g} GiB"


def check_memory(what: str, nbytes: float, sizes: str) -> None:
    """Raise ``ValueError`` when ``nbytes`` (an estimate) exceeds the limit.

    ``what`` names the call (e.g. ``"splat"``), ``sizes`` the sizes behind the estimate
    (e.g. ``"B*V = 6 images of 256 x 704 x 49 channels, float32"``).
    """
    limit = get_memory_limit()
    if limit is not None and (not math.isfinite(nbytes) or nbytes > limit):
        raise ValueError(
            f"{what}: would need about {_gib(nbytes)} ({sizes}), above dego's memory "
            f"limit of {_gib(limit)}; reduce the sizes, or raise the limit with "
            "dego.set_memory_limit(nbytes) (None: no limit)"
        )


def compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype to compute in: float32 for float16 / bfloat16, else ``dtype`` itself."""
    return torch.float32 if dtype in HALF_DTYPES else dtype


def autocast_enabled(device_type: str) -> bool:
    """Whether ``torch.autocast`` is on for ``device_type`` (``"cpu"``, ``"cuda"``)."""
    try:
        return torch.is_autocast_enabled(device_type)
    except TypeError:  # torch < 2.4: one query per device type
        if device_type == "cpu":
            return torch.is_autocast_cpu_enabled()
        return device_type == "cuda" and torch.is_autocast_enabled()


def float32_under_autocast(*, keep_autocast: bool = False) -> Callable[[F], F]:
    """Decorator: under ``torch.autocast`` for the inputs' device, cast every float16 /
    bfloat16 tensor argument (GaussianSets included) to float32, like the ops on autocast's
    float32 list, and run ``fn`` with autocast disabled, so that its geometry (projection,
    compositing, voxel kernels) is computed and returned in float32.

    ``keep_autocast=True`` leaves autocast on inside ``fn`` (its networks then run in the
    autocast dtype) after the same cast of the inputs: for modules that mix learned layers
    with geometry and cast their layers' outputs back themselves.
    """

    def decorate(fn: F) -> F:
        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            device_type = next(
                (t.device.type for t in tree_leaves((args, kwargs)) if isinstance(t, Tensor)),
                None,
            )
            if device_type is None or not autocast_enabled(device_type):
                return fn(*args, **kwargs)
            args, kwargs = tree_map(_to_float32, (args, kwargs))
            if keep_autocast:
                return fn(*args, **kwargs)
            with torch.autocast(device_type, enabled=False):
                return fn(*args, **kwargs)

        return wrapper  # type: ignore[return-value]

    return decorate


def _to_float32(value: Any) -> Any:
    if isinstance(value, Tensor) and value.dtype in HALF_DTYPES:
        return value.float()
    return value


def check_dtype(name: str, tensor: Tensor, expected: torch.dtype, owner: str) -> None:
    """``TypeError`` unless ``tensor`` has the ``expected`` dtype of ``owner``."""
    if tensor.dtype != expected:
        possessive = f"{owner}'" if owner.endswith("s") else f"{owner}'s"  # the gaussians'
        raise TypeError(
            f"{name}: dtype {tensor.dtype} differs from {possessive} {expected}; inputs of "
            f"one call share one floating dtype (convert with .to({expected}))"
        )


Check = tuple[Tensor, str, Callable[[], Exception]]
"""One value check ``(ok, summary, error)``: ``ok`` a bool tensor, True when the values
are valid; ``summary`` the message raised under ``torch.compile``; ``error()`` builds the
eager exception (it runs only on failure, so it may read the tensors for details)."""


def finite_check(name: str, tensor: Tensor) -> Check:
    """The :data:`Check` that ``tensor`` holds no NaN or infinite value."""

    def error() -> Exception:
        bad = int((~torch.isfinite(tensor)).sum())
        return ValueError(f"{name}: {bad} of {tensor.numel()} values are not finite")

    return torch.isfinite(tensor).all(), f"{name}: contains values that are not finite", error


def run_checks(checks: Sequence[Check]) -> None:
    """Run value checks, raising the first failure's error.

    Eager: one host sync for all of them. While ``torch.compile`` traces: each becomes
    ``torch._assert_async(ok, summary)`` in the graph (no host sync, no graph break); a
    failure then raises ``RuntimeError`` with the summary, which names the argument.
    """
    if not checks:
        return
    if _is_compiling():
        for ok, summary, _ in checks:
            torch._assert_async(ok, f"{summary} (dego's value check, under torch.compile)")
        return
    results = torch.stack([ok.reshape(()).to(torch.bool) for ok, _, _ in checks]).tolist()
    for (_, _, error), passed in zip(checks, results, strict=True):
        if not passed:
            raise error()


LOG_SCALES_HINT = (
    "every value is negative, which looks like log-scales: use "
    'GaussianSet.from_tensors(..., scale_space="log")'
)
LOGITS_HINT = (
    "every value lies outside [0, 1], which looks like logits: use "
    'GaussianSet.from_tensors(..., opacity_space="logit")'
)
MOSTLY_LOGITS_HINT = (
    "most values lie outside [0, 1], as logits do: if they are logits, use "
    'GaussianSet.from_tensors(..., opacity_space="logit")'
)


def _example(values: Tensor, bad: Tensor) -> str:
    return f"{values[bad][0].item():.6g}"


def scales_check(
    prefix: str, scales: Tensor, *, positive: bool = True, needed_for: str = ""
) -> Check:
    """Scales must be > 0 (``positive=False``: only scales that are *all* negative are
    refused, as log-scales); the message adds the log-scales hint when every scale is
    negative, and ``needed_for`` (``"; ..."``) says why positivity matters."""

    def error() -> Exception:
        if not positive:
            return ValueError(f"{prefix}scales: {LOG_SCALES_HINT}")
        bad = ~(scales > 0)
        message = (
            f"{prefix}scales: {int(bad.sum())} of {scales.numel()} values are not positive "
            f"(e.g. {_example(scales, bad)}){needed_for}"
        )
        if bool((scales < 0).all()):
            message += f"; {LOG_SCALES_HINT}"
        return ValueError(message)

    if positive:
        return (scales > 0).all(), f"{prefix}scales: values are not positive", error
    ok = ~(scales < 0).all() | (scales.numel() == 0)
    return ok, f"{prefix}scales: every value is negative (log-scales?)", error


def quats_check(prefix: str, quats: Tensor) -> Check:
    """Quaternions must have a norm above :data:`~dego._geometry.QUATERNION_EPS`."""
    zero = torch.linalg.vector_norm(quats, dim=-1) <= QUATERNION_EPS

    def error() -> Exception:
        return ValueError(
            f"{prefix}quats: {int(zero.sum())} of {quats.shape[:-1].numel()} quaternions "
            f"have zero norm (<= {QUATERNION_EPS:g}) and encode no rotation"
        )

    return ~zero.any(), f"{prefix}quats: quaternions have zero norm", error


def opacities_check(prefix: str, opacities: Tensor) -> Check:
    """Opacities must lie in [0, 1]; the message adds the logits hint when none does, and
    a softer one when most do not (logits of a network or a file: about two thirds of
    standard-normal logits lie outside [0, 1]); a few stray values get none."""
    outside = (opacities < 0) | (opacities > 1)

    def error() -> Exception:
        count, total = int(outside.sum()), opacities.numel()
        message = (
            f"{prefix}opacities: {count} of {total} values lie "
            f"outside [0, 1] (e.g. {_example(opacities, outside)})"
        )
        if count == total:
            message += f"; {LOGITS_HINT}"
        elif 2 * count > total:
            message += f"; {MOSTLY_LOGITS_HINT}"
        return ValueError(message)

    return ~outside.any(), f"{prefix}opacities: values lie outside [0, 1]", error


def gaussian_value_checks(
    prefix: str,
    *,
    scales: Tensor,
    opacities: Tensor,
    quats: Tensor | None = None,
    positive_scales: bool = True,
    scales_needed_for: str = "",
) -> list[Check]:
    """The value :data:`Check` s of Gaussian fields, worded once for every entry point:
    :func:`scales_check`, :func:`quats_check` (when ``quats`` is given) and
    :func:`opacities_check`, in this order. ``prefix`` goes before each field name
    (``"gaussians."`` in ``splat``)."""
    checks = [scales_check(prefix, scales, positive=positive_scales, needed_for=scales_needed_for)]
    if quats is not None:
        checks.append(quats_check(prefix, quats))
    checks.append(opacities_check(prefix, opacities))
    return checks


def check_finite(name: str, tensor: Tensor) -> None:
    """``ValueError`` naming ``name`` when ``tensor`` holds NaN or infinite values."""
    run_checks([finite_check(name, tensor)])


__all__ = [
    "HALF_DTYPES",
    "LOGITS_HINT",
    "LOG_SCALES_HINT",
    "MOSTLY_LOGITS_HINT",
    "Check",
    "autocast_enabled",
    "check_dtype",
    "check_finite",
    "check_memory",
    "compute_dtype",
    "finite_check",
    "float32_under_autocast",
    "gaussian_value_checks",
    "get_memory_limit",
    "memory_limit",
    "opacities_check",
    "quats_check",
    "run_checks",
    "scales_check",
    "set_memory_limit",
]
