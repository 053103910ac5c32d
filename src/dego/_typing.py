"""Run-time shape/dtype checking shared by every public entry point.

``typechecked`` checks a function's jaxtyping annotations on every call, eager or compiled:

- **Eager**: jaxtyping's ``jaxtyped`` with beartype as the checker. A wrong shape or dtype
  raises :class:`jaxtyping.TypeCheckError` (a ``TypeError``) whose message names the
  offending parameter and the axis sizes seen so far. Once ``torch._dynamo`` is loaded the
  check runs with TorchDynamo disabled: when an enclosing ``torch.compile`` falls back to
  running a frame eagerly, dynamo must not trace jaxtyping's and beartype's internals (it
  would cache their side effects and report false mismatches on later calls). Before that
  no compilation can be running, and dego does not import ``torch._dynamo`` itself (about
  a second and a half): ``import dego`` stays lean.
- **While ``torch.compile`` traces** (beartype cannot be traced): a traceable check of the
  same annotations, in plain Python over shapes and dtypes, raising the same
  ``TypeCheckError`` naming the parameter. Shapes are known while tracing, so the check
  adds no graph break and no host sync; dynamo's guards make it hold for every call that
  reuses the graph.

Two mistakes get a one-line error instead of the checkers' dump, eager and compiled:

- **A value outside a ``Literal``** (``splat(..., backend="cuda")``): checked before
  anything else, it raises ``ValueError("splat(): backend: expected one of 'torch', ...,
  got 'cuda'")``, naming the function, the parameter, the value and the allowed values
  (:func:`literal_error`; a device name given for an option says the device comes from
  the tensors).
- **A missing argument** (eager): ``TypeError`` naming the function and the argument the
  caller left out, found by trying which omission makes the given positional arguments
  fit their annotations (``deformation(gaussians, times)`` misses ``features``, not
  ``times``), and how to call it.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import itertools
import math
import re
import sys
import types
import typing
from collections.abc import Callable
from typing import Any, TypeVar, cast

import torch
from jaxtyping import TypeCheckError, jaxtyped

from dego._compile import DYNAMO, PlainAndDisabled, plain_and_disabled

F = TypeVar("F", bound=Callable[..., Any])

try:
    from torch.compiler import is_compiling as _is_compiling
except ImportError:  # torch < 2.3
    from torch._dynamo import is_compiling as _is_compiling

# One array alternative of a hint: (dtype names or None for any, dims, hint text); dims
# are ("fixed", size) / ("named", name) / ("variadic", name).
_Array = tuple[tuple[str, ...] | None, tuple[tuple[str, Any], ...], str]
# A parameter's spec: its array alternatives and whether anything else is also accepted.
_Spec = tuple[str, tuple[_Array, ...], bool]


def _array_alternative(hint: Any) -> _Array | None:
    dims = getattr(hint, "dims", None)
    if dims is None or getattr(hint, "array_type", None) is not torch.Tensor:
        return None
    dtypes = hint.dtypes if isinstance(hint.dtypes, tuple | list) else None
    parsed = []
    for dim in dims:
        kind = type(dim).__name__
        if kind == "_FixedDim":
            parsed.append(("fixed", dim.size))
        elif kind == "_NamedDim":
            parsed.append(("named", dim.name))
        elif kind in ("_NamedVariadicDim", "_AnonymousVariadicDim"):
            parsed.append(("variadic", getattr(dim, "name", None)))
        else:  # symbolic or anonymous dims: accept any size
            parsed.append(("named", None))
    return (tuple(dtypes) if dtypes is not None else None, tuple(parsed), hint.dim_str)


def _parameter_spec(name: str, hint: Any) -> _Spec | None:
    union = typing.get_origin(hint) in (typing.Union, types.UnionType)
    alternatives = typing.get_args(hint) if union else (hint,)
    arrays = [a for a in (_array_alternative(h) for h in alternatives) if a is not None]
    if not arrays:
        return None
    return (name, tuple(arrays), len(arrays) < len(alternatives))


class _Enclosing(dict[str, Any]):
    """Names for resolving ``fn``'s annotations at decoration time, when the classes around
    it (``GaussianSet`` for ``GaussianSet.map -> GaussianSet``) are not defined yet: each
    stands for a class that is no tensor, which is all the compile-time check needs to know
    (the eager check resolves the real class on the first call). Any other undefined name is
    the NameError it is."""

    def __init__(self, fn: Callable[..., Any]) -> None:
        super().__init__()
        self.enclosing = set(fn.__qualname__.split(".")[:-1]) - {"<locals>"}
        self.module_globals = fn.__globals__

    def __missing__(self, name: str) -> Any:
        if name in self.enclosing and name not in self.module_globals:
            return type(name, (), {})
        raise KeyError(name)


# A Literal parameter: (name, its position or None when keyword-only, the allowed values,
# whether only strings are checked: the Literal is a union with types that take no string).
_Literal = tuple[str, int | None, tuple[Any, ...], bool]


def _literal_spec(name: str, index: int | None, hint: Any) -> _Literal | None:
    """The :data:`_Literal` of a parameter annotated with a ``Literal`` (or a union of
    ``Literal`` s, ``None`` and types that cannot hold a string); ``None`` for any other."""
    union = typing.get_origin(hint) in (typing.Union, types.UnionType)
    allowed: list[Any] = []
    others = []
    for alternative in typing.get_args(hint) if union else (hint,):
        if typing.get_origin(alternative) is typing.Annotated:
            alternative = typing.get_args(alternative)[0]
        if typing.get_origin(alternative) is typing.Literal:
            allowed.extend(typing.get_args(alternative))
        elif alternative is None or alternative is type(None):
            allowed.append(None)
        else:
            others.append(alternative)
    if not any(value is not None for value in allowed):
        return None
    # beside other types, only a string is known to be wrong (and only if none takes one)
    if any(not isinstance(other, type) or issubclass(str, other) for other in others):
        return None
    return (name, index, tuple(dict.fromkeys(allowed)), bool(others))


def _specs(fn: Callable[..., Any]) -> tuple[tuple[str, ...], tuple[_Spec, ...]]:
    """The names of ``fn``'s positional parameters and the specs of its array parameters."""
    positional, specs, _ = _all_specs(fn)
    return positional, specs


