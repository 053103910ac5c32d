"""Front-to-back alpha compositing of sorted tile lists, chunked, with bounded memory.

Every tile's list is walked in chunks of ``chunk_size`` Gaussians; all tiles that still
have Gaussians and unsaturated pixels advance one chunk per step, in groups of at most
``max_pairs / (chunk_size * tile_size^2)`` tiles. The running transmittance is carried
between chunks. The loop is one autograd node that keeps only each step's indices and
incoming pixel state and recomputes the per-(Gaussian, pixel) values in backward, so
peak memory is set by ``max_pairs``, not by the total number of (Gaussian, pixel) pairs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from dego.splatting.tiles import TileLists


@dataclasses.dataclass(frozen=True)
class CompositeRules:
    """gsplat's per-pixel rules (see :func:`dego.splatting.splat`)."""

    max_alpha: float
    alpha_min: float
    transmittance_min: float


def _alphas(
    mean: Tensor, conic: Tensor, opacity: Tensor, origins: Tensor, size: int, rules: CompositeRules
) -> tuple[Tensor, ...]:
    """Per (Gaussian, pixel) alpha of K Gaussians over G tiles of ``size`` x ``size`` pixels.

    ``mean`` ``(G, K, 2)``, ``conic`` ``(G, K, 3)``, ``opacity`` ``(G, K)`` (0 for padding),
    ``origins`` ``(G, 2)`` centre of each tile's first pixel. sigma = 0.5 (a dx^2 + c dy^2)
    + b dx dy is separable into per-column (dx) and per-row (dy) terms, so only two
    passes touch the ``(G, K, S, S)`` tensor before the exponential. Returns alpha, the
    unclamped ``o exp(-sigma)``, the skip mask, dx ``(G, K, S)`` and dy ``(G, K, S)``.
    """
    steps = torch.arange(size, device=mean.device, dtype=mean.dtype)
    dx = mean[..., 0:1] - (origins[:, None, 0:1] + steps)
    dy = mean[..., 1:2] - (origins[:, None, 1:2] + steps)
    a, b, c = conic.unbind(-1)
    # log(o) - sigma; the clamp keeps log finite for o = 0 (then alpha < alpha_min: skipped)
    log_opacity = opacity.clamp_min(1e-30).log()
    row = (log_opacity.unsqueeze(-1) - 0.5 * c.unsqueeze(-1) * dy * dy).unsqueeze(-1)
    col = (-0.5 * a.unsqueeze(-1) * dx * dx).unsqueeze(-2)
    logit = torch.addcmul(row + col, dy.unsqueeze(-1), (-b.unsqueeze(-1) * dx).unsqueeze(-2))
    raw = torch.exp(logit)
    skip = (raw < rules.alpha_min) | (logit > log_opacity[..., None, None])  # or sigma < 0
    alpha = torch.where(skip, 0.0, raw.clamp(max=rules.max_alpha))
    return alpha, raw, skip, dx, dy


def _transmittances(start: Tensor, alpha: Tensor) -> tuple[Tensor, Tensor]:
    """Relative transmittance before each Gaussian ``prod_{j<k} (1 - alpha_j)`` and the
    absolute transmittance after it, both ``(G, K, S, S)``."""
    product = torch.cumprod(1 - alpha, dim=1)
    relative_before = torch.cat([torch.ones_like(product[:, :1]), product[:, :-1]], dim=1)
    return relative_before, start.unsqueeze(1) * product


