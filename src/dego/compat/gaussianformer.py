"""GaussianFormer's Gaussian-to-voxel heads with its tensors and output layout, computed by
:func:`dego.voxelize`.

:func:`aggregate_gf1` is GaussianFormer's ``LocalAggregator`` (``localagg``): per voxel
``sum_i o_i g_i(x) s_i`` over the Gaussians whose cube reaches the voxel.
:func:`aggregate_gf2` is GaussianFormer-2's probabilistic head (``localagg_prob`` with
``combine_geosem=True``): ``[e(x) alpha(x), 1 - alpha(x)]``. Both take the
``GaussianPrediction`` fields GaussianFormer's ``GaussianHead`` receives and return what it
puts in ``pred_occ``, without GaussianFormer's restrictions: any batch size, CPU or CUDA,
float32 or float64, means outside the grid (partial coverage instead of an assert).

Conventions, as in GaussianFormer's code (commit fa063a8):

- ``rotations`` are wxyz quaternions (normalised inside), and the head builds the
  covariance as ``(S R)^T (S R) = R^T diag(s^2) R``: the transpose of dego's (and gsplat's)
  ``R diag(s^2) R^T``. They are converted exactly with
  ``GaussianSet.from_tensors(..., rotation="R^T")`` (the conjugate quaternion).
- ``scales`` are standard deviations in metres, already activated (``gs_scales``).
- Neighbourhood: the cube ``floor((mu - lower) / voxel) +- r``,
  ``r = max(1, ceil(k max(s) / voxel))`` (``neighborhood="scale_cube"``), k = 3 (GF-1) or
  4 (GF-2).
- The default grid is SurroundOcc's, :meth:`dego.VoxelGrid.surroundocc` (200 x 200 x 16 at
  0.5 m from (-50, -50, -5)), GaussianFormer's query points being its voxel centres.
- Output layout ``"gaussianformer"``: ``[B, K, X*Y*Z]`` with voxel ``(i, j, k)`` at
  ``(i * Y + j) * Z + k`` (GaussianFormer's ``occ_xyz.flatten(1, 3)`` order), the layout of
  ``pred_occ`` that its losses take with labels ``[B, X*Y*Z]``; ``layout="grid"`` gives
  dego's ``[B, X, Y, Z, K]``. The empty class is the last channel (nuScenes, index 17
  with 18 channels).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from typing import Literal, TypedDict

import torch
from jaxtyping import Float
from torch import Tensor

from dego._geometry import conjugate_quaternions
from dego._typing import typechecked
from dego.gaussians import GaussianSet
from dego.grid import VoxelGrid
from dego.voxelizer import voxelize

Layout = Literal["gaussianformer", "grid"]

EMPTY_MEAN = (0.0, 0.0, -1.0)
"""Mean of GaussianFormer's empty Gaussian (``empty_args`` of its "solid" configuration)."""
EMPTY_SCALE = (100.0, 100.0, 8.0)
"""Scales of GaussianFormer's empty Gaussian: its cube covers the whole SurroundOcc grid."""
GF2_EMPTY_THRESHOLD = 1e-9
"""GaussianFormer-2's mixture-weight sum at or below which a voxel's semantics are uniform."""

# dego's field names in the errors of GaussianSet / voxelize -> this module's argument names
_RENAMED = {"quats": "rotations", "features": "semantics"}


class _Like(TypedDict):
    """Where new tensors go: ``torch.zeros(..., **like)``."""

    dtype: torch.dtype
    device: torch.device


@contextlib.contextmanager
def _argument_names() -> Iterator[None]:
    """Re-raise dego's value / type errors with this module's argument names."""
    try:
        yield
    except (ValueError, TypeError) as error:
        message = str(error)
        for ours, theirs in _RENAMED.items():
            if message.startswith(ours):
                raise type(error)(theirs + message[len(ours) :]) from error
        raise


def _opacities(opacities: Tensor | None, means: Tensor) -> Tensor:
    """``(B, P)`` opacities; ``None`` or ``[B, P, 0]`` (GaussianFormer without predicted
    opacities) mean 1, as in GaussianFormer's head."""
    if opacities is None or (opacities.ndim == 3 and opacities.shape[-1] == 0):
        return torch.ones_like(means[..., 0])
    return opacities.squeeze(-1) if opacities.ndim == 3 else opacities


def _gaussians(
    means: Tensor, scales: Tensor, rotations: Tensor, opacities: Tensor, features: Tensor
) -> GaussianSet:
    with _argument_names():
        return GaussianSet(
            means=means,
            quats=conjugate_quaternions(rotations),  # R^T diag(s^2) R -> dego's R diag(s^2) R^T
            scales=scales,
            opacities=opacities,
            features=features,
        )


def _in_layout(features: Tensor, layout: str) -> Tensor:
    if layout == "grid":
        return features
    b, x, y, z, k = features.shape
    return features.reshape(b, x * y * z, k).transpose(1, 2)