def _all_specs(
    fn: Callable[..., Any],
) -> tuple[tuple[str, ...], tuple[_Spec, ...], tuple[_Literal, ...]]:
    """:func:`_specs` and the specs of ``fn``'s ``Literal`` parameters."""
    hints = typing.get_type_hints(fn, localns=_Enclosing(fn), include_extras=True)
    parameters = inspect.signature(fn).parameters
    positional = tuple(
        name
        for name, p in parameters.items()
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
    )
    specs = (_parameter_spec(name, hints[name]) for name in parameters if name in hints)
    literals = (
        _literal_spec(name, positional.index(name) if name in positional else None, hints[name])
        for name, p in parameters.items()
        if name in hints and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    )
    return (
        positional,
        tuple(s for s in specs if s is not None),
        tuple(s for s in literals if s is not None),
    )


_DEVICE = re.compile(r"(cpu|cuda|gpu|mps|xpu|hip|rocm)(:\d+)?", re.IGNORECASE)


def _describe(value: object) -> str:
    """``value`` for a one-line message: a short repr, or its type for anything else."""
    if value is None or isinstance(value, str | int | float | bool):
        text = repr(value)
        return text if len(text) <= 60 else text[:57] + "..."
    if isinstance(value, torch.Tensor):
        return f"a tensor of shape {tuple(value.shape)}"
    return f"a {type(value).__name__}"


def device_hint(name: str, value: object) -> str:
    """``"; 'cuda' is a device, not a backend: ..."`` when ``value``, refused for option
    ``name``, names a device (dego computes where the tensors are); ``""`` otherwise."""
    if not isinstance(value, str) or not _DEVICE.fullmatch(value):
        return ""
    return (
        f"; {value!r} is a device, not a {name}: dego computes on the device of the input "
        f"tensors, so move them there with .to({value!r})"
    )


def literal_error(where: str, name: str, value: object, allowed: tuple[Any, ...]) -> ValueError:
    """The one-line error of a value outside a parameter's ``Literal``: ``where`` (the
    function, ``"splat()"``), the parameter, the value given and the allowed values."""
    choices = ", ".join(map(repr, allowed))
    return ValueError(
        f"{where}: {name}: expected one of {choices}, got {_describe(value)}"
        f"{device_hint(name, value)}"
    )


