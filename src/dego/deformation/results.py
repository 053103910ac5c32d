"""The results of :class:`~dego.deformation.DecoupledDeformation`: the deformed sets
(:class:`DeformationOutput`), their applied deltas (:class:`DeformationDeltas`), and the
deformation losses computed from them (:func:`deformation_loss`).

Re-exported by :mod:`dego.deformation`, their public home. Checkpoints that name these
classes where they were defined before ``dego.deformation`` became a package load through
the aliases in :mod:`dego._safe_globals`.
"""

from __future__ import annotations

import dataclasses

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from dego import _serialization
from dego._typing import check_tensor_fields, literal_error, typechecked
from dego.deformation.loss import REDUCTIONS, DeformationLoss, DeformationLossWeights
from dego.deformation.presets import PARAMETERS, PRESETS, Preset
from dego.gaussians import GaussianSet


@dataclasses.dataclass(frozen=True)
class DeformationDeltas(_serialization.DictForm):
    """Applied deltas per parameter, each ``(B, T, N, k)`` (opacities ``(B, T, N)``).

    ``paper``: the update in each parameter's own space, after the mask: position offset
    in metres, the quaternion increment's offset from the identity, the log-scale change,
    the opacity-logit change. ``official``: deformed minus canonical value (the official
    ``L_reg`` terms).
    """

    means: Float[Tensor, "B T N 3"]
    quats: Float[Tensor, "B T N 4"]
    scales: Float[Tensor, "B T N 3"]
    opacities: Float[Tensor, "B T N"]

    def __post_init__(self) -> None:
        check_tensor_fields(self)


