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


PlainAndDisabled = tuple[Callable[..., Any], Callable[..., Any]]
"""A function as is and run with dynamo disabled: index it with ``DYNAMO in sys.modules``."""


def plain_and_disabled(fn: Callable[..., Any]) -> PlainAndDisabled:
    """``(fn, disabled(fn))``, to call ``[DYNAMO in sys.modules]``: before dynamo is loaded
    nothing can be compiling, and ``fn`` runs as is without importing it."""
    return (fn, disabled(fn))


def eager_only(fn: F) -> F:
    """``fn`` run with TorchDynamo disabled (recursively) once dynamo is loaded."""
    choices = plain_and_disabled(fn)

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        return choices[DYNAMO in sys.modules](*args, **kwargs)

    return cast(F, wrapper)


__all__ = ["DYNAMO", "PlainAndDisabled", "disabled", "eager_only", "plain_and_disabled"]
