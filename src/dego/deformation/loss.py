"""What :func:`dego.deformation.deformation_loss` is given and returns: the loss weights
(:class:`DeformationLossWeights`, with the ``L_reg`` reduction, :data:`REDUCTIONS`) and the
loss terms (:class:`DeformationLoss`).

:func:`~dego.deformation.deformation_loss` itself is in :mod:`dego.deformation.results`,
beside the output it reads (:meth:`DeformationOutput.to_official_dict` calls it). Nothing
here imports another module of the package.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Iterator
from typing import Any, Literal

from jaxtyping import Float
from torch import Tensor

from dego._typing import check_tensor_fields, typechecked

Reduction = Literal["mean", "sum", "weighted"]
REDUCTIONS: tuple[Reduction, ...] = ("mean", "sum", "weighted")
"""How :func:`deformation_loss` reduces ``L_reg`` over (batch, time, Gaussian); see
:class:`DeformationLossWeights`."""


@dataclasses.dataclass(frozen=True)
class DeformationLossWeights:
    """Weights of :func:`deformation_loss`, and how its ``L_reg`` is reduced.

    ``L_reg = sum_p lambda_p R(||d_p||^2)`` over p in :data:`PARAMETERS` and
    ``L_def = reg * L_reg + mask * L_mask``. The paper gives no values; both presets
    default to the official code's (every lambda_p = 1, reg 10, mask 0.5).

    ``reduction`` is R, over the (B, T, N) per-Gaussian values (``paper``: the squared
    norm of each Gaussian's delta; ``official``: its mean over the parameter's elements):

    - ``"mean"`` (default, the paper's and the official code's): the mean over every
      Gaussian and time step. Its scale is ``1 / N``: against a rendering loss averaged
      over pixels, the few Gaussians of a small moving agent weigh their share of the
      *Gaussians*, which can be far more than their share of the *pixels*.
    - ``"sum"``: the sum (``official``: of every element), for losses that are sums too.
    - ``"weighted"``: ``sum_{b,t,i} w_{b,i} v_{b,t,i} / (T sum_{b,i} w_{b,i})`` with
      per-Gaussian weights ``w >= 0`` given to :func:`deformation_loss`
      (``gaussian_weights``): e.g. 1 on the movable Gaussians only, or each Gaussian's
      rendered footprint. All-ones weights give ``"mean"``; all-zero weights give 0.

    ``L_mask`` is always the mean over Gaussians.
    """

    means: float = 1.0
    quats: float = 1.0
    scales: float = 1.0
    opacities: float = 1.0
    reg: float = 10.0
    mask: float = 0.5
    reduction: Reduction = "mean"

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            if field.name == "reduction":
                continue
            value = getattr(self, field.name)
            if not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
                raise ValueError(f"{field.name}: expected a finite weight >= 0, got {value!r}")
        if self.reduction not in REDUCTIONS:
            raise ValueError(f"reduction: expected one of {REDUCTIONS}, got {self.reduction!r}")


_LOSS_TERMS = ("reg", "mask", "total")


@dataclasses.dataclass(frozen=True, eq=False)
class DeformationLoss:
    """Result of :func:`deformation_loss`: DeGO's deformation losses, scalars.

    Attributes:
        reg: ``L_reg = sum_p lambda_p R(||d_p||^2)`` (unweighted by ``weights.reg``).
        mask: ``L_mask = mean(m (1 - m))``.
        total: ``L_def = weights.reg * reg + weights.mask * mask``.

    Deprecated: the dict-style access of the dict that :func:`deformation_loss` returned
    before (``loss["total"]``, ``"total" in loss``, ``keys()``, ``values()``, ``items()``,
    ``get()``, iteration, ``len()``, ``dict(loss)``) still works for one release and warns
    (``DeprecationWarning``); use the attributes (``loss.total``) or :meth:`to_dict`.
    """

    reg: Float[Tensor, ""]
    mask: Float[Tensor, ""]
    total: Float[Tensor, ""]

    def __post_init__(self) -> None:
        check_tensor_fields(self)

    @typechecked
    def to_dict(self) -> dict[str, Tensor]:
        """``{"reg", "mask", "total"}`` -> the tensors (not copied, not detached)."""
        return {name: getattr(self, name) for name in _LOSS_TERMS}

    # -- deprecated dict-style access (one release) -------------------------------------
    def _deprecated(self, used: str, instead: str) -> None:
        warnings.warn(
            f"DeformationLoss: {used} is deprecated (deformation_loss returned a dict before) "
            f"and will be removed in the next release; use {instead}",
            DeprecationWarning,
            stacklevel=3,
        )

    def __getitem__(self, key: str) -> Tensor:
        if key not in _LOSS_TERMS:
            raise KeyError(key)
        self._deprecated(f"loss[{key!r}]", f"loss.{key}")
        return getattr(self, key)

    def get(self, key: str, default: Any = None) -> Any:
        """Deprecated: ``loss.get(key)``; use the attribute."""
        self._deprecated(
            f"loss.get({key!r})", f"loss.{key}" if key in _LOSS_TERMS else "the attributes"
        )
        return getattr(self, key) if key in _LOSS_TERMS else default

    def __contains__(self, key: object) -> bool:
        self._deprecated(f"{key!r} in loss", "the attributes loss.reg, loss.mask, loss.total")
        return key in _LOSS_TERMS

    def __iter__(self) -> Iterator[str]:
        self._deprecated("iterating over loss", "loss.to_dict()")
        return iter(_LOSS_TERMS)

    def __len__(self) -> int:
        self._deprecated("len(loss)", "loss.to_dict()")
        return len(_LOSS_TERMS)

    def __bool__(self) -> bool:  # not through the deprecated __len__
        return True

    def keys(self) -> tuple[str, ...]:
        """Deprecated: the term names; use :meth:`to_dict`."""
        self._deprecated("loss.keys()", "loss.to_dict().keys()")
        return _LOSS_TERMS

    def values(self) -> list[Tensor]:
        """Deprecated: the terms; use the attributes or :meth:`to_dict`."""
        self._deprecated("loss.values()", "loss.to_dict().values()")
        return [getattr(self, name) for name in _LOSS_TERMS]

    def items(self) -> list[tuple[str, Tensor]]:
        """Deprecated: ``(name, term)`` pairs; use :meth:`to_dict`."""
        self._deprecated("loss.items()", "loss.to_dict().items()")
        return [(name, getattr(self, name)) for name in _LOSS_TERMS]


__all__ = [
    "REDUCTIONS",
    "DeformationLoss",
    "DeformationLossWeights",
    "Reduction",
]
