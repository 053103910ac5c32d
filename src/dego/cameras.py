"""Camera helpers: fold resize, crop and image augmentation into K; split lidar2img into pose, K."""

from __future__ import annotations

import math

import torch
from jaxtyping import Float
from torch import Tensor

from dego._policy import check_dtype
from dego._typing import typechecked

_LAST_ROW_ATOL = 1e-6
"""Absolute tolerance on ``[0, 0, 0, 1]`` (4x4 projections) and ``[0, 0, 1]`` (3x3 post_rot)."""

_ROTATION_RTOL = 1e-6
"""post_rot off-diagonals up to this times its largest diagonal entry count as rounding."""


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _fold(
    intrinsics: Tensor,
    sx: Tensor | float,
    sy: Tensor | float,
    tx: Tensor | float,
    ty: Tensor | float,
) -> Tensor:
    """``A @ intrinsics`` with ``A = [[sx, 0, tx], [0, sy, ty], [0, 0, 1]]``, row by row.

    Tensor factors are ``(*, 1)`` so that they broadcast over a row's three entries.
    """
    row0, row1, row2 = intrinsics.unbind(-2)
    return torch.stack([sx * row0 + tx * row2, sy * row1 + ty * row2, row2], dim=-2)


@typechecked
def resize_crop_intrinsics(
    intrinsics: Float[Tensor, "*batch 3 3"],
    scale: float | int | tuple[float | int, float | int],
    crop: tuple[float | int, float | int] = (0, 0),
) -> Float[Tensor, "*batch 3 3"]:
    """Intrinsics ``(*, 3, 3)`` of an image resized by ``scale``, then cropped by ``crop``.

    Pixel ``(u, v)`` has its centre at ``(u + 0.5, v + 0.5)``, so resizing scales continuous
    pixel coordinates by ``s`` exactly and cropping subtracts the offset: ``K`` becomes
    ``[[s_x fx, s_x skew, s_x cx - left], [0, s_y fy, s_y cy - top], [0, 0, 1]]`` (i.e.
    ``A @ K`` with ``A = [[s_x, 0, -left], [0, s_y, -top], [0, 0, 1]]``). Example: nuScenes
    900x1600 resized by 0.44 (396x704) and cropped by ``crop=(140, 0)`` gives 256x704.

    Args:
        intrinsics: ``(*, 3, 3)`` pinhole matrices of the original image.
        scale: resize factor ``s`` (> 0), or ``(s_x, s_y)``: ``s_x`` for the width / x / u
            axis, ``s_y`` for the height / y / v axis.
        crop: ``(top, left)`` (note: rows first), the number of rows removed at the top and
            columns removed at the left of the *resized* image; may be fractional or
            negative (padding).

    Returns:
        ``(*, 3, 3)`` intrinsics of the resized, cropped image (same dtype/device).
    """
    scales = scale if isinstance(scale, tuple) else (scale, scale)
    if not all(_is_number(s) and math.isfinite(s) and s > 0 for s in scales):
        raise ValueError(
            f"scale: expected a finite number > 0 or a pair (s_x, s_y) of them, got {scale!r}"
        )
    if not all(_is_number(c) and math.isfinite(c) for c in crop):
        raise ValueError(f"crop: expected a pair (top, left) of finite numbers, got {crop!r}")
    (sx, sy), (top, left) = map(float, scales), map(float, crop)
    return _fold(intrinsics, sx, sy, -left, -top)