@dataclasses.dataclass(frozen=True)
class DeformationOutput(_serialization.DictForm):
    """Result of :class:`DecoupledDeformation`.

    Attributes:
        gaussians: the deformed sets, batch shape ``(B, T)``; features carried unchanged.
        rigid_mask: m, ``(B, N)`` (``paper``: one per Gaussian) or ``(B, T, N)``
            (``official``: time-dependent); 1 = nonrigid.
        deltas: the applied deltas (:class:`DeformationDeltas`).
        rigid_offsets: raw rigid position head ``d_mu_rig`` ``(B, T, N, 3)``.
        nonrigid_offsets: raw nonrigid position head ``d_mu_def`` ``(B, T, N, 3)``
            (``official``: the same tensor as ``rigid_offsets``).
        preset: the preset that produced it; :func:`deformation_loss` follows it.
        loss_weights: the module's default loss weights.
        canonical_last: ``True`` for the result of :meth:`with_canonical`: the last time
            step is the undeformed canonical set, which :func:`deformation_loss` leaves out.
    """

    gaussians: GaussianSet
    rigid_mask: Float[Tensor, "B N"] | Float[Tensor, "B T N"]
    deltas: DeformationDeltas
    rigid_offsets: Float[Tensor, "B T N 3"]
    nonrigid_offsets: Float[Tensor, "B T N 3"]
    preset: Preset
    loss_weights: DeformationLossWeights
    canonical_last: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.preset, str) or self.preset not in PRESETS:
            raise literal_error("DeformationOutput()", "preset", self.preset, tuple(PRESETS))
        check_tensor_fields(self)

    @property
    def num_times(self) -> int:
        return self.gaussians.batch_shape[1]

    def at(self, t_index: int) -> GaussianSet:
        """The deformed set ``(B, N)`` at time index ``t_index`` (negative counts from the end)."""
        t = self.num_times
        if isinstance(t_index, bool) or not isinstance(t_index, int) or not -t <= t_index < t:
            raise IndexError(f"t_index: expected an int in [{-t}, {t}), got {t_index!r}")
        return self.gaussians.map(lambda _, v: v[:, t_index])

    def _check_canonical(self, name: str, canonical: GaussianSet) -> None:
        deformed = self.gaussians
        b, n = deformed.batch_shape[0], deformed.num_gaussians
        if tuple(canonical.batch_shape) != (b,) or canonical.num_gaussians != n:
            raise ValueError(
                f"{name}: expected the canonical set of batch shape ({b},) with N = {n} "
                f"Gaussians, got batch shape {tuple(canonical.batch_shape)} with N = "
                f"{canonical.num_gaussians}"
            )
        if canonical.dtype != deformed.dtype or canonical.device != deformed.device:
            raise ValueError(
                f"{name}: expected {deformed.dtype} on {deformed.device} like the output, got "
                f"{canonical.dtype} on {canonical.device}"
            )
        if canonical.feature_dim != deformed.feature_dim:
            raise ValueError(
                f"{name}: feature_dim {canonical.feature_dim} differs from the deformed sets' "
                f"{deformed.feature_dim} (features are carried unchanged, so both or neither "
                "have them)"
            )

    @typechecked
    def to_official_dict(self, *, losses: bool = False) -> dict[str, Tensor]:
        """The official DeGO deformation module's return value, from this output.

        Keys and layouts of ``GaussianDeformationMaskStaticRigid.forward``: ``"means"``
        ``(B, N, T, 3)``, ``"rotations"`` ``(B, N, T, 4)``, ``"scales"`` ``(B, N, T, 3)``,
        ``"opacity"`` ``(B, N, T, 1)`` (Gaussian axis before time, opacity with a trailing
        1; contiguous copies of ``gaussians``). The official module does not return its mask.

        Args:
            losses: also return the official module's training losses
                ``"deformation_reg_loss"`` (``deformation_loss``'s ``reg`` with every
                lambda_p = 1) and ``"rigid_non_rigid_loss"`` (its ``mask``), unweighted
                scalars; ``official`` preset only. (The official module returns zeros for
                both in eval mode.) A :meth:`with_canonical` output's canonical step is
                left out, as the official module computes them before the detector appends it.
        """
        if not isinstance(losses, bool):
            raise TypeError(f"losses: expected a bool, got {type(losses).__name__}")
        g = self.gaussians
        result = {
            "means": g.means.transpose(1, 2).contiguous(),
            "rotations": g.quats.transpose(1, 2).contiguous(),
            "scales": g.scales.transpose(1, 2).contiguous(),
            "opacity": g.opacities.transpose(1, 2)[..., None].contiguous(),
        }
        if losses:
            if self.preset != "official":
                raise ValueError(
                    f"losses: the official losses need an 'official' preset output, got preset "
                    f"{self.preset!r} (use deformation_loss for its own losses)"
                )
            terms = deformation_loss(self, DeformationLossWeights())
            result["deformation_reg_loss"] = terms.reg
            result["rigid_non_rigid_loss"] = terms.mask
        return result

    @typechecked
    def with_canonical(self, gaussians: GaussianSet) -> DeformationOutput:
        """This output with the canonical set appended as the last time step (T + 1 steps).

        The official training loop renders T deformed frames plus the undeformed canonical
        set as the current frame, last (8 + 1 = 9 frames). The appended step carries the
        values that mean "no deformation": zero deltas and zero raw offsets, and
        (``official``, whose mask is per time step) mask 0, the only mask value for which
        the update rule gives back the canonical set whatever the shape heads predict; the
        ``paper`` mask ``(B, N)`` is per Gaussian and unchanged. :func:`deformation_loss`
        leaves the appended step out, so the losses do not change.

        Args:
            gaussians: the canonical set that was deformed, batch shape ``(B,)``, same N,
                dtype, device and ``feature_dim`` as the output.
        """
        if self.canonical_last:
            raise ValueError(
                "gaussians: this output already ends with its canonical set (with_canonical "
                "was applied twice)"
            )
        self._check_canonical("gaussians", gaussians)

        def append_zeros(value: Tensor) -> Tensor:
            return torch.cat([value, value.new_zeros(value[:, :1].shape)], 1)

        extended = self.gaussians.map(
            lambda name, value: torch.cat([value, getattr(gaussians, name)[:, None]], 1)
        )
        rigid = append_zeros(self.rigid_offsets)
        shared = self.nonrigid_offsets is self.rigid_offsets
        return dataclasses.replace(
            self,
            gaussians=extended,
            rigid_mask=self.rigid_mask
            if self.rigid_mask.ndim == 2
            else append_zeros(self.rigid_mask),
            deltas=DeformationDeltas(
                *(append_zeros(getattr(self.deltas, name)) for name in PARAMETERS)
            ),
            rigid_offsets=rigid,
            nonrigid_offsets=rigid if shared else append_zeros(self.nonrigid_offsets),
            canonical_last=True,
        )

    @typechecked
    def gated(self, keep: Bool[Tensor, "B N"], canonical: GaussianSet) -> DeformationOutput:
        """This output with the Gaussians where ``keep`` is False left undeformed.

        Those Gaussians get their canonical parameters at every time step, zero deltas,
        zero raw offsets and mask 0 (as in :meth:`with_canonical`); the others are
        unchanged. GaussianFlowOcc's class gating is ``gated(is_dynamic, canonical)``; see
        :func:`gate_by_class`.

        Args:
            keep: ``(B, N)`` bool, True where a Gaussian may deform.
            canonical: the canonical set that was deformed, batch shape ``(B,)``.
        """
        self._check_canonical("canonical", canonical)
        b, n = self.gaussians.batch_shape[0], self.gaussians.num_gaussians
        if tuple(keep.shape) != (b, n) or keep.device != self.gaussians.device:
            raise ValueError(
                f"keep: expected shape ({b}, {n}) on {self.gaussians.device}, got "
                f"{tuple(keep.shape)} on {keep.device}"
            )
        per_step = keep[:, None]  # (B, 1, N)

        def gate(value: Tensor, fallback: Tensor | float) -> Tensor:
            k = per_step if value.ndim == 3 else per_step[..., None]
            return torch.where(k, value, fallback)

        gaussians = self.gaussians.map(
            lambda name, value: (
                value if name == "features" else gate(value, getattr(canonical, name)[:, None])
            )
        )
        mask = (
            torch.where(keep, self.rigid_mask, 0.0)
            if self.rigid_mask.ndim == 2
            else gate(self.rigid_mask, 0.0)
        )
        rigid = gate(self.rigid_offsets, 0.0)
        shared = self.nonrigid_offsets is self.rigid_offsets
        return dataclasses.replace(
            self,
            gaussians=gaussians,
            rigid_mask=mask,
            deltas=DeformationDeltas(
                *(gate(getattr(self.deltas, name), 0.0) for name in PARAMETERS)
            ),
            rigid_offsets=rigid,
            nonrigid_offsets=rigid if shared else gate(self.nonrigid_offsets, 0.0),
        )


