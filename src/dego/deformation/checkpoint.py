"""Official DeGO deformation checkpoints <-> :class:`dego.DecoupledDeformation` weights.

A pure key mapping: the official module's state-dict keys and shapes, size inference from
them, the translation to and from this port's parameter names, and mismatch reporting.
Nothing here builds or imports a module; :meth:`DecoupledDeformation.from_official_state_dict`
and :meth:`DecoupledDeformation.to_official_state_dict` (``official`` preset) do, with
:func:`read_official_state_dict`, :func:`from_official_tensors` and
:func:`official_state_dict`.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from dego._checks import check_int
from dego._policy import check_memory
from dego._typing import typechecked

OFFICIAL_CHECKPOINT_PREFIX = "gaussian_decoder.deformation_module."
"""Where the official DeGO detector keeps its deformation network: the keys of
``GaussianDeformationMaskStaticRigid`` in a released checkpoint's ``state_dict`` start with
this (the detector's ``gaussian_decoder.deformation_module``)."""

# Official module children that this port does not model, with the reason given in errors.
_UNSUPPORTED_OFFICIAL = {
    "static_mask_head": "from use_static_mask=True, not modelled; the released config is False",
}
# official head name -> ours
_OFFICIAL_HEADS = {
    "rigid_mask_head": "mask_head",
    "position_head": "heads.rigid_offset",
    "rotation_head": "heads.rotation",
    "scale_head": "heads.scale",
    "opacity_head": "heads.opacity",
}
_OFFICIAL_BUFFERS = ("pos_enc_freqs", "time_enc_freqs")
_HEAD_OUTPUTS = {  # official head -> its output width
    "rigid_mask_head": 1,
    "position_head": 3,
    "rotation_head": 4,
    "scale_head": 3,
    "opacity_head": 1,
}
_LAYER = re.compile(r"feature_net\.(\d+)\.\w+")
# The deepest feature net inferred from the keys (the released network has 6 layers);
# a deeper one loads with an explicit depth.
_MAX_INFERRED_DEPTH = 64
_LISTED = 20  # keys listed per kind of mismatch; the rest are counted
_KEY_CHARS = 120  # longer keys are cut in messages


class StateDictMismatchError(KeyError, ValueError):
    """A state dict does not match the module it should load into.

    Raised by :meth:`DecoupledDeformation.from_official_state_dict` with every missing,
    unexpected and mis-shaped key listed; it is both a ``KeyError`` and a ``ValueError``.
    """

    def __str__(self) -> str:  # KeyError would print the repr of the message
        return str(self.args[0]) if self.args else ""


_WB = ("weight", "bias")
_ARCHITECTURE = ("feature_dim", "hidden_dim", "depth", "time_dim", "pos_levels", "time_levels")


def _normalized_prefix(prefix: str) -> str:
    if not isinstance(prefix, str):
        raise TypeError(f"prefix: expected a str, got {type(prefix).__name__}")
    return prefix + "." if prefix and not prefix.endswith(".") else prefix


def _shape(given: Mapping[str, Any], key: str, ndim: int) -> tuple[int, ...] | None:
    value = given.get(key)
    if isinstance(value, Tensor) and value.ndim == ndim:
        return tuple(value.shape)
    return None


def _infer_official_sizes(
    given: Mapping[str, Any], kwargs: dict[str, Any]
) -> tuple[dict[str, int], list[str]]:
    """The official module's sizes: ``kwargs`` first, else the shapes, else the defaults.

    Returns the sizes (popped from ``kwargs``) and the names that could not be inferred.
    """
    sizes: dict[str, int] = {}
    if "head_hidden" in kwargs:
        sizes["head_hidden"] = kwargs.pop("head_hidden")
    unknown: list[str] = []

    def first(*candidates: int | None) -> int | None:
        return next((c for c in candidates if c is not None), None)

    def dim(shape: tuple[int, ...] | None, axis: int) -> int | None:
        return None if shape is None else shape[axis]

    freqs = {name: _shape(given, name, 1) for name in _OFFICIAL_BUFFERS}
    time_in = _shape(given, "time_embed.0.weight", 2)
    time_out = _shape(given, "time_embed.2.weight", 2)
    first_layer = _shape(given, "feature_net.0.weight", 2)
    first_bias = _shape(given, "feature_net.0.bias", 1)
    indices = [
        int(m.group(1)) for key in given if (m := re.fullmatch(r"feature_net\.(\d+)\.\w+", key))
    ]
    inferred = {
        "pos_levels": dim(freqs["pos_enc_freqs"], 0),
        "time_levels": first(
            dim(freqs["time_enc_freqs"], 0),
            (time_in[1] - 1) // 2 if time_in and time_in[1] % 2 else None,
        ),
        "time_dim": first(dim(time_in, 0), dim(time_out, 0)),
        "hidden_dim": first(dim(first_layer, 0), dim(first_bias, 0)),
        "depth": max(indices) // 2 + 1 if indices else None,
    }
    defaults = {"pos_levels": 6, "time_levels": 4, "time_dim": 32, "hidden_dim": 256, "depth": 6}
    for name, default in defaults.items():
        if name in kwargs:
            sizes[name] = kwargs.pop(name)
        elif inferred[name] is not None:
            sizes[name] = inferred[name]  # type: ignore[assignment]
        else:
            sizes[name] = default
            unknown.append(name)
    if "feature_dim" in kwargs:
        sizes["feature_dim"] = kwargs.pop("feature_dim")
    elif first_layer is not None:
        for name in ("pos_levels", "time_dim"):
            check_int(name, sizes[name], 0)
        rest = 3 * (2 * sizes["pos_levels"] + 1) + sizes["time_dim"]
        if first_layer[1] < rest:
            raise StateDictMismatchError(
                f"feature_net.0.weight: its {first_layer[1]} input columns are fewer than "
                f"PE(mu)'s {3 * (2 * sizes['pos_levels'] + 1)} plus the time embedding's "
                f"{sizes['time_dim']}: no room for the features"
            )
        sizes["feature_dim"] = first_layer[1] - rest
    else:
        sizes["feature_dim"] = 256  # the released config's
        unknown.append("feature_dim")
    return sizes, unknown


def _official_shapes(sizes: Mapping[str, int]) -> dict[str, tuple[int, ...]]:
    """The official module's state-dict shapes for ``sizes``, in its order, computed
    without building anything (``official_tensors`` of the module with these sizes)."""
    f, h, d = sizes["feature_dim"], sizes["hidden_dim"], sizes["depth"]
    t, p, q = sizes["time_dim"], sizes["pos_levels"], sizes["time_levels"]
    g = sizes.get("head_hidden", h)
    shapes: dict[str, tuple[int, ...]] = {"pos_enc_freqs": (p,), "time_enc_freqs": (q,)}
    for i, (rows, cols) in ((0, (t, 2 * q + 1)), (2, (t, t))):
        shapes |= {f"time_embed.{i}.weight": (rows, cols), f"time_embed.{i}.bias": (rows,)}
    shapes["feature_net.0.weight"] = (h, f + 3 * (2 * p + 1) + t)
    shapes["feature_net.0.bias"] = (h,)
    for j in range(1, d):
        shapes |= {f"feature_net.{2 * j}.weight": (h, h), f"feature_net.{2 * j}.bias": (h,)}
    for head, k in _HEAD_OUTPUTS.items():
        shapes |= {f"{head}.0.weight": (g, h), f"{head}.0.bias": (g,)}
        shapes |= {f"{head}.2.weight": (k, g), f"{head}.2.bias": (k,)}
    return shapes


def _short(key: str) -> str:
    return key if len(key) <= _KEY_CHARS else key[:_KEY_CHARS] + "..."


def _listing(items: list[str], sep: str = ", ") -> str:
    """The first ``_LISTED`` items, then how many more."""
    shown = sep.join(items[:_LISTED])
    more = len(items) - _LISTED
    return shown + (f"{sep}... and {more} more" if more > 0 else "")


def _check_layers(given: Mapping[str, Any], depth: int) -> None:
    """The feature net's layer indices in ``given`` must be exactly ``0, 2, ..., 2(depth -
    1)`` for the ``depth`` inferred from them (the largest), which must be at most
    ``_MAX_INFERRED_DEPTH``: one stray key must not make a 100,000-layer module."""
    found: dict[int, str] = {}
    for key in given:
        if match := _LAYER.fullmatch(key):
            index = int(match.group(1))
            found[index] = min(found.get(index, key), key)
    if not found:
        return
    top = max(found)
    advice = "pass depth=... explicitly to load such a network"
    if depth > _MAX_INFERRED_DEPTH:
        raise StateDictMismatchError(
            f"state_dict: {_short(found[top])} implies a feature net of depth {depth} "
            f"(Linear layers feature_net.0, .2, ..., .{2 * (depth - 1)}), above "
            f"{_MAX_INFERRED_DEPTH}, the deepest inferred from the keys (the released "
            f"network has 6); {advice}"
        )
    layers = sorted(found)
    if layers != list(range(0, 2 * depth, 2)):
        shown = _listing([str(index) for index in layers])
        raise StateDictMismatchError(
            f"state_dict: feature_net: layer indices [{shown}] are not 0, 2, ..., {top} "
            "(Linear layers sit at even indices, without gaps), so the depth cannot be "
            f"inferred from them; {advice} (absent layers are then missing keys)"
        )


def _prefix_hint(state_dict: Mapping[str, Any], prefix: str) -> str:
    anchor = "feature_net.0.weight"
    found = sorted(
        {k[: -len(anchor)] for k in state_dict if isinstance(k, str) and k.endswith(anchor)}
    )
    hint = f"; did you mean prefix={found[0]!r}?" if found else ""
    return f"no key starts with prefix {prefix!r}{hint}"


def _mismatch_message(sizes: dict[str, int], prefix: str, lines: list[str]) -> str:
    arch = ", ".join(f"{name}={sizes[name]}" for name in _ARCHITECTURE)
    where = f" under prefix {prefix!r}" if prefix else ""
    return (
        f"state_dict: does not match the official DeGO deformation module ({arch}){where}:\n  "
        + "\n  ".join(lines)
    )


@typechecked
def official_names(depth: int) -> dict[str, str]:
    """Official parameter name -> ours for a feature net of ``depth`` layers (all but the
    first layer's weight, ``feature_net.0.weight``, split column-wise into
    ``input_static.weight`` and ``input_time.weight``; the frequency buffers have none)."""
    names = {f"time_embed.{i}.{p}": f"time_embedding.{i}.{p}" for i in (0, 2) for p in _WB}
    names["feature_net.0.bias"] = "input_static.bias"
    for j in range(1, depth):
        for p in _WB:
            names[f"feature_net.{2 * j}.{p}"] = f"trunk.{2 * (j - 1)}.{p}"
    for official, ours in _OFFICIAL_HEADS.items():
        for i in (0, 2):
            for p in _WB:
                names[f"{official}.{i}.{p}"] = f"{ours}.{i}.{p}"
    return names


def _our_depth(ours: Mapping[str, Any]) -> int:
    """The feature-net depth of our parameters: the first layer plus the trunk's Linears."""
    return 1 + sum(1 for key in ours if re.fullmatch(r"trunk\.\d+\.weight", key))


@typechecked
def official_tensors(
    ours: Mapping[str, Tensor], pos_levels: int, time_levels: int
) -> dict[str, Tensor]:
    """The official module's state dict, in its order, from our parameters ``ours`` (an
    ``official`` preset :class:`~dego.DecoupledDeformation`'s ``named_parameters()``);
    detached, the first layer's weight a new concatenation."""
    weight = ours["input_static.weight"]
    result = {
        name: 2.0 ** torch.arange(levels, dtype=weight.dtype, device=weight.device)
        for name, levels in zip(_OFFICIAL_BUFFERS, (pos_levels, time_levels), strict=True)
    }
    for official, name in official_names(_our_depth(ours)).items():
        if official == "feature_net.0.bias":  # the whole first layer goes in order
            result["feature_net.0.weight"] = torch.cat(
                [ours["input_static.weight"], ours["input_time.weight"]], 1
            ).detach()
        result[official] = ours[name].detach()
    return result


@typechecked
def official_state_dict(
    ours: Mapping[str, Tensor], pos_levels: int, time_levels: int, prefix: str
) -> dict[str, Tensor]:
    """:func:`official_tensors` with ``prefix`` (a missing trailing ``"."`` added) on every key."""
    prefix = _normalized_prefix(prefix)
    tensors = official_tensors(ours, pos_levels, time_levels)
    return {prefix + key: value for key, value in tensors.items()}


@typechecked
def from_official_tensors(
    official: Mapping[str, Tensor], static_dim: int, depth: int
) -> dict[str, Tensor]:
    """Our parameter name -> tensor for each official key in ``official`` (prefix removed),
    for a feature net of ``depth`` layers whose first layer takes ``static_dim`` per-Gaussian
    input columns; keys without a parameter (the frequency buffers) are left out. Detached."""
    names = official_names(depth)
    ours: dict[str, Tensor] = {}
    for key, value in official.items():
        value = value.detach()
        if key == "feature_net.0.weight":
            ours["input_static.weight"] = value[:, :static_dim]
            ours["input_time.weight"] = value[:, static_dim:]
        elif key in names:
            ours[names[key]] = value
    return ours


@dataclasses.dataclass(frozen=True)
class OfficialWeights:
    """What :func:`read_official_state_dict` found in an official state dict.

    Attributes:
        sizes: the :class:`~dego.DecoupledDeformation` size arguments (``feature_dim``,
            ``hidden_dim``, ``depth``, ``time_dim``, ``pos_levels``, ``time_levels``,
            ``head_hidden``).
        tensors: official key (prefix removed) -> value, for every key that fits, in the
            official module's order.
        skipped: ``strict=False`` only: the report of the keys that did not fit (``None``
            when all did).
    """

    sizes: dict[str, int]
    tensors: dict[str, Tensor]
    skipped: str | None


@typechecked
def read_official_state_dict(
    state_dict: Mapping[str, Any], prefix: str, strict: bool, kwargs: dict[str, Any]
) -> OfficialWeights:
    """The checks of :meth:`DecoupledDeformation.from_official_state_dict`, on the keys and
    shapes alone (nothing is built): the sizes (popped from ``kwargs``, as is ``preset``),
    the tensors that fit, and the report of the others.

    Raises:
        StateDictMismatchError: keys do not match and ``strict``, or sizes that cannot be
            inferred and are not given.
        TypeError: ``state_dict`` is not a mapping, ``prefix`` not a str, ``strict`` not a
            bool.
        ValueError: ``preset`` other than ``"official"`` or ``head_hidden`` other than
            ``hidden_dim`` in ``kwargs``; a size out of range.
    """
    if not isinstance(state_dict, Mapping):
        raise TypeError(f"state_dict: expected a mapping, got {type(state_dict).__name__}")
    if isinstance(state_dict.get("state_dict"), Mapping):  # a whole checkpoint file
        state_dict = state_dict["state_dict"]
    if not isinstance(strict, bool):
        raise TypeError(f"strict: expected a bool, got {type(strict).__name__}")
    if kwargs.pop("preset", "official") != "official":
        raise ValueError("preset: official checkpoints load only into preset='official'")
    prefix = _normalized_prefix(prefix)
    given = {
        key[len(prefix) :]: value
        for key, value in state_dict.items()
        if isinstance(key, str) and key.startswith(prefix)
    }
    depth_inferred = "depth" not in kwargs
    sizes, unknown = _infer_official_sizes(given, kwargs)
    if sizes.get("head_hidden", sizes["hidden_dim"]) != sizes["hidden_dim"]:
        raise ValueError(
            f"head_hidden: the official heads are hidden_dim = {sizes['hidden_dim']} wide, "
            f"got head_hidden={sizes['head_hidden']}"
        )
    sizes["head_hidden"] = sizes["hidden_dim"]
    # Everything below is checked on the keys and shapes alone; the caller builds the
    # module last, once its size is known to be sane.
    for name, low in [
        ("feature_dim", 0),
        ("pos_levels", 0),
        ("time_levels", 0),
        ("time_dim", 1),
        ("hidden_dim", 1),
        ("depth", 1),
    ]:
        check_int(name, sizes[name], low)
    if depth_inferred:
        _check_layers(given, sizes["depth"])
    expected = _official_shapes(sizes)
    count = sum(math.prod(shape) for shape in expected.values())
    check_memory(
        "from_official_state_dict",
        12 * count,  # float32 parameters, then a copy in the state dict's dtype
        f"{count} parameters: depth {sizes['depth']}, hidden_dim {sizes['hidden_dim']}",
    )

    missing = [key for key in expected if key not in given]
    unexpected = [key for key in given if key not in expected]
    problems: dict[str, str] = {}  # official key -> what is wrong with its value
    for key, want in expected.items():
        if key not in given:
            continue
        value = given[key]
        if not isinstance(value, Tensor) or not value.is_floating_point():
            got = type(value).__name__ if not isinstance(value, Tensor) else value.dtype
            problems[key] = f"expected a floating-point tensor, got {got}"
        elif tuple(value.shape) != want:
            problems[key] = f"shape {tuple(value.shape)}, expected {want}"
        elif key in _OFFICIAL_BUFFERS:
            powers = 2.0 ** torch.arange(want[0], dtype=torch.float64)
            if not torch.equal(value.detach().cpu().double(), powers):
                want_text, got_text = (
                    _listing(list(map(str, v.tolist()))) for v in (powers, value)
                )
                problems[key] = f"expected the frequencies 2^k = [{want_text}], got [{got_text}]"
    lines = []
    if missing:
        lines.append(f"missing ({len(missing)}): {_listing([prefix + k for k in missing])}")
    if unexpected:
        notes = {
            key: f" ({_UNSUPPORTED_OFFICIAL[key.split('.')[0]]})"
            for key in unexpected
            if key.split(".")[0] in _UNSUPPORTED_OFFICIAL
        }
        lines.append(
            f"unexpected ({len(unexpected)}): "
            + _listing([_short(prefix + k) + notes.get(k, "") for k in unexpected])
        )
    if problems:
        lines.append(
            f"mis-shaped or invalid ({len(problems)}):\n    "
            + _listing([f"{prefix}{k}: {why}" for k, why in problems.items()], "\n    ")
        )
    if not given:
        lines.append(_prefix_hint(state_dict, prefix))
    if unknown and not strict:
        lines.append(f"cannot infer {', '.join(unknown)} from the state dict; pass them")
        raise StateDictMismatchError(_mismatch_message(sizes, prefix, lines))
    skipped = _mismatch_message(sizes, prefix, lines) if lines else None
    if skipped is not None and strict:
        raise StateDictMismatchError(skipped)
    fitting = {k: given[k] for k in expected if k in given and k not in problems}
    return OfficialWeights(sizes=sizes, tensors=fitting, skipped=skipped)


__all__ = [
    "OFFICIAL_CHECKPOINT_PREFIX",
    "OfficialWeights",
    "StateDictMismatchError",
    "from_official_tensors",
    "official_names",
    "official_state_dict",
    "official_tensors",
    "read_official_state_dict",
]
