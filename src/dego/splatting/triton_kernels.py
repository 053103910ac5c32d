"""The Triton compositing kernels of ``backend="triton"`` and their launchers.

One program per (tile, channel block) forward and one per tile backward. A program walks
its tile's depth-sorted list in batches of ``BLOCK_G`` Gaussians against the tile's
``S * S`` pixels, with the torch path's rules (:mod:`dego.splatting.composite`): alpha =
``min(max_alpha, o exp(-sigma))``, skipped below ``alpha_min`` or where sigma < 0, and a
pixel stops before the Gaussian that would take its transmittance to
``transmittance_min`` or below. Forward saves per pixel the final transmittance and
``stop``, the list position (within the tile) of that first excluded Gaussian, or the
list length. Backward walks back to front from ``stop``, recovering each transmittance
by division as gsplat does, reduces each Gaussian's gradients over the tile's pixels
(``tl.sum``) and adds them once per tile (``tl.atomic_add``).

Importing this module imports triton; set ``TRITON_INTERPRET=1`` before it is first
imported to run the kernels on CPU tensors through Triton's interpreter.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl
from torch import Tensor

from dego.splatting.tiles import TileLists

BLOCK_G = 16
"""Gaussians per batch (the inner dimension of the ``tl.dot`` products; at least 16)."""
BLOCK_D = 32
"""Channels per program forward and per inner step backward (at least 16)."""
FP_FUSION = True
"""Let the compiler fuse multiply-adds (Triton's default until 3.9), said explicitly:
Triton 3.9 warns at every compile where it is left to its default."""
NUM_WARPS = 8
"""Warps per program: a (BLOCK_G, 256) float32 tensor is 16 registers a thread at 8 warps,
and backward holds about 15 of them. Not tuned on a GPU yet (none was at hand)."""


@triton.jit
def _tile_pixels(tile, tiles_x, tiles_per_image, S: tl.constexpr, PIX: tl.constexpr):
    """Pixel-centre coordinates ``(PIX,)`` of a tile and which of the PIX lanes are pixels."""
    in_image = tile % tiles_per_image
    lane = tl.arange(0, PIX)
    px = ((in_image % tiles_x) * S + lane % S).to(tl.float32) + 0.5
    py = ((in_image // tiles_x) * S + lane // S).to(tl.float32) + 0.5
    return px, py, lane < S * S


@triton.jit
def _batch_alpha(means_ptr, conics_ptr, opacities_ptr, ids, valid, px, py, max_alpha, alpha_min):
    """Alpha ``(BLOCK_G, PIX)`` of a batch of Gaussians at a tile's pixels, as
    :func:`dego.splatting.composite._alphas` computes it, with what backward needs."""
    mx = tl.load(means_ptr + ids * 2, mask=valid, other=0.0)
    my = tl.load(means_ptr + ids * 2 + 1, mask=valid, other=0.0)
    ca = tl.load(conics_ptr + ids * 3, mask=valid, other=0.0)
    cb = tl.load(conics_ptr + ids * 3 + 1, mask=valid, other=0.0)
    cc = tl.load(conics_ptr + ids * 3 + 2, mask=valid, other=0.0)
    opacity = tl.load(opacities_ptr + ids, mask=valid, other=0.0)
    dx = mx[:, None] - px[None, :]
    dy = my[:, None] - py[None, :]
    log_opacity = tl.log(tl.maximum(opacity, 1e-30))[:, None]
    row = log_opacity - 0.5 * cc[:, None] * dy * dy
    col = -0.5 * ca[:, None] * dx * dx
    logit = (row + col) + dy * (-cb[:, None] * dx)
    raw = tl.exp(logit)
    skip = (raw < alpha_min) | (logit > log_opacity)
    alpha = tl.where(skip, 0.0, tl.minimum(raw, max_alpha))
    return alpha, raw, skip, dx, dy, ca, cb, cc, opacity


@triton.jit
def _forward_kernel(
    means_ptr,
    conics_ptr,
    opacities_ptr,
    colors_ptr,
    pairs_ptr,
    starts_ptr,
    counts_ptr,
    out_ptr,
    transmittance_ptr,
    stop_ptr,
    tiles_x,
    tiles_per_image,
    dim,
    max_alpha,
    alpha_min,
    transmittance_min,
    S: tl.constexpr,
    PIX: tl.constexpr,
    BLOCK_G: tl.constexpr,
    BLOCK_D: tl.constexpr,
):
    tile = tl.program_id(0).to(tl.int64)
    block = tl.program_id(1)
    start = tl.load(starts_ptr + tile)
    count = tl.load(counts_ptr + tile)
    px, py, is_pixel = _tile_pixels(tile, tiles_x, tiles_per_image, S, PIX)
    channel = block * BLOCK_D + tl.arange(0, BLOCK_D)
    transmittance = tl.full((PIX,), 1.0, tl.float32)
    done = ~is_pixel
    stop = tl.zeros((PIX,), tl.int64) + count
    acc = tl.zeros((PIX, BLOCK_D), tl.float32)
    position = tl.arange(0, BLOCK_G)
    offset = tl.zeros((), tl.int64)
    while (offset < count) & (tl.min(done.to(tl.int32), 0) == 0):
        local = offset + position
        valid = local < count
        ids = tl.load(pairs_ptr + start + local, mask=valid, other=0)
        alpha = _batch_alpha(
            means_ptr, conics_ptr, opacities_ptr, ids, valid, px, py, max_alpha, alpha_min
        )[0]
        keep = 1.0 - alpha
        product = tl.cumprod(keep, 0)
        after = transmittance[None, :] * product
        blocked = (after <= transmittance_min) | done[None, :]
        # the product before each Gaussian; where keep = 0 (alpha = 1) after = 0 blocks it
        exclusive = product / tl.where(blocked, 1.0, keep)
        weights = tl.where(blocked, 0.0, transmittance[None, :] * exclusive * alpha)
        colors = tl.load(
            colors_ptr + ids[:, None] * dim + channel[None, :],
            mask=valid[:, None] & (channel < dim)[None, :],
            other=0.0,
        )
        acc += tl.dot(tl.trans(weights), colors, input_precision="ieee")
        # the product of (1 - alpha), not 1 - sum(w): backward divides it back, and the
        # difference would have lost its relative precision where T is small
        transmittance = tl.min(tl.where(blocked, transmittance[None, :], after), 0)
        newly = blocked & ~done[None, :]
        first = tl.min(tl.where(newly, local[:, None], count), 0)
        stop = tl.where(done, stop, first)
        done = done | (first < count)
        offset += BLOCK_G
    pixel = tl.arange(0, PIX)
    out = out_ptr + (tile * (S * S) + pixel[:, None]) * dim + channel[None, :]
    tl.store(out, acc, mask=is_pixel[:, None] & (channel < dim)[None, :])
    if block == 0:
        tl.store(transmittance_ptr + tile * (S * S) + pixel, transmittance, mask=is_pixel)
        tl.store(stop_ptr + tile * (S * S) + pixel, stop.to(tl.int32), mask=is_pixel)


@triton.jit
def _backward_kernel(
    means_ptr,
    conics_ptr,
    opacities_ptr,
    colors_ptr,
    pairs_ptr,
    starts_ptr,
    transmittance_ptr,
    stop_ptr,
    grad_out_ptr,
    grad_transmittance_ptr,
    grad_means_ptr,
    grad_conics_ptr,
    grad_opacities_ptr,
    grad_colors_ptr,
    absgrad_ptr,
    tiles_x,
    tiles_per_image,
    dim,
    max_alpha,
    alpha_min,
    S: tl.constexpr,
    PIX: tl.constexpr,
    BLOCK_G: tl.constexpr,
    BLOCK_D: tl.constexpr,
    ABSGRAD: tl.constexpr,
):
    tile = tl.program_id(0).to(tl.int64)
    start = tl.load(starts_ptr + tile)
    px, py, is_pixel = _tile_pixels(tile, tiles_x, tiles_per_image, S, PIX)
    pixel = tile * (S * S) + tl.arange(0, PIX)
    stop = tl.load(stop_ptr + pixel, mask=is_pixel, other=0).to(tl.int64)
    # running per-pixel state, back to front: the transmittance after the current batch
    # and sum_{i > k} w_i h_i over everything behind it
    transmittance = tl.load(transmittance_ptr + pixel, mask=is_pixel, other=1.0)
    grad_t = tl.load(grad_transmittance_ptr + pixel, mask=is_pixel, other=0.0)
    later = tl.zeros((PIX,), tl.float32)
    position = tl.arange(0, BLOCK_G)
    high = tl.max(stop, 0)
    while high > 0:
        local = high - BLOCK_G + position
        valid = local >= 0
        ids = tl.load(pairs_ptr + start + local, mask=valid, other=0)
        alpha, raw, skip, dx, dy, ca, cb, cc, opacity = _batch_alpha(
            means_ptr, conics_ptr, opacities_ptr, ids, valid, px, py, max_alpha, alpha_min
        )
        drawn = valid[:, None] & (local[:, None] < stop[None, :])
        alpha = tl.where(drawn, alpha, 0.0)
        keep = 1.0 - alpha
        # reverse inclusive product: prod_{j >= k} (1 - alpha_j) within the batch
        behind = tl.cumprod(keep, 0, reverse=True)
        before = transmittance[None, :] / behind
        weights = before * alpha
        # h_k = dL/dw_k = g_out . c_k - g_T, and dL/dc_k = sum_p w_k g_out
        h = tl.zeros((BLOCK_G, PIX), tl.float32) - grad_t[None, :]
        for block in range(0, tl.cdiv(dim, BLOCK_D)):
            channel = block * BLOCK_D + tl.arange(0, BLOCK_D)
            in_dim = channel < dim
            grad_out = tl.load(
                grad_out_ptr + pixel[:, None] * dim + channel[None, :],
                mask=is_pixel[:, None] & in_dim[None, :],
                other=0.0,
            )
            colors = tl.load(
                colors_ptr + ids[:, None] * dim + channel[None, :],
                mask=valid[:, None] & in_dim[None, :],
                other=0.0,
            )
            h += tl.dot(colors, tl.trans(grad_out), input_precision="ieee")
            grad_colors = tl.dot(weights, grad_out, input_precision="ieee")
            tl.atomic_add(
                grad_colors_ptr + ids[:, None] * dim + channel[None, :],
                grad_colors,
                mask=valid[:, None] & in_dim[None, :],
            )
        h = tl.where(drawn, h, 0.0)
        wh = weights * h
        behind_sum = tl.cumsum(wh, 0, reverse=True)
        # dL/dalpha_k = T_before_k h_k - (sum_{i > k} w_i h_i) / (1 - alpha_k)
        after_k = later[None, :] + (behind_sum - wh)
        grad_alpha = before * h - after_k / tl.maximum(keep, 1e-30)
        grad_logit = tl.where(drawn & ~skip & (raw <= max_alpha), grad_alpha * raw, 0.0)
        # d(-sigma)/d(mean) = -(a dx + b dy, c dy + b dx), d(-sigma)/d(a, b, c) =
        # -(dx^2 / 2, dx dy, dy^2 / 2): five sums over the pixels, then per Gaussian
        along_x = grad_logit * dx
        along_y = grad_logit * dy
        sum_x, sum_y = tl.sum(along_x, 1), tl.sum(along_y, 1)
        tl.atomic_add(grad_means_ptr + ids * 2, -(ca * sum_x + cb * sum_y), mask=valid)
        tl.atomic_add(grad_means_ptr + ids * 2 + 1, -(cc * sum_y + cb * sum_x), mask=valid)
        tl.atomic_add(grad_conics_ptr + ids * 3, -0.5 * tl.sum(along_x * dx, 1), mask=valid)
        tl.atomic_add(grad_conics_ptr + ids * 3 + 1, -tl.sum(along_x * dy, 1), mask=valid)
        tl.atomic_add(grad_conics_ptr + ids * 3 + 2, -0.5 * tl.sum(along_y * dy, 1), mask=valid)
        total = tl.sum(grad_logit, 1)
        grad_opacity = tl.where(opacity > 1e-30, total / tl.maximum(opacity, 1e-30), 0.0)
        tl.atomic_add(grad_opacities_ptr + ids, grad_opacity, mask=valid)
        if ABSGRAD:
            per_x = tl.abs(ca[:, None] * along_x + cb[:, None] * along_y)
            per_y = tl.abs(cc[:, None] * along_y + cb[:, None] * along_x)
            tl.atomic_add(absgrad_ptr + ids * 2, tl.sum(per_x, 1), mask=valid)
            tl.atomic_add(absgrad_ptr + ids * 2 + 1, tl.sum(per_y, 1), mask=valid)
        later += tl.sum(wh, 0)
        transmittance = tl.sum(tl.where(position[:, None] == 0, before, 0.0), 0)
        high -= BLOCK_G


def _pixels(tile_size: int) -> int:
    """Lanes per program: the tile's pixels, rounded up to a power of two (>= 16 for tl.dot)."""
    return max(16, triton.next_power_of_2(tile_size * tile_size))


def forward(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    lists: TileLists,
    tile_size: int,
    rules: tuple[float, float, float],
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite every tile: ``(tiles (T, S, S, D), transmittance (T, S, S), stop (T, S, S))``.

    ``means2d (M, 2)``, ``conics (M, 3)``, ``opacities (M,)``, ``colors (M, D)`` float32
    contiguous; ``lists`` the tiles' sorted Gaussians; ``rules`` ``(max_alpha, alpha_min,
    transmittance_min)``.
    """
    pairs, counts = lists.gaussians, lists.counts
    num_tiles, dim = counts.shape[0], colors.shape[1]
    size = tile_size
    out = colors.new_zeros(num_tiles, size, size, dim)
    transmittance = colors.new_ones(num_tiles, size, size)
    stop = torch.zeros(num_tiles, size, size, dtype=torch.int32, device=colors.device)
    if num_tiles == 0 or pairs.numel() == 0:
        return out, transmittance, stop
    grid = (num_tiles, max(1, triton.cdiv(dim, BLOCK_D)))
    _forward_kernel[grid](
        means2d,
        conics,
        opacities,
        colors,
        pairs,
        lists.starts,
        counts,
        out,
        transmittance,
        stop,
        lists.tiles_x,
        lists.tiles_x * lists.tiles_y,
        dim,
        *rules,
        S=size,
        PIX=_pixels(size),
        BLOCK_G=BLOCK_G,
        BLOCK_D=BLOCK_D,
        num_warps=NUM_WARPS,
        enable_fp_fusion=FP_FUSION,
    )
    return out, transmittance, stop


def backward(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    lists: TileLists,
    transmittance: Tensor,
    stop: Tensor,
    grad_out: Tensor,
    grad_transmittance: Tensor,
    rules: tuple[float, float, float],
    absgrad: bool,
) -> tuple[Tensor, ...]:
    """Gradients of :func:`forward` w.r.t. means2d, conics, opacities and colors (and,
    with ``absgrad``, the summed per-pixel absolute means2d gradients ``(M, 2)``)."""
    num_tiles, size = stop.shape[0], stop.shape[1]
    grads = [torch.zeros_like(t) for t in (means2d, conics, opacities, colors)]
    absolute = torch.zeros_like(means2d) if absgrad else grads[0]
    if num_tiles and lists.gaussians.numel():
        _backward_kernel[(num_tiles,)](
            means2d,
            conics,
            opacities,
            colors,
            lists.gaussians,
            lists.starts,
            transmittance,
            stop,
            grad_out.contiguous(),
            grad_transmittance.contiguous(),
            *grads,
            absolute,
            lists.tiles_x,
            lists.tiles_x * lists.tiles_y,
            colors.shape[1],
            rules[0],
            rules[1],
            S=size,
            PIX=_pixels(size),
            BLOCK_G=BLOCK_G,
            BLOCK_D=BLOCK_D,
            ABSGRAD=absgrad,
            num_warps=NUM_WARPS,
            enable_fp_fusion=FP_FUSION,
        )
    return (*grads, absolute) if absgrad else tuple(grads)


__all__ = ["BLOCK_D", "BLOCK_G", "FP_FUSION", "NUM_WARPS", "backward", "forward"]
