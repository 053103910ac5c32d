"""The box neighbourhoods: each Gaussian's ``cutoff_sigma`` ellipsoid box (``"ellipsoid"``)
or GaussianFormer's scale cube (``"scale_cube"``) as per-axis voxel index ranges, and their
(Gaussian, voxel) pairs enumerated a bounded number at a time (``searchsorted`` over the
running pair count, so a chunk may split a Gaussian's box)."""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from dego._compile import eager_only
from dego._geometry import rotation_matrices
from dego.grid import VoxelGrid
from dego.voxelizer.inputs import check_size
from dego.voxelizer.kernels import Kernel, pair_terms
from dego.voxelizer.output import VoxelOutput
from dego.voxelizer.records import FlatGaussians, VoxelSums, requiring_grad
from dego.voxelizer.types import VoxelizerConfig


def grid_float64(grid: VoxelGrid, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """The grid's lower corner, voxel size and largest index per axis, float64 ``(3,)``."""
    lower = torch.tensor(grid.lower, dtype=torch.float64, device=device)
    size = torch.tensor(grid.voxel_size, dtype=torch.float64, device=device)
    top = torch.tensor(grid.shape, dtype=torch.float64, device=device) - 1
    return lower, size, top


def _clip_to_grid(low: Tensor, high: Tensor, top: Tensor) -> tuple[Tensor, Tensor]:
    """Float64 index ranges clamped to ``[-1, shape]`` before the int64 conversion (no
    overflow whatever their size; empty where high < low)."""
    low = torch.minimum(low.clamp_min(0), top + 1)
    high = torch.minimum(high.clamp_min(-1), top)
    return low.long(), high.long()


def _ellipsoid_boxes(
    means: Tensor,  # (M, 3)
    rotations: Tensor,  # (M, 3, 3)
    scales: Tensor,  # (M, 3)
    grid: VoxelGrid,
    cutoff_sigma: float,
) -> tuple[Tensor, Tensor]:
    """Inclusive per-axis voxel index ranges ``(M, 3)`` low / high of the voxels whose centres
    lie in the axis-aligned box of each Gaussian's ``cutoff_sigma`` ellipsoid, clipped to the
    grid (empty where high < low).

    Computed in float64 and clamped to ``[-1, shape]`` in floating point before the integer
    conversion, so huge scales, huge ``cutoff_sigma`` (``inf``: the whole grid) or far
    means never overflow int64.
    """
    lower, size, top = grid_float64(grid, means.device)
    if math.isinf(cutoff_sigma):
        low = torch.zeros_like(means, dtype=torch.float64)
        high = top.expand_as(low)
    else:
        position = (means.double() - lower) / size  # voxel units; centre of voxel i: i + 0.5
        # sqrt(Sigma_jj) = |row j of R diag(s)| (inf where it overflows: the whole axis)
        std = (rotations.double() * scales.double().unsqueeze(-2)).square().sum(-1).sqrt()
        half = cutoff_sigma * std / size
        # voxel i is inside iff |i + 0.5 - position| <= half; NaN (inf - inf) -> whole axis
        low = torch.ceil(position - half - 0.5)
        high = torch.floor(position + half - 0.5)
        low = torch.where(low.isnan(), 0.0, low)
        high = torch.where(high.isnan(), top, high)
    return _clip_to_grid(low, high, top)


def _scale_cube_boxes(
    means: Tensor,  # (M, 3)
    scales: Tensor,  # (M, 3)
    grid: VoxelGrid,
    scale_multiplier: float,
) -> tuple[Tensor, Tensor]:
    """GaussianFormer's cubes as inclusive per-axis index ranges ``(M, 3)`` low / high:
    ``floor((mu - lower) / voxel) +- r`` with ``r = max(1, ceil(k max(s) / voxel))`` per
    axis, clipped to the grid (empty where high < low: cubes wholly outside it).

    Computed in float64 and clamped to ``[-1, shape]`` in floating point before the integer
    conversion (huge scales or ``k = inf``: the whole grid; far means: no voxel).
    """
    lower, size, top = grid_float64(grid, means.device)
    if math.isinf(scale_multiplier):
        low = torch.zeros_like(means, dtype=torch.float64)
        high = top.expand_as(low)
    else:
        home = torch.floor((means.double() - lower) / size)  # finite: means are finite
        largest = scales.double().amax(-1, keepdim=True)  # (M, 1)
        radius = torch.ceil(scale_multiplier * largest / size).clamp_min(1)  # may be inf
        low, high = home - radius, home + radius
    return _clip_to_grid(low, high, top)


def voxelize_boxes(flat: FlatGaussians, grid: VoxelGrid, config: VoxelizerConfig) -> VoxelOutput:
    """The ellipsoid or scale-cube neighbourhood: whitening matrices and index boxes, then
    the pairs of the boxes reduced into the grid."""
    rotations = rotation_matrices(flat.quats)
    whitening = (rotations / flat.scales.unsqueeze(-2)).transpose(-1, -2).reshape(-1, 9)
    with torch.no_grad():
        means, scales = flat.means.detach(), flat.scales.detach()
        if config.neighborhood == "scale_cube":
            assert config.scale_multiplier is not None  # VoxelizerConfig requires it
            boxes = _scale_cube_boxes(means, scales, grid, float(config.scale_multiplier))
        else:
            boxes = _ellipsoid_boxes(means, rotations.detach(), scales, grid, config.cutoff_sigma)
    return _sum_box_pairs(flat, grid, config, boxes, whitening)


# Data-dependent by nature (the number of (Gaussian, voxel) pairs): run eagerly under
# torch.compile, as one graph break, rather than recompiling for every pair count.
@eager_only
def _sum_box_pairs(
    flat: FlatGaussians,
    grid: VoxelGrid,
    config: VoxelizerConfig,
    boxes: tuple[Tensor, Tensor],  # (M, 3) inclusive low / high voxel indices, in the grid
    whitening: Tensor,  # (M, 9)
) -> VoxelOutput:
    """Per-Gaussian index boxes (ellipsoid or scale cube): pairs enumerated in fixed-size
    ranges of the running pair count."""
    n, (x, y, z) = flat.num_gaussians, grid.shape
    dtype, device = flat.dtype, flat.device
    means, opacities, features = flat.means, flat.opacities, flat.features
    log_normaliser = flat.log_normaliser
    kernel = Kernel.of(config)
    differentiable = requiring_grad(means, whitening, opacities, features, log_normaliser)
    grad_needed = bool(differentiable)
    low, high = boxes
    with torch.no_grad():
        extent = (high - low + 1).clamp(min=0)  # (M, 3)
        counts = extent.prod(-1)
        ends = torch.cumsum(counts, 0)
    total = int(ends[-1]) if ends.numel() else 0
    chunk = min(config.chunk_size, total)
    check_size(
        flat,
        grid,
        chunk,
        56 + (27 + 2 * flat.channels) * dtype.itemsize,
        total * (16 + 3 * dtype.itemsize) if grad_needed else 0,
    )
    lower = torch.tensor(grid.lower, dtype=dtype, device=device)
    size = torch.tensor(grid.voxel_size, dtype=dtype, device=device)
    shape = (flat.batch_size, x, y, z)
    sums = VoxelSums.zeros(math.prod(shape), flat.channels, dtype, device)
    for first in range(0, total, max(chunk, 1)):  # bounded chunks of pairs
        with torch.no_grad():
            pair = torch.arange(first, min(first + chunk, total), device=device)
            owner = torch.searchsorted(ends, pair, right=True)
            local = pair - (ends[owner] - counts[owner])
            ey, ez = extent[owner, 1], extent[owner, 2]
            index = low[owner] + torch.stack(
                [local // (ey * ez), (local // ez) % ey, local % ez], -1
            )
            batch = owner // n  # n >= 1 whenever there are pairs
            voxel = ((batch * x + index[:, 0]) * y + index[:, 1]) * z + index[:, 2]
            centres = lower + (index.to(dtype) + 0.5) * size
        args = (means, whitening, opacities, features, owner, centres, log_normaliser, kernel)
        if grad_needed:
            terms = checkpoint(pair_terms, *args, use_reentrant=False)
        else:
            terms = pair_terms(*args)
        sums.add(voxel, terms)
    return sums.finish(kernel, config, shape, differentiable)
