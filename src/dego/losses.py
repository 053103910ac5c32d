"""The paper's training objective in one place: the rendering losses and the other terms.

DeGO trains on 2D pseudo labels (Grounded-SAM semantics, Metric3D depth) rendered against
the splatted Gaussians (paper section 4.3, "Optimization and Inference"):

- ``L_seg`` (Eq. 14): pixel-wise cross-entropy of the rendered class distribution
  ``y_hat_v(u)`` against the pseudo label ``y^pseudo_v(u)``:
  :func:`semantic_cross_entropy_map` (per pixel) -> :func:`semantic_loss` (scalar) ->
  :class:`SemanticLoss` (module).
- ``L_dep`` (Eq. 15): L1 between the rendered depth ``d_hat_v(u)`` and the pseudo depth
  ``d^pseudo_v(u)``: :func:`depth_l1_map` -> :func:`depth_loss` -> :class:`DepthLoss`.
- Both together, weighted by ``lambda_seg`` and ``lambda_dep`` of Eq. 16:
  :func:`rendering_loss` (a :class:`RenderingLoss` with ``semantic``, ``depth`` and
  ``total``) and its module :class:`RenderingCriterion`; weights in
  :class:`RenderingLossWeights`.

The two other terms of Eq. 16 live beside the modules they regularise and are re-exported
here, so that this module lists the whole objective
``L_total = lambda_seg L_seg + lambda_dep L_dep + lambda_distill L_distill + lambda_def L_def``:

- ``L_def`` (Eq. 8): :func:`~dego.deformation.deformation_loss` (a
  :class:`~dego.deformation.DeformationLoss`, weights in
  :class:`~dego.deformation.DeformationLossWeights`), from :mod:`dego.deformation`.
- ``L_distill`` (Eq. 13): :func:`~dego.teacher.distillation_loss`,
  :class:`~dego.teacher.DistillationLoss` and :func:`~dego.teacher.cosine_distance_map`,
  from :mod:`dego.teacher`.

The rendering losses take plain tensors (``(B, V, C, H, W)`` class scores, ``(B, V, H, W)``
alpha, depth, labels and masks), not a :class:`~dego.splatting.SplatOutput`, so a render
from :mod:`dego.compat.gsplat` or any other renderer can be scored. For a ``SplatOutput``
``out``: ``rendering_loss(out.features, out.alpha, out.depth, labels, depth, mask)``.

Masks select with ``torch.where`` *before* any arithmetic: NaN or inf in masked-out pixels
(of the renders or of the pseudo labels) reaches neither the loss nor its gradients, which
are exactly 0 there. The scalar losses are means over the valid pixels pooled over batch,
cameras and pixels (the ``1 / (|V| |Omega|)`` of Eqs. 14-15 taken over the valid pixels);
with no valid pixel they are exactly 0, never NaN. Eager, the valid pixels are selected by
boolean indexing (the summation order of the demo's former ``weak_losses``: its numbers
are unchanged, bit for bit); under ``torch.compile`` they are pooled with ``torch.where``,
so the losses trace into one graph with no break (equal to eager up to rounding).
"""

from __future__ import annotations

import dataclasses
import math

import torch
from jaxtyping import Bool, Float, Integer, UInt8
from torch import Tensor, nn

from dego._policy import Check, check_dtype, compute_dtype, float32_under_autocast, run_checks
from dego._typing import check_tensor_fields, typechecked
from dego.deformation import DeformationLoss, DeformationLossWeights, deformation_loss
from dego.metrics.confusion import as_mask_tensor
from dego.teacher import DistillationLoss, cosine_distance_map, distillation_loss

try:
    from torch.compiler import is_compiling as _is_compiling
except ImportError:  # torch < 2.3
    from torch._dynamo import is_compiling as _is_compiling

# -- checks ---------------------------------------------------------------------------


def _check_eps(eps: float) -> None:
    if isinstance(eps, bool) or not isinstance(eps, int | float) or not 0 < eps < 1:
        raise ValueError(f"eps: expected a float in (0, 1), got {eps!r}")