def _check_common(semantics: Tensor, layout: str) -> None:
    if semantics.shape[-1] < 1:
        raise ValueError("semantics: expected at least one class channel, got C = 0")
    if layout not in ("gaussianformer", "grid"):  # also a Literal: beartype checks it first
        raise ValueError(f"layout: expected 'gaussianformer' or 'grid', got {layout!r}")


@typechecked
def aggregate_gf1(
    means: Float[Tensor, "B P 3"],
    scales: Float[Tensor, "B P 3"],
    rotations: Float[Tensor, "B P 4"],
    opacities: Float[Tensor, "B P"] | Float[Tensor, "B P 1"] | Float[Tensor, "B P 0"] | None,
    semantics: Float[Tensor, "B P C"],
    *,
    grid: VoxelGrid | None = None,
    scale_multiplier: float | int = 3,
    empty_logit: float | int | Float[Tensor, "*e"] | None = None,
    layout: Layout = "gaussianformer",
    chunk_size: int = 1 << 21,
) -> Float[Tensor, "B K V"] | Float[Tensor, "B X Y Z K"]:
    """GaussianFormer's occupancy logits: ``logits(x)[c] = sum_i o_i g_i(x) s_i[c]``.

    ``g_i(x) = exp(-0.5 (x - mu_i)^T Sigma_i^-1 (x - mu_i))`` at the voxel centres of each
    Gaussian's scale cube, i.e. :func:`dego.voxelize` with ``mode="additive",
    neighborhood="scale_cube", feature_weight="opacity_kernel"``. Voxels no Gaussian reaches
    get all-zero logits. The prediction is the argmax over the channels, the last being
    the empty class.

    Args:
        means: ``[B, P, 3]`` centres in metres.
        scales: ``[B, P, 3]`` activated scales (standard deviations, metres, > 0).
        rotations: ``[B, P, 4]`` GaussianFormer quaternions, wxyz (see the module notes: its
            covariance is ``R^T diag(s^2) R``). xyzw quaternions cannot be detected: reorder
            them first.
        opacities: ``[B, P]`` or ``[B, P, 1]`` in [0, 1]; ``None`` or ``[B, P, 0]`` (the
            configuration without predicted opacities) mean 1.
        semantics: ``[B, P, C]`` per-Gaussian class scores as the head receives them (the
            encoder's ``semantics_activation`` already applied). Without ``empty_logit``
            they include the empty class as the last channel (the 144k configuration: 18).
        grid: defaults to :meth:`dego.VoxelGrid.surroundocc`.
        scale_multiplier: k of the scale cube (GaussianFormer: 3).
        empty_logit: the "solid"/NonEmpty configuration: ``semantics`` hold the C
            non-empty classes and get a zero empty-class channel, and one empty Gaussian
            (mean :data:`EMPTY_MEAN`, scales :data:`EMPTY_SCALE`, identity rotation,
            opacity 1) with logit ``empty_logit`` on the empty channel (GaussianFormer's
            learnable ``empty_scalar``, initialised to 10; a tensor keeps its gradient)
            is appended to every batch element. The output then has C + 1 channels.
        layout: ``"gaussianformer"``: ``[B, K, X*Y*Z]`` (``pred_occ``); ``"grid"``:
            ``[B, X, Y, Z, K]``.
        chunk_size: (Gaussian, voxel) pairs evaluated at once (see :func:`dego.voxelize`).

    Returns:
        The logits, K = C (or C + 1 with ``empty_logit``) channels, in the dtype of the
        inputs. Differentiable w.r.t. every input tensor (scales included; GaussianFormer
        detaches them in the radius only, as here).

    Raises:
        TypeError: a wrong shape or dtype, naming the argument.
        ValueError: naming the argument: non-finite values, scales <= 0, zero-norm
            rotations, opacities outside [0, 1], C = 0, a bad option.
    """
    _check_common(semantics, layout)
    grid = VoxelGrid.surroundocc() if grid is None else grid
    opacity = _opacities(opacities, means)
    features = semantics
    if empty_logit is not None:
        if isinstance(empty_logit, Tensor) and empty_logit.numel() != 1:
            raise ValueError(
                f"empty_logit: expected one value (shape () or (1,)), got shape "
                f"{tuple(empty_logit.shape)}"
            )
        if isinstance(empty_logit, int | float) and not math.isfinite(empty_logit):
            raise ValueError(f"empty_logit: expected a finite number, got {empty_logit!r}")
        b, c = means.shape[0], semantics.shape[-1]
        like: _Like = {"dtype": means.dtype, "device": means.device}
        logit = torch.as_tensor(empty_logit, **like).reshape(1, 1, 1).expand(b, 1, 1)
        features = torch.cat([semantics, semantics.new_zeros(*semantics.shape[:2], 1)], -1)
        empty_features = torch.cat([torch.zeros(b, 1, c, **like), logit], -1)
        features = torch.cat([features, empty_features], 1)
        means = torch.cat([means, torch.tensor(EMPTY_MEAN, **like).expand(b, 1, 3)], 1)
        scales = torch.cat([scales, torch.tensor(EMPTY_SCALE, **like).expand(b, 1, 3)], 1)
        identity = torch.tensor((1.0, 0.0, 0.0, 0.0), **like).expand(b, 1, 4)
        rotations = torch.cat([rotations, identity], 1)
        opacity = torch.cat([opacity, torch.ones(b, 1, **like)], 1)
    gaussians = _gaussians(means, scales, rotations, opacity, features)
    with _argument_names():
        out = voxelize(
            gaussians,
            grid,
            mode="additive",
            neighborhood="scale_cube",
            scale_multiplier=scale_multiplier,
            feature_weight="opacity_kernel",
            chunk_size=chunk_size,
        )
    return _in_layout(out.features, layout)


