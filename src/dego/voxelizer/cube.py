"""The official fixed-cube neighbourhood (``"cube"``): all ``(2 nbh + 1)^3`` cells around
each Gaussian's voxel, a bounded number of Gaussians at a time, with float64 quadratics."""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from dego._compile import eager_only
from dego._geometry import scaled_rotation_gram
from dego.grid import VoxelGrid
from dego.voxelizer.boxes import grid_float64
from dego.voxelizer.inputs import check_size
from dego.voxelizer.kernels import NEGLIGIBLE_QUADRATIC, Kernel, kernel_terms
from dego.voxelizer.output import VoxelOutput
from dego.voxelizer.records import FlatGaussians, VoxelSums, requiring_grad
from dego.voxelizer.types import VoxelizerConfig


def _cube_quadratics(
    means: Tensor,  # (n, 3)
    precisions: Tensor,  # (n, 6) float64: xx, yy, zz, xy, xz, yz
    cell: Tensor,  # (n, 3) long, voxel index of each mean (may be off-grid)
    axis_centres: tuple[Tensor, Tensor, Tensor],  # float64 voxel centres along x, y, z
    r: Tensor,  # (K,) offsets -nbh..nbh
    reach: tuple[float, float, float],  # (nbh + 1) voxels per axis, metres
) -> Tensor:
    """``(n, K, K, K)`` float64 quadratics ``d^T P d`` over each Gaussian's cube.

    ``d`` is formed per axis in float64, as (the grid's float64 centre) - (mean): the
    official code forms it in float32, where ``lower + (i + 0.5) * voxel`` is up to 4.6e-6 m
    off on the Occ3D grid (0.4 is no float32 number) and the difference of two numbers
    near 40 m loses another ~2e-6 m; those two dominate its float32 error. The quadratic
    form is then separable into (n, K) and (n, K, K) terms broadcast together, so nothing
    is gathered per (Gaussian, voxel) pair. Off-grid cube cells get clamped (meaningless)
    values: the caller drops them. ``d`` is clamped to ``+-reach``, which no in-grid cell of
    the cube exceeds, so far means cannot overflow the products (or their gradients).
    """
    d = []
    for a, centres in enumerate(axis_centres):
        index = (cell[:, a, None] + r).clamp(0, centres.shape[0] - 1)
        offset = centres[index] - means[:, a, None].double()
        d.append(offset.clamp(-reach[a], reach[a]))
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
    reach: tuple[float, float, float],
    kernel: Kernel,
) -> tuple[Tensor, Tensor, Tensor]:
    quadratic = _cube_quadratics(means, precisions, cell, axis_centres, r, reach)
    quadratic = quadratic.flatten()[flat]
    return kernel_terms(
        quadratic.to(means.dtype),
        opacities[local],
        features[local],
        log_normaliser[local],
        kernel,
    )


def voxelize_cube(flat: FlatGaussians, grid: VoxelGrid, config: VoxelizerConfig) -> VoxelOutput:
    """The official cube: float64 precisions ``(M, 6)``, then the cube pairs reduced into
    the grid."""
    # float64 from the input-dtype quats and scales: in float32 the rounding of these
    # entries is the largest error of the cube on grids whose centres are exact
    precision = scaled_rotation_gram(flat.quats.double(), flat.scales.double().reciprocal())
    rows, cols = (0, 1, 2, 0, 0, 1), (0, 1, 2, 1, 2, 2)  # xx, yy, zz, xy, xz, yz
    return _sum_cube_pairs(flat, grid, config, precision[:, rows, cols])


