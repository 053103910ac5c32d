"""Helpers of tests/metrics/test_occupancy.py, also used by

- tests/compat/test_torchmetrics.py
- tests/metrics/test_occupancy_distributed.py
"""

from __future__ import annotations

import numpy as np

FREE = 17


def random_sample(seed: int, shape=(6, 5, 4), free_fraction: float = 0.5):
    """(pred, gt, mask) uint8/uint8/bool grids with many free voxels, like Occ3D."""
    rng = np.random.default_rng(seed)
    gt = rng.integers(0, 17, shape, dtype=np.uint8)
    gt[rng.random(shape) < free_fraction] = FREE
    pred = np.where(rng.random(shape) < 0.6, gt, rng.integers(0, 18, shape)).astype(np.uint8)
    mask = rng.random(shape) < 0.7
    return pred, gt, mask
