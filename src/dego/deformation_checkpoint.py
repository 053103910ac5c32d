"""Official DeGO deformation checkpoints <-> :class:`dego.DecoupledDeformation`.

The key mapping, size inference and mismatch reporting behind
:meth:`DecoupledDeformation.from_official_state_dict` and
:meth:`DecoupledDeformation.to_official_state_dict` (official preset).
"""

from __future__ import annotations

import math
import re
import warnings
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from dego._checks import check_int
from dego._policy import check_memory

if TYPE_CHECKING:
    from dego.deformation import DecoupledDeformation

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

    freqs = {name: _shape(given, name, 1) for name in _OFFICIAL_BUFFERS}
    time_in = _shape(given, "time_embed.0.weight", 2)
    time_out = _shape(given, "time_embed.2.weight", 2)
    first_layer = _shape(given, "feature_net.0.weight", 2)
    first_bias = _shape(given, "feature_net.0.bias", 1)
    indices = [
        int(m.group(1)) for key in given if (m := re.fullmatch(r"feature_net\.(\d+)\.\w+", key))
    ]
    inferred = {
        "pos_levels": first(freqs["pos_enc_freqs"] and freqs["pos_enc_freqs"][0]),
        "time_levels": first(
            freqs["time_enc_freqs"] and freqs["time_enc_freqs"][0],
            (time_in[1] - 1) // 2 if time_in and time_in[1] % 2 else None,
        ),
        "time_dim": first(time_in and time_in[0], time_out and time_out[0]),
        "hidden_dim": first(first_layer and first_layer[0], first_bias and first_bias[0]),
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


def official_names(module: DecoupledDeformation) -> dict[str, str]:
    """Official parameter name -> ours (except the split first layer's weight)."""
    names = {f"time_embed.{i}.{p}": f"time_embedding.{i}.{p}" for i in (0, 2) for p in _WB}
    names["feature_net.0.bias"] = "input_static.bias"
    depth = 1 + (0 if module.trunk is None else (len(module.trunk) + 1) // 2)
    for j in range(1, depth):
        for p in _WB:
            names[f"feature_net.{2 * j}.{p}"] = f"trunk.{2 * (j - 1)}.{p}"
    for official, ours in _OFFICIAL_HEADS.items():
        for i in (0, 2):
            for p in _WB:
                names[f"{official}.{i}.{p}"] = f"{ours}.{i}.{p}"
    return names


def official_tensors(module: DecoupledDeformation) -> dict[str, Tensor]:
    """The official module's state dict, in its order, from this module's parameters."""
    ours = dict(module.named_parameters())
    weight = module.input_static.weight
    result = {
        name: 2.0 ** torch.arange(levels, dtype=weight.dtype, device=weight.device)
        for name, levels in zip(
            _OFFICIAL_BUFFERS, (module.pos_levels, module.time_levels), strict=True
        )
    }
    for official, name in official_names(module).items():
        if official == "feature_net.0.bias":  # the whole first layer goes in order
            result["feature_net.0.weight"] = torch.cat(
                [module.input_static.weight, module.input_time.weight], 1
            ).detach()
        result[official] = ours[name].detach()
    return result


def export_official_state_dict(module: DecoupledDeformation, prefix: str) -> dict[str, Tensor]:
    """The body of :meth:`DecoupledDeformation.to_official_state_dict`."""
    if module.preset != "official":
        raise ValueError(
            f"preset: only an 'official' preset module has an official state dict, this one "
            f"is {module.preset!r} (a different network: separate nonrigid head, "
            "per-Gaussian mask)"
        )
    prefix = _normalized_prefix(prefix)
    head_hidden = module.mask_head[0].out_features
    hidden = module.input_static.out_features
    if head_hidden != hidden:
        raise ValueError(
            f"head_hidden: the official heads are hidden_dim = {hidden} wide, this module's "
            f"are {head_hidden}"
        )
    differences = [
        f"{name}={value}"
        for name, value, default in [
            ("time_scale", module.time_scale, 1.0),
            ("pos_scale", module.pos_scale, 1.0),
            ("fixed_mask", module.fixed_mask, None),
        ]
        if value != default
    ]
    if differences:
        warnings.warn(
            f"to_official_state_dict: the official module has no {', '.join(differences)}; "
            "it will load these weights but compute something else",
            stacklevel=3,
        )
    return {prefix + key: value for key, value in official_tensors(module).items()}


def load_official_state_dict(
    cls: type[DecoupledDeformation],
    state_dict: Mapping[str, Any],
    prefix: str,
    strict: bool,
    kwargs: dict[str, Any],
) -> DecoupledDeformation:
    """The body of :meth:`DecoupledDeformation.from_official_state_dict`."""
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
    # Everything below is checked on the keys and shapes alone; the module is built last,
    # once its size is known to be sane.
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
    if lines:
        message = _mismatch_message(sizes, prefix, lines)
        if strict:
            raise StateDictMismatchError(message)
        warnings.warn(
            f"from_official_state_dict(strict=False) skipped keys; the parameters they "
            f"would fill keep their initialisation. {message}",
            stacklevel=3,
        )
    module = cls(**sizes, preset="official", **kwargs)  # type: ignore[arg-type]

    # dtype and device from the first layer (else any floating tensor that fits)
    fitting = [k for k in expected if k in given and k not in problems]
    reference = next((given[k] for k in ["feature_net.0.weight", *fitting] if k in fitting), None)
    if reference is not None:
        module = module.to(dtype=reference.dtype, device=reference.device)
    params = dict(module.named_parameters())
    names = official_names(module)
    static_dim = module.input_static.in_features
    with torch.no_grad():
        for key in fitting:
            value = given[key].detach()
            if key == "feature_net.0.weight":
                params["input_static.weight"].copy_(value[:, :static_dim])
                params["input_time.weight"].copy_(value[:, static_dim:])
            elif key in names:
                params[names[key]].copy_(value)
    return module


__all__ = ["OFFICIAL_CHECKPOINT_PREFIX", "StateDictMismatchError"]
