"""Vectorised (Gaussian, tile) intersection and the per-tile front-to-back ordering."""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor


@dataclasses.dataclass(frozen=True)
class TileLists:
    """Each tile's Gaussians, sorted front to back, stored as one flat array.

    Tiles are numbered ``image * tiles_per_image + ty * tiles_x + tx`` with ``image``
    the flattened ``(B, V)`` index. ``gaussians`` holds indices into the flattened
    ``(B * V * N)`` projected Gaussians; tile ``t`` owns
    ``gaussians[starts[t] : starts[t] + counts[t]]``.
    """

    gaussians: Tensor  # (P,) int64, P = number of (Gaussian, tile) pairs
    starts: Tensor  # (num_tiles,) int64
    counts: Tensor  # (num_tiles,) int64
    tiles_x: int
    tiles_y: int

    @property
    def num_tiles(self) -> int:
        return self.counts.shape[0]


def tile_grid_shape(image_size: tuple[int, int], tile_size: int) -> tuple[int, int]:
    """``(tiles_y, tiles_x)``: the tiles of ``tile_size`` pixels covering an ``(H, W)`` image
    (the last row and column may overhang it)."""
    height, width = image_size
    return math.ceil(height / tile_size), math.ceil(width / tile_size)


def contributing_extents(
    variances2d: Tensor, radii: Tensor, opacities: Tensor, alpha_min: float
) -> tuple[Tensor, Tensor]:
    """Per-axis half-extents (pixels) of the region where a Gaussian can reach ``alpha_min``.

    That region is the ellipse ``sigma <= log(o / alpha_min)``, whose bounding box has
    half-extents ``sqrt(2 log(o / alpha_min) var)`` per axis; it is intersected with the
    radius box (``radii`` ``(..., 2)``, per axis). Dropping what lies outside is lossless:
    there alpha < alpha_min, which the compositing rules skip anyway. Returns the extents
    ``(..., 2)`` (0 = nothing to draw) and ``max_sigma = log(o / alpha_min)``.
    """
    max_sigma = torch.log(opacities.detach().clamp_min(1e-30) / alpha_min)
    reach = torch.sqrt(2 * max_sigma.clamp_min(0).unsqueeze(-1) * variances2d) * (1 + 1e-4) + 1e-3
    extents = torch.minimum(reach, radii.to(reach.dtype))
    drawn = (radii > 0).all(-1) & (max_sigma >= 0)
    return torch.where(drawn.unsqueeze(-1), extents, torch.zeros_like(extents)), max_sigma


def _min_sigma_over_rectangles(mean: Tensor, conic: Tensor, low: Tensor, high: Tensor) -> Tensor:
    """Minimum of ``0.5 d^T C d`` (``d = p - mean``) over axis-aligned rectangles [low, high].

    Convex, so the minimum is 0 when the mean is inside, else on an edge, where it is the
    1-D minimiser clamped to the edge.
    """
    a, b, c = conic.unbind(-1)
    lo, hi = low - mean, high - mean  # rectangle in mean-centred coordinates
    best = torch.full_like(a, float("inf"))
    for axis in (0, 1):
        other = 1 - axis
        for edge in (lo[..., axis], hi[..., axis]):
            # on the edge d_axis = edge; minimise over d_other within [lo, hi]
            coupled, own = (c, a) if axis == 0 else (a, c)
            d_other = (-b * edge / coupled).clamp(lo[..., other], hi[..., other])
            value = 0.5 * (own * edge * edge + 2 * b * edge * d_other + coupled * d_other * d_other)
            best = torch.minimum(best, value)
    inside = ((lo <= 0) & (hi >= 0)).all(-1)
    return torch.where(inside, torch.zeros_like(best), best)


