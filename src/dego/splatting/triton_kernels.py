"""The Triton compositing kernels of ``backend="triton"`` and their launchers.

The rules are the torch path's (:mod:`dego.splatting.composite`): alpha =
``min(max_alpha, o exp(-sigma))``, skipped below ``alpha_min`` or where sigma < 0, and a
pixel stops before the Gaussian that would take its transmittance to
``transmittance_min`` or below.

**Forward**, one program per (tile, channel block): it walks the tile's depth-sorted list
in batches of ``BLOCK_G`` Gaussians against the tile's ``S * S`` pixels and saves per
pixel the final transmittance and ``stop``, the list position (within the tile) of that
first excluded Gaussian, or the list length.

**Backward**, parallel over the Gaussians: each tile's list is cut into buckets of
``BUCKET`` positions, and one program handles a (bucket, block of ``BLOCK_P`` pixels).

1. ``_backward_kernel`` with ``SUMS``: per (bucket, pixel), the product of ``1 - alpha`` over the
   bucket and ``sum_k w_k h_k / T_start`` (``h = dL/dw``, ``T_start`` the transmittance
   before the bucket);
2. ``_scan_kernel``: per (tile, pixel), front to back, each bucket's ``T_start`` (a
   product, no division of a small transmittance), then back to front what lies behind
   each bucket, ``sum_{i >= next} w_i h_i`` (a sum, no difference of totals);
3. ``_backward_kernel``: each bucket's alphas again from its ``T_start``, each Gaussian's
   gradients reduced over the program's pixels (``tl.sum``) and added with one relaxed
   atomic per Gaussian and program.

The scan's buffers hold 8 bytes per (bucket, pixel) while the backward runs; the forward
keeps nothing for it but ``stop``. Nothing assumes a warp size: the layouts are Triton's,
for any ``num_warps``. Launch settings come from :mod:`dego.splatting.triton_configs`.

Importing this module imports triton; set ``TRITON_INTERPRET=1`` before it is first
imported to run the kernels on CPU tensors through Triton's interpreter.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl
from torch import Tensor

from dego.splatting import triton_configs
from dego.splatting.tiles import TileLists

BLOCK_G = 16
"""Gaussians per forward batch (the inner dimension of the ``tl.dot`` products; at least
16)."""
SCAN_PIXELS = 64
"""Pixels per program of the scan over a tile's buckets (two loads and stores a bucket)."""
SCAN_WARPS = 2
"""Warps per scan program: 64 pixels, one value each, per step."""
FP_FUSION = True
"""Let the compiler fuse multiply-adds (Triton's default until 3.9), said explicitly:
Triton 3.9 warns at every compile where it is left to its default."""


