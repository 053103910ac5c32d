"""The last long error dumps (issue 51, item 6): each mistake a new user makes raises one
line naming the function (or field) and the argument, with the fix.

- a value outside a ``Literal`` (every public one, found by enumerating the exports;
  ``splat(..., backend="cuda")`` also says the device comes from the tensors);
- ``GaussianSet`` given ``(*batch, N, 1)`` opacities or logits: points at
  ``GaussianSet.from_tensors(..., opacity_space="logit")``;
- ``backend="triton"`` without triton: both requirements (the package and a GPU, or the
  interpreter);
- a forgotten argument (``deformation(gaussians, times)``): the one the caller left out.
"""

from __future__ import annotations

import dataclasses
import inspect
import types
import typing
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import torch

from dego import DecoupledDeformation, DifferentiableSplatter, GaussianSet, splat
from dego._typing import TYPECHECKED
from dego.compat.gsplat import rasterization
from dego.deformation import DeformationLossWeights
from dego.encoding import PositionalEncoding
from dego.splatting import SplatConfig, triton_backend
from dego.teacher import FactorizedTeacherFeatures
from dego.voxelizer import VoxelizerConfig
from tests.helpers.deformation import literal_output, make_inputs, make_module
from tests.helpers.splatting import small_scene
from tests.test_typechecked_exports import MODULES, _module

BAD = "not-an-option"


def _one_line(error: BaseException) -> str:
    message = str(error)
    assert "\n" not in message, f"a {len(message.splitlines())}-line message:\n{message}"
    return message


# ---------------------------------------------------------------------------------------
# every Literal parameter of the public API


def _literal_values(hint: Any) -> tuple[Any, ...]:
    """The values a parameter's ``Literal`` allows (``None`` included when optional); ``()``
    when the annotation has no ``Literal``."""
    if typing.get_origin(hint) is typing.Annotated:
        hint = typing.get_args(hint)[0]
    if typing.get_origin(hint) is typing.Literal:
        return typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        parts = [_literal_values(a) for a in typing.get_args(hint)]
        if any(parts):
            return tuple(
                v for a, p in zip(typing.get_args(hint), parts, strict=True) for v in p
            ) + ((None,) if type(None) in typing.get_args(hint) else ())
    return ()


def _callables() -> Iterator[tuple[str, Callable[..., Any]]]:
    """``(key, function)`` for every exported function and every public method,
    ``__init__`` and ``__call__`` of an exported class (dego's own, inherited included)."""
    seen: set[str] = set()
    for name in MODULES:
        module = _module(name)
        if module is None:  # an optional dependency is missing
            continue
        for export in getattr(module, "__all__", ()):
            obj = getattr(module, export)
            if inspect.isfunction(obj):
                found = [(f"{obj.__module__}.{obj.__qualname__}", obj)]
            elif inspect.isclass(obj) and not issubclass(obj, BaseException):
                found = []
                for kls in obj.__mro__:
                    if not kls.__module__.startswith("dego"):
                        continue
                    for attr, raw in vars(kls).items():
                        if attr.startswith("_") and attr not in ("__init__", "__call__"):
                            continue
                        fn = raw.__func__ if isinstance(raw, staticmethod | classmethod) else raw
                        if inspect.isfunction(fn):
                            key = f"{kls.__module__}.{kls.__qualname__}.{attr}"
                            found.append((key, fn))
            else:
                continue
            for key, fn in found:
                if key not in seen:
                    seen.add(key)
                    yield key, fn


def _literal_parameters() -> list[tuple[str, Callable[..., Any], str, tuple[Any, ...]]]:
    cases = []
    for key, fn in _callables():
        hints = typing.get_type_hints(fn, include_extras=True)
        for name in inspect.signature(fn).parameters:
            allowed = _literal_values(hints.get(name))
            if allowed:
                cases.append((key, fn, name, allowed))
    return cases


# Callables with Literal parameters that are not wrapped by dego._typing.typechecked (no
# tensor parameter: constructors that validate their options by hand, in __init__ or a
# dataclass's __post_init__, after checks of other arguments): called with valid
# arguments but the bad option. A new such callable fails test_the_table_is_complete.
_VALID = (2, 3)  # any small positive ints