def _check_same(name: str, tensor: Tensor, reference: Tensor, owner: str) -> None:
    check_dtype(name, tensor, reference.dtype, owner)
    if tensor.device != reference.device:
        raise ValueError(f"{name}: on device {tensor.device} but {owner} is on {reference.device}")


def _valid(mask: Tensor | None, reference: Tensor) -> Tensor | None:
    """``mask`` as a bool tensor (uint8 0/1 accepted), or ``None`` for all valid."""
    if mask is None:
        return None
    if mask.device != reference.device:
        raise ValueError(f"mask: on device {mask.device} but the inputs are on {reference.device}")
    return as_mask_tensor(mask, mask.shape, reference.device)


def _label_check(labels: Tensor, num_labels: int, valid: Tensor | None) -> Check:
    bad = (labels < 0) | (labels >= num_labels)
    if valid is not None:
        bad = bad & valid
    expected = f"expected 0..{num_labels - 1} ({num_labels - 1} class scores, then free space)"

    def error() -> Exception:
        value = int(labels[bad][0])
        return ValueError(f"labels: label {value} is out of range; {expected}")

    return ~bad.any(), f"labels: a label is out of range; {expected}", error


def _checked_class_weights(
    class_weights: Tensor | None, num_labels: int, scores: Tensor
) -> tuple[Tensor | None, list[Check]]:
    """``class_weights`` in the compute dtype and its value check (finite, >= 0)."""
    if class_weights is None:
        return None, []
    if class_weights.shape != (num_labels,):
        raise ValueError(
            f"class_weights: expected shape ({num_labels},), one weight per class score and "
            f"one for free space, got {tuple(class_weights.shape)}"
        )
    if class_weights.device != scores.device:
        raise ValueError(
            f"class_weights: on device {class_weights.device} but scores is on {scores.device}"
        )
    weights = class_weights.to(compute_dtype(scores.dtype))

    def error() -> Exception:
        return ValueError(f"class_weights: expected finite weights >= 0, got {weights.tolist()}")

    ok = (torch.isfinite(weights) & (weights >= 0)).all()
    return weights, [(ok, "class_weights: expected finite weights >= 0", error)]


def _pooled(values: Tensor, valid: Tensor | None) -> tuple[Tensor, Tensor | int]:
    """The sum of ``values`` over the valid pixels, and their count (at least 1).

    Eager: the valid values are selected (boolean indexing) and summed, the order of the
    demo's former ``weak_losses``, so its numbers stay bit-identical. While
    ``torch.compile`` traces: a ``torch.where`` and a full sum instead, which needs no
    data-dependent shape (no graph break; equal up to rounding).
    """
    if valid is None:
        return values.sum(), max(values.numel(), 1)
    if _is_compiling():
        return torch.where(valid, values, values.new_zeros(())).sum(), valid.sum().clamp_min(1)
    selected = values[valid]
    return selected.sum(), max(selected.numel(), 1)


# -- L_seg ----------------------------------------------------------------------------


def _picked_probability(scores: Tensor, alpha: Tensor, labels: Tensor) -> Tensor:
    """``p_y`` per pixel: the score of class ``y``, or ``1 - alpha`` for free space."""
    free = scores.shape[2]
    labels = labels.long()
    if free == 0:
        picked = torch.zeros_like(alpha)
    else:
        picked = scores.gather(2, labels.clamp(0, free - 1)[:, :, None]).squeeze(2)
    return torch.where(labels == free, 1 - alpha, picked)


def _cross_entropy(
    scores: Tensor, alpha: Tensor, labels: Tensor, class_weights: Tensor | None, eps: float
) -> Tensor:
    """``-w_y log(max(p_y, eps))`` per pixel, in the compute dtype."""
    dtype = compute_dtype(scores.dtype)
    picked = _picked_probability(scores.to(dtype), alpha.to(dtype), labels)
    loss = -picked.clamp_min(eps).log()
    if class_weights is not None:
        loss = loss * class_weights[labels.long()]
    return loss