@triton.jit
def _tile_pixels(tile, lane, tiles_x, tiles_per_image, S: tl.constexpr):
    """Pixel-centre coordinates of a tile's pixels ``lane`` (row-major within the tile) and
    which lanes are pixels."""
    in_image = tile % tiles_per_image
    px = ((in_image % tiles_x) * S + lane % S).to(tl.float32) + 0.5
    py = ((in_image // tiles_x) * S + lane // S).to(tl.float32) + 0.5
    return px, py, lane < S * S


@triton.jit
def _batch_alpha(means_ptr, conics_ptr, opacities_ptr, ids, valid, px, py, max_alpha, alpha_min):
    """Alpha ``(G, P)`` of a batch of Gaussians at pixels, as
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
    lane = tl.arange(0, PIX)
    px, py, is_pixel = _tile_pixels(tile, lane, tiles_x, tiles_per_image, S)
    channel = block * BLOCK_D + tl.arange(0, BLOCK_D)
    in_dim = channel < dim
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
            mask=valid[:, None] & in_dim[None, :],
            other=0.0,
        )
        acc += tl.dot(tl.trans(weights), colors, input_precision="ieee")
        # the product of (1 - alpha), not 1 - sum(w): the difference would lose its
        # relative precision where T is small
        transmittance = tl.min(tl.where(blocked, transmittance[None, :], after), 0)
        newly = blocked & ~done[None, :]
        first = tl.min(tl.where(newly, local[:, None], count), 0)
        stop = tl.where(done, stop, first)
        done = done | (first < count)
        offset += BLOCK_G
    out = out_ptr + (tile * (S * S) + lane[:, None]) * dim + channel[None, :]
    tl.store(out, acc, mask=is_pixel[:, None] & in_dim[None, :])
    if block == 0:
        tl.store(transmittance_ptr + tile * (S * S) + lane, transmittance, mask=is_pixel)
        tl.store(stop_ptr + tile * (S * S) + lane, stop.to(tl.int32), mask=is_pixel)


@triton.jit
def _bucket_of(
    bucket_tile_ptr,
    first_bucket_ptr,
    counts_ptr,
    starts_ptr,
    pairs_ptr,
    stop_ptr,
    tiles_x,
    tiles_per_image,
    S: tl.constexpr,
    BLOCK_P: tl.constexpr,
    BUCKET: tl.constexpr,
):
    """A backward program's bucket and pixels: its tile, its list positions ``local``
    ``(BUCKET,)`` and Gaussians ``ids``, its pixels ``lane`` ``(BLOCK_P,)`` with their
    centres, global index and ``stop``, and ``live``, whether any of them reaches it."""
    bucket = tl.program_id(0).to(tl.int64)
    tile = tl.load(bucket_tile_ptr + bucket)
    local = (bucket - tl.load(first_bucket_ptr + tile)) * BUCKET + tl.arange(0, BUCKET)
    valid = local < tl.load(counts_ptr + tile)
    ids = tl.load(pairs_ptr + tl.load(starts_ptr + tile) + local, mask=valid, other=0)
    lane = tl.program_id(1) * BLOCK_P + tl.arange(0, BLOCK_P)
    px, py, is_pixel = _tile_pixels(tile, lane, tiles_x, tiles_per_image, S)
    pixel = tile * (S * S) + lane
    stop = tl.load(stop_ptr + pixel, mask=is_pixel, other=0).to(tl.int64)
    live = tl.max(stop, 0) > tl.min(local, 0)
    return bucket * (S * S) + lane, local, valid, ids, px, py, is_pixel, pixel, stop, live


@triton.jit
def _weights_of(
    means_ptr, conics_ptr, opacities_ptr, ids, valid, local, stop, px, py, max_alpha, alpha_min
):
    """A bucket's alphas ``(BUCKET, BLOCK_P)`` (zero where a pixel stopped before them)
    with ``keep = 1 - alpha``, the products of ``keep`` within the bucket in front of each
    Gaussian and through it, and what the gradients need besides."""
    alpha, raw, skip, dx, dy, ca, cb, cc, opacity = _batch_alpha(
        means_ptr, conics_ptr, opacities_ptr, ids, valid, px, py, max_alpha, alpha_min
    )
    drawn = valid[:, None] & (local[:, None] < stop[None, :])
    alpha = tl.where(drawn, alpha, 0.0)
    keep = 1.0 - alpha  # > 0 where drawn: alpha = 1 takes T to 0 and stops the pixel
    through = tl.cumprod(keep, 0)
    return alpha, keep, through / keep, through, drawn, raw, skip, dx, dy, ca, cb, cc, opacity


@triton.jit
def _channel_sums(
    grad_out_ptr,
    colors_ptr,
    pixel,
    is_pixel,
    ids,
    valid,
    grad_t,
    dim,
    BUCKET: tl.constexpr,
    BLOCK_P: tl.constexpr,
):
    """``h = g . c - g_T`` ``(BUCKET, BLOCK_P)``: dL/dw of each Gaussian at each pixel, one
    channel at a time (outer products; a ``tl.dot`` would hold both operands, replicated,
    in registers)."""
    h = tl.zeros((BUCKET, BLOCK_P), tl.float32) - grad_t[None, :]
    for channel in range(0, dim):
        grad_out = tl.load(grad_out_ptr + pixel * dim + channel, mask=is_pixel, other=0.0)
        color = tl.load(colors_ptr + ids * dim + channel, mask=valid, other=0.0)
        h += color[:, None] * grad_out[None, :]
    return h


@triton.jit
def _scan_kernel(
    first_bucket_ptr,
    counts_ptr,
    product_ptr,
    partial_ptr,
    S: tl.constexpr,
    BLOCK_P: tl.constexpr,
    BUCKET: tl.constexpr,
):
    """Per tile and pixel, over its buckets, in place: each bucket's product becomes the
    transmittance before it, and its partial sum becomes ``sum_{i >= next} w_i h_i``, all
    that lies behind it (front to back, then back to front; no subtraction)."""
    tile = tl.program_id(0).to(tl.int64)
    lane = tl.program_id(1) * BLOCK_P + tl.arange(0, BLOCK_P)
    is_pixel = lane < S * S
    first = tl.load(first_bucket_ptr + tile)
    buckets = tl.cdiv(tl.load(counts_ptr + tile), BUCKET)
    transmittance = tl.full((BLOCK_P,), 1.0, tl.float32)
    for k in range(0, buckets):
        at = (first + k) * (S * S) + lane
        product = tl.load(product_ptr + at, mask=is_pixel, other=1.0)
        tl.store(product_ptr + at, transmittance, mask=is_pixel)
        transmittance *= product
    behind = tl.zeros((BLOCK_P,), tl.float32)
    for k in range(0, buckets):
        at = (first + buckets - 1 - k) * (S * S) + lane
        partial = tl.load(partial_ptr + at, mask=is_pixel, other=0.0)
        before = tl.load(product_ptr + at, mask=is_pixel, other=0.0)
        tl.store(partial_ptr + at, behind, mask=is_pixel)
        behind += before * partial


@triton.jit
def _backward_kernel(
    means_ptr,
    conics_ptr,
    opacities_ptr,
    colors_ptr,
    pairs_ptr,
    starts_ptr,
    counts_ptr,
    first_bucket_ptr,
    bucket_tile_ptr,
    stop_ptr,
    grad_out_ptr,
    grad_transmittance_ptr,
    start_transmittance_ptr,
    behind_ptr,
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
    BLOCK_P: tl.constexpr,
    BUCKET: tl.constexpr,
    ABSGRAD: tl.constexpr,
    SUMS: tl.constexpr,
):
    """With ``SUMS``, the first pass: per (bucket, pixel) the product of ``1 - alpha`` over
    the bucket into ``start_transmittance_ptr`` and ``sum_k w_k h_k / T_start`` into
    ``behind_ptr`` (the scan then turns both into what their names say). Without, the
    gradients, from the scanned buffers."""
    saved, local, valid, ids, px, py, is_pixel, pixel, stop, live = _bucket_of(
        bucket_tile_ptr, first_bucket_ptr, counts_ptr, starts_ptr, pairs_ptr, stop_ptr,
        tiles_x, tiles_per_image, S, BLOCK_P, BUCKET,
    )  # fmt: skip
    if SUMS:
        product = tl.full((BLOCK_P,), 1.0, tl.float32)
        partial = tl.zeros((BLOCK_P,), tl.float32)
    if live:
        # h first: few (Gaussian, pixel) arrays are alive during its loop over the channels
        grad_t = tl.load(grad_transmittance_ptr + pixel, mask=is_pixel, other=0.0)
        h = _channel_sums(
            grad_out_ptr, colors_ptr, pixel, is_pixel, ids, valid, grad_t, dim, BUCKET, BLOCK_P
        )
        alpha, keep, in_front, through, drawn, raw, skip, dx, dy, ca, cb, cc, opacity = _weights_of(
            means_ptr,
            conics_ptr,
            opacities_ptr,
            ids,
            valid,
            local,
            stop,
            px,
            py,
            max_alpha,
            alpha_min,
        )  # fmt: skip
        if SUMS:
            partial = tl.sum(in_front * alpha * h, 0)
            last = (local == tl.max(local, 0))[:, None]
            product = tl.sum(tl.where(last, through, 0.0), 0)
        else:
            start_t = tl.load(start_transmittance_ptr + saved, mask=is_pixel, other=0.0)
            behind = tl.load(behind_ptr + saved, mask=is_pixel, other=0.0)
            _gradients(
                start_t[None, :] * in_front, alpha, keep, drawn, raw, skip, dx, dy, ca, cb, cc,
                opacity, h, behind, ids, valid, pixel, is_pixel, dim, max_alpha, grad_out_ptr,
                grad_means_ptr, grad_conics_ptr, grad_opacities_ptr, grad_colors_ptr,
                absgrad_ptr, ABSGRAD,
            )  # fmt: skip
    if SUMS:
        tl.store(start_transmittance_ptr + saved, product, mask=is_pixel)
        tl.store(behind_ptr + saved, partial, mask=is_pixel)


@triton.jit
def _gradients(
    before, alpha, keep, drawn, raw, skip, dx, dy, ca, cb, cc, opacity, h, behind, ids, valid,
    pixel, is_pixel, dim, max_alpha, grad_out_ptr, grad_means_ptr, grad_conics_ptr,
    grad_opacities_ptr, grad_colors_ptr, absgrad_ptr, ABSGRAD: tl.constexpr,
):  # fmt: skip
    """A bucket's gradients from the transmittance ``before`` each Gaussian at each pixel
    and the sum ``behind`` the bucket, reduced over the pixels, added with relaxed atomics."""
    weights = before * alpha
    h = tl.where(drawn, h, 0.0)
    wh = weights * h
    # dL/dalpha_k = T_before_k h_k - (sum_{i > k} w_i h_i) / (1 - alpha_k)
    after_k = behind[None, :] + (tl.cumsum(wh, 0, reverse=True) - wh)
    grad_alpha = before * h - after_k / tl.maximum(keep, 1e-30)
    grad_logit = tl.where(drawn & ~skip & (raw <= max_alpha), grad_alpha * raw, 0.0)
    # d(-sigma)/d(mean) = -(a dx + b dy, c dy + b dx), d(-sigma)/d(a, b, c) =
    # -(dx^2 / 2, dx dy, dy^2 / 2): five sums over the pixels, then per Gaussian
    along_x = grad_logit * dx
    along_y = grad_logit * dy
    sum_x, sum_y = tl.sum(along_x, 1), tl.sum(along_y, 1)
    to_means = grad_means_ptr + ids * 2
    tl.atomic_add(to_means, -(ca * sum_x + cb * sum_y), mask=valid, sem="relaxed")
    tl.atomic_add(to_means + 1, -(cc * sum_y + cb * sum_x), mask=valid, sem="relaxed")
    to_conics = grad_conics_ptr + ids * 3
    tl.atomic_add(to_conics, -0.5 * tl.sum(along_x * dx, 1), mask=valid, sem="relaxed")
    tl.atomic_add(to_conics + 1, -tl.sum(along_x * dy, 1), mask=valid, sem="relaxed")
    tl.atomic_add(to_conics + 2, -0.5 * tl.sum(along_y * dy, 1), mask=valid, sem="relaxed")
    total = tl.sum(grad_logit, 1)
    grad_opacity = tl.where(opacity > 1e-30, total / tl.maximum(opacity, 1e-30), 0.0)
    tl.atomic_add(grad_opacities_ptr + ids, grad_opacity, mask=valid, sem="relaxed")
    if ABSGRAD:
        per_x = tl.abs(ca[:, None] * along_x + cb[:, None] * along_y)
        per_y = tl.abs(cc[:, None] * along_y + cb[:, None] * along_x)
        tl.atomic_add(absgrad_ptr + ids * 2, tl.sum(per_x, 1), mask=valid, sem="relaxed")
        tl.atomic_add(absgrad_ptr + ids * 2 + 1, tl.sum(per_y, 1), mask=valid, sem="relaxed")
    # dL/dc_k = sum_p w_k g
    for channel in range(0, dim):
        grad_out = tl.load(grad_out_ptr + pixel * dim + channel, mask=is_pixel, other=0.0)
        grad_color = tl.sum(weights * grad_out[None, :], 1)
        tl.atomic_add(grad_colors_ptr + ids * dim + channel, grad_color, mask=valid, sem="relaxed")


def _pixels(tile_size: int) -> int:
    """Lanes per forward program: the tile's pixels, rounded up to a power of two (>= 16
    for tl.dot)."""
    return max(16, triton.next_power_of_2(tile_size * tile_size))


def _buckets(counts: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """Each tile's first bucket ``(T,)`` and each bucket's tile ``(B,)``."""
    per_tile = torch.div(counts + (size - 1), size, rounding_mode="floor")
    first = torch.cumsum(per_tile, 0) - per_tile
    tiles = torch.repeat_interleave(torch.arange(counts.shape[0], device=counts.device), per_tile)
    return first, tiles


def forward(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    lists: TileLists,
    tile_size: int,
    rules: tuple[float, float, float],
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite every tile: ``tiles (T, S, S, D)``, ``transmittance (T, S, S)`` and ``stop
    (T, S, S)``.

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
    tensors = (means2d, conics, opacities, colors, pairs, lists.starts, counts)
    layout = (lists.tiles_x, lists.tiles_x * lists.tiles_y, dim, *rules)
    triton_configs.run(
        _forward_kernel,
        lambda meta: (num_tiles, max(1, triton.cdiv(dim, meta["BLOCK_D"]))),
        (*tensors, out, transmittance, stop, *layout),
        {"S": size, "PIX": _pixels(size), "BLOCK_G": BLOCK_G},
        device=colors.device,
        options={"enable_fp_fusion": FP_FUSION},
    )
    return out, transmittance, stop


def backward(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    lists: TileLists,
    stop: Tensor,
    grad_out: Tensor,
    grad_transmittance: Tensor,
    rules: tuple[float, float, float],
    absgrad: bool,
) -> tuple[Tensor, ...]:
    """Gradients of :func:`forward` w.r.t. means2d, conics, opacities and colors (and,
    with ``absgrad``, the summed per-pixel absolute means2d gradients ``(M, 2)``).
    ``stop`` is what the forward returned.

    Three launches: the per-(bucket, pixel) products and partial sums, the scan over each
    tile's buckets that turns them into each bucket's starting transmittance and what lies
    behind it (``8 * S * S`` bytes per bucket while the backward runs), then the gradients.
    """
    size = stop.shape[1]
    grads = [torch.zeros_like(t) for t in (means2d, conics, opacities, colors)]
    absolute = torch.zeros_like(means2d) if absgrad else grads[0]
    config = triton_configs.config_for(colors.device)
    first, bucket_tiles = _buckets(lists.counts, config.bucket)
    buckets, tiles = bucket_tiles.shape[0], lists.counts.shape[0]
    if buckets == 0:
        return (*grads, absolute) if absgrad else tuple(grads)
    product = colors.new_empty(buckets, size * size)
    partial = colors.new_empty(buckets, size * size)
    grad_out, grad_transmittance = grad_out.contiguous(), grad_transmittance.contiguous()
    lists_of = (lists.gaussians, lists.starts, lists.counts, first, bucket_tiles, stop)
    inputs = (means2d, conics, opacities, colors, *lists_of, grad_out, grad_transmittance)
    layout = (lists.tiles_x, lists.tiles_x * lists.tiles_y, colors.shape[1], *rules[:2])

    def grid(meta: dict[str, int]) -> tuple[int, int]:
        return buckets, triton.cdiv(size * size, meta["BLOCK_P"])

    options = {"enable_fp_fusion": FP_FUSION}
    for sums in (True, False):
        triton_configs.run(
            _backward_kernel,
            grid,
            (*inputs, product, partial, *grads, absolute, *layout),
            {"S": size, "ABSGRAD": absgrad and not sums, "SUMS": sums},
            device=colors.device,
            bucket=config.bucket,
            zeroed=(*grads, absolute),
            options=options,
        )
        if sums:
            _scan_kernel[(tiles, triton.cdiv(size * size, SCAN_PIXELS))](
                *(first, lists.counts, product, partial),
                S=size,
                BLOCK_P=SCAN_PIXELS,
                BUCKET=config.bucket,
                num_warps=SCAN_WARPS,
                **options,
            )
    return (*grads, absolute) if absgrad else tuple(grads)


__all__ = ["BLOCK_G", "FP_FUSION", "backward", "forward"]
