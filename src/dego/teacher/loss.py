"""Feature distillation loss: mean (1 - cosine) between rendered student and teacher maps.

The paper's L_distill = 1 / (|V| |Omega|) sum_v sum_u (1 - cos(F_s(u), F_t(u))), pooled over
the batch, the cameras and the (valid) pixels.
"""

from __future__ import annotations

import torch
from jaxtyping import Bool, Float, UInt8
from torch import Tensor, nn

from dego._policy import check_dtype, compute_dtype, float32_under_autocast
from dego._typing import typechecked
from dego.metrics.confusion import as_mask_tensor


def _check_eps(eps: float) -> None:
    if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not eps > 0:
        raise ValueError(f"eps: expected a float > 0, got {eps!r}")


def _check_pair(student: Tensor, teacher: Tensor) -> None:
    check_dtype("teacher", teacher, student.dtype, "student")
    if teacher.device != student.device:
        raise ValueError(f"teacher: on device {teacher.device} but student is on {student.device}")
    if student.shape[2] == 0:
        raise ValueError("student: expected at least one feature channel, got C = 0")


def _distance(student: Tensor, teacher: Tensor, eps: float) -> Tensor:
    """``1 - cos`` along axis 2, in the compute dtype (float32 for float16 / bfloat16)."""
    dtype = compute_dtype(student.dtype)
    s, t = student.to(dtype), teacher.to(dtype)
    s = s / torch.linalg.vector_norm(s, dim=2, keepdim=True).clamp_min(eps)
    t = t / torch.linalg.vector_norm(t, dim=2, keepdim=True).clamp_min(eps)
    return 1.0 - (s * t).sum(dim=2)


@typechecked
def cosine_distance_map(
    student: Float[Tensor, "B V C H W"],
    teacher: Float[Tensor, "B V C H W"],
    *,
    eps: float = 1e-8,
) -> Float[Tensor, "B V H W"]:
    """Per-pixel ``1 - cos(student, teacher)`` along the channel axis, in ``[0, 2]``.

    Each side is divided by ``max(||x||, eps)`` (as ``F.normalize``), so a zero vector has
    cosine 0 with anything (distance 1) instead of NaN, and its gradient stays finite.
    float16 / bfloat16 inputs are computed in float32 (their squared norms would
    overflow above ~256) and the result is returned in the input dtype. A NaN or inf in
    a pixel's features makes that pixel's distance NaN (nothing is checked or clamped).

    Args:
        student: ``(B, V, C, H, W)`` rendered student features, C >= 1.
        teacher: ``(B, V, C, H, W)`` teacher targets, same dtype and device.
        eps: lower bound on the norms.

    Returns:
        ``(B, V, H, W)`` cosine distances, in the input dtype.

    Raises:
        TypeError: ``teacher``'s dtype differs from ``student``'s.
        ValueError: different devices, C = 0, or ``eps`` not > 0.
    """
    _check_eps(eps)
    _check_pair(student, teacher)
    return _distance(student, teacher, eps).to(student.dtype)


@float32_under_autocast()
@typechecked
def distillation_loss(
    student: Float[Tensor, "B V C H W"],
    teacher: Float[Tensor, "B V C H W"],
    mask: Bool[Tensor, "B V H W"] | UInt8[Tensor, "B V H W"] | None = None,
    *,
    eps: float = 1e-8,
) -> Float[Tensor, ""]:
    """Mean of ``1 - cos`` over batch, cameras and valid pixels (the paper's L_distill).

    Args:
        student: ``(B, V, C, H, W)`` rendered student features (e.g. splatted C_a = 32
            maps), C >= 1.
        teacher: ``(B, V, C, H, W)`` teacher targets at the same resolution, same dtype and
            device (detach them, or not, as the training scheme requires).
        mask: optional ``(B, V, H, W)`` valid-pixel mask, bool (or uint8 holding only 0/1),
            on the inputs' device. Masked-out pixels contribute nothing: their features
            are replaced (``torch.where``) before the cosine, so NaN or inf there cannot
            reach the loss, and the gradient w.r.t. ``student`` and ``teacher`` is exactly
            0 there. That guarantee ends at these two tensors: a layer upstream whose own
            input is inf at those pixels computes ``0 * inf = NaN`` in its weight gradient
            (autograd's rule, out of this function's reach); zero such inputs with
            ``torch.where`` before the layer. The mean is over the valid pixels only,
            pooled over the batch and cameras.
        eps: lower bound on each feature norm, see :func:`cosine_distance_map`.

    Returns:
        A scalar in ``[0, 2]`` in the input dtype: 0 for aligned maps, 1 for orthogonal,
        2 for opposite. With no valid pixel (all-False mask or empty maps) it is exactly 0
        with a zero gradient, never NaN. float16 / bfloat16 inputs are computed in
        float32.

    Non-finite values in valid pixels are not checked: like torch's own losses, a NaN or
    inf there makes the loss NaN (and its gradient), which anomaly detection and
    gradient scalers can see. Mask such pixels out, or check the inputs, to exclude them.

    Raises:
        TypeError: ``teacher``'s dtype differs from ``student``'s, or ``mask`` is neither
            bool nor uint8.
        ValueError: ``teacher`` or ``mask`` on another device, a uint8 ``mask`` holding
            values other than 0/1, C = 0, or ``eps`` not > 0.

    The official code uses no mask (every pixel of the 256x704 render counts).
    """
    _check_eps(eps)
    _check_pair(student, teacher)
    if mask is None:
        distance = _distance(student, teacher, eps)
        return (distance.sum() / max(distance.numel(), 1)).to(student.dtype)
    if mask.device != student.device:
        raise ValueError(f"mask: on device {mask.device} but student is on {student.device}")
    valid = as_mask_tensor(mask, mask.shape, student.device)
    # Select before the cosine: a multiplication (or a fill after it) would still send
    # 0 * NaN = NaN back through the masked-out pixels' gradients.
    keep = valid.unsqueeze(2)
    zero = student.new_zeros(())
    distance = _distance(torch.where(keep, student, zero), torch.where(keep, teacher, zero), eps)
    total = torch.where(valid, distance, distance.new_zeros(())).sum()
    count = valid.sum().clamp_min(1).to(distance.dtype)
    return (total / count).to(student.dtype)


class DistillationLoss(nn.Module):
    """Module form of :func:`distillation_loss`; stateless (holds only ``eps``)."""

    def __init__(self, *, eps: float = 1e-8) -> None:
        super().__init__()
        _check_eps(eps)
        self.eps = float(eps)

    @typechecked
    def forward(
        self,
        student: Float[Tensor, "B V C H W"],
        teacher: Float[Tensor, "B V C H W"],
        mask: Bool[Tensor, "B V H W"] | UInt8[Tensor, "B V H W"] | None = None,
    ) -> Float[Tensor, ""]:
        """See :func:`distillation_loss`."""
        return distillation_loss(student, teacher, mask, eps=self.eps)

    def extra_repr(self) -> str:
        return f"eps={self.eps}"


__all__ = ["DistillationLoss", "cosine_distance_map", "distillation_loss"]
