"""Gaussians -> voxel grids: exact, chunked Gaussian-to-voxel splatting.

Each Gaussian is evaluated only at the voxel centres of its neighbourhood: the exact
axis-aligned box of its ``cutoff_sigma`` ellipsoid (``"ellipsoid"``), or the official
fixed ``(2 nbh + 1)^3`` cube around its voxel (``"cube"``). (Gaussian, voxel) pairs are
generated with ``repeat_interleave`` over per-Gaussian box sizes, a bounded number at a
time, and reduced into the grid with ``index_add_``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import torch
from jaxtyping import Float, Int
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from dego._typing import typechecked
from dego.classes import FREE_LABEL
from dego.gaussians import GaussianSet, _gram_of_scaled_rotation
from dego.grid import VoxelGrid

Mode = Literal["additive", "probabilistic"]
Neighborhood = Literal["ellipsoid", "cube"]

_TINY_WEIGHT = 1e-30
# Additive cube mode skips (Gaussian, voxel) pairs with exp(-q/2) < 1e-10, i.e. q > 2 * 23.03;
# the skipped total per voxel is below (2 nbh + 1)^3 * 1e-10 (1.3e-7 for nbh = 5) times the
# largest |opacity| or |feature|.
_NEGLIGIBLE_QUADRATIC = 2 * 23.026


@dataclasses.dataclass(frozen=True)
class VoxelOutput:
    """Voxelised Gaussians.

    Attributes:
        density: ``(B, X, Y, Z)`` occupancy in [0, 1].
        features: ``(B, X, Y, Z, C)`` aggregated features (C may be 0).
    """

    density: Float[Tensor, "B X Y Z"]
    features: Float[Tensor, "B X Y Z C"]

    def labels(
        self,
        threshold: float = 0.05,
        free_label: int = FREE_LABEL,
        label_offset: int = 1,
        min_density: float | None = None,
        max_z_index: int | None = None,
    ) -> Int[Tensor, "B X Y Z"]:
        """Label grid: ``argmax(features) + label_offset``, ``free_label`` where density
        < ``threshold``.

        The official DeGO post-processing is available as two knobs, off by default:
        ``min_density`` (density below it is zeroed first; official 1e-3) and
        ``max_z_index`` (voxels with z index >= it are free; the official "roof" is 11).
        """
        density = self.density.detach()
        if min_density is not None:
            density = torch.where(density < min_density, torch.zeros_like(density), density)
        if self.features.shape[-1]:
            labels = self.features.detach().argmax(-1) + label_offset
        else:
            labels = torch.full_like(density, label_offset, dtype=torch.long)
        free = density < threshold
        if max_z_index is not None:
            z = torch.arange(density.shape[-1], device=density.device)
            free = free | (z >= max_z_index)
        return labels.masked_fill(free, free_label)


@dataclasses.dataclass(frozen=True)
class VoxelizerConfig:
    """Settings shared by :func:`voxelize` and :class:`GaussianVoxelizer`."""

    mode: Mode = "additive"
    neighborhood: Neighborhood = "ellipsoid"
    cutoff_sigma: float = 3.0
    nbh: int | None = None
    chunk_size: int = 1 << 21

    def __post_init__(self) -> None:
        if self.mode not in ("additive", "probabilistic"):
            raise ValueError(f"mode: expected 'additive' or 'probabilistic', got {self.mode!r}")
        if self.neighborhood not in ("ellipsoid", "cube"):
            raise ValueError(
                f"neighborhood: expected 'ellipsoid' or 'cube', got {self.neighborhood!r}"
            )
        if not (isinstance(self.cutoff_sigma, int | float) and self.cutoff_sigma > 0):
            raise ValueError(f"cutoff_sigma: expected a positive number, got {self.cutoff_sigma!r}")
        if self.neighborhood == "cube":
            if self.nbh is None:
                raise ValueError("nbh: required with neighborhood='cube' (official: 4 or 5)")
            if not isinstance(self.nbh, int) or isinstance(self.nbh, bool) or self.nbh < 0:
                raise ValueError(f"nbh: expected an int >= 0, got {self.nbh!r}")
        if not isinstance(self.chunk_size, int) or self.chunk_size < 1:
            raise ValueError(f"chunk_size: expected a positive int, got {self.chunk_size!r}")


def _ellipsoid_boxes(
    gaussians: GaussianSet, grid: VoxelGrid, cutoff_sigma: float
) -> tuple[Tensor, Tensor]:
    """Inclusive per-axis voxel index ranges ``(M, 3)`` low / high of the voxels whose centres
    lie in the axis-aligned box of each Gaussian's ``cutoff_sigma`` ellipsoid, clipped to the
    grid (empty where high < low)."""
    means = gaussians.means.detach().reshape(-1, 3)
    lower = torch.tensor(grid.lower, dtype=means.dtype, device=means.device)
    size = torch.tensor(grid.voxel_size, dtype=means.dtype, device=means.device)
    shape = torch.tensor(grid.shape, device=means.device)
    position = (means - lower) / size  # in voxel units; centre of voxel i is at i + 0.5
    # sqrt(Sigma_jj) = |row j of R diag(s)|
    scaled_rotation = gaussians.rotation_matrices().detach() * gaussians.scales.detach().unsqueeze(
        -2
    )
    std = scaled_rotation.square().sum(-1).sqrt().reshape(-1, 3)
    half = cutoff_sigma * std / size
    # voxel i is inside iff |i + 0.5 - position| <= half
    low = torch.ceil(position - half - 0.5).long()
    high = torch.floor(position + half - 0.5).long()
    return low.clamp(min=0), torch.minimum(high, shape - 1)


def _pair_quadratic(
    means: Tensor,  # (M, 3)
    precisions: Tensor,  # (M, 6): xx, yy, zz, xy, xz, yz
    owner: Tensor,  # (P,) Gaussian of each pair
    centres: Tensor,  # (P, 3) voxel centre of each pair
) -> Tensor:
    """Per-pair Mahalanobis quadratic ``d^T P d`` ``(P,)`` from the 6 unique entries."""
    d = centres - means[owner]
    p = precisions[owner]
    dx, dy, dz = d.unbind(-1)
    return (
        p[:, 0] * dx * dx
        + p[:, 1] * dy * dy
        + p[:, 2] * dz * dz
        + 2 * (p[:, 3] * dx * dy + p[:, 4] * dx * dz + p[:, 5] * dy * dz)
    )


def _kernel_terms(
    quadratic: Tensor,  # (P,)
    opacity: Tensor,  # (P,) opacity of each pair's Gaussian
    features: Tensor,  # (P, C) features of each pair's Gaussian
    log_normaliser: Tensor,  # (P,) log of (2 pi)^(-3/2) sqrt(det P) of each pair's Gaussian
    probabilistic: bool,
) -> tuple[Tensor, Tensor, Tensor]:
    """Per-pair density term, feature term and (probabilistic) mixture weight."""
    g = torch.exp(-0.5 * quadratic)
    if not probabilistic:
        return opacity * g, g.unsqueeze(-1) * features, g.new_zeros(0)
    # log(1 - o g), kept finite where o g reaches 1 (a single Gaussian then saturates)
    survival = torch.log1p(-(opacity * g).clamp(max=1 - torch.finfo(g.dtype).eps))
    weight = opacity * torch.exp(log_normaliser - 0.5 * quadratic)
    return survival, weight.unsqueeze(-1) * features, weight


def _pair_terms(
    means: Tensor,
    precisions: Tensor,
    opacities: Tensor,  # (M,)
    features: Tensor,  # (M, C)
    owner: Tensor,
    centres: Tensor,
    log_normaliser: Tensor,  # (M,)
    probabilistic: bool,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_kernel_terms` of the (Gaussian ``owner``, voxel centre) pairs."""
    quadratic = _pair_quadratic(means, precisions, owner, centres)
    return _kernel_terms(
        quadratic, opacities[owner], features[owner], log_normaliser[owner], probabilistic
    )


