"""The custom operators that ``torch.compile`` sees of ``backend="triton"``
(:mod:`dego.splatting.triton_backend`); they need ``torch.library.custom_op`` (torch >= 2.4).

Binning and compositing are one forward operator, ``dego::triton_rasterize``, with static
output shapes: the pair list's length is data-dependent, and dynamo breaks the graph on an
operator whose output shape is. Its backward operator, ``dego::triton_rasterize_backward``,
bins again (the binning is deterministic) rather than keep the pair list. Both call the
kernels of :mod:`dego.splatting.triton_kernels`.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from dego.splatting.tiles import TileLists, build_tile_lists, tile_grid_shape


def tile_lists(
    means2d: Tensor,
    extents: Tensor,
    depths: Tensor,
    conics: Tensor,
    max_sigma: Tensor,
    height: int,
    width: int,
    tile_size: int,
) -> TileLists:
    """The keyed tile lists of ``(I, N)`` projected Gaussians (the binning inputs)."""
    return build_tile_lists(
        means2d,
        extents,
        depths,
        (height, width),
        tile_size,
        conics=conics,
        max_sigma=max_sigma,
        keyed=True,
    )


@torch.library.custom_op("dego::triton_rasterize", mutates_args=())
def _rasterize(
    bin_means2d: Tensor,
    bin_extents: Tensor,
    bin_depths: Tensor,
    bin_conics: Tensor,
    bin_max_sigma: Tensor,
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    height: int,
    width: int,
    tile_size: int,
    max_alpha: float,
    alpha_min: float,
    transmittance_min: float,
) -> tuple[Tensor, Tensor, Tensor]:
    from dego.splatting import triton_kernels

    lists = tile_lists(
        bin_means2d, bin_extents, bin_depths, bin_conics, bin_max_sigma, height, width, tile_size
    )
    rules = (max_alpha, alpha_min, transmittance_min)
    return triton_kernels.forward(means2d, conics, opacities, colors, lists, tile_size, rules)


@_rasterize.register_fake
def _(*args: Any) -> tuple[Tensor, Tensor, Tensor]:
    # the operator's arguments, in order: 5 binning tensors (bin_depths is (I, N)), the 4
    # compositing tensors (colors is (M, D)), height, width, tile_size, then the rules
    bin_depths, colors, (height, width, size) = args[2], args[8], args[9:12]
    tiles_y, tiles_x = tile_grid_shape((height, width), size)
    tiles = bin_depths.shape[0] * tiles_y * tiles_x
    return (
        colors.new_empty(tiles, size, size, colors.shape[1]),
        colors.new_empty(tiles, size, size),
        torch.empty(tiles, size, size, dtype=torch.int32, device=colors.device),
    )


@torch.library.custom_op("dego::triton_rasterize_backward", mutates_args=())
def _rasterize_backward(
    bin_means2d: Tensor,
    bin_extents: Tensor,
    bin_depths: Tensor,
    bin_conics: Tensor,
    bin_max_sigma: Tensor,
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    stop: Tensor,
    grad_tiles: Tensor,
    grad_transmittance: Tensor,
    height: int,
    width: int,
    tile_size: int,
    max_alpha: float,
    alpha_min: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    from dego.splatting import triton_kernels

    lists = tile_lists(
        bin_means2d, bin_extents, bin_depths, bin_conics, bin_max_sigma, height, width, tile_size
    )
    grads = triton_kernels.backward(
        *(means2d, conics, opacities, colors, lists, stop),
        *(grad_tiles, grad_transmittance, (max_alpha, alpha_min, 0.0), False),
    )
    return grads[0], grads[1], grads[2], grads[3]


@_rasterize_backward.register_fake
def _(*args: Any) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    # arguments 5-8 are the compositing tensors, whose gradients are returned
    return tuple(torch.empty_like(t) for t in args[5:9])  # type: ignore[return-value]


def _setup_context(ctx: Any, inputs: tuple[Any, ...], output: tuple[Tensor, ...]) -> None:
    ctx.save_for_backward(*inputs[:9], output[2])  # and stop
    ctx.options = inputs[9:14]  # height, width, tile_size, max_alpha, alpha_min


def _backward(
    ctx: Any, grad_tiles: Tensor, grad_transmittance: Tensor, _grad_stop: Tensor | None
) -> tuple[Tensor | None, ...]:
    grads = torch.ops.dego.triton_rasterize_backward(
        *ctx.saved_tensors,
        grad_tiles.contiguous(),
        grad_transmittance.contiguous(),
        *ctx.options,
    )
    return (None,) * 5 + tuple(grads) + (None,) * 6


_rasterize.register_autograd(_backward, setup_context=_setup_context)


__all__ = ["tile_lists"]
