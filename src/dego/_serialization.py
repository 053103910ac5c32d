"""Saving and loading dego's dataclasses: ``torch.save`` / ``torch.load(weights_only=True)``
of the objects themselves, and a plain ``to_dict`` / ``from_dict`` form.

One generic implementation serves every class: :func:`to_dict` / :func:`from_dict` turn a
dataclass into a dict of plain values (tensors, lists, dicts, str, int, float, bool,
None; nested dataclasses become nested dicts) and back, checking every value against the
field's annotation; :func:`get_state` / :func:`set_state` are the pickle state behind
``torch.save``, checked the same way on load, so a checkpoint cannot build an object the
constructor would refuse. :func:`register_safe_globals` (called once by ``import dego``)
allowlists the classes of :func:`safe_types` for ``torch.load(weights_only=True)``: dego's
dataclasses only, no function, so all a checkpoint can reach is their constructors and
their checked state (from torch 2.5 through stand-ins that become the class only once the
checked state has arrived, so that ``NEWOBJ`` alone builds no dego object).
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any, TypeVar

from torch import Tensor

T = TypeVar("T")

_SCALARS = (bool, int, float, str)


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """The resolved annotation of every ``__init__`` field of dataclass ``cls``."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if f.init}


def _join(where: str, name: str) -> str:
    return f"{where}.{name}" if where else name


def _is_dataclass_type(hint: Any) -> bool:
    return isinstance(hint, type) and dataclasses.is_dataclass(hint)


def _plain(value: Any, where: str, keep_objects: bool) -> Any:
    """``value`` with containers as lists / dicts and nested dataclasses as dicts (or, with
    ``keep_objects``, as they are)."""
    if isinstance(value, Tensor) or value is None:
        return value
    if isinstance(value, _SCALARS):  # subclasses (IntEnum, numpy.float64) -> builtins
        return next(kind(value) for kind in _SCALARS if isinstance(value, kind))
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return value if keep_objects else _fields_of(value, where, keep_objects)
    if isinstance(value, list | tuple):
        return [_plain(v, f"{where}[{i}]", keep_objects) for i, v in enumerate(value)]
    if isinstance(value, Mapping):
        return {k: _plain(v, f"{where}[{k!r}]", keep_objects) for k, v in value.items()}
    raise TypeError(f"{where}: a {type(value).__name__} has no plain form")


def _fields_of(obj: Any, where: str, keep_objects: bool) -> dict[str, Any]:
    out = {}
    for field in dataclasses.fields(obj):
        value = getattr(obj, field.name)
        if value is None and field.default is None:
            continue  # an optional field left at its default: omitted
        out[field.name] = _plain(value, _join(where, field.name), keep_objects)
    return out


def to_dict(obj: Any) -> dict[str, Any]:
    """The fields of dataclass ``obj`` as plain values: tensors as they are (not copied, not
    detached), tuples as lists, mappings as dicts, nested dataclasses as nested dicts, and
    fields whose value and default are ``None`` left out. Such a dict loads with
    ``torch.load(weights_only=True)`` without dego."""
    return _fields_of(obj, "", keep_objects=False)


def _describe_hint(hint: Any) -> str:
    if isinstance(hint, type):
        return hint.__name__
    return str(hint).replace("jaxtyping.", "").replace("typing.", "")


def _describe_value(value: Any) -> str:
    if isinstance(value, Tensor):
        return f"a {value.dtype} tensor of shape {tuple(value.shape)}"
    return f"{type(value).__name__} {value!r}"[:120]


@functools.cache
def _bearable() -> Callable[[Any, Any], bool]:
    """beartype's ``is_bearable`` with an int a valid float, as in the constructors
    (imported when a pickle is first loaded: 0.25 s that ``import dego`` need not pay)."""
    from beartype import BeartypeConf
    from beartype.door import is_bearable

    return functools.partial(is_bearable, conf=BeartypeConf(is_pep484_tower=True))


def _check_leaf(value: Any, hint: Any, where: str) -> Any:
    if not _bearable()(value, hint):
        raise TypeError(f"{where}: expected {_describe_hint(hint)}, got {_describe_value(value)}")
    return value