def _is_allowed(value: object, allowed: tuple[Any, ...]) -> bool:
    # by type and value, like beartype: 1 is not '1', a tensor is compared to nothing
    for choice in allowed:
        if value is choice or (
            choice is not None and isinstance(value, type(choice)) and value == choice
        ):
            return True
    return False


def _check_literals(
    where: str, literals: tuple[_Literal, ...], args: tuple[Any, ...], kwargs: dict[str, Any]
) -> None:
    """Raise :func:`literal_error` for the first given argument outside its ``Literal``."""
    for name, index, allowed, strings_only in literals:
        if name in kwargs:
            value = kwargs[name]
        elif index is not None and index < len(args):
            value = args[index]
        else:  # the default
            continue
        if strings_only and not isinstance(value, str):
            continue
        if not _is_allowed(value, allowed):
            raise literal_error(where, name, value, allowed)


_MAX_GUESSES = 64  # placements of the omitted arguments tried by _binding_error


def _fits(value: object, hint: Any) -> bool:
    from beartype.door import is_bearable

    try:
        return bool(is_bearable(value, hint))
    except Exception:  # a hint beartype cannot check alone: no evidence either way
        return True


def _binding_error(
    fn: Callable[..., Any], where: str, args: tuple[Any, ...], kwargs: dict[str, Any]
) -> TypeError | None:
    """The one-line ``TypeError`` of a call whose arguments do not bind to ``fn``'s
    parameters (``None`` when they do). A missing argument is named as the caller left
    it out: when positional arguments came shifted (``deformation(gaussians, times)``),
    the first placement of the omitted parameters under which every positional argument
    fits its annotation names them (``features``), rather than the last ones Python
    reports (``times``)."""
    signature = inspect.signature(fn)
    try:
        signature.bind(*args, **kwargs)
        return None
    except TypeError as error:
        reason = str(error)
    try:
        bound = signature.bind_partial(*args, **kwargs).arguments
    except TypeError:  # too many arguments, an unknown keyword, one given twice
        return TypeError(f"{where}: {reason}")
    parameters = list(signature.parameters.values())
    required = [
        p
        for p in parameters
        if p.default is p.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    ]
    positional_kinds = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    method = bool(parameters) and parameters[0].name in ("self", "cls") and "." in fn.__qualname__
    slots = [p for p in required if p.kind in positional_kinds and p.name not in kwargs]
    fixed = 1 if method and args and slots and slots[0] is parameters[0] else 0
    count = len(args) - fixed
    candidates = slots[fixed:]
    omitted = [p.name for p in candidates[count:]]  # Python's reading: the last ones
    if 0 < len(omitted) and math.comb(len(candidates), len(omitted)) <= _MAX_GUESSES:
        try:
            hints = typing.get_type_hints(fn, include_extras=True)
        except Exception:
            hints = {}
        placements = itertools.combinations(range(len(candidates)), len(omitted))
        for placement in placements:
            given = [p for i, p in enumerate(candidates) if i not in placement]
            if all(
                p.name not in hints or _fits(value, hints[p.name])
                for p, value in zip(given, args[fixed:], strict=True)
            ):
                omitted = [candidates[i].name for i in placement]
                break
    omitted += [p.name for p in required if p.kind is p.KEYWORD_ONLY and p.name not in bound]
    if not omitted:
        return TypeError(f"{where}: {reason}")
    call = ", ".join(
        p.name if p.kind in positional_kinds else f"{p.name}=..." for p in required[fixed:]
    )
    if not method:
        callee = fn.__name__
    elif fn.__name__ in ("forward", "__call__"):
        callee = "module" if fn.__name__ == "forward" else "obj"
    else:
        callee = f"obj.{fn.__name__}"
    names = ", ".join(map(repr, omitted))
    plural = "s" if len(omitted) > 1 else ""
    return TypeError(
        f"{where} missing required argument{plural} {names} (call it as {callee}({call}))"
    )