def _chunk_forward(
    transmittance: Tensor,  # (G, S, S) at the start of the chunk
    finished: Tensor,  # (G, S, S) bool: pixel already stopped
    mean: Tensor,  # (G, K, 2)
    conic: Tensor,  # (G, K, 3)
    opacity: Tensor,  # (G, K), 0 for padding
    color: Tensor,  # (G, K, D)
    origins: Tensor,  # (G, 2)
    rules: CompositeRules,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite K sorted Gaussians into G tiles (no autograd): the colour contribution
    ``(G, S*S, D)``, the transmittance after the chunk and the updated ``finished``."""
    size = transmittance.shape[-1]
    alpha = _alphas(mean, conic, opacity, origins, size, rules)[0]
    # A finished pixel enters with zero transmittance, so it blocks and weighs nothing.
    start = transmittance.masked_fill(finished, 0.0)
    relative_before, after = _transmittances(start, alpha)
    # A pixel stops before the first Gaussian that would take its transmittance to
    # transmittance_min or below; "after" is non-increasing, so blocked stays blocked.
    blocked = after <= rules.transmittance_min
    weights = (relative_before * alpha).mul_(start.unsqueeze(1)).masked_fill_(blocked, 0.0)
    contribution = torch.bmm(weights.flatten(2).transpose(1, 2), color)
    new_transmittance = torch.where(finished, transmittance, start - weights.sum(1))
    return contribution, new_transmittance, finished | blocked[:, -1]


def _chunk_backward(
    transmittance: Tensor,
    finished: Tensor,
    mean: Tensor,
    conic: Tensor,
    opacity: Tensor,
    color: Tensor,
    origins: Tensor,
    rules: CompositeRules,
    grad_contribution: Tensor,  # (G, S*S, D)
    grad_transmittance: Tensor,  # (G, S, S) of the transmittance after the chunk
    absgrad: bool = False,
) -> tuple[Tensor, ...]:
    """Closed-form gradients of :func:`_chunk_forward`, recomputing alpha once.

    Returns the gradients of the incoming transmittance, mean, conic, opacity and colour,
    and with ``absgrad`` also the per-pixel absolute mean gradients summed over pixels.
    """
    g, k, _ = color.shape
    size = transmittance.shape[-1]
    alpha, raw, skip, dx, dy = _alphas(mean, conic, opacity, origins, size, rules)
    start = transmittance.masked_fill(finished, 0.0)
    relative_before, after = _transmittances(start, alpha)
    blocked = after <= rules.transmittance_min
    del after
    # L = sum_k w_k (g_out . c_k) + g_T (start - sum_k w_k), w_k = start r_k alpha_k with
    # r_k = prod_{j<k} (1 - alpha_j); h_k = dL/dw_k, zero where blocked (w_k = 0).
    grad_t = grad_transmittance.masked_fill(finished, 0.0)
    h = torch.bmm(color, grad_contribution.transpose(1, 2)).view(g, k, size, size)
    h.sub_(grad_t.unsqueeze(1)).masked_fill_(blocked, 0.0)
    weights = (relative_before * alpha).mul_(start.unsqueeze(1)).masked_fill_(blocked, 0.0)
    grad_color = torch.bmm(weights.flatten(2), grad_contribution)
    wh = weights.mul_(h)
    grad_start = grad_t + wh.sum(1) / start.clamp_min(1e-30)
    later = wh.sum(1, keepdim=True) - torch.cumsum(wh, dim=1)  # sum over i > k of w_i h_i
    del wh
    # dL/dalpha_k = start r_k h_k - (sum_{i>k} w_i h_i) / (1 - alpha_k)
    grad_alpha = relative_before.mul_(start.unsqueeze(1)).mul_(h)
    grad_alpha.sub_(later.div_((1 - alpha).clamp_min_(1e-30)))
    grad_in = torch.where(finished, grad_transmittance, grad_start)
    # alpha = where(skip, 0, min(raw, max_alpha)), raw = exp(log o - sigma)
    grad_logit = grad_alpha.mul_(raw).masked_fill_(skip | (raw > rules.max_alpha), 0.0)
    per_col = grad_logit.sum(-2)  # (G, K, S): summed over rows
    per_row = grad_logit.sum(-1)  # (G, K, S): summed over columns
    x1, x2 = (per_col * dx).sum(-1), (per_col * dx * dx).sum(-1)
    y1, y2 = (per_row * dy).sum(-1), (per_row * dy * dy).sum(-1)
    xy = (torch.einsum("gkrc,gkc->gkr", grad_logit, dx) * dy).sum(-1)
    a, b, c = conic.unbind(-1)
    # d(-sigma)/d(mean) = -(a dx + b dy, c dy + b dx)
    # d(-sigma)/d(a, b, c) = -(dx^2 / 2, dx dy, dy^2 / 2)
    grad_mean = -torch.stack([a * x1 + b * y1, c * y1 + b * x1], -1)
    grad_conic = -torch.stack([0.5 * x2, xy, 0.5 * y2], -1)
    total = grad_logit.sum((-1, -2))
    grad_opacity = torch.where(opacity > 1e-30, total / opacity.clamp_min(1e-30), 0.0)
    if not absgrad:
        return grad_in, grad_mean, grad_conic, grad_opacity, grad_color
    # rows index dy, columns dx: the per-pixel mean gradient is -grad_logit (a dx + b dy, ...)
    row_dy, col_dx = dy.unsqueeze(-1), dx.unsqueeze(-2)
    per_pixel_x = (a[..., None, None] * col_dx + b[..., None, None] * row_dy) * grad_logit
    per_pixel_y = (c[..., None, None] * row_dy + b[..., None, None] * col_dx) * grad_logit
    abs_mean = torch.stack([per_pixel_x.abs().sum((-1, -2)), per_pixel_y.abs().sum((-1, -2))], -1)
    return grad_in, grad_mean, grad_conic, grad_opacity, grad_color, abs_mean


COMPILED_KERNELS: str | None = "inductor"
"""The ``torch.compile`` backend of the chunk kernels when a splat is itself being compiled
(the compositing loop is data-dependent and runs eagerly; its kernels need not): read
while tracing. ``None``: eager kernels."""

_KERNELS: dict[str, tuple[Callable[..., Any], Callable[..., Any]]] = {}


def chunk_kernels(backend: str | None) -> tuple[Callable[..., Any], Callable[..., Any]]:
    """``(forward, backward)`` chunk kernels: the eager functions, or (``backend``, e.g.
    ``"inductor"``) ``torch.compile``-d with dynamic shapes, compiled once per process
    and backend. Compiled, the elementwise chains over ``(G, K, S, S)`` fuse into a few
    loops, which is where a compiled splat gains its speed."""
    if backend is None:
        return _chunk_forward, _chunk_backward
    if backend not in _KERNELS:
        _KERNELS[backend] = (
            torch.compile(_chunk_forward, backend=backend, dynamic=True),
            torch.compile(_chunk_backward, backend=backend, dynamic=True),
        )
    return _KERNELS[backend]


@dataclasses.dataclass(frozen=True)
class _Step:
    """What backward needs of one (chunk, tile group) step: tiny next to its pairs."""

    group: Tensor  # (G,) tile indices
    ids: Tensor  # (G, K) flat Gaussian indices (padding repeats a valid index)
    valid: Tensor  # (G, K) bool: not padding
    transmittance: Tensor  # (G, S, S) before the step
    finished: Tensor  # (G, S, S) before the step

    def chunk_inputs(
        self, means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, origins: Tensor
    ) -> tuple[Tensor, ...]:
        """The step's arguments of :func:`_chunk_forward` / :func:`_chunk_backward`."""
        ids = self.ids
        opacity = torch.where(self.valid, opacities[ids], 0.0)
        return (
            self.transmittance,
            self.finished,
            means2d[ids],
            conics[ids],
            opacity,
            colors[ids],
            origins[self.group],
        )


class _CompositeTiles(torch.autograd.Function):
    """The whole chunked compositing loop as one autograd node.

    Forward runs without autograd and records, per step, only the tiles, the Gaussian
    indices and the incoming per-pixel state. Backward walks the steps in reverse,
    recomputes each with :func:`_chunk_backward` and accumulates the per-Gaussian
    gradients into one buffer each, carrying the transmittance gradient per tile.
    """

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
        chunk_size: int,
        max_pairs: int,
        absgrad_sink: Callable[[Tensor], None] | None,
        kernel_backend: str | None,
    ) -> tuple[Tensor, Tensor]:
        chunk_forward, _ = chunk_kernels(kernel_backend)
        num_tiles, dim = lists.num_tiles, colors.shape[-1]
        device, dtype = colors.device, colors.dtype
        pixels = tile_size * tile_size
        out = torch.zeros(num_tiles, pixels, dim, device=device, dtype=dtype)
        transmittance = torch.ones(num_tiles, tile_size, tile_size, device=device, dtype=dtype)
        finished = torch.zeros(num_tiles, tile_size, tile_size, device=device, dtype=torch.bool)
        origins = _tile_origins(lists, tile_size, dtype)
        ends = lists.starts + lists.counts
        last = max(lists.gaussians.shape[0] - 1, 0)
        offsets = torch.arange(chunk_size, device=device)
        group_size = max(1, max_pairs // (chunk_size * pixels))
        steps: list[_Step] = []

        active = torch.arange(num_tiles, device=device)[lists.counts > 0]
        step = 0
        while active.numel():
            for group in active.split(group_size):
                position = lists.starts[group, None] + step * chunk_size + offsets
                valid = position < ends[group, None]
                ids = lists.gaussians[position.clamp(max=last)]
                record = _Step(group, ids, valid, transmittance[group], finished[group])
                contribution, t_new, f_new = chunk_forward(
                    *record.chunk_inputs(means2d, conics, opacities, colors, origins), rules
                )
                out.index_add_(0, group, contribution)
                transmittance.index_copy_(0, group, t_new)
                finished.index_copy_(0, group, f_new)
                steps.append(record)
            step += 1
            more = (lists.counts[active] > step * chunk_size) & ~finished[active].flatten(1).all(1)
            active = active[more]

        ctx.save_for_backward(means2d, conics, opacities, colors, origins)
        ctx.steps, ctx.rules, ctx.absgrad_sink = steps, rules, absgrad_sink
        ctx.kernel_backend = kernel_backend
        return out.view(num_tiles, tile_size, tile_size, dim), transmittance

    @staticmethod
    def backward(
        ctx: Any, grad_out: Tensor, grad_transmittance: Tensor
    ) -> tuple[Tensor | None, ...]:
        means2d, conics, opacities, colors, origins = ctx.saved_tensors
        grads = [torch.zeros_like(t) for t in (means2d, conics, opacities, colors)]
        sink = ctx.absgrad_sink
        if sink is not None:
            grads.append(torch.zeros_like(means2d))
        grad_out = grad_out.flatten(1, 2)  # (T, S*S, D)
        grad_t = grad_transmittance.clone()  # gradient of the running transmittance, per tile
        _, chunk_backward = chunk_kernels(ctx.kernel_backend)
        for record in reversed(ctx.steps):
            ids, valid, group = record.ids, record.valid, record.group
            grad_in, *per_gaussian = chunk_backward(
                *record.chunk_inputs(means2d, conics, opacities, colors, origins),
                ctx.rules,
                grad_out[group],
                grad_t[group],
                absgrad=sink is not None,
            )
            grad_t.index_copy_(0, group, grad_in)
            per_gaussian[2] = per_gaussian[2] * valid  # padding repeats real ids
            flat_ids = ids.reshape(-1)
            for total, grad in zip(grads, per_gaussian, strict=True):
                total.index_add_(0, flat_ids, grad.flatten(0, 1))
        if sink is not None:
            sink(grads.pop())
        return (*grads, None, None, None, None, None, None, None)


def _tile_origins(lists: TileLists, tile_size: int, dtype: torch.dtype) -> Tensor:
    """``(T, 2)`` pixel-centre coordinates of each tile's first pixel."""
    in_image = torch.arange(lists.num_tiles, device=lists.counts.device) % (
        lists.tiles_x * lists.tiles_y
    )
    origins = torch.stack([in_image % lists.tiles_x, in_image // lists.tiles_x], -1)
    return origins.to(dtype) * tile_size + 0.5


def composite_tiles(
    lists: TileLists,
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    *,
    tile_size: int,
    rules: CompositeRules,
    chunk_size: int,
    max_pairs: int,
    absgrad_sink: Callable[[Tensor], None] | None = None,
    kernel_backend: str | None = None,
) -> tuple[Tensor, Tensor]:
    """Composite every tile; returns per-tile colour sums ``(T, S, S, D)`` and final
    transmittance ``(T, S, S)`` for the ``T = lists.num_tiles`` tiles. Differentiable
    w.r.t. ``means2d``, ``conics``, ``opacities`` and ``colors``. With ``absgrad_sink``,
    backward also sums each Gaussian's per-pixel ``|dL/d means2d|`` (AbsGS) and passes
    the ``(M, 2)`` result to it. ``kernel_backend``: see :func:`chunk_kernels`."""
    return _CompositeTiles.apply(
        means2d,
        conics,
        opacities,
        colors,
        lists,
        tile_size,
        rules,
        chunk_size,
        max_pairs,
        absgrad_sink,
        kernel_backend,
    )
