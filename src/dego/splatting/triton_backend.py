"""``backend="triton"``: the torch path's projection, then tile binning with one ``torch.sort``
of int64 keys and Triton kernels for the compositing (:mod:`dego.splatting.triton_kernels`),
forward and backward. No C++ build: Triton compiles for the GPU present at first use.

Needs ``pip install -e ".[triton]"`` (in a clone) and CUDA tensors (NVIDIA, or AMD through
Triton's ROCm backend), float32 (float16 / bfloat16 inputs are computed in float32);
float64 stays on the torch path. With ``TRITON_INTERPRET=1`` set before dego first uses
Triton, ``backend="triton"`` also runs on CPU tensors through Triton's interpreter (slow:
for tests). ``backend="auto"`` takes this path on CUDA when triton is installed and its
kernels compiled on the device (a one-time probe; a failure warns once and keeps the torch
path), and never on CPU.

Inside ``torch.compile`` the binning and the compositing are one custom operator
(``dego::triton_rasterize``, with ``dego::triton_rasterize_backward``; see
:mod:`dego.splatting.triton_ops`, which needs torch >= 2.4) with fake implementations, so
dynamo traces through it without a graph break; ``absgrad`` needs a Python callback in
backward and runs eagerly (one graph break).
"""

from __future__ import annotations

import importlib.util
import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from dego._compile import eager_only
from dego._typing import _is_compiling
from dego.gaussians import GaussianSet
from dego.splatting.tiles import TileLists
from dego.splatting.types import SplatConfig

CUSTOM_OPS = hasattr(torch.library, "custom_op")
"""torch >= 2.4: the operators that let ``torch.compile`` trace the Triton path."""
if CUSTOM_OPS:
    from dego.splatting.triton_ops import tile_lists

INSTALL = 'pip install -e ".[triton]" in your dego clone'

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
            raise ImportError(_missing_triton(gaussians.device))
        return False
    if not CUSTOM_OPS:
        if strict:
            raise ImportError(
                f"backend: 'triton' needs torch >= 2.4 (torch.library.custom_op), "
                f"got torch {torch.__version__}"
            )
        return False
    device = gaussians.device
    if not _runs_on(device, strict):
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
        failure = _PROBED[key] = _probe(device)
        if failure is not None and not strict:
            warnings.warn(
                f"backend='auto': the Triton kernels failed on {_device_name(device)} "
                f"({failure}); rendering with the torch path",
                RuntimeWarning,
                stacklevel=4,
            )
    failure = _PROBED[key]
    if failure is None:
        return True
    if strict:
        raise RuntimeError(f"backend: 'triton' cannot run on {_device_name(device)}: {failure}")
    return False


def _missing_triton(device: torch.device) -> str:
    """Why ``backend="triton"`` cannot run without the triton package: both of its
    requirements, and what ``device`` (the tensors') lacks besides."""
    message = (
        f"backend: 'triton' needs two things: the triton package ({INSTALL}) and CUDA "
        "tensors on an NVIDIA GPU (or an AMD GPU through ROCm), or, for CPU tensors, "
        "Triton's interpreter (TRITON_INTERPRET=1 set before dego first uses Triton; slow, "
        "for tests); triton is not installed"
    )
    if device.type != "cuda":
        message += (
            f" and the tensors are on {device} (backend='torch' or 'auto' renders them "
            "without triton)"
        )
    return message


def _runs_on(device: torch.device, strict: bool) -> bool:
    """CUDA tensors; CPU tensors only when asked for by name and interpreted."""
    return device.type == "cuda" or (strict and device.type == "cpu" and interpreting())


def _device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)})"
    return str(device)


@eager_only
def _probe(device: torch.device) -> str | None:
    """Compile and run both kernels once on a tiny input; the error text if they fail.
    Runs with gradients on, whatever the caller's mode (``no_grad``, ``inference_mode``)."""
    try:
        with torch.inference_mode(False), torch.enable_grad():
            _run_probe(device)
    except Exception as error:  # any failure of the compiler or the driver
        return f"{type(error).__name__}: {error}".strip().splitlines()[0][:300]
    return None