def _semantic_inputs(
    scores: Tensor,
    alpha: Tensor,
    labels: Tensor,
    mask: Tensor | None,
    class_weights: Tensor | None,
    eps: float,
) -> tuple[Tensor | None, Tensor | None]:
    """The checks of the ``L_seg`` functions: ``(weights, valid)``, the class weights in the
    compute dtype and the mask as bool (``None`` for all pixels)."""
    _check_eps(eps)
    _check_same("alpha", alpha, scores, "scores")
    if labels.device != scores.device:
        raise ValueError(f"labels: on device {labels.device} but scores is on {scores.device}")
    valid = _valid(mask, scores)
    num_labels = scores.shape[2] + 1
    weights, checks = _checked_class_weights(class_weights, num_labels, scores)
    run_checks([_label_check(labels, num_labels, valid), *checks])
    return weights, valid


@typechecked
def semantic_cross_entropy_map(
    scores: Float[Tensor, "B V C H W"],
    alpha: Float[Tensor, "B V H W"],
    labels: Integer[Tensor, "B V H W"],
    *,
    class_weights: Float[Tensor, " K"] | None = None,
    eps: float = 1e-6,
) -> Float[Tensor, "B V H W"]:
    """Per-pixel cross-entropy of the rendered class distribution, free space included.

    The splatted class scores are class *probabilities* blended by alpha compositing, so
    at each pixel they sum to its alpha; the transparency ``1 - alpha`` is the probability
    of free space. With ``C`` class scores the ``C + 1`` values

        y_hat_v(u) = (s_0(u), ..., s_{C-1}(u), 1 - alpha(u))

    form the rendered distribution of Eq. 14, label ``C`` is free space (``C = 17`` for
    Occ3D-nuScenes: :data:`dego.FREE_LABEL`), and

        CE(u) = -w_y log(max(y_hat_v(u)[y], eps)),    y = y^pseudo_v(u),

    with ``w_y = 1`` unless ``class_weights`` is given. The floor ``eps`` keeps an empty
    pixel with a surface label finite (``-log(1e-6) = 13.8``) and its gradient bounded.
    Nothing else is normalised: scores that do not sum to alpha are used as they are.

    The official code blends the 16 raw *logits* and applies a softmax afterwards (and
    ignores label 0); this is the form dego's demo uses, where Gaussians carry class
    probabilities and sky pixels teach them to stay out of the way.

    Args:
        scores: ``(B, V, C, H, W)`` rendered class probabilities (e.g. ``splat`` of
            per-Gaussian softmax scores: ``SplatOutput.features``).
        alpha: ``(B, V, H, W)`` rendered opacity, same dtype and device.
        labels: ``(B, V, H, W)`` pseudo labels in ``0..C`` (``C`` = free space), any
            integer dtype, same device.
        class_weights: optional ``(C + 1,)`` weights ``w_y >= 0`` per label (free space
            last), as the ``weight`` of ``torch.nn.functional.cross_entropy``.
        eps: the probability floor, in ``(0, 1)``.

    Returns:
        ``(B, V, H, W)`` cross-entropies ``>= 0`` (0 where the label's probability is 1),
        in the input dtype (float16 / bfloat16 are computed in float32). A NaN in a
        pixel's inputs makes that pixel NaN; :func:`semantic_loss` masks pixels out.

    Raises:
        jaxtyping.TypeCheckError: a wrong shape or dtype (naming the argument).
        TypeError: ``alpha``'s dtype differs from ``scores``'.
        ValueError: a label outside ``0..C``; ``class_weights`` of the wrong shape or
            device, negative or not finite; a device mismatch; ``eps`` not in ``(0, 1)``.

    Example:
        >>> scores = torch.tensor([0.6, 0.2]).reshape(1, 1, 2, 1, 1)
        >>> alpha = torch.full((1, 1, 1, 1), 0.8)
        >>> labels = torch.tensor([0, 1, 2]).reshape(1, 1, 1, 3)  # class 0, 1, free
        >>> semantic_cross_entropy_map(scores.expand(1, 1, 2, 1, 3), alpha.expand(1, 1, 1, 3),
        ...                            labels).squeeze()
        tensor([0.5108, 1.6094, 1.6094])
    """
    weights, _ = _semantic_inputs(scores, alpha, labels, None, class_weights, eps)
    return _cross_entropy(scores, alpha, labels, weights, eps).to(scores.dtype)


