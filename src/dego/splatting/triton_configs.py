"""Launch settings of the Triton kernels (:mod:`dego.splatting.triton_kernels`), per GPU
family, and the opt-in autotuner for GPUs the table does not know.

The table holds one :class:`LaunchConfig` per family: ``"sm_90"`` (H100, H200), ``"sm_80"``
(A100), ``"gfx942"`` (MI300) and ``"cpu"`` (Triton's interpreter, which runs each
program in Python: a whole tile per backward program there). The NVIDIA entries are
those at which Triton's compiler reports no register spill (``tests/splatting/
test_triton_targets.py`` checks it; docs/performance.md lists the registers); none was
timed on a GPU yet. A GPU without an entry runs :data:`SAFE` and is warned once, as is a
GPU whose entry does not fit it (the compiler runs out of registers or shared memory).

``autotune(True)`` (or ``DEGO_TRITON_AUTOTUNE=1`` in the environment) times a few settings
on the first call for each channel count and keeps the fastest; every buffer the backward
accumulates into is zeroed before each trial (``reset_to_zero``). Tests never time
anything: one runs the autotuner's path in Triton's interpreter with its timer replaced.
Importing this module does not import triton.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import torch

_POWERS = (16, 32, 64, 128, 256)
ACCUMULATED = (
    "grad_means_ptr",
    "grad_conics_ptr",
    "grad_opacities_ptr",
    "grad_colors_ptr",
    "absgrad_ptr",
)
"""The arguments the backward accumulates into with atomics: an autotuner must zero them
before every trial (``reset_to_zero``)."""


@dataclasses.dataclass(frozen=True)
class LaunchConfig:
    """How the kernels launch on one GPU family.

    ``forward_warps`` / ``backward_warps``: warps per program; ``channels``: channels per
    forward program (Triton's ``BLOCK_D``); ``pixels``: a tile's pixels per backward
    program (``BLOCK_P``: fewer pixels, fewer registers, more atomics);
    ``bucket``: list positions per backward program;
    ``maxnreg``: a register cap per thread for NVIDIA's compiler, or ``None``.
    """

    forward_warps: int = 8
    backward_warps: int = 8
    channels: int = 32
    pixels: int = 32
    bucket: int = 32
    maxnreg: int | None = None

    def __post_init__(self) -> None:
        for name in ("forward_warps", "backward_warps"):
            value = getattr(self, name)
            if not (_integer(value) and value in (1, 2, 4, 8, 16, 32)):
                raise ValueError(
                    f"LaunchConfig: {name}: expected 1, 2, 4, 8, 16 or 32, got {value!r}"
                )
        for name in ("channels", "pixels", "bucket"):
            value = getattr(self, name)
            if not (_integer(value) and value in _POWERS):
                raise ValueError(
                    f"LaunchConfig: {name}: expected a power of two from 16 to 256, got {value!r}"
                )
        if self.maxnreg is not None and not (_integer(self.maxnreg) and 32 <= self.maxnreg <= 255):
            raise ValueError(
                f"LaunchConfig: maxnreg: expected None or an integer from 32 to 255, "
                f"got {self.maxnreg!r}"
            )

    def options(self, backward: bool) -> dict[str, Any]:
        """The launch's meta-parameters and compiler options."""
        options: dict[str, Any] = {
            "num_warps": self.backward_warps if backward else self.forward_warps,
        }
        options.update({"BLOCK_P": self.pixels} if backward else {"BLOCK_D": self.channels})
        if self.maxnreg is not None:
            options["maxnreg"] = self.maxnreg
        return options


def _integer(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


SAFE = LaunchConfig(forward_warps=4, channels=16)
"""For a GPU the table does not know, or whose entry does not fit it: small programs."""

TABLE: dict[str, LaunchConfig] = {
    "sm_90": LaunchConfig(),
    "sm_80": LaunchConfig(),
    "gfx942": LaunchConfig(forward_warps=4, backward_warps=4),  # 64-lane wavefronts
    "cpu": LaunchConfig(pixels=256),
}
"""The shipped settings per family; :func:`set_launch_config` changes them."""

_shipped = dict(TABLE)
_warned: set[str] = set()
_unfit: set[str] = set()  # devices whose entry the compiler refused: SAFE from then on
_autotune = os.environ.get("DEGO_TRITON_AUTOTUNE", "") not in ("", "0")
_tuned: dict[Any, Any] = {}


def family(device: torch.device) -> str:
    """The table's key for ``device``: ``"sm_<major><minor>"`` on NVIDIA, the gfx name on
    AMD, ``"cpu"`` for Triton's interpreter."""
    if device.type != "cuda":
        return device.type
    properties = torch.cuda.get_device_properties(device)
    if getattr(torch.version, "hip", None):
        return str(getattr(properties, "gcnArchName", "gfx")).split(":")[0]
    return f"sm_{properties.major}{properties.minor}"


def set_launch_config(name: str, config: LaunchConfig | None) -> None:
    """Use ``config`` for the GPU family ``name`` (``"sm_89"``, ``"gfx90a"``...); ``None``
    restores the shipped entry (or removes one the table did not ship)."""
    if not isinstance(name, str) or not name:
        raise ValueError(
            f"set_launch_config: name: expected a family such as 'sm_89', got {name!r}"
        )
    if config is not None and not isinstance(config, LaunchConfig):
        raise TypeError(
            f"set_launch_config: config: expected a LaunchConfig or None, got "
            f"{type(config).__name__}"
        )
    if config is None:
        TABLE.pop(name, None)
        if name in _shipped:
            TABLE[name] = _shipped[name]
    else:
        TABLE[name] = config
    _unfit.clear()


def autotune(enabled: bool = True) -> None:
    """Time a few launch settings on each kernel's first call per channel count and keep
    the fastest (instead of the table); the first calls are slower."""
    global _autotune
    if not isinstance(enabled, bool):
        raise TypeError(f"autotune: enabled: expected a bool, got {type(enabled).__name__}")
    _autotune = enabled


def autotuning() -> bool:
    """Whether :func:`autotune` is on."""
    return _autotune


def config_for(device: torch.device) -> LaunchConfig:
    """The launch settings for ``device``: its table entry, else :data:`SAFE` (warned once)."""
    key = family(device)
    entry = TABLE.get(key)
    if entry is not None and str(device) not in _unfit:
        return entry
    if entry is None and key not in _warned:
        _warned.add(key)
        warnings.warn(
            f"backend='triton': no launch configuration for {key} ({_name(device)}); using a "
            "safe default. dego.splatting.triton_configs.autotune() tunes for this GPU, "
            "set_launch_config() sets one",
            RuntimeWarning,
            stacklevel=6,
        )
    return SAFE


def _name(device: torch.device) -> str:
    return torch.cuda.get_device_name(device) if device.type == "cuda" else str(device)


def run(
    kernel: Any,
    grid: Callable[[dict[str, Any]], tuple[int, ...]],
    args: Sequence[Any],
    constants: dict[str, Any],
    *,
    device: torch.device,
    bucket: int | None = None,
    zeroed: Sequence[torch.Tensor] = (),
    options: dict[str, Any] | None = None,
) -> None:
    """Launch ``kernel`` with ``device``'s settings: a backward kernel when ``bucket`` (its
    list positions per program) is given; ``zeroed``: the buffers it accumulates into."""
    backward = bucket is not None
    extra = {**(options or {}), **({"BUCKET": bucket} if backward else {})}
    if _autotune and device.type == "cuda":
        _autotuned(kernel, backward)[grid](*args, **constants, **extra)
        return
    config = config_for(device)
    if device.type != "cuda":
        config = dataclasses.replace(config, maxnreg=None)
    try:
        kernel[grid](*args, **constants, **config.options(backward), **extra)
    except Exception as error:
        if config == SAFE or not _out_of_resources(error):
            raise
        _unfit.add(str(device))
        warnings.warn(
            f"backend='triton': the launch configuration for {family(device)} does not fit "
            f"{_name(device)} ({type(error).__name__}); using a safe default from now on",
            RuntimeWarning,
            stacklevel=5,
        )
        for tensor in zeroed:
            tensor.zero_()
        kernel[grid](*args, **constants, **SAFE.options(backward), **extra)


def _out_of_resources(error: Exception) -> bool:
    try:
        from triton.runtime.errors import OutOfResources
    except ImportError:  # no triton: nothing it launched can have run out
        return False
    return isinstance(error, OutOfResources)


def _autotuned(kernel: Any, backward: bool) -> Any:
    """``kernel`` under ``triton.autotune`` over warps and channels (forward) or pixels
    (backward), keyed on the channel count, the tile size and the pass, with every output it
    accumulates into (of :data:`ACCUMULATED`) reset to zero."""
    import triton

    if kernel not in _tuned:
        name, sizes = ("BLOCK_P", (32, 64, 128)) if backward else ("BLOCK_D", (16, 32, 64))
        configs = [triton.Config({name: n}, num_warps=w) for w in (4, 8) for n in sizes]
        zero = [n for n in kernel.arg_names if n in ACCUMULATED]
        key = ["dim", "S", "SUMS"] if backward else ["dim", "S"]  # each pass its own choice
        _tuned[kernel] = triton.autotune(configs, key=key, reset_to_zero=zero)(kernel)
    return _tuned[kernel]


__all__ = [
    "ACCUMULATED",
    "SAFE",
    "TABLE",
    "LaunchConfig",
    "autotune",
    "autotuning",
    "config_for",
    "family",
    "run",
    "set_launch_config",
]