def _gsplat_call(**option: Any) -> Any:
    n = 4
    return rasterization(
        torch.zeros(n, 3),
        torch.tensor([1.0, 0, 0, 0]).expand(n, 4),
        torch.ones(n, 3),
        torch.full((n,), 0.5),
        torch.zeros(n, 3),
        torch.eye(4)[None],
        torch.eye(3)[None],
        8,
        8,
        **option,
    )


UNCHECKED: dict[str, Callable[..., Any]] = {
    "dego.deformation.module.DecoupledDeformation.__init__": lambda **o: DecoupledDeformation(
        *_VALID[:1], **o
    ),
    "dego.deformation.loss.DeformationLossWeights.__init__": DeformationLossWeights,
    "dego.deformation.results.DeformationOutput.__init__": lambda **o: dataclasses.replace(
        literal_output("paper"), **o
    ),
    "dego.teacher.features.FactorizedTeacherFeatures.__init__": lambda **o: (
        FactorizedTeacherFeatures(*_VALID[:1], **o)
    ),
    "dego.encoding.PositionalEncoding.__init__": lambda **o: PositionalEncoding(*_VALID[:1], **o),
    "dego.splatting.types.SplatConfig.__init__": SplatConfig,
    "dego.voxelizer.types.VoxelizerConfig.__init__": VoxelizerConfig,
    # PENDING in tests/test_typechecked_exports.py: not typechecked yet
    "dego.compat.gsplat.rasterization": _gsplat_call,
}

CASES = _literal_parameters()


def test_the_enumeration_finds_the_literal_parameters() -> None:
    found = {(key, name) for key, _, name, _ in CASES}
    assert ("dego.splatting.splatter.splat", "backend") in found
    assert ("dego.splatting.splatter.splat", "radius_rule") in found  # Optional[Literal]
    assert ("dego.voxelizer.api.voxelize", "mode") in found
    assert len(found) >= 20


def test_the_table_is_complete() -> None:
    unchecked = {key for key, fn, *_ in CASES if not getattr(fn, TYPECHECKED, False)}
    assert unchecked == set(UNCHECKED), (
        "a callable with a Literal parameter that is not @typechecked needs an entry in "
        f"UNCHECKED (or @typechecked): {sorted(unchecked ^ set(UNCHECKED))}"
    )


def _dummy_call(fn: Callable[..., Any], name: str, value: object) -> Any:
    """``fn`` called with ``None`` for every required argument (a method's ``self``
    included) and ``value`` for ``name``: only a check that runs first names the option."""
    args: list[Any] = []
    kwargs: dict[str, Any] = {}
    for parameter in inspect.signature(fn).parameters.values():
        given = value if parameter.name == name else None
        if parameter.name != name and parameter.default is not parameter.empty:
            continue
        if parameter.kind in (parameter.VAR_POSITIONAL, parameter.VAR_KEYWORD):
            continue
        if parameter.kind is parameter.POSITIONAL_ONLY:
            args.append(given)
        elif parameter.name == name or parameter.kind is parameter.KEYWORD_ONLY:
            kwargs[parameter.name] = given
        else:
            args.append(given)
    return fn(*args, **kwargs)


@pytest.mark.parametrize(
    ("key", "fn", "name", "allowed"),
    CASES,
    ids=[f"{key}:{name}" for key, _, name, _ in CASES],
)
def test_a_value_outside_a_literal_is_one_line(
    key: str, fn: Callable[..., Any], name: str, allowed: tuple[Any, ...]
) -> None:
    checked = getattr(fn, TYPECHECKED, False)
    with pytest.raises(ValueError) as info:
        if checked:
            _dummy_call(fn, name, BAD)
        else:
            UNCHECKED[key](**{name: BAD})
    message = _one_line(info.value)
    assert f"{name}: expected" in message
    assert repr(BAD) in message
    for value in allowed:
        assert repr(value) in message, f"{value!r} not listed: {message}"
    if checked:  # the decorator names the function
        assert message.startswith(f"{fn.__qualname__}(): {name}: expected one of ")