@float32_under_autocast()
@typechecked
def semantic_loss(
    scores: Float[Tensor, "B V C H W"],
    alpha: Float[Tensor, "B V H W"],
    labels: Integer[Tensor, "B V H W"],
    mask: Bool[Tensor, "B V H W"] | UInt8[Tensor, "B V H W"] | None = None,
    *,
    class_weights: Float[Tensor, " K"] | None = None,
    eps: float = 1e-6,
) -> Float[Tensor, ""]:
    """The paper's ``L_seg`` (Eq. 14): mean cross-entropy over the valid pixels.

        L_seg = 1 / (|V| |Omega|) sum_{v in V} sum_{u in Omega} CE(y_hat_v(u), y^pseudo_v(u))

    with CE per pixel as in :func:`semantic_cross_entropy_map` (class scores plus
    ``1 - alpha`` for free space), and ``Omega`` the valid pixels of every batch element
    and camera, pooled. With ``class_weights`` it is the weighted mean
    ``sum_u w_y CE(u) / sum_u w_y`` (as torch's ``cross_entropy(..., weight=w)``).

    Args:
        scores: ``(B, V, C, H, W)`` rendered class probabilities, see
            :func:`semantic_cross_entropy_map`.
        alpha: ``(B, V, H, W)`` rendered opacity, same dtype and device.
        labels: ``(B, V, H, W)`` pseudo labels in ``0..C`` (``C`` = free space) on valid
            pixels; masked-out pixels may hold anything (an ignore value such as 255).
        mask: optional ``(B, V, H, W)`` valid pixels, bool (or uint8 holding 0/1);
            ``None``: every pixel. Masked-out pixels are replaced (``torch.where``) before
            the cross-entropy: NaN or inf there reaches neither the value nor the
            gradients of ``scores`` and ``alpha``, which are exactly 0 there.
        class_weights: optional ``(C + 1,)`` per-label weights ``>= 0`` (free space last).
        eps: the probability floor, in ``(0, 1)``.

    Returns:
        A scalar ``>= 0`` in the input dtype (float16 / bfloat16 are computed in float32,
        and under ``torch.autocast`` returned in float32). With no valid pixel (or a zero
        total weight) it is exactly 0 with a zero gradient. A NaN in a valid pixel makes
        it NaN (not checked, as torch's losses).

    Raises:
        jaxtyping.TypeCheckError: a wrong shape or dtype (naming the argument), e.g. a
            ``mask`` whose shape is not the ``labels``' shape.
        TypeError: ``alpha``'s dtype differs from ``scores``'.
        ValueError: a label outside ``0..C`` on a valid pixel; a uint8 ``mask`` holding
            other values than 0/1; ``class_weights`` of the wrong shape or device, negative
            or not finite; a device mismatch; ``eps`` not in ``(0, 1)``.
    """
    weights, valid = _semantic_inputs(scores, alpha, labels, mask, class_weights, eps)
    if valid is not None:
        # Select before the arithmetic: a multiplication (or a fill after it) would still
        # send 0 * NaN = NaN back through the masked-out pixels' gradients. A masked-out
        # pixel becomes certain free space: probability 1, cross-entropy 0.
        free = scores.shape[2]
        scores = torch.where(valid[:, :, None], scores, scores.new_zeros(()))
        alpha = torch.where(valid, alpha, alpha.new_zeros(()))
        labels = torch.where(valid, labels, torch.full_like(labels, free))
    total, count = _pooled(_cross_entropy(scores, alpha, labels, weights, eps), valid)
    if weights is not None:
        norm, _ = _pooled(weights[labels.long()], valid)
        return (total / torch.where(norm > 0, norm, torch.ones_like(norm))).to(scores.dtype)
    return (total / count).to(scores.dtype)