def _mean(values: Tensor) -> Tensor:
    """Mean that is 0 (not NaN) over no elements, e.g. N = 0 padding-only batches."""
    return values.sum() / max(values.numel(), 1)


@typechecked
def deformation_loss(
    output: DeformationOutput,
    weights: DeformationLossWeights | None = None,
    *,
    reduction: str | None = None,
    gaussian_weights: Tensor | None = None,
) -> DeformationLoss:
    """DeGO's deformation losses: a :class:`DeformationLoss` with ``reg``, ``mask`` and
    ``total`` (scalars).

    ``reg = sum_p lambda_p R(||d_p||^2)`` over the applied deltas, reduced by R (see
    :class:`DeformationLossWeights`; ``"mean"``, the default: ``paper``, the mean over
    (B, T, N) of the squared norm; ``official``, the mean over every element);
    ``mask = mean(m (1 - m))`` (``official``: the last time step's mask only);
    ``total = weights.reg * reg + weights.mask * mask``. ``weights`` defaults to
    ``output.loss_weights``. The canonical step of a
    :meth:`DeformationOutput.with_canonical` output is left out.

    Args:
        output: a :class:`DecoupledDeformation` result.
        weights: the lambdas and the default reduction.
        reduction: overrides ``weights.reduction``: ``"mean"``, ``"sum"`` or ``"weighted"``.
        gaussian_weights: ``(N,)`` or ``(B, N)`` weights ``>= 0`` of the ``"weighted"``
            reduction (required by it, refused by the others), real or bool, e.g.
            ``is_movable``. Not differentiated through (detached).

    Raises:
        ValueError: an unknown ``reduction``; ``gaussian_weights`` missing for
            ``"weighted"``, given for another reduction, of the wrong shape or device,
            negative or not finite.
    """
    weights = output.loss_weights if weights is None else weights
    reduction = weights.reduction if reduction is None else reduction
    if reduction not in REDUCTIONS:
        raise ValueError(f"reduction: expected one of {REDUCTIONS}, got {reduction!r}")
    spec = PRESETS[output.preset]
    steps = slice(None, -1) if output.canonical_last else slice(None)
    per_gaussian = _reduction_weights(output, reduction, gaussian_weights)
    reg = output.deltas.means.new_zeros(())
    for name in PARAMETERS:
        squared = getattr(output.deltas, name)[:, steps].square()
        if name == "opacities":
            value = squared  # (B, T, N): one element per Gaussian
        elif spec.reg_element_mean and reduction != "sum":
            value = squared.mean(-1)
        else:
            value = squared.sum(-1)
        if reduction == "mean":
            term = _mean(value)
        elif reduction == "sum":
            term = value.sum()
        else:
            assert per_gaussian is not None
            w = per_gaussian[:, None]  # (B, 1, N)
            total_weight = w.sum() * value.shape[1]
            # all-zero weights give 0 (numerator 0); tiny but positive sums divide exactly
            term = (w * value).sum() / torch.where(total_weight > 0, total_weight, 1.0)
        reg = reg + getattr(weights, name) * term
    m = output.rigid_mask if output.rigid_mask.ndim == 2 else output.rigid_mask[:, steps]
    m = m[:, -1] if spec.mask_loss_last_step else m
    mask = _mean(m * (1 - m))
    return DeformationLoss(reg=reg, mask=mask, total=weights.reg * reg + weights.mask * mask)


