"""A shared contract tester for dego's tensor ops (in the spirit of torchmetrics' MetricTester
and kornia's BaseTester).

An op is described once by an :class:`OpCase`: the callable, a factory of valid keyword
inputs for a dtype, device and size ``n`` (the N or B axis), the documented shape of each
tensor output, and the bad inputs it must reject. The ``check_*`` functions test one
property each; the ``*_params`` functions turn a list of cases into ``pytest.param`` lists
(ids, skips for CUDA, ``xfail(strict=True)`` for known bugs) for parametrised tests:

- ``check_shapes``: every documented output has its documented shape;
- ``check_dtype``: floating outputs follow the input dtype (float32, float64, and float16 /
  bfloat16 where the op documents them), others have their documented fixed dtype;
- ``check_device``: every tensor output lies on the input device;
- ``check_empty``: ``n = 0`` works and gives the documented (empty) shapes;
- ``check_bad_input``: a bad input raises the documented exception type, whose message
  names the offending argument.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import pytest
import torch
from torch import Tensor

Inputs = dict[str, Any]
Shape = tuple[int, ...]

FLOATS = (torch.float32, torch.float64)
HALVES = (torch.float16, torch.bfloat16)
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")


@dataclasses.dataclass(frozen=True)
class BadInput:
    """One invalid call: ``mutate`` turns valid inputs into invalid ones.

    ``error``: the exception type(s) the op must raise; ``names``: a string the message
    must contain (the argument, e.g. ``"scales"`` or ``"gaussians.means"``); ``xfail``: the
    bug, when the op is known to break the contract here.
    """

    id: str
    names: str
    mutate: Callable[[Inputs], Inputs]
    error: type[Exception] | tuple[type[Exception], ...] = TypeError
    xfail: str | None = None


@dataclasses.dataclass(frozen=True)
class OpCase:
    """The contract of one op.

    Attributes:
        name: the test id.
        fn: called as ``fn(**inputs)``.
        make_inputs: ``(dtype, device, n) -> inputs``; ``n`` is the size of the axis the
            empty check sets to 0.
        shapes: ``n -> {output: shape}`` for the outputs (see :func:`tensor_outputs`)
            whose shape is documented.
        dtypes: the input dtypes the op documents (floating or integer).
        fixed_dtypes: outputs whose dtype does not follow the input (``{name: dtype}``);
            every other floating output of ``shapes`` must have the input dtype.
        empty: whether ``n = 0`` is documented to work.
        size: the ``n`` of the non-empty checks.
        bad: the bad inputs.
        xfail: ``{check: bug}`` for checks (``"shapes"``, ``"empty"``, ``"dtype:float16"``,
            ``"device:cpu"``...) known to fail.
        skip: ``{"*": why}`` skips every check of the case here (an optional package is
            missing, say), ``{"cpu": why}`` every check that runs on the CPU (all but
            ``"device:cuda"``).
    """

    name: str
    fn: Callable[..., Any]
    make_inputs: Callable[[torch.dtype, torch.device, int], Inputs]
    shapes: Callable[[int], Mapping[str, Shape]]
    dtypes: tuple[torch.dtype, ...] = FLOATS
    fixed_dtypes: Mapping[str, torch.dtype] = dataclasses.field(default_factory=dict)
    empty: bool = True
    size: int = 3
    bad: tuple[BadInput, ...] = ()
    xfail: Mapping[str, str] = dataclasses.field(default_factory=dict)
    skip: Mapping[str, str] = dataclasses.field(default_factory=dict)

    def __repr__(self) -> str:
        return f"OpCase({self.name})"

    def call(self, dtype: torch.dtype, device: torch.device | str, n: int) -> dict[str, Tensor]:
        torch.manual_seed(0)
        inputs = self.make_inputs(dtype, torch.device(device), n)
        return tensor_outputs(self.fn(**inputs))


def tensor_outputs(result: Any, prefix: str = "") -> dict[str, Tensor]:
    """The tensors of a result by name: ``"out"`` for a tensor, ``"0"``, ``"1"`` for a tuple,
    field names for dataclasses (nested ones dotted: ``"gaussians.means"``)."""
    if isinstance(result, Tensor):
        return {prefix or "out": result}
    found: dict[str, Tensor] = {}
    if dataclasses.is_dataclass(result) and not isinstance(result, type):
        items: Iterable[tuple[str, Any]] = (
            (f.name, getattr(result, f.name)) for f in dataclasses.fields(result)
        )
    elif isinstance(result, tuple | list):
        items = ((str(i), v) for i, v in enumerate(result))
    else:
        return found
    for key, value in items:
        found.update(tensor_outputs(value, f"{prefix}.{key}" if prefix else key))
    return found


def _expected_dtype(case: OpCase, output: str, tensor: Tensor, dtype: torch.dtype) -> torch.dtype:
    if output in case.fixed_dtypes:
        return case.fixed_dtypes[output]
    return dtype if tensor.is_floating_point() or tensor.is_complex() else tensor.dtype


# -- checks -------------------------------------------------------------------------------


def check_shapes(case: OpCase, n: int | None = None) -> None:
    n = case.size if n is None else n
    outputs = case.call(torch.float64 if torch.float64 in case.dtypes else case.dtypes[0], "cpu", n)
    for output, shape in case.shapes(n).items():
        assert output in outputs, f"{case.name}: no output {output!r} (have {sorted(outputs)})"
        assert tuple(outputs[output].shape) == tuple(shape), (
            f"{case.name}: {output} has shape {tuple(outputs[output].shape)}, documented {shape}"
        )


def check_dtype(case: OpCase, dtype: torch.dtype) -> None:
    outputs = case.call(dtype, "cpu", case.size)
    for output in case.shapes(case.size):
        tensor = outputs[output]
        expected = _expected_dtype(case, output, tensor, dtype)
        assert tensor.dtype == expected, (
            f"{case.name}: {output} is {tensor.dtype} for {dtype} input, expected {expected}"
        )
        if tensor.is_floating_point() and tensor.numel():
            assert bool(torch.isfinite(tensor.float()).all()), (
                f"{case.name}: {output} has non-finite values for valid {dtype} input"
            )


def check_device(case: OpCase, device: str) -> None:
    outputs = case.call(case.dtypes[0], device, case.size)
    for output, tensor in outputs.items():
        assert tensor.device.type == torch.device(device).type, (
            f"{case.name}: {output} is on {tensor.device}, input on {device}"
        )


def check_empty(case: OpCase) -> None:
    check_shapes(case, 0)


def check_bad_input(case: OpCase, bad: BadInput) -> None:
    dtype = case.dtypes[0]
    torch.manual_seed(0)
    inputs = bad.mutate(case.make_inputs(dtype, torch.device("cpu"), case.size))
    with pytest.raises(bad.error, match=re.escape(bad.names)):
        case.fn(**inputs)


# -- parametrisation ----------------------------------------------------------------------


def _param(case: OpCase, check: str, *values: Any, extra: str | None = None) -> Any:
    marks = []
    skip = case.skip.get("*") or (None if check == "device:cuda" else case.skip.get("cpu"))
    if skip:
        marks.append(pytest.mark.skip(reason=skip))
    reason = extra or case.xfail.get(check)
    if reason:
        marks.append(pytest.mark.xfail(strict=True, reason=reason))
    if check == "device:cuda":
        marks.append(CUDA)
    return pytest.param(case, *values, marks=marks, id=f"{case.name}-{check}")


def shape_params(cases: Iterable[OpCase]) -> list[Any]:
    return [_param(c, "shapes") for c in cases]


def dtype_params(cases: Iterable[OpCase]) -> list[Any]:
    return [_param(c, f"dtype:{str(d)[6:]}", d) for c in cases for d in c.dtypes]


def device_params(cases: Iterable[OpCase]) -> list[Any]:
    return [_param(c, f"device:{d}", d) for c in cases for d in ("cpu", "cuda")]


def empty_params(cases: Iterable[OpCase]) -> list[Any]:
    return [_param(c, "empty") for c in cases if c.empty]


def bad_input_params(cases: Iterable[OpCase]) -> list[Any]:
    return [_param(c, f"bad:{b.id}", b, extra=b.xfail) for c in cases for b in c.bad]


# -- mutations ----------------------------------------------------------------------------


def with_nan(name: str, index: int = 0) -> Callable[[Inputs], Inputs]:
    """Inputs with one NaN in ``inputs[name]`` (a tensor) or in a GaussianSet's field
    (``"gaussians.means"``)."""

    def mutate(inputs: Inputs) -> Inputs:
        return _replace(inputs, name, lambda t: _nan_at(t, index))

    return mutate


def with_value(name: str, fn: Callable[[Tensor], Tensor]) -> Callable[[Inputs], Inputs]:
    """Inputs with ``inputs[name]`` (or a GaussianSet's field, dotted) replaced by ``fn(it)``."""

    def mutate(inputs: Inputs) -> Inputs:
        return _replace(inputs, name, fn)

    return mutate


def _nan_at(t: Tensor, index: int) -> Tensor:
    t = t.clone()
    t.view(-1)[index] = float("nan")
    return t


def _replace(inputs: Inputs, name: str, fn: Callable[[Any], Any]) -> Inputs:
    inputs = dict(inputs)
    if "." in name:
        owner, field = name.split(".", 1)
        inputs[owner] = inputs[owner].replace(**{field: fn(getattr(inputs[owner], field))})
    else:
        inputs[name] = fn(inputs[name])
    return inputs
