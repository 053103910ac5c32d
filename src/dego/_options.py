"""One source of truth for the keyword options of ``splat`` / ``voxelize`` and their modules.

A frozen config dataclass holds each option once: its annotation, its default and (in
``__post_init__``) its validation. The functions build the config by name from their
keywords (:func:`config_from`), the modules take ``config=None, **overrides``
(:func:`build_config`), and both refuse an unknown name with one message
(:func:`check_option_names`). :func:`keyword_mismatches` is what the parity tests assert
on: every keyword of the function is a config field with the same default and annotation.
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
from collections.abc import Callable, Iterable, Mapping
from typing import Any, TypeVar

C = TypeVar("C")


def field_names(config_type: type) -> tuple[str, ...]:
    """The option names of a config dataclass, in declaration order."""
    return tuple(f.name for f in dataclasses.fields(config_type))


def check_option_names(
    owner: str,
    names: Iterable[str],
    config_type: type,
    *,
    foreign: Mapping[str, str] | None = None,
) -> None:
    """Raise ``TypeError`` naming ``owner`` for any name that is not a field of ``config_type``.

    ``foreign`` maps names other libraries use onto a hint (``{"width": "image_size=(H, W)"}``).
    """
    valid = field_names(config_type)
    for name in names:
        if name in valid:
            continue
        if foreign is not None and name in foreign:
            raise TypeError(
                f"{owner} got another library's keyword {name!r}: dego calls it {foreign[name]}"
            )
        close = difflib.get_close_matches(name, valid, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise TypeError(
            f"{owner} got an unknown option {name!r}{hint}; valid options: {', '.join(valid)}"
        )


def build_config(
    owner: str,
    config_type: type[C],
    config: C | None,
    overrides: Mapping[str, Any],
    *,
    foreign: Mapping[str, str] | None = None,
) -> C:
    """``config`` (or the defaults) with ``overrides`` applied, validated once."""
    if config is not None and not isinstance(config, config_type):
        raise TypeError(
            f"{owner}: config must be a {config_type.__name__} or None, got {type(config).__name__}"
        )
    check_option_names(owner, overrides, config_type, foreign=foreign)
    if config is None:
        return config_type(**overrides)
    return dataclasses.replace(config, **overrides) if overrides else config  # type: ignore[type-var]


def config_from(config_type: type[C], values: Mapping[str, Any]) -> C:
    """The config built by field name from ``values`` (e.g. a function's ``locals()``)."""
    return config_type(**{name: values[name] for name in field_names(config_type)})


def keyword_mismatches(fn: Callable[..., Any], config_type: type) -> list[str]:
    """How ``fn``'s keyword-only options differ from the fields of ``config_type`` (empty: none).

    Compares names, defaults and annotations (as written, ``from __future__ import
    annotations`` style), both ways, so neither side can gain an option alone.
    """
    fields = {f.name: f for f in dataclasses.fields(config_type)}
    parameters = {name: p for name, p in inspect.signature(fn).parameters.items() if name in fields}
    problems = [
        f"{name}: a config field but not a keyword" for name in fields if name not in parameters
    ]
    for name, parameter in parameters.items():
        field = fields[name]
        if parameter.default != field.default:
            problems.append(f"{name}: default {parameter.default!r} != field {field.default!r}")
        annotation = parameter.annotation
        if not isinstance(annotation, str):
            annotation = inspect.formatannotation(annotation)
        field_type = (
            field.type if isinstance(field.type, str) else inspect.formatannotation(field.type)
        )
        if annotation != field_type:
            problems.append(f"{name}: annotation {annotation!r} != field {field_type!r}")
    return problems