def _coerce(value: Any, hint: Any, where: str) -> Any:
    """``value`` checked against ``hint``, with plain containers turned back into the
    annotated ones (list -> tuple, dict -> read-only mapping, dict -> dataclass)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is typing.Union or origin is types.UnionType:
        if value is None and type(None) in args:
            return None
        arms = [arm for arm in args if arm is not type(None)]
        return _coerce(value, arms[0], where) if len(arms) == 1 else _check_leaf(value, hint, where)
    if _is_dataclass_type(hint):
        if isinstance(value, Mapping):
            return from_dict(hint, value, where=where)
        if isinstance(value, hint):  # a nested object of a pickle: its fields checked too
            _checked_fields(hint, get_state(value), where)
            return value
        raise TypeError(
            f"{where}: expected a {hint.__name__} or a dict of its fields, got "
            f"{_describe_value(value)}"
        )
    if origin is tuple or origin is list:
        if not isinstance(value, list | tuple):
            raise TypeError(f"{where}: expected a list or tuple, got {_describe_value(value)}")
        if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):
            if len(value) != len(args):
                raise TypeError(f"{where}: expected {len(args)} items, got {len(value)}")
            item_hints = list(args)
        else:
            item_hints = [args[0] if args else Any] * len(value)
        pairs = enumerate(zip(value, item_hints, strict=True))
        items = [_coerce(v, h, f"{where}[{i}]") for i, (v, h) in pairs]
        return tuple(items) if origin is tuple else items
    if origin is Mapping or origin is dict:
        if not isinstance(value, Mapping):
            raise TypeError(f"{where}: expected a dict, got {_describe_value(value)}")
        key_hint, value_hint = args or (Any, Any)
        entries = {
            _check_leaf(k, key_hint, f"{where} key {k!r}"): _coerce(
                v, value_hint, f"{where}[{k!r}]"
            )
            for k, v in value.items()
        }
        return MappingProxyType(entries) if origin is Mapping else entries
    return _check_leaf(value, hint, where)


def _checked_fields(cls: type, data: Any, where: str) -> dict[str, Any]:
    """The ``__init__`` arguments of ``cls`` from ``data``: every key known, every field
    without a default present, every value of its annotated type."""
    if not isinstance(data, Mapping):
        raise TypeError(
            f"{where or 'data'}: expected a dict of {cls.__name__}'s fields, got "
            f"{_describe_value(data)}"
        )
    hints = _hints(cls)
    unknown = [k for k in data if k not in hints]
    if unknown:
        raise ValueError(
            f"{_join(where, str(unknown[0]))}: unknown key for {cls.__name__}; expected keys "
            f"{list(hints)}"
        )
    values = {}
    for field in dataclasses.fields(cls):
        name = field.name
        if name not in hints:
            continue
        if name in data:
            values[name] = _coerce(data[name], hints[name], _join(where, name))
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise ValueError(f"{_join(where, name)}: missing key, required by {cls.__name__}")
    return values


def _construct(cls: type[T], values: dict[str, Any], where: str, into: T | None = None) -> T:
    """``cls(**values)`` (or its ``__init__`` on ``into``): the constructor's own checks run;
    their errors get ``where`` in front when the object is nested."""
    try:
        if into is None:
            return cls(**values)
        cls.__init__(into, **values)
        return into
    except (TypeError, ValueError) as err:
        if not where:
            raise
        raise type(err)(f"{where}: {err}") from err


def from_dict(cls: type[T], data: Mapping[str, Any], *, where: str = "") -> T:
    """A ``cls`` from the dict :func:`to_dict` made: missing or unknown keys raise
    ``ValueError`` and values of the wrong type ``TypeError``, naming the key; then the
    constructor's own checks run."""
    return _construct(cls, _checked_fields(cls, data, where), where)


def get_state(obj: Any) -> dict[str, Any]:
    """Pickle state of dataclass ``obj``: its fields, nested dataclasses kept as objects and
    containers as lists / dicts (a read-only ``MappingProxyType`` cannot be pickled)."""
    return _fields_of(obj, type(obj).__name__, keep_objects=True)


def set_state(obj: Any, state: Any) -> None:
    """Restore ``obj`` from :func:`get_state`'s dict with :func:`from_dict`'s checks (the
    constructor runs on ``obj``), so a checkpoint cannot build an invalid object."""
    cls = type(obj)
    _construct(cls, _checked_fields(cls, state, cls.__name__), cls.__name__, into=obj)


class DictForm:
    """Mixin of dego's dataclasses: ``to_dict`` / ``from_dict`` and the checked pickle state
    behind ``torch.save`` / ``torch.load(weights_only=True)``."""

    def to_dict(self) -> dict[str, Any]:
        """The fields as a plain dict of the object's own tensors (not copied, not detached)
        and scalars; nested dataclasses as nested dicts, tuples as lists, and fields that
        are ``None`` by default left out when ``None``. ``torch.save`` it and
        ``torch.load(weights_only=True)`` reads it back without dego; :meth:`from_dict`
        rebuilds the object."""
        return to_dict(self)

    @classmethod
    def from_dict(cls: type[T], data: Mapping[str, Any]) -> T:
        """The object :meth:`to_dict` stored, validated as by the constructor.

        Raises:
            ValueError: a missing or unknown key (named), or the constructor's checks.
            TypeError: a value of the wrong type, dtype or rank (its key named).
        """
        return from_dict(cls, data)

    def __getstate__(self) -> dict[str, Any]:
        return get_state(self)

    def __setstate__(self, state: dict[str, Any]) -> None:
        # torch.load / copy: the fields are checked as by from_dict and the constructor
        set_state(self, state)


__all__ = ["from_dict", "get_state", "set_state", "to_dict"]