@typechecked
def aggregate_gf2(
    means: Float[Tensor, "B P 3"],
    scales: Float[Tensor, "B P 3"],
    rotations: Float[Tensor, "B P 4"],
    opacities: Float[Tensor, "B P"] | Float[Tensor, "B P 1"] | Float[Tensor, "B P 0"] | None,
    semantics: Float[Tensor, "B P C"],
    *,
    grid: VoxelGrid | None = None,
    scale_multiplier: float | int = 4,
    layout: Layout = "gaussianformer",
    chunk_size: int = 1 << 21,
) -> Float[Tensor, "B K V"] | Float[Tensor, "B X Y Z K"]:
    """GaussianFormer-2's occupancy: ``[e(x)_1..C * alpha(x), 1 - alpha(x)]``, C + 1 channels.

    - ``alpha(x) = 1 - prod_i (1 - g_i(x))``: the geometry ignores opacity, so one Gaussian
      gives alpha = 1 at its mean whatever its opacity.
    - ``e(x) = sum_i p_i(x) softmax(s_i) / sum_i p_i(x)`` with the mixture weight
      ``p_i = o_i N(x; mu_i, Sigma_i)``; where ``sum_i p_i <= 1e-9``, e(x) = 1/C on every
      channel (GaussianFormer-2's uniform fallback).

    i.e. :func:`dego.voxelize` with ``mode="probabilistic", neighborhood="scale_cube",
    feature_weight="opacity_kernel", opacity_in_density=False, empty_value=1/C,
    empty_threshold=1e-9`` on ``softmax(semantics)``, then the concatenation. (GaussianFormer
    pads the softmax with a zero empty-class channel before the mixture; that channel's
    mixture is 0 and the concatenation drops it, so it is not computed.) The prediction is
    the argmax, the last channel (1 - alpha) being the empty class.

    Args:
        means: ``[B, P, 3]``, as in :func:`aggregate_gf1`.
        scales: ``[B, P, 3]``, as in :func:`aggregate_gf1`.
        rotations: ``[B, P, 4]`` GaussianFormer quaternions, as in :func:`aggregate_gf1`.
        opacities: ``[B, P]``, ``[B, P, 1]``, ``[B, P, 0]`` or ``None``, as in
            :func:`aggregate_gf1`; the mixture weights of the semantics only.
        semantics: ``[B, P, C]`` logits of the C non-empty classes (17 on nuScenes), before
            the softmax (GaussianFormer-2's encoder uses the identity activation).
        grid: defaults to :meth:`dego.VoxelGrid.surroundocc`.
        scale_multiplier: k of the scale cube (GaussianFormer-2: 4).
        layout: ``"gaussianformer"``: ``[B, C + 1, X*Y*Z]``; ``"grid"``:
            ``[B, X, Y, Z, C + 1]``.
        chunk_size: (Gaussian, voxel) pairs evaluated at once (see :func:`dego.voxelize`).

    Returns:
        The C + 1 channels in the dtype of the inputs; differentiable w.r.t. every input.

    Raises:
        TypeError / ValueError: as :func:`aggregate_gf1`.
    """
    _check_common(semantics, layout)
    grid = VoxelGrid.surroundocc() if grid is None else grid
    gaussians = _gaussians(
        means, scales, rotations, _opacities(opacities, means), semantics.softmax(-1)
    )
    with _argument_names():
        out = voxelize(
            gaussians,
            grid,
            mode="probabilistic",
            neighborhood="scale_cube",
            scale_multiplier=scale_multiplier,
            feature_weight="opacity_kernel",
            opacity_in_density=False,
            empty_value=1.0 / semantics.shape[-1],
            empty_threshold=GF2_EMPTY_THRESHOLD,
            chunk_size=chunk_size,
        )
    alpha = out.density.unsqueeze(-1)
    return _in_layout(torch.cat([out.features * alpha, 1 - alpha], -1), layout)


__all__ = ["EMPTY_MEAN", "EMPTY_SCALE", "GF2_EMPTY_THRESHOLD", "aggregate_gf1", "aggregate_gf2"]