def _matches(value: torch.Tensor, array: _Array, sizes: dict[str, Any]) -> bool:
    dtypes, dims, _ = array
    if dtypes is not None and str(value.dtype).removeprefix("torch.") not in dtypes:
        return False
    shape = value.shape
    variadic = [i for i, (kind, _) in enumerate(dims) if kind == "variadic"]
    if variadic:
        at = variadic[0]
        fixed = len(dims) - 1
        if len(shape) < fixed:
            return False
        head, tail = dims[:at], dims[at + 1 :]
        middle = tuple(shape[at : len(shape) - len(tail)])
        pairs = [
            *zip(head, shape[:at], strict=True),
            *zip(tail, shape[len(shape) - len(tail) :], strict=True),
        ]
        name = dims[at][1]
        if name is not None and name in sizes and sizes[name] != middle:
            return False
        bound: dict[str, Any] = {name: middle} if name is not None else {}
    else:
        if len(shape) != len(dims):
            return False
        pairs, bound = list(zip(dims, shape, strict=True)), {}
    for (kind, label), size in pairs:
        if kind == "fixed" and size != label:
            return False
        if kind == "named" and label is not None:
            expected = bound.get(label, sizes.get(label))
            if expected is not None and expected != size:
                return False
            bound[label] = size
    sizes.update(bound)
    return True


def _traced_check(qualname: str, specs: tuple[_Spec, ...], arguments: dict[str, Any]) -> None:
    """The compile-time check: plain Python over shapes and dtypes, traceable by dynamo."""
    sizes: dict[str, Any] = {}
    for name, arrays, others in specs:
        if name not in arguments:
            continue
        value = arguments[name]
        if not isinstance(value, torch.Tensor):
            if others:
                continue
            raise TypeCheckError(
                f"Type-check error whilst checking the parameters of {qualname}.\n"
                f"The problem arose whilst typechecking parameter '{name}'.\n"
                f"Actual value: {type(value).__name__}\n"
                f"Expected type: a tensor ({' or '.join(repr(a[2]) for a in arrays)})."
            )
        trial = dict(sizes)
        for array in arrays:
            if _matches(value, array, trial):
                sizes = trial
                break
            trial = dict(sizes)
        else:
            shape = ",".join(str(s) for s in value.shape)
            raise TypeCheckError(
                f"Type-check error whilst checking the parameters of {qualname}.\n"
                f"The problem arose whilst typechecking parameter '{name}'.\n"
                f"Actual value: {str(value.dtype).removeprefix('torch.')}[{shape}]\n"
                f"Expected type: {' or '.join(repr(a[2]) for a in arrays)}"
                f"{' (or a non-tensor value)' if others else ''}.\n"
                f"Axis sizes seen so far: {sizes}"
            )


_RESULT = "_dego_result"
TYPECHECKED = "__dego_typechecked__"
"""The attribute :func:`typechecked` sets to ``True`` on its wrappers. ``functools.wraps``
copies a function's ``__dict__``, so it also marks a decorator's wrapper around a checked
function (tests/test_typechecked_exports.py reads it)."""


def _stub(fn: Callable[..., Any], with_return: bool) -> Callable[..., Any]:
    """A function with ``fn``'s parameters, annotations and globals and an empty body, for
    jaxtyping + beartype to check the arguments (and, ``with_return``, a result passed as
    the extra keyword ``_dego_result``) without running ``fn`` inside the checker."""
    positional, keyword, variadic = [], [], []
    for p in inspect.signature(fn).parameters.values():
        default = "=None" if p.default is not p.empty else ""
        if p.kind is p.VAR_POSITIONAL:
            positional.append(f"*{p.name}")
        elif p.kind is p.VAR_KEYWORD:
            variadic.append(f"**{p.name}")
        elif p.kind is p.KEYWORD_ONLY:
            keyword.append(p.name + default)
        else:
            positional.append(p.name + default)
    if with_return:
        keyword.append(f"{_RESULT}=None")
    star = [] if not keyword or any(t.startswith("*") for t in positional) else ["*"]
    namespace: dict[str, Any] = {}
    body = f"return {_RESULT}" if with_return else "return None"
    exec(f"def stub({', '.join(positional + star + keyword + variadic)}):\n    {body}", namespace)
    stub = types.FunctionType(namespace["stub"].__code__, fn.__globals__, fn.__name__)
    stub.__defaults__ = fn.__defaults__
    stub.__kwdefaults__ = {**(fn.__kwdefaults__ or {}), **({_RESULT: None} if with_return else {})}
    annotations = dict(fn.__annotations__)
    if with_return:
        annotations[_RESULT] = annotations.pop("return")
    annotations.pop("return", None)
    stub.__annotations__ = annotations
    stub.__module__, stub.__qualname__ = fn.__module__, fn.__qualname__
    return stub


