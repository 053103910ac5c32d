"""``backend="triton"``: the torch path's projection, then tile binning with one ``torch.sort``
of int64 keys and Triton kernels for the compositing (:mod:`dego.splatting.triton_kernels`),
forward and backward. No C++ build: Triton compiles for the GPU present at first use.

Needs ``pip install "dego-occupancy[triton]"`` and CUDA tensors (NVIDIA, or AMD through
Triton's ROCm backend), float32 (float16 / bfloat16 inputs are computed in float32);
float64 stays on the torch path. With ``TRITON_INTERPRET=1`` set before dego first uses
Triton, ``backend="triton"`` also runs on CPU tensors through Triton's interpreter (slow:
for tests). ``backend="auto"`` takes this path on CUDA when triton is installed and its
kernels compiled on the device (a one-time probe; a failure warns once and keeps the torch
path), and never on CPU.

Inside ``torch.compile`` the binning and the compositing are custom operators
(``dego::triton_tile_lists``, ``dego::triton_composite``) with fake implementations, so
dynamo traces through them without a graph break; ``absgrad`` needs a Python callback in
backward and runs eagerly.
"""

from __future__ import annotations

import importlib.util
import math
import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from dego._typing import _is_compiling
from dego.gaussians import GaussianSet
from dego.splatting.composite import CompositeRules
from dego.splatting.tiles import TileLists, build_tile_lists
from dego.splatting.types import SplatConfig

INSTALL = "pip install 'dego-occupancy[triton]'"

# Per device ("cuda:0", "cpu"): None when the kernels compiled and ran there, else why not.
_PROBED: dict[str, str | None] = {}


def installed() -> bool:
    """Whether triton can be imported."""
    return importlib.util.find_spec("triton") is not None


def interpreting() -> bool:
    """Whether dego's kernels run in Triton's interpreter (``TRITON_INTERPRET=1`` was set
    when they were first imported): then they take CPU tensors."""
    from dego.splatting import triton_kernels

    return type(triton_kernels._forward_kernel).__name__ == "InterpretedFunction"


def usable(gaussians: GaussianSet, config: SplatConfig, *, strict: bool) -> bool:
    """Whether the Triton kernels render this call. float64 never does (the torch path
    renders it, also under ``backend="triton"``); with ``strict`` (``backend="triton"``)
    every other reason is raised: ``ImportError`` without triton, ``ValueError`` for a
    device it cannot run on, ``RuntimeError`` when the kernels fail to compile there."""
    if gaussians.dtype == torch.float64:
        return False
    if not installed():
        if strict:
            raise ImportError(f"backend: 'triton' needs triton ({INSTALL})")
        return False
    device = gaussians.device
    if device.type != "cuda" and not (strict and device.type == "cpu" and interpreting()):
        if strict:
            raise ValueError(
                f"backend: 'triton' needs CUDA tensors, got {device} (on CPU, the torch path "
                "renders with backend='torch' or 'auto'; Triton's interpreter runs the kernels "
                "on CPU when TRITON_INTERPRET=1 is set before dego first uses Triton)"
            )
        return False
    key = str(device)
    if key not in _PROBED:
        if _is_compiling():  # probed at the first eager call; a compiled first call assumes it
            return True
        _PROBED[key] = _probe(device)
    failure = _PROBED[key]
    if failure is None:
        return True
    if strict:
        raise RuntimeError(f"backend: 'triton' cannot run on {_device_name(device)}: {failure}")
    return False


def _device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)})"
    return str(device)


@torch._dynamo.disable
def _probe(device: torch.device) -> str | None:
    """Compile and run both kernels once on a tiny input; the error text if they fail."""
    try:
        means2d = torch.tensor([[8.0, 8.0]], device=device, requires_grad=True)
        conics = torch.tensor([[0.1, 0.0, 0.1]], device=device, requires_grad=True)
        opacities = torch.tensor([0.5], device=device, requires_grad=True)
        colors = torch.ones(1, 1, device=device, requires_grad=True)
        lists = TileLists(
            gaussians=torch.zeros(1, dtype=torch.int64, device=device),
            starts=torch.zeros(1, dtype=torch.int64, device=device),
            counts=torch.ones(1, dtype=torch.int64, device=device),
            tiles_x=1,
            tiles_y=1,
        )
        rules = CompositeRules(0.999, 1 / 255, 1e-4)
        tiles, transmittance = _Composite.apply(
            means2d, conics, opacities, colors, lists, 16, rules, None
        )
        (tiles.sum() + transmittance.sum()).backward()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
    except Exception as error:  # any failure of the compiler or the driver
        message = f"{type(error).__name__}: {error}".strip().splitlines()[0][:300]
        warnings.warn(
            f"backend='auto': the Triton kernels failed on {_device_name(device)} ({message}); "
            "rendering with the torch path",
            RuntimeWarning,
            stacklevel=2,
        )
        return message
    return None