class SemanticLoss(nn.Module):
    """Module form of :func:`semantic_loss` (``L_seg``, Eq. 14); holds only its options.

    ``class_weights`` is kept as a non-persistent buffer (it follows ``.to(device)`` and
    stays out of the ``state_dict``).
    """

    class_weights: Tensor | None

    @typechecked
    def __init__(
        self, *, class_weights: Float[Tensor, " K"] | None = None, eps: float = 1e-6
    ) -> None:
        super().__init__()
        _check_eps(eps)
        if class_weights is not None:
            if not bool((torch.isfinite(class_weights) & (class_weights >= 0)).all()):
                raise ValueError(
                    f"class_weights: expected finite weights >= 0, got {class_weights.tolist()}"
                )
            class_weights = class_weights.detach().clone()
        self.register_buffer("class_weights", class_weights, persistent=False)
        self.eps = float(eps)

    @typechecked
    def forward(
        self,
        scores: Float[Tensor, "B V C H W"],
        alpha: Float[Tensor, "B V H W"],
        labels: Integer[Tensor, "B V H W"],
        mask: Bool[Tensor, "B V H W"] | UInt8[Tensor, "B V H W"] | None = None,
    ) -> Float[Tensor, ""]:
        """See :func:`semantic_loss`."""
        return semantic_loss(
            scores, alpha, labels, mask, class_weights=self.class_weights, eps=self.eps
        )

    def extra_repr(self) -> str:
        if self.class_weights is None:
            return f"eps={self.eps}"
        return f"eps={self.eps}, class_weights={self.class_weights.tolist()}"


# -- L_dep ----------------------------------------------------------------------------


@typechecked
def depth_l1_map(
    depth: Float[Tensor, "B V H W"], target: Float[Tensor, "B V H W"]
) -> Float[Tensor, "B V H W"]:
    """Per-pixel absolute depth error ``|d_hat_v(u) - d^pseudo_v(u)|`` (Eq. 15's summand).

    No pixel is left out here (``target <= 0``, "no pseudo depth", included): see
    :func:`depth_loss` for the valid pixels.

    Args:
        depth: ``(B, V, H, W)`` rendered depth in metres (e.g. ``SplatOutput.depth``).
        target: ``(B, V, H, W)`` pseudo depth, same dtype and device.

    Returns:
        ``(B, V, H, W)`` errors ``>= 0`` in metres, in the input dtype.

    Raises:
        jaxtyping.TypeCheckError: a wrong shape or dtype (naming the argument).
        TypeError: ``target``'s dtype differs from ``depth``'s.
        ValueError: ``target`` on another device.
    """
    _check_same("target", target, depth, "depth")
    return (depth - target).abs()


@float32_under_autocast()
@typechecked
def depth_loss(
    depth: Float[Tensor, "B V H W"],
    target: Float[Tensor, "B V H W"],
    mask: Bool[Tensor, "B V H W"] | UInt8[Tensor, "B V H W"] | None = None,
) -> Float[Tensor, ""]:
    """The paper's ``L_dep`` (Eq. 15): mean L1 depth error over the pixels with depth.

        L_dep = 1 / (|V| |Omega|) sum_{v in V} sum_{u in Omega} |d_hat_v(u) - d^pseudo_v(u)|

    where ``Omega`` is the pixels with ``mask`` True **and** ``target > 0``, pooled over
    batch and cameras: pseudo-depth maps hold 0 where they have no depth (sky, or beyond
    the official code's 40 m). A NaN target therefore never counts either.

    Args:
        depth: ``(B, V, H, W)`` rendered depth in metres (dego's ``splat`` renders the
            alpha-normalised expected depth; the official code the accumulated one).
        target: ``(B, V, H, W)`` pseudo depth (0: none), same dtype and device.
        mask: optional ``(B, V, H, W)`` valid pixels, bool (or uint8 holding 0/1);
            ``None``: every pixel with ``target > 0``. Both inputs are replaced
            (``torch.where``) outside the valid pixels before the subtraction, so NaN or
            inf there reaches neither the value nor the gradients, which are 0 there.

    Returns:
        A scalar ``>= 0`` in metres, in the input dtype (under ``torch.autocast``, half
        inputs are computed and returned in float32). With no valid pixel it is exactly
        0 with a zero gradient. A NaN rendered depth on a valid pixel makes it NaN.

    Raises:
        jaxtyping.TypeCheckError: a wrong shape or dtype (naming the argument).
        TypeError: ``target``'s dtype differs from ``depth``'s.
        ValueError: ``target`` or ``mask`` on another device, a uint8 ``mask`` holding
            other values than 0/1.

    The official code uses ``0.05 * MSE`` on ``0 < d <= 40`` m instead of L1 (see the
    paper-and-code page of the docs).
    """
    _check_same("target", target, depth, "depth")
    valid = _valid(mask, depth)
    valid = target > 0 if valid is None else valid & (target > 0)
    zero = depth.new_zeros(())
    error = (torch.where(valid, depth, zero) - torch.where(valid, target, zero)).abs()
    total, count = _pooled(error, valid)
    return total / count