def _has_array_return(fn: Callable[..., Any]) -> bool:
    annotation = fn.__annotations__.get("return")
    return annotation is not None and "Tensor" in str(annotation)


def _check_of(stub: Callable[..., Any]) -> PlainAndDisabled:
    """jaxtyping + beartype's check of ``stub``: as is, and run with dynamo disabled."""
    from beartype import beartype  # 0.25 s to import: not before a first check

    return plain_and_disabled(jaxtyped(typechecker=beartype)(stub))


def typechecked(fn: F) -> F:
    """Check ``fn``'s jaxtyping annotations on every call, eager or compiled.

    The annotations must name objects of ``fn``'s module (or the classes around it): they
    are resolved in its globals, at decoration for the compiled check and on the first
    eager call for jaxtyping + beartype's."""
    # Built on the first eager call (jaxtyping + beartype generate code for each check:
    # about 4 ms a function, 0.6 s for the whole package were it done at import).
    checks: list[tuple[PlainAndDisabled, PlainAndDisabled | None]] = []

    def build_checks() -> tuple[PlainAndDisabled, PlainAndDisabled | None]:
        arguments = _check_of(_stub(fn, with_return=False))
        result = _check_of(_stub(fn, with_return=True)) if _has_array_return(fn) else None
        checks.append((arguments, result))
        return checks[0]

    qualname = f"{fn.__module__}.{fn.__qualname__}"
    where = f"{fn.__qualname__}()"
    # now: a first call under torch.compile needs no break
    positional, specs, literals = _all_specs(fn)

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if literals:  # first: a wrong option is named whatever else is wrong
            _check_literals(where, literals, args, kwargs)
        if _is_compiling():
            _traced_check(qualname, specs, {**dict(zip(positional, args, strict=False)), **kwargs})
            return fn(*args, **kwargs)
        check_arguments, check_result = checks[0] if checks else build_checks()
        # Each check as is, or with dynamo disabled once torch._dynamo is loaded (see the
        # module docstring).
        try:
            check_arguments[DYNAMO in sys.modules](*args, **kwargs)
        except TypeError as error:
            if isinstance(error, TypeCheckError):
                raise
            binding = _binding_error(fn, where, args, kwargs)
            if binding is None:
                raise
            raise binding from None
        result = fn(*args, **kwargs)
        if check_result is not None:
            check_result[DYNAMO in sys.modules](*args, **kwargs, **{_RESULT: result})
        return result

    wrapper.__dict__[TYPECHECKED] = True
    return cast(F, wrapper)


_FIELD_CHECKS: dict[type, tuple[tuple[str, ...], PlainAndDisabled]] = {}


def check_tensor_fields(record: Any) -> None:
    """Check the fields of dataclass instance ``record`` whose annotations name a tensor
    (jaxtyping + beartype, axis sizes shared across the fields), for ``__post_init__``.

    Raises :class:`jaxtyping.TypeCheckError` naming the field. Skipped while
    ``torch.compile`` traces (beartype cannot be traced).
    """
    if _is_compiling():
        return
    cls = type(record)
    if cls not in _FIELD_CHECKS:
        hints = typing.get_type_hints(cls, include_extras=True)
        names = tuple(
            f.name for f in dataclasses.fields(cls) if "Tensor" in str(hints.get(f.name, ""))
        )
        namespace: dict[str, Any] = {}
        exec(f"def fields(*, {', '.join(names)}):\n    return None", namespace)
        check = namespace["fields"]
        check.__annotations__ = {name: hints[name] for name in names}
        check.__qualname__ = f"{cls.__qualname__}.__init__"
        check.__module__ = cls.__module__
        _FIELD_CHECKS[cls] = (names, _check_of(check))
    names, checkers = _FIELD_CHECKS[cls]
    if names:
        checkers[DYNAMO in sys.modules](**{name: getattr(record, name) for name in names})


__all__ = ["check_tensor_fields", "device_hint", "literal_error", "typechecked"]