def bin_and_composite(
    means2d: Tensor,
    extents: Tensor,
    depths: Tensor,
    conics: Tensor,
    max_sigma: Tensor,
    opacities: Tensor,
    colors: Tensor,
    size: tuple[int, int],
    config: SplatConfig,
    absgrad_sink: Callable[[Tensor], None] | None,
    compositing_means2d: Tensor,
) -> tuple[Tensor, Tensor, TileLists]:
    """Tile lists and composited tiles, as the torch path's ``_bin_and_composite`` returns
    them. ``means2d``, ``extents``, ``depths``, ``conics``, ``max_sigma``: ``(I, N, ...)``
    per image for the binning; ``compositing_means2d`` ``(M, 2)``, ``opacities`` ``(M,)``,
    ``colors`` ``(M, D)`` what the compositing reads and differentiates."""
    height, width = size
    pairs, starts, counts = torch.ops.dego.triton_tile_lists(
        means2d.detach().float(),
        extents.detach().float(),
        depths.detach().float(),
        conics.detach().float(),
        max_sigma.detach().float(),
        height,
        width,
        config.tile_size,
    )
    lists = TileLists(
        gaussians=pairs,
        starts=starts,
        counts=counts,
        tiles_x=math.ceil(width / config.tile_size),
        tiles_y=math.ceil(height / config.tile_size),
    )
    rules = CompositeRules(config.max_alpha, config.alpha_min, config.transmittance_min)
    tensors = (
        compositing_means2d.contiguous(),
        conics.reshape(-1, 3).contiguous(),
        opacities.contiguous(),
        colors.contiguous(),
    )
    if absgrad_sink is not None:
        tiles, transmittance = _composite_with_absgrad(
            *tensors, lists, config.tile_size, rules, absgrad_sink
        )
    else:
        tiles, transmittance, _ = torch.ops.dego.triton_composite(
            *tensors,
            pairs,
            starts,
            counts,
            lists.tiles_x,
            lists.tiles_x * lists.tiles_y,
            config.tile_size,
            *_rules(rules),
        )
    return tiles, transmittance, lists


def _rules(rules: CompositeRules) -> tuple[float, float, float]:
    return float(rules.max_alpha), float(rules.alpha_min), float(rules.transmittance_min)


class _Composite(torch.autograd.Function):
    """The compositing as one eager autograd node whose backward can hand the summed
    absolute means2d gradients to a callback (``absgrad``)."""

    @staticmethod
    def forward(
        ctx: Any,
        means2d: Tensor,
        conics: Tensor,
        opacities: Tensor,
        colors: Tensor,
        lists: TileLists,
        tile_size: int,
        rules: CompositeRules,
        absgrad_sink: Callable[[Tensor], None] | None,
    ) -> tuple[Tensor, Tensor]:
        from dego.splatting import triton_kernels

        per_image = lists.tiles_x * lists.tiles_y
        tiles, transmittance, stop = triton_kernels.forward(
            means2d,
            conics,
            opacities,
            colors,
            lists.gaussians,
            lists.starts,
            lists.counts,
            lists.tiles_x,
            per_image,
            tile_size,
            _rules(rules),
        )
        ctx.save_for_backward(
            means2d, conics, opacities, colors, lists.gaussians, lists.starts, transmittance, stop
        )
        ctx.tiles_x, ctx.per_image, ctx.rules, ctx.sink = (
            lists.tiles_x,
            per_image,
            _rules(rules),
            absgrad_sink,
        )
        ctx.mark_non_differentiable(stop)
        return tiles, transmittance

    @staticmethod
    def backward(ctx: Any, grad_tiles: Tensor, grad_t: Tensor) -> tuple[Tensor | None, ...]:
        from dego.splatting import triton_kernels

        grads = triton_kernels.backward(
            *ctx.saved_tensors,
            grad_tiles,
            grad_t,
            ctx.tiles_x,
            ctx.per_image,
            ctx.rules,
            ctx.sink is not None,
        )
        if ctx.sink is not None:
            ctx.sink(grads[4])
        return (*grads[:4], None, None, None, None)


@torch._dynamo.disable
def _composite_with_absgrad(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    lists: TileLists,
    tile_size: int,
    rules: CompositeRules,
    absgrad_sink: Callable[[Tensor], None],
) -> tuple[Tensor, Tensor]:
    return _Composite.apply(means2d, conics, opacities, colors, lists, tile_size, rules, absgrad_sink)


# The custom operators: what torch.compile sees. Each calls the same kernels.