class DepthLoss(nn.Module):
    """Module form of :func:`depth_loss` (``L_dep``, Eq. 15); it has no options."""

    @typechecked
    def forward(
        self,
        depth: Float[Tensor, "B V H W"],
        target: Float[Tensor, "B V H W"],
        mask: Bool[Tensor, "B V H W"] | UInt8[Tensor, "B V H W"] | None = None,
    ) -> Float[Tensor, ""]:
        """See :func:`depth_loss`."""
        return depth_loss(depth, target, mask)


# -- both -----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class RenderingLossWeights:
    """``lambda_seg`` and ``lambda_dep`` of Eq. 16, the weights of :func:`rendering_loss`.

    The paper gives no values. The defaults are dego's demo's (``dego demo``,
    ``FitConfig``: semantics 1, depth 0.1 per metre), which suit its L1 on
    alpha-normalised depth. The official code weighs its variants of the two terms with
    2.0 (cross-entropy over blended logits) and 0.05 (MSE on accumulated depth).
    """

    semantic: float = 1.0
    depth: float = 0.1

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if (
                isinstance(value, bool)
                or not isinstance(value, int | float)
                or not math.isfinite(value)
                or value < 0
            ):
                raise ValueError(f"{field.name}: expected a finite weight >= 0, got {value!r}")


_TERMS = ("semantic", "depth", "total")


@dataclasses.dataclass(frozen=True, eq=False)
class RenderingLoss:
    """Result of :func:`rendering_loss`: the rendering terms of Eq. 16, scalars.

    Attributes:
        semantic: ``L_seg`` (Eq. 14), unweighted.
        depth: ``L_dep`` (Eq. 15), unweighted, in metres.
        total: ``lambda_seg * L_seg + lambda_dep * L_dep``.

    Add the other terms of Eq. 16 yourself: ``loss.total + lambda_def *
    deformation_loss(output).total + lambda_distill * distillation_loss(s, t)``.
    """

    semantic: Float[Tensor, ""]
    depth: Float[Tensor, ""]
    total: Float[Tensor, ""]

    def __post_init__(self) -> None:
        check_tensor_fields(self)

    @typechecked
    def to_dict(self) -> dict[str, Tensor]:
        """``{"semantic", "depth", "total"}`` -> the tensors (not copied, not detached)."""
        return {name: getattr(self, name) for name in _TERMS}