def test_a_wrong_type_for_a_literal_is_one_line_too() -> None:
    with pytest.raises(ValueError, match=r"^splat\(\): depth_mode: .* got 3$") as info:
        splat(None, None, None, None, depth_mode=3)  # type: ignore[arg-type]
    _one_line(info.value)
    scene = small_scene()
    with pytest.raises(ValueError, match=r"got a tensor of shape \(2,\)$"):
        splat(*_scene_args(scene), rasterize_mode=torch.zeros(2))  # type: ignore[arg-type]


def test_valid_options_pass_the_check() -> None:
    scene = small_scene()
    for backend in ("torch", "auto"):
        out = splat(*_scene_args(scene), backend=backend, radius_rule=None, depth_mode="none")
        assert out.depth is None


def _scene_args(scene: Any) -> tuple[Any, ...]:
    return scene.gaussians, scene.world_to_cam, scene.intrinsics, scene.image_size


# ---------------------------------------------------------------------------------------
# 1. backend="cuda"


@pytest.mark.parametrize("device", ["cuda", "cpu", "cuda:0"])
def test_splat_backend_cuda_says_the_device_comes_from_the_tensors(device: str) -> None:
    scene = small_scene()
    with pytest.raises(ValueError) as info:
        splat(*_scene_args(scene), backend=device)  # type: ignore[arg-type]
    message = _one_line(info.value)
    assert message.startswith(
        f"splat(): backend: expected one of 'torch', 'auto', 'gsplat', 'triton', got {device!r}"
    )
    assert "device of the input tensors" in message
    assert f".to({device!r})" in message


def test_splatter_and_config_backend_cuda_say_it_too() -> None:
    for build in (SplatConfig, DifferentiableSplatter):
        with pytest.raises(ValueError, match=r"^backend: expected .*'triton', got 'cuda'") as info:
            build(backend="cuda")  # type: ignore[arg-type]
        assert ".to('cuda')" in _one_line(info.value)
    with pytest.raises(ValueError) as info:
        SplatConfig(backend="bogus")  # type: ignore[arg-type]
    assert "device" not in str(info.value)  # the hint only for a device name


# ---------------------------------------------------------------------------------------
# 2. opacities as gsplat / 3DGS store them


def _fields(n: int = 6, batch: tuple[int, ...] = (2,)) -> dict[str, Any]:
    return {
        "means": torch.zeros(*batch, n, 3),
        "quats": torch.tensor([1.0, 0, 0, 0]).expand(*batch, n, 4),
        "scales": torch.ones(*batch, n, 3),
        "opacities": torch.full((*batch, n), 0.5),
    }


@pytest.mark.parametrize("batch", [(), (2,)])
def test_opacities_n1_point_at_from_tensors(batch: tuple[int, ...]) -> None:
    fields = _fields(batch=batch)
    fields["opacities"] = fields["opacities"][..., None]  # (*batch, N, 1)
    with pytest.raises(ValueError, match=r"^opacities: expected shape \(\*batch, N\)") as info:
        GaussianSet(**fields)
    message = _one_line(info.value)
    assert "GaussianSet.from_tensors(" in message
    assert 'opacity_space="logit"' in message
    assert GaussianSet.from_tensors(**fields).opacities.shape == (*(batch or (1,)), 6)


def test_other_opacity_shapes_get_no_hint() -> None:
    fields = _fields()
    fields["opacities"] = torch.full((2, 6, 2), 0.5)
    with pytest.raises(ValueError, match="opacities: expected shape") as info:
        GaussianSet(**fields)
    assert "from_tensors" not in str(info.value)


