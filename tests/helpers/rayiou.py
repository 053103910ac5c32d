"""Helpers of tests/metrics/test_rayiou.py, also used by

- tests/compat/test_torchmetrics.py
- tests/metrics/test_rayiou_distributed.py
"""

from __future__ import annotations

import numpy as np

from dego.grid import VoxelGrid
from dego.raycast import generate_lidar_rays

FREE = 17


# a small Occ3D-like grid (0.4 m voxels, 8 x 8 x 2.4 m) and a subsample of the ray pattern
SMALL_GRID = VoxelGrid((-4.0, -4.0, -1.0), (4.0, 4.0, 1.4), 0.4)
SMALL_RAYS = generate_lidar_rays()[::53]  # 265 rays


def random_scene(seed: int, grid: VoxelGrid = SMALL_GRID, free_fraction: float = 0.9):
    """(pred uint8, gt uint8, origins float32 (K, 3)): a sparse gt and a prediction that keeps
    most of it, drops some, shifts some along x and adds some clutter."""
    rng = np.random.default_rng(seed)
    shape = grid.shape
    gt = rng.integers(0, 17, shape).astype(np.uint8)
    gt[rng.random(shape) < free_fraction] = FREE
    pred = gt.copy()
    pred[rng.random(shape) < 0.2] = FREE
    shifted = np.roll(gt, int(rng.integers(-3, 4)), axis=0)
    take = rng.random(shape) < 0.3
    pred[take] = shifted[take]
    clutter = rng.random(shape) < 0.03
    pred[clutter] = rng.integers(0, 17, int(clutter.sum()))
    lower, upper = np.asarray(grid.lower), np.asarray(grid.upper)
    k = int(rng.integers(1, 4))
    origins = lower + rng.uniform(-0.1, 1.1, (k, 3)) * (upper - lower)
    return pred, gt, origins.astype(np.float32)