@typechecked
def split_projection(
    projection: Float[Tensor, "*batch 3 4"] | Float[Tensor, "*batch 4 4"],
) -> tuple[Float[Tensor, "*batch 4 4"], Float[Tensor, "*batch 3 3"]]:
    """Split a ``lidar2img``-style projection ``P = K [R | t]`` into ``(world_to_cam, K)``.

    ``P`` is defined up to a non-zero scale ``lambda`` (negative allowed): the result
    satisfies ``K @ world_to_cam[:3] = P[:3] / lambda`` with ``lambda`` chosen such that
    ``K[2, 2] = 1`` and ``det R = +1``. ``K`` is upper triangular with positive ``fx, fy``;
    ``R`` comes from an RQ decomposition of ``P[:3, :3]`` (QR of the row-flipped transpose)
    and ``t = K^-1 P[:3, 3] / lambda``. Round-trip error ``max |K [R | t] - P / lambda|``:
    below ``1e-14`` (float64) and ``2e-6`` (float32) times ``max |P / lambda|``.

    ``K[0, 1]`` (skew) is returned as it comes out and is non-zero for a general ``P``;
    :func:`dego.splatting.splat` renders zero-skew cameras only (as gsplat) and raises
    on a skewed ``K``.

    Args:
        projection: ``(*, 3, 4)`` or ``(*, 4, 4)`` (GaussianFormer/BEVFormer/mmdet3d
            layout: last row ``[0, 0, 0, 1]``, only the top three rows are used).

    Returns:
        ``world_to_cam`` ``(*, 4, 4)`` ``[[R, t], [0, 0, 0, 1]]`` and ``K`` ``(*, 3, 3)``.

    Raises:
        ValueError: ``projection`` is not finite, its last row (4x4) is not
            ``[0, 0, 0, 1]`` within 1e-6, or its left 3x3 block is (near) singular.
    """
    if not bool(torch.isfinite(projection).all()):
        raise ValueError("projection: expected finite values, got NaN or inf")
    if projection.shape[-2] == 4:
        last = projection[..., 3, :]
        expected = torch.tensor([0, 0, 0, 1], dtype=last.dtype, device=last.device)
        if not bool(((last - expected).abs() <= _LAST_ROW_ATOL).all()):
            raise ValueError(
                "projection: a 4x4 projection must have last row [0, 0, 0, 1] (within 1e-6); "
                "pass the top 3x4 block if it is scaled differently"
            )
    p = projection[..., :3, :]
    m = p[..., :3]
    # RQ via QR: with J the row reversal, (J M)^T = Q' R'  =>  M = (J R'^T J) (J Q'^T).
    q_t, r_t = torch.linalg.qr(m.flip(-2).mT)
    k_raw = r_t.mT.flip(-2, -1)  # upper triangular
    rot = q_t.mT.flip(-2)
    # Each |R'_jj| is the part of row 2 - j of M orthogonal to the rows below it, so the
    # product of these sines is a scale-free measure of how far M is from singular.
    row_norms = torch.linalg.vector_norm(m, dim=-1)  # (*, 3)
    diag = k_raw.diagonal(dim1=-2, dim2=-1)  # (*, 3)
    sines = diag.abs() / row_norms.clamp_min(torch.finfo(m.dtype).tiny)
    tol = math.sqrt(torch.finfo(m.dtype).eps)
    if not bool((sines.prod(-1) > tol).all()):
        raise ValueError(
            "projection: the left 3x3 block of P is singular or nearly so (product of "
            f"row-independence sines <= {tol:.1e}); it is not a pinhole projection K [R | t]"
        )
    signs = torch.where(diag >= 0, 1.0, -1.0).to(m.dtype)
    k_raw = k_raw * signs.unsqueeze(-2)  # scale columns: positive diagonal
    rot = rot * signs.unsqueeze(-1)  # scale rows: K R unchanged
    det_sign = torch.where(torch.linalg.det(rot.detach()) >= 0, 1.0, -1.0).to(m.dtype)
    scale = det_sign * k_raw[..., 2, 2]  # lambda
    k = k_raw / k_raw[..., 2:3, 2:3]
    rot = rot * det_sign[..., None, None]
    t = torch.linalg.solve_triangular(
        k, (p[..., 3] / scale.unsqueeze(-1)).unsqueeze(-1), upper=True
    )
    top = torch.cat([rot, t], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], dim=-2), k