@float32_under_autocast()
@typechecked
def rendering_loss(
    scores: Float[Tensor, "B V C H W"],
    alpha: Float[Tensor, "B V H W"],
    depth: Float[Tensor, "B V H W"],
    labels: Integer[Tensor, "B V H W"],
    target_depth: Float[Tensor, "B V H W"],
    mask: Bool[Tensor, "B V H W"] | UInt8[Tensor, "B V H W"] | None = None,
    *,
    weights: RenderingLossWeights | None = None,
    class_weights: Float[Tensor, " K"] | None = None,
    eps: float = 1e-6,
) -> RenderingLoss:
    """``L_seg`` and ``L_dep`` against one set of pseudo labels, and their weighted sum.

        total = lambda_seg L_seg + lambda_dep L_dep

    the rendering part of Eq. 16: :func:`semantic_loss` on the ``mask`` pixels and
    :func:`depth_loss` on the ``mask`` pixels whose ``target_depth > 0``. For a
    :class:`~dego.splatting.SplatOutput` ``out``:
    ``rendering_loss(out.features, out.alpha, out.depth, labels, target_depth, mask)``.

    Args:
        scores: ``(B, V, C, H, W)`` rendered class probabilities.
        alpha: ``(B, V, H, W)`` rendered opacity.
        depth: ``(B, V, H, W)`` rendered depth in metres.
        labels: ``(B, V, H, W)`` pseudo labels in ``0..C`` (``C`` = free space).
        target_depth: ``(B, V, H, W)`` pseudo depth (0: none).
        mask: optional ``(B, V, H, W)`` supervised pixels (bool, or uint8 holding 0/1).
        weights: ``lambda_seg`` and ``lambda_dep``; default :class:`RenderingLossWeights`
            ``()`` (1 and 0.1: the paper gives none; these are the demo's).
        class_weights: optional ``(C + 1,)`` per-label weights of ``L_seg``.
        eps: the probability floor of ``L_seg``.

    Returns:
        A :class:`RenderingLoss` (scalars in the inputs' dtype; float32 under autocast).

    Raises:
        jaxtyping.TypeCheckError: a wrong shape or dtype (naming the argument).
        TypeError: ``alpha`` or ``target_depth`` of another dtype than ``scores`` /
            ``depth``.
        ValueError: as :func:`semantic_loss` and :func:`depth_loss`.
    """
    weights = RenderingLossWeights() if weights is None else weights
    _check_same("depth", depth, scores, "scores")
    semantic = semantic_loss(scores, alpha, labels, mask, class_weights=class_weights, eps=eps)
    depth_term = depth_loss(depth, target_depth, mask)
    total = weights.semantic * semantic + weights.depth * depth_term
    return RenderingLoss(semantic=semantic, depth=depth_term, total=total)


class RenderingCriterion(nn.Module):
    """Module form of :func:`rendering_loss`; holds only the weights and options.

    ``class_weights`` is kept as a non-persistent buffer, as in :class:`SemanticLoss`.
    """

    class_weights: Tensor | None

    @typechecked
    def __init__(
        self,
        weights: RenderingLossWeights | None = None,
        *,
        class_weights: Float[Tensor, " K"] | None = None,
        eps: float = 1e-6,
    ) -> None:
        super().__init__()
        self.weights = RenderingLossWeights() if weights is None else weights
        self.semantic = SemanticLoss(class_weights=class_weights, eps=eps)
        self.eps = self.semantic.eps

    @typechecked
    def forward(
        self,
        scores: Float[Tensor, "B V C H W"],
        alpha: Float[Tensor, "B V H W"],
        depth: Float[Tensor, "B V H W"],
        labels: Integer[Tensor, "B V H W"],
        target_depth: Float[Tensor, "B V H W"],
        mask: Bool[Tensor, "B V H W"] | UInt8[Tensor, "B V H W"] | None = None,
    ) -> RenderingLoss:
        """See :func:`rendering_loss`."""
        return rendering_loss(
            scores,
            alpha,
            depth,
            labels,
            target_depth,
            mask,
            weights=self.weights,
            class_weights=self.semantic.class_weights,
            eps=self.eps,
        )

    def extra_repr(self) -> str:
        return f"weights={self.weights}"


__all__ = [
    "DeformationLoss",
    "DeformationLossWeights",
    "DepthLoss",
    "DistillationLoss",
    "RenderingCriterion",
    "RenderingLoss",
    "RenderingLossWeights",
    "SemanticLoss",
    "cosine_distance_map",
    "deformation_loss",
    "depth_l1_map",
    "depth_loss",
    "distillation_loss",
    "rendering_loss",
    "semantic_cross_entropy_map",
    "semantic_loss",
]
