"""A plain numpy re-statement of the Occ3D / GaussianFlowOcc / DeGO evaluation recipe.

Written from the published description of the devkit (see the metrics facts): boolean
camera mask, drop gt outside [0, C), ``bincount(C * gt + pred)`` summed over the data
set in float64, IoU = diag / (rows + cols - diag), mIoU = nanmean over the protocol's
classes, geometric IoU from the relabelled occupied/free 2x2 matrix, and the weak
protocol's ``mask &= ~((gt == 0) | (gt == 12))``. Used only as a test oracle.
"""

from __future__ import annotations

import warnings

import numpy as np

OCC3D = list(range(17))
WEAK = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 13, 14, 15, 16]


def _hist(pred: np.ndarray, gt: np.ndarray, n: int) -> np.ndarray:
    keep = (gt >= 0) & (gt < n)
    return np.bincount(n * gt[keep].astype(int) + pred[keep].astype(int), minlength=n * n).reshape(
        n, n
    )


def _iou(hist: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.diag(hist) / (hist.sum(1) + hist.sum(0) - np.diag(hist))


def reference_scores(
    samples: list[tuple[np.ndarray, np.ndarray, np.ndarray]], protocol: str
) -> dict:
    """Scores over ``[(pred, gt, mask_camera)]`` as the reference code reports them."""
    hist = np.zeros((18, 18))
    geo = np.zeros((2, 2))
    for pred, gt, mask in samples:
        mask = mask.astype(bool)
        if protocol == "weak":
            mask = mask & ~((gt == 0) | (gt == 12))
        p, g = pred[mask], gt[mask]
        hist += _hist(p, g, 18)
        geo += _hist(np.where(p != 17, 0, 1), np.where(g != 17, 0, 1), 2)
    per_class = _iou(hist)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        miou = np.nanmean(per_class[WEAK if protocol == "weak" else OCC3D])
    return {
        "hist": hist,
        "per_class": per_class,
        "miou": round(miou * 100, 2),
        "iou": round(_iou(geo)[0] * 100, 2),
    }
