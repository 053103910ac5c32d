"""Benchmark scenes for the splatter: a nuScenes-like surround rig over the Occ3D volume."""

from __future__ import annotations

import math

import torch

from dego import GaussianSet, VoxelGrid


def surround_rig(
    height: int,
    width: int,
    *,
    cameras: int = 6,
    focal_scale: float = 0.8,
    dtype: torch.dtype = torch.float32,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(1, V, 4, 4)`` world_to_cam and ``(1, V, 3, 3)`` K of V cameras 1.5 m above the
    ego origin, yawed evenly around z (x forward, y left, z up; OpenCV camera axes)."""
    focal = focal_scale * width
    w2c, intrinsics = [], []
    for i in range(cameras):
        yaw = 2 * math.pi * i / cameras
        forward = torch.tensor([math.cos(yaw), math.sin(yaw), 0.0], dtype=torch.float64)
        right = torch.tensor([math.sin(yaw), -math.cos(yaw), 0.0], dtype=torch.float64)
        down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
        rotation = torch.stack([right, down, forward])  # rows: camera axes in ego coordinates
        origin = torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64)
        m = torch.eye(4, dtype=torch.float64)
        m[:3, :3] = rotation
        m[:3, 3] = -rotation @ origin
        w2c.append(m)
        k = torch.tensor(
            [[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=torch.float64
        )
        intrinsics.append(k)
    return torch.stack(w2c)[None].to(dtype), torch.stack(intrinsics)[None].to(dtype)


def occ3d_gaussians(
    n: int,
    channels: int,
    *,
    seed: int = 0,
    scale_range: tuple[float, float] = (0.05, 1.0),
    dtype: torch.dtype = torch.float32,
) -> GaussianSet:
    """``(1, n)`` Gaussians uniform in the Occ3D volume, log-uniform scales, random features."""
    g = torch.Generator().manual_seed(seed)
    grid = VoxelGrid.occ3d()
    lower, upper = torch.tensor(grid.lower), torch.tensor(grid.upper)
    lo, hi = math.log(scale_range[0]), math.log(scale_range[1])
    return GaussianSet(
        means=(lower + torch.rand(1, n, 3, generator=g) * (upper - lower)).to(dtype),
        quats=torch.randn(1, n, 4, generator=g).to(dtype),
        scales=torch.exp(lo + torch.rand(1, n, 3, generator=g) * (hi - lo)).to(dtype),
        opacities=(0.05 + 0.9 * torch.rand(1, n, generator=g)).to(dtype),
        features=torch.randn(1, n, channels, generator=g).to(dtype),
    )
