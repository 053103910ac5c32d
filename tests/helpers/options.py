"""Checks shared by the options parity tests of splat and voxelize."""

from __future__ import annotations

import inspect
import typing

from dego._options import field_names


def assert_overrides_typed_as_config(options: type, config: type, module: type) -> None:
    """``options`` (the TypedDict of ``module``'s ``**overrides``) has exactly ``config``'s
    fields and types, none required, and types the module's ``**overrides``."""
    assert list(options.__annotations__) == list(field_names(config))
    assert typing.get_type_hints(options) == typing.get_type_hints(config)
    assert not options.__required_keys__  # type: ignore[attr-defined]
    parameter = inspect.signature(module).parameters["overrides"]
    assert parameter.kind is parameter.VAR_KEYWORD
    assert parameter.annotation == f"Unpack[{options.__name__}]"
