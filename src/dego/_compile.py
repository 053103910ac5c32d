"""Keeping TorchDynamo out of functions that must run eagerly, without importing it.

``torch._dynamo.disable`` imports ``torch._dynamo`` (about 1.5 s) when a module applies it.
:func:`eager_only` defers that: until ``torch._dynamo`` is imported nothing can be
compiling, so the function runs as is; once it is, the function runs with dynamo disabled
(recursively), which under ``torch.compile`` is one graph break at the call, as before.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import Any, TypeVar, cast

import torch

F = TypeVar("F", bound=Callable[..., Any])

DYNAMO = "torch._dynamo"
"""The module whose presence in ``sys.modules`` means compilation may be running."""


def disabled(fn: F) -> F:
    """``fn`` run with TorchDynamo disabled, recursively (``torch._dynamo.disable``), with
    ``torch._dynamo`` imported on the first call rather than now."""
    return cast(F, torch._disable_dynamo(fn, recursive=True))


def eager_only(fn: F) -> F:
    """``fn`` run with TorchDynamo disabled (recursively) once dynamo is loaded."""
    fn_disabled = disabled(fn)

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if DYNAMO in sys.modules:
            return fn_disabled(*args, **kwargs)
        return fn(*args, **kwargs)

    return cast(F, wrapper)


__all__ = ["DYNAMO", "disabled", "eager_only"]
