"""Run-time shape/dtype checking shared by every public entry point.

``typechecked`` is jaxtyping's ``jaxtyped`` with beartype as the checker: a wrong
shape or dtype raises :class:`jaxtyping.TypeCheckError` (a ``TypeError``) whose
message names the offending parameter and the axis sizes seen so far. While
``torch.compile`` traces a function the check is skipped (dynamo cannot trace
beartype), so compiled graphs stay whole; eager calls are always checked.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, TypeVar

from beartype import beartype
from jaxtyping import jaxtyped

F = TypeVar("F", bound=Callable[..., Any])

try:
    from torch.compiler import is_compiling as _is_compiling
except ImportError:  # torch < 2.3
    from torch._dynamo import is_compiling as _is_compiling


def typechecked(fn: F) -> F:
    """Check ``fn``'s jaxtyping annotations with beartype on every eager call."""
    checked = jaxtyped(typechecker=beartype)(fn)

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if _is_compiling():
            return fn(*args, **kwargs)
        return checked(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


__all__ = ["typechecked"]