def _chunks(counts: Tensor, chunk_size: int) -> list[tuple[int, int]]:
    """Consecutive Gaussian ranges whose pair counts sum to at most ``chunk_size``
    (a single Gaussian with more pairs forms its own chunk)."""
    ends = torch.cumsum(counts, 0).tolist()
    ranges, start, base = [], 0, 0
    for i, end in enumerate(ends):
        if end - base > chunk_size and i > start:
            ranges.append((start, i))
            start, base = i, ends[i - 1]
    if ends:
        ranges.append((start, len(ends)))
    return ranges


@typechecked
def voxelize(
    gaussians: GaussianSet,
    grid: VoxelGrid,
    *,
    features: Float[Tensor, "B N C"] | None = None,
    mode: Mode = "additive",
    neighborhood: Neighborhood = "ellipsoid",
    cutoff_sigma: float = 3.0,
    nbh: int | None = None,
    chunk_size: int = 1 << 21,
) -> VoxelOutput:
    """Splat ``(B, N)`` Gaussians into ``grid``: ``g_i(x) = exp(-0.5 d^T P_i d)`` at voxel centres.

    Args:
        gaussians: batch shape ``(B,)``.
        grid: the voxel grid.
        features: ``(B, N, C)``; defaults to ``gaussians.features`` (none: C = 0).
        mode: ``"additive"`` (official DeGO / GaussianFlowOcc): density =
            clamp(sum o_i g_i, 0, 1), features = sum g_i f_i. ``"probabilistic"``
            (GaussianFormer-2 with opacity): density = 1 - prod(1 - o_i g_i) (in log
            space), features = sum p_i f_i / sum p_i with p_i = o_i N(x; mu_i, Sigma_i)
            (0 where the sum vanishes).
        neighborhood: ``"ellipsoid"``: every voxel whose centre lies in the axis-aligned
            box of the ``cutoff_sigma`` ellipsoid (half-extent ``k sqrt(Sigma_jj)``), so no
            voxel with Mahalanobis distance <= k is missed, rotated Gaussians included.
            ``"cube"``: the official fixed ``(2 nbh + 1)^3`` cube around
            ``floor((mu - lower) / voxel)``.
        cutoff_sigma: k of the ellipsoid neighbourhood.
        nbh: half-width of the cube neighbourhood (official: 4; its evaluation uses 5).
        chunk_size: (Gaussian, voxel) pairs evaluated at once; bounds peak memory
            (about ``chunk_size * (40 + 8 C)`` bytes in float32), whatever N is.

    Gaussians partly or wholly outside the grid contribute where they overlap it.
    Differentiable w.r.t. means, quats, scales, opacities and features.
    """
    config = VoxelizerConfig(mode, neighborhood, cutoff_sigma, nbh, chunk_size)
    return _voxelize(gaussians, grid, features, config)