# Data-dependent by nature (the number of (Gaussian, voxel) pairs): run eagerly under
# torch.compile, as one graph break, rather than recompiling for every pair count.
@eager_only
def _sum_cube_pairs(
    flat: FlatGaussians,
    grid: VoxelGrid,
    config: VoxelizerConfig,
    precision6: Tensor,  # (M, 6) float64
) -> VoxelOutput:
    """The official fixed-cube neighbourhood: quadratics of all ``(2 nbh + 1)^3`` cells of a
    bounded number of Gaussians at once, negligible and off-grid pairs dropped, the rest
    reduced with ``index_add_``."""
    (b, n), (x, y, z) = (flat.batch_size, flat.num_gaussians), grid.shape
    assert config.nbh is not None  # VoxelizerConfig requires it for the cube
    dtype, device = flat.dtype, flat.device
    means, opacities, features = flat.means, flat.opacities, flat.features
    log_normaliser = flat.log_normaliser
    kernel = Kernel.of(config)
    probabilistic = kernel.probabilistic
    side = 2 * config.nbh + 1
    cube_size = side**3
    per_chunk = max(1, config.chunk_size // cube_size)
    differentiable = requiring_grad(means, precision6, opacities, features, log_normaliser)
    grad_needed = bool(differentiable)
    # before anything of the cube exists, its int64 offset tables (r, three per cell and
    # one flat per cell) included: nbh = 2**40 asked for 16 TB of them first
    check_size(
        flat,
        grid,
        min(per_chunk, b * n) * cube_size,
        49 + (5 + 2 * flat.channels) * dtype.itemsize,
        (b * n * cube_size * 24 if grad_needed else 0) + 8 * side + 32 * cube_size,
        f", nbh = {config.nbh}: a (2 nbh + 1)^3 = {side}^3-cell cube",
    )
    r = torch.arange(-config.nbh, config.nbh + 1, device=device)
    lower = torch.tensor(grid.lower, dtype=dtype, device=device)
    size = torch.tensor(grid.voxel_size, dtype=dtype, device=device)
    shape = torch.tensor(grid.shape, device=device)
    offsets = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    offsets_flat = (offsets[:, 0] * y + offsets[:, 1]) * z + offsets[:, 2]
    # float64 centres (the grid's own, lower + (i + 0.5) * voxel, in float64); the home voxel
    # below stays the official float32 floor((mu - lower) / voxel)
    lower64, size64, _ = grid_float64(grid, device)
    cx, cy, cz = (
        lower64[a]
        + (torch.arange(grid.shape[a], device=device, dtype=torch.float64) + 0.5) * size64[a]
        for a in range(3)
    )
    axis_centres = (cx, cy, cz)
    vx, vy, vz = grid.voxel_size
    reach = ((config.nbh + 1) * vx, (config.nbh + 1) * vy, (config.nbh + 1) * vz)
    with torch.no_grad():
        # home voxel, clamped in floating point to just outside the reach of the cube before
        # the integer conversion (a cell that far has no in-grid cube cell either way)
        cell = torch.floor((means.detach() - lower) / size)
        cell = torch.minimum(cell.clamp_min(-config.nbh - 1), shape + config.nbh).long()
        batch = torch.arange(b * n, device=device) // max(n, 1)
        cell_flat = batch * (x * y * z) + (cell[:, 0] * y + cell[:, 1]) * z + cell[:, 2]

    out_shape = (b, x, y, z)
    sums = VoxelSums.zeros(math.prod(out_shape), flat.channels, dtype, device)
    for start in range(0, b * n, per_chunk):  # bounded chunks of Gaussians
        part = slice(start, start + per_chunk)
        with torch.no_grad():
            quadratic = _cube_quadratics(
                means[part].detach(), precision6[part].detach(), cell[part], axis_centres, r, reach
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
            # weight, so only the additive mode skips negligible pairs (NaN: far, skipped).
            if not probabilistic:
                keep &= quadratic < NEGLIGIBLE_QUADRATIC
            kept = keep.flatten().nonzero().squeeze(1)
            local = kept // cube_size
            voxel = cell_flat[start + local] + offsets_flat[kept % cube_size]
        if grad_needed:
            inputs = (means, precision6, opacities, features, log_normaliser, cell)
            terms = checkpoint(
                _cube_pair_terms,
                *(t[part] for t in inputs),
                local,
                kept,
                axis_centres,
                r,
                reach,
                kernel,
                use_reentrant=False,
            )
        else:  # the screening quadratics are the values: no recomputation
            terms = kernel_terms(
                quadratic.flatten()[kept].to(dtype),
                opacities[part][local],
                features[part][local],
                log_normaliser[part][local],
                kernel,
            )
        sums.add(voxel, terms)
    return sums.finish(kernel, config, out_shape, differentiable)
