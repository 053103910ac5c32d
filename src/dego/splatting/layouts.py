"""Output finishing per layout: the composited tiles ``(B*V*ty*tx, S, S, D)`` -> images.

Each layout is one autograd node that lays out the tiles, adds ``T_final * background``
to the features and divides an expected depth by ``max(alpha, 1e-10)``: one new image
forward and one transposed copy backward (slicing one image into features and depth would
allocate a zero-filled gradient per slice in backward, and a transposition another copy).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch
from torch import Tensor

from dego.splatting.tiles import tile_grid_shape

_TINY_ALPHA = 1e-10


@dataclasses.dataclass(frozen=True)
class TileGrid:
    """How the tiles cover ``B * V`` images of ``(H, W)`` pixels."""

    b: int
    v: int
    tiles_y: int
    tiles_x: int
    tile_size: int
    height: int
    width: int

    @classmethod
    def of(cls, b: int, v: int, tile_size: int, size: tuple[int, int]) -> TileGrid:
        return cls(b, v, *tile_grid_shape(size, tile_size), tile_size, *size)

    @property
    def cropped(self) -> bool:
        """Whether the tiles overhang the image (sizes not multiples of the tile size)."""
        ts = self.tile_size
        return (self.tiles_y * ts, self.tiles_x * ts) != (self.height, self.width)

    def blocks(self, tiles: Tensor) -> Tensor:
        """``(B*V*ty*tx, S, S, *D)`` -> a ``(B, V, ty, tx, S, S, *D)`` view."""
        ts = self.tile_size
        return tiles.view(self.b, self.v, self.tiles_y, self.tiles_x, ts, ts, *tiles.shape[3:])


def untile(transmittance: Tensor, grid: TileGrid) -> Tensor:
    """Per-tile ``(B*V*ty*tx, S, S)`` values -> ``(B, V, H, W)`` images."""
    ts = grid.tile_size
    image = grid.blocks(transmittance).permute(0, 1, 2, 4, 3, 5)
    image = image.reshape(grid.b, grid.v, grid.tiles_y * ts, grid.tiles_x * ts)
    return image[..., : grid.height, : grid.width]


def channels_first(
    tiles: Tensor,
    final_t: Tensor,
    background: Tensor | None,
    channels: int,
    depth_mode: str,
    grid: TileGrid,
) -> tuple[Tensor, Tensor | None]:
    """``(features (B, V, C, H, W), depth (B, V, H, W) or None)`` from the tiles."""
    if background is not None and background.ndim == 1:
        background = background.expand(grid.b, grid.v, channels)
    features, depth = _FinishChannelsFirst.apply(
        tiles, final_t, background, channels, depth_mode, grid
    )
    return features, (None if depth_mode == "none" else depth)


def channels_last(
    tiles: Tensor,
    final_t: Tensor,
    background: Tensor | None,
    channels: int,
    depth_mode: str,
    grid: TileGrid,
) -> Tensor:
    """``(B, V, H, W, X)`` from the tiles: the features, then the depth if rendered."""
    ts, d = grid.tile_size, tiles.shape[-1]
    image = grid.blocks(tiles).permute(0, 1, 2, 4, 3, 5, 6)
    image = image.reshape(grid.b, grid.v, grid.tiles_y * ts, grid.tiles_x * ts, d)
    image = image[:, :, : grid.height, : grid.width]
    if background is not None and background.ndim == 1:
        background = background.expand(grid.b, grid.v, channels)
    expected = depth_mode == "expected"
    if background is not None or expected:
        image = _FinishChannelsLast.apply(image, final_t, background, channels, expected)
    return image


class _FinishChannelsFirst(torch.autograd.Function):
    """Tiles ``(B*V*ty*tx, S, S, D)`` -> features ``(B, V, C, H, W)`` plus
    ``T_final * background`` and depth ``(B, V, H, W)`` (divided by ``max(alpha, 1e-10)``
    when expected; an empty placeholder with ``depth_mode="none"``), as one node: backward
    writes both gradients into the tile layout in one transposed copy."""

    @staticmethod
    def forward(
        ctx: Any,
        tiles: Tensor,
        final_t: Tensor,
        background: Tensor | None,
        channels: int,
        depth_mode: str,
        grid: TileGrid,
    ) -> tuple[Tensor, Tensor]:
        b, v, h, w, c = grid.b, grid.v, grid.height, grid.width, channels
        with_depth = depth_mode != "none"
        # (B, V, ty, tx, S, S, D) -> (B, V, D, ty, S, tx, S)
        blocks = grid.blocks(tiles).permute(0, 1, 6, 2, 4, 3, 5)
        features = tiles.new_empty(b, v, c, h, w)
        depth = tiles.new_empty(b, v, h, w) if with_depth else tiles.new_empty(0)
        if grid.cropped:
            full = blocks.reshape(
                b, v, tiles.shape[-1], grid.tiles_y * grid.tile_size, grid.tiles_x * grid.tile_size
            )
            features.copy_(full[:, :, :c, :h, :w])
            if with_depth:
                depth.copy_(full[:, :, c, :h, :w])
        else:
            features.view(blocks[:, :, :c].shape).copy_(blocks[:, :, :c])
            if with_depth:
                depth.view(blocks[:, :, c].shape).copy_(blocks[:, :, c])
        if background is not None:
            # multiply, then add (not addcmul): bitwise the channels-last layout's sums
            features += final_t.unsqueeze(2) * background[..., None, None]
        expected = depth_mode == "expected"
        if expected:
            depth.div_((1 - final_t).clamp_min(_TINY_ALPHA))
        ctx.save_for_backward(final_t, background, depth if expected else None)
        ctx.channels, ctx.expected, ctx.with_depth, ctx.grid = c, expected, with_depth, grid
        ctx.tiles_shape = tiles.shape
        return features, depth

    @staticmethod
    def backward(ctx: Any, grad_features: Tensor, grad_depth: Tensor) -> tuple[Tensor | None, ...]:
        final_t, background, depth = ctx.saved_tensors
        c, grid = ctx.channels, ctx.grid
        grad_t, grad_background = None, None
        if background is not None:
            grad_t = torch.einsum("bvchw,bvc->bvhw", grad_features, background)
            grad_background = torch.einsum("bvchw,bvhw->bvc", grad_features, final_t)
        if ctx.expected:
            alpha = 1 - final_t
            # depth = accumulated / alpha, alpha = 1 - T: d depth / dT = depth / alpha
            # (no gradient where the clamp is active, as with clamp_min)
            extra = torch.where(alpha > _TINY_ALPHA, grad_depth * depth / alpha, 0.0)
            grad_t = extra if grad_t is None else grad_t + extra
            grad_depth = grad_depth / alpha.clamp_min(_TINY_ALPHA)
        grad_tiles = grad_features.new_empty(ctx.tiles_shape)
        blocks = grid.blocks(grad_tiles).permute(0, 1, 6, 2, 4, 3, 5)
        if grid.cropped:  # the overhanging pixels get no gradient
            full = grad_features.new_zeros(blocks.shape)
            padded = full.flatten(5, 6).flatten(3, 4)
            padded[:, :, :c, : grid.height, : grid.width] = grad_features
            if ctx.with_depth:
                padded[:, :, c, : grid.height, : grid.width] = grad_depth
            blocks.copy_(full)
        else:
            blocks[:, :, :c].copy_(grad_features.reshape(blocks[:, :, :c].shape))
            if ctx.with_depth:
                blocks[:, :, c].copy_(grad_depth.reshape(blocks[:, :, c].shape))
        return grad_tiles, grad_t, grad_background, None, None, None


class _FinishChannelsLast(torch.autograd.Function):
    """Adds ``T_final * background`` to the feature channels and divides the depth channel
    (the last) by ``max(alpha, 1e-10)`` of a channels-last ``(B, V, H, W, X)`` image, as one
    autograd node: one new image forward, at most one backward (slicing the image into
    parts would allocate a zero-filled image per part in backward)."""

    @staticmethod
    def forward(
        ctx: Any,
        image: Tensor,
        final_t: Tensor,
        background: Tensor | None,
        channels: int,
        expected: bool,
    ) -> Tensor:
        out = image.clone(memory_format=torch.contiguous_format)
        if background is not None:
            out[..., :channels] += final_t.unsqueeze(-1) * background[:, :, None, None]
        alpha = (1 - final_t).clamp_min(_TINY_ALPHA)
        if expected:
            out[..., channels] /= alpha
        ctx.save_for_backward(final_t, background, out[..., channels] if expected else None)
        ctx.channels, ctx.expected = channels, expected
        return out

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        final_t, background, depth = ctx.saved_tensors
        channels = ctx.channels
        grad_image, grad_t, grad_background = grad, None, None
        if background is not None:
            grad_features = grad[..., :channels]
            grad_t = torch.einsum("bvhwc,bvc->bvhw", grad_features, background)
            grad_background = torch.einsum("bvhwc,bvhw->bvc", grad_features, final_t)
        if ctx.expected:
            alpha = 1 - final_t
            grad_depth = grad[..., channels]
            grad_image = grad.clone(memory_format=torch.contiguous_format)
            grad_image[..., channels] /= alpha.clamp_min(_TINY_ALPHA)
            # depth = accumulated / alpha, alpha = 1 - T: d depth / dT = depth / alpha
            # (no gradient where the clamp is active, as with clamp_min)
            extra = torch.where(alpha > _TINY_ALPHA, grad_depth * depth / alpha, 0.0)
            grad_t = extra if grad_t is None else grad_t + extra
        return grad_image, grad_t, grad_background, None, None


__all__ = ["TileGrid", "channels_first", "channels_last", "untile"]
