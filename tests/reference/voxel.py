"""Dense, plainly written re-statements of the voxelisation rules, used only as test oracles.

Written from the maths of the voxelizer's contract, not from its code:

* :func:`dense_voxelize` evaluates every Gaussian at every voxel centre (small grids only),
  ``g_i(x) = exp(-0.5 d^T P_i d)`` with ``d = x - mu_i``, optionally multiplied by a
  per-(Gaussian, voxel) inclusion mask that expresses a neighbourhood rule
  (:func:`ellipsoid_box_mask`, :func:`cube_mask`, :func:`scale_cube_mask`), and with the
  GaussianFormer options (where opacity enters, the empty-voxel value).
* :func:`official_cube_voxelize` transcribes the official GaussianFlowOcc / DeGO algorithm:
  candidate voxels ``floor((mu - lower) / voxel) + [-nbh..nbh]^3``, out-of-grid ones
  dropped, one (Gaussian, voxel) pair per candidate with its own copy of the 3x3 precision,
  weights scattered into the grid.

Both are differentiable by plain autograd.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import torch
from torch import Tensor

from dego import GaussianSet, VoxelGrid

MaskFn = Callable[[GaussianSet, VoxelGrid], Tensor]
"""``(gaussians (B, N), grid) -> (B, N, X, Y, Z)`` bool: which voxels each Gaussian reaches."""

TINY_WEIGHT = 1e-30
"""Probabilistic features are 0 where the summed mixture weight is at most this."""


def _centres(gaussians: GaussianSet, grid: VoxelGrid) -> Tensor:
    return grid.centers(dtype=gaussians.dtype, device=gaussians.device)


def ellipsoid_box_mask(cutoff_sigma: float, slack: float = 0.0) -> MaskFn:
    """Voxels whose centre lies in ``mu_i +/- (k sqrt(Sigma_i[j, j]) + slack)`` on every axis."""

    def mask(gaussians: GaussianSet, grid: VoxelGrid) -> Tensor:
        centres = _centres(gaussians, grid)  # (X, Y, Z, 3)
        std = torch.diagonal(gaussians.covariances(), dim1=-2, dim2=-1).sqrt()  # (B, N, 3)
        half = (cutoff_sigma * std + slack)[:, :, None, None, None, :]
        offset = centres[None, None] - gaussians.means[:, :, None, None, None, :]
        return (offset.abs() <= half).all(dim=-1)

    return mask


def cube_mask(nbh: int) -> MaskFn:
    """Voxels ``idx`` with ``|idx - floor((mu_i - lower) / voxel)|_inf <= nbh``."""

    def mask(gaussians: GaussianSet, grid: VoxelGrid) -> Tensor:
        lower = torch.tensor(grid.lower, dtype=gaussians.dtype, device=gaussians.device)
        size = torch.tensor(grid.voxel_size, dtype=gaussians.dtype, device=gaussians.device)
        home = torch.floor((gaussians.means - lower) / size).long()  # (B, N, 3)
        axes = [torch.arange(n, device=gaussians.device) for n in grid.shape]
        index = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)  # (X, Y, Z, 3)
        gap = index[None, None] - home[:, :, None, None, None, :]
        return (gap.abs() <= nbh).all(dim=-1)

    return mask


def scale_cube_mask(scale_multiplier: float) -> MaskFn:
    """GaussianFormer's cube: voxels ``idx`` with ``|idx_a - floor((mu_i - lower) / v)_a|
    <= max(1, ceil(k max(s_i) / v_a))`` on every axis a (all voxels for k = inf)."""

    def mask(gaussians: GaussianSet, grid: VoxelGrid) -> Tensor:
        b, n = gaussians.means.shape[:2]
        axes = [torch.arange(size, device=gaussians.device) for size in grid.shape]
        index = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)  # (X, Y, Z, 3)
        if math.isinf(scale_multiplier):
            return torch.ones(b, n, *grid.shape, dtype=torch.bool, device=gaussians.device)
        lower = torch.tensor(grid.lower, dtype=torch.float64, device=gaussians.device)
        size = torch.tensor(grid.voxel_size, dtype=torch.float64, device=gaussians.device)
        means = gaussians.means.double()
        home = torch.floor((means - lower) / size)  # (B, N, 3)
        largest = gaussians.scales.double().max(dim=-1, keepdim=True).values  # (B, N, 1)
        radius = torch.ceil(scale_multiplier * largest / size).clamp_min(1)  # (B, N, 3)
        gap = index[None, None].double() - home[:, :, None, None, None, :]
        return (gap.abs() <= radius[:, :, None, None, None, :]).all(dim=-1)

    return mask


def gaussian_values(gaussians: GaussianSet, grid: VoxelGrid) -> Tensor:
    """``g_i(x)`` of every Gaussian at every voxel centre, ``(B, N, X, Y, Z)``."""
    centres = _centres(gaussians, grid)
    d = centres[None, None] - gaussians.means[:, :, None, None, None, :]  # (B, N, X, Y, Z, 3)
    quadratic = torch.einsum("bnxyzi,bnij,bnxyzj->bnxyz", d, gaussians.precisions(), d)
    return torch.exp(-0.5 * quadratic)


def dense_voxelize(
    gaussians: GaussianSet,
    grid: VoxelGrid,
    features: Tensor | None = None,
    mode: str = "additive",
    mask_fn: MaskFn | None = None,
    *,
    feature_weight: str | None = None,
    opacity_in_density: bool = True,
    empty_value: float = 0.0,
    empty_threshold: float = TINY_WEIGHT,
) -> tuple[Tensor, Tensor]:
    """``(density (B, X, Y, Z), features (B, X, Y, Z, C))`` by evaluating everything densely.

    additive: density = clamp(sum_i a_i g_i, 0, 1), features = sum_i w_i f_i with w_i = g_i.
    probabilistic: density = 1 - prod_i (1 - a_i g_i), features = sum_i w_i f_i / sum_i w_i
    with w_i = o_i (2 pi)^(-3/2) sqrt(det P_i) g_i.
    a_i = o_i, or 1 with ``opacity_in_density=False``; ``feature_weight="kernel"`` drops o_i
    from w_i, ``"opacity_kernel"`` puts it in (None: the mode's default, as above). Features
    are ``empty_value`` where sum_i w_i <= ``empty_threshold``.
    """
    b, n = gaussians.means.shape[:2]
    if features is None:
        features = gaussians.features
    if features is None:
        features = gaussians.means.new_zeros(b, n, 0)
    g = gaussian_values(gaussians, grid)
    if mask_fn is not None:
        g = g * mask_fn(gaussians, grid).to(g.dtype)
    opacities = gaussians.opacities[:, :, None, None, None]
    if mode not in ("additive", "probabilistic"):
        raise ValueError(f"unknown mode {mode!r}")
    with_opacity = (
        mode == "probabilistic" if feature_weight is None else (feature_weight == "opacity_kernel")
    )
    occupancy = opacities * g if opacity_in_density else g
    fill = g.new_full((b, *grid.shape, 1), empty_value)
    if mode == "additive":
        density = occupancy.sum(dim=1).clamp(0, 1)
        w = opacities * g if with_opacity else g
        total = w.sum(dim=1)
        summed = torch.einsum("bnxyz,bnc->bxyzc", w, features)
        return density, torch.where((total > empty_threshold).unsqueeze(-1), summed, fill)
    density = 1 - torch.prod(1 - occupancy, dim=1)
    normaliser = (2 * math.pi) ** -1.5 * torch.linalg.det(gaussians.precisions()).sqrt()
    p = normaliser[:, :, None, None, None] * g
    if with_opacity:
        p = opacities * p
    total = p.sum(dim=1)
    weighted = torch.einsum("bnxyz,bnc->bxyzc", p, features)
    safe = total > empty_threshold
    mixed = weighted / torch.where(safe, total, torch.ones_like(total)).unsqueeze(-1)
    return density, torch.where(safe.unsqueeze(-1), mixed, fill)


def official_cube_voxelize(
    gaussians: GaussianSet, grid: VoxelGrid, features: Tensor | None, nbh: int
) -> tuple[Tensor, Tensor]:
    """The official fixed-cube additive voxelisation, one (Gaussian, voxel) pair at a time."""
    b, n = gaussians.means.shape[:2]
    if features is None:
        features = gaussians.features
    if features is None:
        features = gaussians.means.new_zeros(b, n, 0)
    dtype, device = gaussians.dtype, gaussians.device
    x_size, y_size, z_size = grid.shape
    lower = torch.tensor(grid.lower, dtype=dtype, device=device)
    voxel = torch.tensor(grid.voxel_size, dtype=dtype, device=device)
    shape = torch.tensor(grid.shape, device=device)

    means = gaussians.means.reshape(b * n, 3)
    precisions = gaussians.precisions().reshape(b * n, 3, 3)
    opacities = gaussians.opacities.reshape(b * n)
    flat_features = features.reshape(b * n, features.shape[-1])
    batch_of = torch.arange(b, device=device).repeat_interleave(n)

    # candidate voxels: the home voxel of each Gaussian plus every offset in [-nbh, nbh]^3
    home = torch.floor((means - lower) / voxel).long()  # (M, 3)
    offsets = torch.tensor(
        list(itertools.product(range(-nbh, nbh + 1), repeat=3)), dtype=torch.long, device=device
    )  # (K, 3)
    candidates = home[:, None, :] + offsets[None, :, :]  # (M, K, 3)
    inside = ((candidates >= 0) & (candidates < shape)).all(dim=-1)  # (M, K)
    owner = torch.arange(b * n, device=device)[:, None].expand_as(inside)[inside]  # (P,)
    index = candidates[inside]  # (P, 3)

    # one row per pair, each with its own (repeated) precision matrix
    pair_precision = precisions[owner]  # (P, 3, 3)
    centres = lower + (index.to(dtype) + 0.5) * voxel
    d = centres - means[owner]
    quadratic = (d.unsqueeze(-2) @ pair_precision @ d.unsqueeze(-1)).reshape(-1)
    w = torch.exp(-0.5 * quadratic)

    flat = ((batch_of[owner] * x_size + index[:, 0]) * y_size + index[:, 1]) * z_size + index[:, 2]
    num_voxels = b * x_size * y_size * z_size
    density = torch.zeros(num_voxels, dtype=dtype, device=device)
    density = density.scatter_add(0, flat, opacities[owner] * w).clamp(0, 1)
    channels = flat_features.shape[-1]
    accumulated = torch.zeros(num_voxels, channels, dtype=dtype, device=device)
    accumulated = accumulated.scatter_add(
        0, flat[:, None].expand(-1, channels), w[:, None] * flat_features[owner]
    )
    return (
        density.reshape(b, x_size, y_size, z_size),
        accumulated.reshape(b, x_size, y_size, z_size, channels),
    )