def test_typical_logits_point_at_from_tensors() -> None:
    """Logits of a network or a file: most, not all, lie outside [0, 1]."""
    fields = _fields(n=12, batch=())
    logits = torch.linspace(-3, 3, 12)  # 2 of 12 in [0, 1]
    fields["opacities"] = logits
    with pytest.raises(ValueError, match=r"^opacities: 10 of 12 values lie outside") as info:
        GaussianSet(**fields).check_values()
    assert 'GaussianSet.from_tensors(..., opacity_space="logit")' in _one_line(info.value)
    with pytest.raises(ValueError, match=r'opacity_space="logit"'):
        GaussianSet.from_tensors(**fields)
    scene = small_scene(batch=1, n=12)
    gs = scene.gaussians.replace(opacities=logits[None].double())
    with pytest.raises(ValueError, match=r'^gaussians\.opacities: .*opacity_space="logit"'):
        splat(*_scene_args(scene.replace(gaussians=gs)))
    converted = GaussianSet.from_tensors(**fields, opacity_space="logit")
    torch.testing.assert_close(converted.opacities[0], torch.sigmoid(logits))


# ---------------------------------------------------------------------------------------
# 3. backend="triton" without triton


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_triton_missing_names_both_requirements(
    monkeypatch: pytest.MonkeyPatch, device: str
) -> None:
    monkeypatch.setattr(triton_backend, "installed", lambda: False)
    message = triton_backend._missing_triton(torch.device(device))
    assert "\n" not in message
    for needed in (triton_backend.INSTALL, "[triton]", "CUDA", "ROCm", "TRITON_INTERPRET=1"):
        assert needed in message
    assert ("backend='torch'" in message) == (device == "cpu")


def test_splat_triton_without_triton_on_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(triton_backend, "installed", lambda: False)
    scene = small_scene().to(torch.float32)
    with pytest.raises(ImportError, match=r"^backend: 'triton' needs two things") as info:
        splat(*_scene_args(scene), backend="triton")
    message = _one_line(info.value)
    assert "triton package" in message
    assert "GPU" in message and "TRITON_INTERPRET=1" in message
    assert "tensors are on cpu" in message


# ---------------------------------------------------------------------------------------
# 4. a forgotten argument


def test_deformation_without_features_names_features() -> None:
    module = make_module(feature_dim=4)
    gaussians, features = make_inputs(1, 3, feature_dim=4)
    times = torch.tensor([0.0, 1.0], dtype=torch.float64)
    expected = (
        "DecoupledDeformation.forward() missing required argument 'features' "
        "(call it as module(gaussians, features, times))"
    )
    for call in (lambda: module(gaussians, times), lambda: module(gaussians, times=times)):
        with pytest.raises(TypeError) as info:
            call()
        assert _one_line(info.value) == expected
        assert info.value.__suppress_context__
    with pytest.raises(TypeError) as info:
        module(gaussians, features)  # the times are what is missing here
    assert "missing required argument 'times'" in _one_line(info.value)
    assert module(gaussians, features, times).gaussians.batch_shape == (1, 2)


def test_other_binding_errors_name_the_function() -> None:
    scene = small_scene()
    gaussians, w2c, k, size = _scene_args(scene)
    with pytest.raises(TypeError) as info:
        splat(gaussians, w2c, k)  # type: ignore[call-arg]
    assert _one_line(info.value) == (
        "splat() missing required argument 'image_size' "
        "(call it as splat(gaussians, world_to_cam, intrinsics, image_size))"
    )
    with pytest.raises(TypeError) as info:
        splat(gaussians, w2c, k, size, colour=1)  # type: ignore[call-arg]
    message = _one_line(info.value)
    assert message.startswith("splat()") and "'colour'" in message
    with pytest.raises(TypeError, match=r"^splat\(\): too many positional arguments$"):
        splat(gaussians, w2c, k, size, None)  # type: ignore[call-arg]


@pytest.mark.slow
def test_a_value_outside_a_literal_under_compile_is_one_line() -> None:
    scene = small_scene()

    def render() -> torch.Tensor:
        return splat(*_scene_args(scene), backend="cuda").features.sum()  # type: ignore[arg-type]

    with pytest.raises(ValueError, match=r"^splat\(\): backend: expected one of ") as info:
        torch.compile(render, backend="eager")()
    assert ".to('cuda')" in _one_line(info.value)