@torch.library.custom_op("dego::triton_tile_lists", mutates_args=())
def _tile_lists(
    means2d: Tensor,
    extents: Tensor,
    depths: Tensor,
    conics: Tensor,
    max_sigma: Tensor,
    height: int,
    width: int,
    tile_size: int,
) -> tuple[Tensor, Tensor, Tensor]:
    lists = build_tile_lists(
        means2d,
        extents,
        depths,
        (height, width),
        tile_size,
        conics=conics,
        max_sigma=max_sigma,
        keyed=True,
    )
    return lists.gaussians, lists.starts, lists.counts


@_tile_lists.register_fake
def _(
    means2d: Tensor,
    extents: Tensor,
    depths: Tensor,
    conics: Tensor,
    max_sigma: Tensor,
    height: int,
    width: int,
    tile_size: int,
) -> tuple[Tensor, Tensor, Tensor]:
    pairs = torch.library.get_ctx().new_dynamic_size()
    tiles = depths.shape[0] * math.ceil(width / tile_size) * math.ceil(height / tile_size)
    index = {"dtype": torch.int64, "device": depths.device}
    return torch.empty(pairs, **index), torch.empty(tiles, **index), torch.empty(tiles, **index)


@torch.library.custom_op("dego::triton_composite", mutates_args=())
def _composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    pairs: Tensor,
    starts: Tensor,
    counts: Tensor,
    tiles_x: int,
    tiles_per_image: int,
    tile_size: int,
    max_alpha: float,
    alpha_min: float,
    transmittance_min: float,
) -> tuple[Tensor, Tensor, Tensor]:
    from dego.splatting import triton_kernels

    return triton_kernels.forward(
        means2d,
        conics,
        opacities,
        colors,
        pairs,
        starts,
        counts,
        tiles_x,
        tiles_per_image,
        tile_size,
        (max_alpha, alpha_min, transmittance_min),
    )


@_composite.register_fake
def _(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    pairs: Tensor,
    starts: Tensor,
    counts: Tensor,
    tiles_x: int,
    tiles_per_image: int,
    tile_size: int,
    max_alpha: float,
    alpha_min: float,
    transmittance_min: float,
) -> tuple[Tensor, Tensor, Tensor]:
    tiles, size = counts.shape[0], tile_size
    return (
        colors.new_empty(tiles, size, size, colors.shape[1]),
        colors.new_empty(tiles, size, size),
        torch.empty(tiles, size, size, dtype=torch.int32, device=colors.device),
    )


@torch.library.custom_op("dego::triton_composite_backward", mutates_args=())
def _composite_backward(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    pairs: Tensor,
    starts: Tensor,
    transmittance: Tensor,
    stop: Tensor,
    grad_tiles: Tensor,
    grad_transmittance: Tensor,
    tiles_x: int,
    tiles_per_image: int,
    max_alpha: float,
    alpha_min: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    from dego.splatting import triton_kernels

    grads = triton_kernels.backward(
        means2d,
        conics,
        opacities,
        colors,
        pairs,
        starts,
        transmittance,
        stop,
        grad_tiles,
        grad_transmittance,
        tiles_x,
        tiles_per_image,
        (max_alpha, alpha_min, 0.0),
        False,
    )
    return grads[0], grads[1], grads[2], grads[3]


@_composite_backward.register_fake
def _(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    pairs: Tensor,
    starts: Tensor,
    transmittance: Tensor,
    stop: Tensor,
    grad_tiles: Tensor,
    grad_transmittance: Tensor,
    tiles_x: int,
    tiles_per_image: int,
    max_alpha: float,
    alpha_min: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    return tuple(torch.empty_like(t) for t in (means2d, conics, opacities, colors))  # type: ignore[return-value]


def _setup_context(ctx: Any, inputs: tuple[Any, ...], output: tuple[Tensor, ...]) -> None:
    means2d, conics, opacities, colors, pairs, starts, _, tiles_x, per_image, _, *rules = inputs
    _, transmittance, stop = output
    ctx.save_for_backward(means2d, conics, opacities, colors, pairs, starts, transmittance, stop)
    ctx.tiles_x, ctx.per_image, ctx.rules = tiles_x, per_image, rules


def _backward(
    ctx: Any, grad_tiles: Tensor, grad_transmittance: Tensor, _grad_stop: Tensor | None
) -> tuple[Tensor | None, ...]:
    grads = torch.ops.dego.triton_composite_backward(
        *ctx.saved_tensors,
        grad_tiles.contiguous(),
        grad_transmittance.contiguous(),
        ctx.tiles_x,
        ctx.per_image,
        ctx.rules[0],
        ctx.rules[1],
    )
    return (*grads, *(None,) * 9)


_composite.register_autograd(_backward, setup_context=_setup_context)


__all__ = ["INSTALL", "bin_and_composite", "installed", "interpreting", "usable"]
