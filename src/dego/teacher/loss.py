"""Feature distillation loss: mean (1 - cosine) between rendered student and teacher maps.

The paper's L_distill = 1 / (|V| |Omega|) sum_v sum_u (1 - cos(F_s(u), F_t(u))), pooled over
the batch, the cameras and the (valid) pixels.
"""

from __future__ import annotations

import torch
from jaxtyping import Bool, Float, UInt8
from torch import Tensor, nn

from dego._typing import typechecked
from dego.metrics.confusion import as_mask_tensor


def _check_eps(eps: float) -> None:
    if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not eps > 0:
        raise ValueError(f"eps: expected a float > 0, got {eps!r}")


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

    Args:
        student: ``(B, V, C, H, W)`` rendered student features.
        teacher: ``(B, V, C, H, W)`` teacher targets, same dtype and device.
        eps: lower bound on the norms.

    Returns:
        ``(B, V, H, W)`` cosine distances.
    """
    _check_eps(eps)
    if teacher.dtype != student.dtype:
        raise TypeError(
            f"teacher: dtype {teacher.dtype} differs from student's dtype {student.dtype}"
        )
    if teacher.device != student.device:
        raise ValueError(f"teacher: on device {teacher.device} but student is on {student.device}")
    if student.shape[2] == 0:
        raise ValueError("student: expected at least one feature channel, got C = 0")
    s = student / torch.linalg.vector_norm(student, dim=2, keepdim=True).clamp_min(eps)
    t = teacher / torch.linalg.vector_norm(teacher, dim=2, keepdim=True).clamp_min(eps)
    return 1.0 - (s * t).sum(dim=2)


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
        student: ``(B, V, C, H, W)`` rendered student features (e.g. splatted C_a = 32 maps).
        teacher: ``(B, V, C, H, W)`` teacher targets at the same resolution, same dtype and
            device (detach them, or not, as the training scheme requires).
        mask: optional ``(B, V, H, W)`` valid-pixel mask, bool (or uint8 holding only 0/1).
            Masked-out pixels contribute nothing, not even through their gradient; the
            mean is over the valid pixels only, pooled over the batch and cameras.
        eps: lower bound on each feature norm, see :func:`cosine_distance_map`.

    Returns:
        A scalar in ``[0, 2]``: 0 for aligned maps, 1 for orthogonal, 2 for opposite.
        With no valid pixel (empty mask or empty maps) it is exactly 0 with a zero
        gradient, never NaN. Non-finite inputs are not checked and propagate.

    The official code uses no mask (every pixel of the 256x704 render counts).
    """
    distance = cosine_distance_map(student, teacher, eps=eps)
    if mask is None:
        return distance.sum() / max(distance.numel(), 1)
    valid = as_mask_tensor(mask, mask.shape, student.device)
    # A fill (not a multiplication), so masked-out pixels cannot leak NaN/inf into the sum.
    total = distance.masked_fill(valid.logical_not(), 0.0).sum()
    count = valid.sum().clamp_min(1).to(distance.dtype)
    return total / count


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