@typechecked
def apply_image_aug(
    intrinsics: Float[Tensor, "*batch 3 3"],
    post_rot: Float[Tensor, "*batch 2 2"] | Float[Tensor, "*batch 3 3"],
    post_tran: Float[Tensor, "*batch 2"] | Float[Tensor, "*batch 3"],
) -> Float[Tensor, "*batch 3 3"]:
    """Fold a BEVDet-style image augmentation ``p -> post_rot @ p + post_tran`` into ``K``.

    Returns ``A @ K`` with ``A = [[post_rot_2x2, post_tran], [0, 0, 1]]``. Only per-axis
    positive scaling (resize), translation (crop, pad) fold exactly into a pinhole ``K``;
    ``apply_image_aug(K, diag(s, s), (-left, -top))`` equals
    ``resize_crop_intrinsics(K, s, (top, left))``.

    Args:
        intrinsics: ``(*, 3, 3)`` intrinsics of the original image.
        post_rot: ``(*, 2, 2)``, or ``(*, 3, 3)`` with the 2x2 top-left and ``[0, 0, 1]``
            as last row and column (BEVDet). Must be diagonal (off-diagonal entries up to
            1e-6 times the largest diagonal entry are treated as rounding and dropped)
            with positive diagonal.
        post_tran: ``(*, 2)``, or ``(*, 3)`` with last entry 0 (BEVDet), in pixels.

    Returns:
        ``(*, 3, 3)`` intrinsics of the augmented image.

    Raises:
        TypeError: ``post_rot`` or ``post_tran`` of another dtype than ``intrinsics``
            (nothing is promoted silently).
        ValueError: non-finite inputs, a bad 3x3/3-vector layout, or a ``post_rot`` that
            rotates or flips the image, which no pinhole ``K`` with zero skew and positive
            focal lengths can represent: warp the image instead (undo the rotation/flip on
            it), or move the rotation about the optical axis into ``world_to_cam``.
    """
    for name, value in (("post_rot", post_rot), ("post_tran", post_tran)):
        check_dtype(name, value, intrinsics.dtype, "intrinsics")
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"{name}: expected finite values, got NaN or inf")
    if post_rot.shape[-1] == 3:
        pattern = torch.stack(
            [post_rot[..., 2, 0], post_rot[..., 2, 1], post_rot[..., 0, 2], post_rot[..., 1, 2]],
            dim=-1,
        )
        if not bool(
            (pattern.abs() <= _LAST_ROW_ATOL).all()
            and ((post_rot[..., 2, 2] - 1).abs() <= _LAST_ROW_ATOL).all()
        ):
            raise ValueError(
                "post_rot: a 3x3 post_rot must be [[a, b, 0], [c, d, 0], [0, 0, 1]] (within 1e-6)"
            )
    if post_tran.shape[-1] == 3 and not bool((post_tran[..., 2].abs() <= _LAST_ROW_ATOL).all()):
        raise ValueError("post_tran: a 3-vector post_tran must have last entry 0 (within 1e-6)")
    sx, sy = post_rot[..., 0, 0], post_rot[..., 1, 1]
    off = torch.maximum(post_rot[..., 0, 1].abs(), post_rot[..., 1, 0].abs())
    reach = torch.maximum(sx.abs(), sy.abs())
    if not bool((off <= _ROTATION_RTOL * reach).all()):
        raise ValueError(
            "post_rot: has non-zero off-diagonal entries (an in-plane rotation), which a "
            "pinhole K with zero skew cannot represent; warp the image instead (e.g. undo "
            "the rotation on the image), or move the rotation about the optical axis into "
            "world_to_cam; only resize/crop/translation fold into K"
        )
    if not bool(((sx > 0) & (sy > 0)).all()):
        raise ValueError(
            "post_rot: has a non-positive diagonal entry (a flip, or a degenerate scale), "
            "which a pinhole K with positive focal lengths cannot represent; warp the image "
            "instead (flip it back), or move the flip into world_to_cam; only "
            "resize/crop/translation fold into K"
        )
    tx, ty = post_tran[..., 0], post_tran[..., 1]
    return _fold(intrinsics, *(x.unsqueeze(-1) for x in (sx, sy, tx, ty)))


__all__ = ["apply_image_aug", "resize_crop_intrinsics", "split_projection"]