def _voxelize(
    gaussians: GaussianSet, grid: VoxelGrid, features: Tensor | None, config: VoxelizerConfig
) -> VoxelOutput:
    if len(gaussians.batch_shape) != 1:
        raise ValueError(
            f"gaussians: expected batch shape (B,), got {tuple(gaussians.batch_shape)}; "
            "flatten extra axes with GaussianSet.flatten_batch()"
        )
    b, n = gaussians.batch_shape[0], gaussians.num_gaussians
    features = gaussians.features if features is None else features
    if features is None:
        features = gaussians.means.new_zeros(b, n, 0)
    if features.shape[:2] != (b, n) or features.dtype != gaussians.dtype:
        raise ValueError(
            f"features: expected ({b}, {n}, C) {gaussians.dtype}, got "
            f"{tuple(features.shape)} {features.dtype}"
        )
    dtype, device = gaussians.dtype, gaussians.device
    x, y, z = grid.shape
    channels = features.shape[-1]
    probabilistic = config.mode == "probabilistic"

    precision = _gram_of_scaled_rotation(gaussians.quats, gaussians.scales.reciprocal())
    precision = precision.reshape(-1, 3, 3)
    precision6 = torch.stack(
        [
            precision[:, 0, 0],
            precision[:, 1, 1],
            precision[:, 2, 2],
            precision[:, 0, 1],
            precision[:, 0, 2],
            precision[:, 1, 2],
        ],
        -1,
    )
    log_normaliser = -1.5 * math.log(2 * math.pi) - gaussians.scales.log().sum(-1).reshape(-1)
    means = gaussians.means.reshape(-1, 3)
    opacities = gaussians.opacities.reshape(-1)
    flat_features = features.reshape(b * n, channels)
    lower = torch.tensor(grid.lower, dtype=dtype, device=device)
    size = torch.tensor(grid.voxel_size, dtype=dtype, device=device)

    if config.neighborhood == "cube":
        return _voxelize_cube(gaussians, grid, flat_features, precision6, log_normaliser, config)
    low, high = _ellipsoid_boxes(gaussians, grid, config.cutoff_sigma)
    extent = (high - low + 1).clamp(min=0)  # (M, 3)
    counts = extent.prod(-1)
    num_voxels = b * x * y * z
    density = torch.zeros(num_voxels, dtype=dtype, device=device)
    accumulated = torch.zeros(num_voxels, channels, dtype=dtype, device=device)
    weights = torch.zeros(num_voxels if probabilistic else 0, dtype=dtype, device=device)
    grad_needed = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means, precision6, opacities, flat_features)
    )
    for start, stop in _chunks(counts, config.chunk_size):
        with torch.no_grad():
            owner = torch.arange(start, stop, device=device).repeat_interleave(counts[start:stop])
            first = torch.cumsum(counts[start:stop], 0) - counts[start:stop]
            local = torch.arange(owner.shape[0], device=device) - first.repeat_interleave(
                counts[start:stop]
            )
            ey, ez = extent[owner, 1], extent[owner, 2]
            index = low[owner] + torch.stack(
                [local // (ey * ez), (local // ez) % ey, local % ez], -1
            )
            batch = owner // n if n else owner
            voxel = ((batch * x + index[:, 0]) * y + index[:, 1]) * z + index[:, 2]
            centres = lower + (index.to(dtype) + 0.5) * size
        args = (
            means,
            precision6,
            opacities,
            flat_features,
            owner,
            centres,
            log_normaliser,
            probabilistic,
        )
        if grad_needed:
            terms = checkpoint(_pair_terms, *args, use_reentrant=False)
        else:
            terms = _pair_terms(*args)
        density.index_add_(0, voxel, terms[0])
        accumulated.index_add_(0, voxel, terms[1])
        if probabilistic:
            weights.index_add_(0, voxel, terms[2])

    return _finish(density, accumulated, weights, probabilistic, (b, x, y, z))


def _finish(
    density: Tensor,
    accumulated: Tensor,
    weights: Tensor,
    probabilistic: bool,
    shape: tuple[int, ...],
) -> VoxelOutput:
    if probabilistic:
        density = 1 - torch.exp(density)
        safe = weights > _TINY_WEIGHT
        accumulated = torch.where(
            safe.unsqueeze(-1), accumulated / weights.clamp_min(_TINY_WEIGHT).unsqueeze(-1), 0.0
        )
    else:
        density = density.clamp(0, 1)
    return VoxelOutput(density=density.view(*shape), features=accumulated.view(*shape, -1))


def _cube_quadratics(
    means: Tensor,  # (n, 3)
    precisions: Tensor,  # (n, 6): xx, yy, zz, xy, xz, yz
    cell: Tensor,  # (n, 3) long, voxel index of each mean (may be off-grid)
    axis_centres: tuple[Tensor, Tensor, Tensor],  # the grid's voxel centres along x, y, z
    r: Tensor,  # (K,) offsets -nbh..nbh
) -> Tensor:
    """``(n, K, K, K)`` float64 quadratics ``d^T P d`` over each Gaussian's cube.

    ``d`` is formed per axis as (the grid's centre) - (mean) in the input dtype, exactly the
    official code's ``d``; the quadratic form is then separable into (n, K) and (n, K, K)
    terms broadcast together, so nothing is gathered per (Gaussian, voxel) pair. Off-grid
    cube cells get clamped (meaningless) values: the caller drops them.
    """
    d = []
    for a, centres in enumerate(axis_centres):
        index = (cell[:, a, None] + r).clamp(0, centres.shape[0] - 1)
        d.append((centres[index] - means[:, a, None]).double())
    dx, dy, dz = d
    p = precisions.double()
    xy = p[:, 0, None, None] * (dx * dx)[:, :, None] + p[:, 1, None, None] * (dy * dy)[:, None]
    xy = xy + 2 * p[:, 3, None, None] * dx[:, :, None] * dy[:, None, :]
    xz = 2 * p[:, 4, None, None] * dx[:, :, None] * dz[:, None, :]
    yz = (
        p[:, 2, None, None] * (dz * dz)[:, None, :]
        + 2 * p[:, 5, None, None] * dy[:, :, None] * dz[:, None, :]
    )
    return (xy[..., None] + xz[:, :, None, :]) + yz[:, None, :, :]


def _cube_pair_terms(
    means: Tensor,  # (n, 3) this chunk's Gaussians
    precisions: Tensor,  # (n, 6)
    opacities: Tensor,  # (n,)
    features: Tensor,  # (n, C)
    log_normaliser: Tensor,  # (n,)
    cell: Tensor,  # (n, 3)
    local: Tensor,  # (P,) Gaussian of each kept pair, in the chunk
    flat: Tensor,  # (P,) its index into the flattened (n, K, K, K) quadratics
    axis_centres: tuple[Tensor, Tensor, Tensor],
    r: Tensor,
    probabilistic: bool,
) -> tuple[Tensor, Tensor, Tensor]:
    quadratic = _cube_quadratics(means, precisions, cell, axis_centres, r).flatten()[flat]
    return _kernel_terms(
        quadratic.to(means.dtype),
        opacities[local],
        features[local],
        log_normaliser[local],
        probabilistic,
    )


def _voxelize_cube(
    gaussians: GaussianSet,
    grid: VoxelGrid,
    features: Tensor,
    precision6: Tensor,
    log_normaliser: Tensor,
    config: VoxelizerConfig,
) -> VoxelOutput:
    """The official fixed-cube neighbourhood: quadratics of all ``(2 nbh + 1)^3`` cells of a
    bounded number of Gaussians at once, negligible and off-grid pairs dropped, the rest
    reduced with ``index_add_``."""
    b, n = gaussians.batch_shape[0], gaussians.num_gaussians
    dtype, device = gaussians.dtype, gaussians.device
    x, y, z = grid.shape
    channels = features.shape[-1]
    probabilistic = config.mode == "probabilistic"
    lower = torch.tensor(grid.lower, dtype=dtype, device=device)
    size = torch.tensor(grid.voxel_size, dtype=dtype, device=device)
    shape = torch.tensor(grid.shape, device=device)
    r = torch.arange(-config.nbh, config.nbh + 1, device=device)
    cube_size = r.shape[0] ** 3
    offsets = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    offsets_flat = (offsets[:, 0] * y + offsets[:, 1]) * z + offsets[:, 2]
    # the same float operations as the grid's own centres (and the official code's)
    axis_centres = tuple(
        lower[a] + (torch.arange(grid.shape[a], device=device, dtype=dtype) + 0.5) * size[a]
        for a in range(3)
    )
    means, opacities = gaussians.means.reshape(-1, 3), gaussians.opacities.reshape(-1)
    with torch.no_grad():
        cell = torch.floor((means.detach() - lower) / size).long()  # (M, 3), may be off-grid
        batch = torch.arange(b * n, device=device) // max(n, 1)
        cell_flat = batch * (x * y * z) + (cell[:, 0] * y + cell[:, 1]) * z + cell[:, 2]

    num_voxels = b * x * y * z
    density = torch.zeros(num_voxels, dtype=dtype, device=device)
    accumulated = torch.zeros(num_voxels, channels, dtype=dtype, device=device)
    weights = torch.zeros(num_voxels if probabilistic else 0, dtype=dtype, device=device)
    grad_needed = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means, precision6, opacities, features)
    )
    per_chunk = max(1, config.chunk_size // cube_size)
    for start in range(0, b * n, per_chunk):
        part = slice(start, start + per_chunk)
        with torch.no_grad():
            quadratic = _cube_quadratics(
                means[part].detach(), precision6[part].detach(), cell[part], axis_centres, r
            )
            axis_ok = [
                ((cell[part, a, None] + r) >= 0) & ((cell[part, a, None] + r) < shape[a])
                for a in range(3)
            ]
            keep = (
                axis_ok[0][:, :, None, None]
                & axis_ok[1][:, None, :, None]
                & axis_ok[2][:, None, None, :]
            )
            # In probabilistic mode a tiny kernel can still carry a large normalised mixture
            # weight, so only the additive mode skips negligible pairs.
            if not probabilistic:
                keep &= quadratic < _NEGLIGIBLE_QUADRATIC
            flat = keep.flatten().nonzero().squeeze(1)
            local = flat // cube_size
            voxel = cell_flat[start + local] + offsets_flat[flat % cube_size]
        if grad_needed:
            inputs = (means, precision6, opacities, features, log_normaliser, cell)
            terms = checkpoint(
                _cube_pair_terms,
                *(t[part] for t in inputs),
                local,
                flat,
                axis_centres,
                r,
                probabilistic,
                use_reentrant=False,
            )
        else:  # the screening quadratics are the values: no recomputation
            terms = _kernel_terms(
                quadratic.flatten()[flat].to(dtype),
                opacities[part][local],
                features[part][local],
                log_normaliser[part][local],
                probabilistic,
            )
        density.index_add_(0, voxel, terms[0])
        accumulated.index_add_(0, voxel, terms[1])
        if probabilistic:
            weights.index_add_(0, voxel, terms[2])
    return _finish(density, accumulated, weights, probabilistic, (b, x, y, z))


class GaussianVoxelizer(nn.Module):
    """Module form of :func:`voxelize`: holds the grid and settings; ``forward(gaussians,
    features=None)`` voxelises."""

    def __init__(self, grid: VoxelGrid | None = None, **config: object) -> None:
        super().__init__()
        self.grid = VoxelGrid.occ3d() if grid is None else grid
        self.config = VoxelizerConfig(**config)  # type: ignore[arg-type]

    @typechecked
    def forward(
        self, gaussians: GaussianSet, features: Float[Tensor, "B N C"] | None = None
    ) -> VoxelOutput:
        return _voxelize(gaussians, self.grid, features, self.config)

    def extra_repr(self) -> str:
        fields = ", ".join(
            f"{f.name}={getattr(self.config, f.name)!r}" for f in dataclasses.fields(self.config)
        )
        return f"grid={self.grid}, {fields}"


__all__ = ["GaussianVoxelizer", "VoxelOutput", "VoxelizerConfig", "voxelize"]