def tile_ranges(
    means2d: Tensor, extents: Tensor, tile_size: int, tiles_x: int, tiles_y: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Half-open tile ranges ``[x0, x1) x [y0, y1)`` of each Gaussian's box of half-extents
    ``extents`` (the radius for gsplat's rule)."""
    mx, my = means2d.detach().unbind(-1)
    ex, ey = extents.unbind(-1)
    x0 = torch.floor((mx - ex) / tile_size).clamp(0, tiles_x).long()
    x1 = torch.ceil((mx + ex) / tile_size).clamp(0, tiles_x).long()
    y0 = torch.floor((my - ey) / tile_size).clamp(0, tiles_y).long()
    y1 = torch.ceil((my + ey) / tile_size).clamp(0, tiles_y).long()
    return x0, x1, y0, y1


@torch.no_grad()
def build_tile_lists(
    means2d: Tensor,
    extents: Tensor,
    depths: Tensor,
    image_size: tuple[int, int],
    tile_size: int,
    *,
    conics: Tensor | None = None,
    max_sigma: Tensor | None = None,
    keyed: bool = False,
) -> TileLists:
    """Intersect ``(I, N)`` projected Gaussians (I images) with their tiles and sort each
    tile's list by depth, with no Python loop over Gaussians or tiles.

    ``extents`` ``(I, N, 2)`` are per-axis half-widths of each Gaussian's box (0: none).
    With ``conics`` and ``max_sigma``, (Gaussian, tile) pairs whose tile lies wholly
    outside the ellipse ``sigma <= max_sigma`` are dropped too. Pairs are generated in
    global depth order (one argsort), then stably sorted by tile id, which leaves every
    tile's list front to back. With ``keyed`` (the Triton path), pairs are generated in
    index order and sorted once by an int64 key, the global tile id (which holds the
    image) in the high 32 bits and the float32 depth's order-preserving bits in the low
    32: the same lists, ties in depth broken by index in both.
    """
    tiles_y, tiles_x = tile_grid_shape(image_size, tile_size)
    num_images, n = depths.shape
    x0, x1, y0, y1 = (
        t.reshape(-1) for t in tile_ranges(means2d, extents, tile_size, tiles_x, tiles_y)
    )
    span_x = x1 - x0
    drawn = (extents > 0).all(-1).reshape(-1)
    counts = torch.where(drawn, span_x * (y1 - y0), torch.zeros_like(span_x))
    if keyed:
        order = torch.nonzero(counts > 0).squeeze(-1)
    else:
        order = torch.argsort(depths.reshape(-1), stable=True)
        order = order[counts[order] > 0]
    per_gaussian = counts[order]
    pair_gaussian = order.repeat_interleave(per_gaussian)
    first = torch.cumsum(per_gaussian, 0) - per_gaussian
    local = torch.arange(pair_gaussian.shape[0], device=depths.device) - first.repeat_interleave(
        per_gaussian
    )
    width_in_tiles = span_x[pair_gaussian].clamp_min(1)
    tx = x0[pair_gaussian] + local % width_in_tiles
    ty = y0[pair_gaussian] + local // width_in_tiles
    if conics is not None and max_sigma is not None:
        corner = torch.stack([tx, ty], -1).to(means2d.dtype) * tile_size + 0.5
        lowest = _min_sigma_over_rectangles(
            means2d.detach().reshape(-1, 2)[pair_gaussian],
            conics.detach().reshape(-1, 3)[pair_gaussian],
            corner,
            corner + (tile_size - 1),
        )
        limit = max_sigma.reshape(-1)[pair_gaussian]
        keep = lowest <= limit + 1e-4 * limit.abs() + 1e-3
        pair_gaussian, tx, ty = pair_gaussian[keep], tx[keep], ty[keep]
    image = pair_gaussian // n
    tile = (image * tiles_y + ty) * tiles_x + tx
    if keyed:
        depth_bits = depth_order_bits(depths.reshape(-1)[pair_gaussian])
        tile, perm = torch.sort((tile << 32) | depth_bits, stable=True)
        tile = tile >> 32
    else:
        tile, perm = torch.sort(tile, stable=True)
    num_tiles = num_images * tiles_x * tiles_y
    tile_counts = torch.bincount(tile, minlength=num_tiles)
    return TileLists(
        gaussians=pair_gaussian[perm],
        starts=torch.cumsum(tile_counts, 0) - tile_counts,
        counts=tile_counts,
        tiles_x=tiles_x,
        tiles_y=tiles_y,
    )


def depth_order_bits(depths: Tensor) -> Tensor:
    """int64 in ``[0, 2^32)`` ordered as the float32 ``depths`` are (-0.0 before +0.0)."""
    bits = depths.to(torch.float32).view(torch.int32).to(torch.int64)
    # negative floats order reversed in their magnitude bits: flip those, then offset
    return torch.where(bits < 0, bits ^ 0x7FFFFFFF, bits) + (1 << 31)
