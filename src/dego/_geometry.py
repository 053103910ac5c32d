"""Quaternion and covariance kernels shared across the package.

Unchecked: the public, run-time type-checked forms live in :mod:`dego.gaussians`
(``normalize_quaternions``, ``quaternions_to_rotation_matrices``, ``build_covariances``,
``quaternion_multiply``...). :class:`~dego.GaussianSet` (validated once at construction) and
the other modules call these directly so that checks are not paid per call.
"""

from __future__ import annotations

import torch
from torch import Tensor

QUATERNION_EPS = 1e-12
"""Norms below this are treated as zero when normalising quaternions."""


def unit_quaternions(quats: Tensor, eps: float = QUATERNION_EPS) -> Tensor:
    """``q / max(|q|, eps)``, with ``|q|`` computed from ``q / max_k |q_k|`` so that it
    neither overflows (``|q| > 1.8e19`` in float32) nor underflows; finite for ``q = 0``."""
    largest = quats.abs().amax(-1, keepdim=True)
    scaled = quats / torch.where(largest > 0, largest, torch.ones_like(largest))
    norm = torch.linalg.vector_norm(scaled, dim=-1, keepdim=True)  # in [1, 2], or 0 for q = 0
    # the eps clamp: a (near-)zero quaternion maps to q / eps (0 for q = 0), never 0 / 0
    return torch.where(norm * largest >= eps, scaled / norm.clamp_min(1), quats / eps)


def rotation_matrices(quats: Tensor) -> Tensor:
    w, x, y, z = unit_quaternions(quats).unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = (
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    )  # fmt: skip
    return torch.stack(rows, dim=-1).unflatten(-1, (3, 3))


def scaled_rotation_gram(quats: Tensor, column_scales: Tensor) -> Tensor:
    """``(R diag(c)) (R diag(c))^T = R diag(c^2) R^T``, symmetric by construction."""
    scaled = rotation_matrices(quats) * column_scales.unsqueeze(-2)
    return scaled @ scaled.transpose(-1, -2)


def quaternion_product(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a (x) b`` of wxyz quaternions ``(..., 4)`` (broadcasting)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def conjugate_quaternions(quats: Tensor) -> Tensor:
    """``(w, -x, -y, -z)``: the inverse rotation; exact (only signs change)."""
    return torch.cat([quats[..., :1], -quats[..., 1:]], dim=-1)