def _reduction_weights(
    output: DeformationOutput, reduction: str, gaussian_weights: Tensor | None
) -> Tensor | None:
    """``gaussian_weights`` checked and broadcast to ``(B, N)`` (``None`` unless weighted)."""
    if reduction != "weighted":
        if gaussian_weights is not None:
            raise ValueError(
                f"gaussian_weights: only used by reduction='weighted', got reduction={reduction!r}"
            )
        return None
    if gaussian_weights is None:
        raise ValueError("gaussian_weights: reduction='weighted' needs (N,) or (B, N) weights")
    b, n = output.gaussians.batch_shape[0], output.gaussians.num_gaussians
    reference = output.deltas.means
    if gaussian_weights.is_complex():
        raise ValueError("gaussian_weights: expected real or bool weights, got complex")
    if (
        gaussian_weights.ndim not in (1, 2)
        or gaussian_weights.shape[-1] != n
        or (gaussian_weights.ndim == 2 and gaussian_weights.shape[0] != b)
    ):
        raise ValueError(
            f"gaussian_weights: expected shape ({n},) or ({b}, {n}), got "
            f"{tuple(gaussian_weights.shape)}"
        )
    if gaussian_weights.device != reference.device:
        raise ValueError(
            f"gaussian_weights: expected device {reference.device}, got {gaussian_weights.device}"
        )
    weights = gaussian_weights.detach().to(reference.dtype)
    if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()):
        raise ValueError("gaussian_weights: expected finite weights >= 0")
    # The weighted mean is scale-free: dividing by the largest weight first keeps tiny
    # (subnormal) weights and their products with the values at full precision.
    peak = weights.amax() if weights.numel() else weights.new_ones(())
    weights = weights / torch.where(peak > 0, peak, torch.ones_like(peak))
    return weights.expand(b, n)


__all__ = [
    "DeformationDeltas",
    "DeformationOutput",
    "deformation_loss",
]