def _run_probe(device: torch.device) -> None:
    """One Gaussian in one tile, forward and backward, through the eager node."""
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
    rules = (0.999, 1 / 255, 1e-4)
    tiles, transmittance = _Composite.apply(
        means2d, conics, opacities, colors, lists, 16, rules, None
    )
    (tiles.sum() + transmittance.sum()).backward()
    if device.type == "cuda":
        torch.cuda.synchronize(device)


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
) -> tuple[Tensor, Tensor]:
    """Composited tiles ``(T, S, S, D)`` and final transmittance ``(T, S, S)``, as the torch
    path's ``_bin_and_composite`` returns them. ``means2d``, ``extents``, ``depths``,
    ``conics``, ``max_sigma``: ``(I, N, ...)`` per image, for the binning (no gradient);
    ``compositing_means2d`` ``(M, 2)``, ``conics`` (flattened), ``opacities`` ``(M,)``,
    ``colors`` ``(M, D)``: what the compositing reads and differentiates."""
    means2d, extents, depths, bin_conics, max_sigma = (
        t.detach().float().contiguous() for t in (means2d, extents, depths, conics, max_sigma)
    )
    binning = (means2d, extents, depths, bin_conics, max_sigma)
    shape = (*size, config.tile_size)
    # (max_alpha, alpha_min, transmittance_min) as floats: the operator's schema says float
    rules = (float(config.max_alpha), float(config.alpha_min), float(config.transmittance_min))
    tensors = (
        compositing_means2d.contiguous(),
        conics.reshape(-1, 3).contiguous(),
        opacities.contiguous(),
        colors.contiguous(),
    )
    if _is_compiling() and absgrad_sink is None:
        # one operator with static output shapes: dynamo does not break the graph on it
        tiles, transmittance, _ = torch.ops.dego.triton_rasterize(
            *binning, *tensors, *shape, *rules
        )
        return tiles, transmittance
    return _eager(binning, tensors, shape, rules, absgrad_sink)


@eager_only
def _eager(
    binning: tuple[Tensor, Tensor, Tensor, Tensor, Tensor],
    tensors: tuple[Tensor, ...],
    shape: tuple[int, int, int],
    rules: tuple[float, float, float],
    absgrad_sink: Callable[[Tensor], None] | None,
) -> tuple[Tensor, Tensor]:
    lists = tile_lists(*binning, *shape)
    return _Composite.apply(*tensors, lists, shape[2], rules, absgrad_sink)


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
        rules: tuple[float, float, float],
        absgrad_sink: Callable[[Tensor], None] | None,
    ) -> tuple[Tensor, Tensor]:
        from dego.splatting import triton_kernels

        tiles, transmittance, stop = triton_kernels.forward(
            means2d, conics, opacities, colors, lists, tile_size, rules
        )
        ctx.save_for_backward(means2d, conics, opacities, colors, stop)
        # the lists hold no gradient: kept as they are, not as saved tensors
        ctx.lists, ctx.rules, ctx.sink = lists, rules, absgrad_sink
        return tiles, transmittance

    @staticmethod
    def backward(ctx: Any, grad_tiles: Tensor, grad_t: Tensor) -> tuple[Tensor | None, ...]:
        from dego.splatting import triton_kernels

        means2d, conics, opacities, colors, stop = ctx.saved_tensors
        grads = triton_kernels.backward(
            *(means2d, conics, opacities, colors, ctx.lists, stop),
            *(grad_tiles, grad_t, ctx.rules, ctx.sink is not None),
        )
        if ctx.sink is not None:
            ctx.sink(grads[4])
        return (*grads[:4], None, None, None, None)


__all__ = ["INSTALL", "bin_and_composite", "installed", "interpreting", "usable"]
