"""Gaussians -> voxel grids: exact, chunked Gaussian-to-voxel splatting.

Each Gaussian is evaluated only at the voxel centres of its neighbourhood: the exact
axis-aligned box of its ``cutoff_sigma`` ellipsoid (``"ellipsoid"``), the official
fixed ``(2 nbh + 1)^3`` cube around its voxel (``"cube"``), or GaussianFormer's cube of
``ceil(k max(scale) / voxel)`` voxels around its voxel (``"scale_cube"``). (Gaussian, voxel)
pairs of the box neighbourhoods are generated a bounded number at a time (``searchsorted``
over the running pair count, so a chunk may split a Gaussian's box) and reduced into the
grid with ``index_add_``. ``feature_weight``, ``opacity_in_density``, ``empty_value`` and
``empty_threshold`` select the GaussianFormer variants of the aggregation
(:mod:`dego.compat.gaussianformer` wraps them).

Input policy (see :mod:`dego._policy`): non-finite values, scales <= 0, zero-norm
quaternions and opacities outside [0, 1] raise ``ValueError`` naming the field; box
extents are clamped to the grid in floating point before any integer conversion; the
output and chunk sizes are checked against dego's memory limit before allocating;
float16 / bfloat16 inputs are computed in float32.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import torch
from jaxtyping import Float, Int
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from dego import _serialization
from dego._geometry import QUATERNION_EPS, rotation_matrices, scaled_rotation_gram
from dego._policy import (
    check_dtype,
    check_memory,
    compute_dtype,
    finite_check,
    float32_under_autocast,
    run_checks,
)
from dego._typing import typechecked
from dego.classes import FREE_LABEL
from dego.gaussians import GaussianSet
from dego.grid import VoxelGrid

Mode = Literal["additive", "probabilistic"]
Neighborhood = Literal["ellipsoid", "cube", "scale_cube"]
FeatureWeight = Literal["kernel", "opacity_kernel"]

_TINY_WEIGHT = 1e-30  # default empty_threshold
# log(1 - x) used for a saturated pair (x = 1: the voxel is certainly occupied); exp of it
# is exactly 0 in float32 and float64, and sums of it stay finite.
_SATURATED_LOG = -1e4
# Additive cube mode skips (Gaussian, voxel) pairs with exp(-q/2) < 1e-10, i.e. q > 2 * 23.03;
# the skipped total per voxel is below (2 nbh + 1)^3 * 1e-10 (1.3e-7 for nbh = 5) times the
# largest |opacity| or |feature|.
_NEGLIGIBLE_QUADRATIC = 2 * 23.026


def _scale_floor(dtype: torch.dtype) -> float:
    """Smallest scale used in the kernel: ``finfo.tiny ** 0.25`` (1.1e-10 m in float32,
    1.2e-77 m in float64), so ``1/s^2`` and its products with offsets stay finite."""
    return torch.finfo(dtype).tiny ** 0.25


def _log_normaliser_bound(dtype: torch.dtype) -> float:
    """``|log|`` bound of the mixture normaliser: ``0.5 log(finfo.max)`` (44.4 in float32,
    354.9 in float64), so probabilistic weights and their sums never overflow."""
    return 0.5 * math.log(torch.finfo(dtype).max)


@dataclasses.dataclass(frozen=True)
class VoxelOutput(_serialization.DictForm):
    """Voxelised Gaussians.

    Attributes:
        density: ``(B, X, Y, Z)`` occupancy in [0, 1].
        features: ``(B, X, Y, Z, C)`` aggregated features (C may be 0).
    """

    density: Float[Tensor, "B X Y Z"]
    features: Float[Tensor, "B X Y Z C"]

    def labels(
        self,
        threshold: float = 0.05,
        free_label: int = FREE_LABEL,
        label_offset: int = 1,
        min_density: float | None = None,
        max_z_index: int | None = None,
    ) -> Int[Tensor, "B X Y Z"]:
        """Label grid: ``argmax(features) + label_offset``, ``free_label`` where density
        < ``threshold``.

        The official DeGO post-processing is available as two knobs, off by default:
        ``min_density`` (density below it is zeroed first; official 1e-3) and
        ``max_z_index`` (voxels with z index >= it are free; the official "roof" is 11).
        """
        density = self.density.detach()
        if min_density is not None:
            density = torch.where(density < min_density, torch.zeros_like(density), density)
        if self.features.shape[-1]:
            labels = self.features.detach().argmax(-1) + label_offset
        else:
            labels = torch.full_like(density, label_offset, dtype=torch.long)
        free = density < threshold
        if max_z_index is not None:
            z = torch.arange(density.shape[-1], device=density.device)
            free = free | (z >= max_z_index)
        return labels.masked_fill(free, free_label)


@dataclasses.dataclass(frozen=True)
class VoxelizerConfig:
    """Settings shared by :func:`voxelize` and :class:`GaussianVoxelizer`."""

    mode: Mode = "additive"
    neighborhood: Neighborhood = "ellipsoid"
    cutoff_sigma: float = 3.0
    nbh: int | None = None
    chunk_size: int = 1 << 21
    scale_multiplier: float | None = None
    feature_weight: FeatureWeight | None = None
    opacity_in_density: bool = True
    empty_value: float = 0.0
    empty_threshold: float = _TINY_WEIGHT

    def __post_init__(self) -> None:
        if self.mode not in ("additive", "probabilistic"):
            raise ValueError(f"mode: expected 'additive' or 'probabilistic', got {self.mode!r}")
        if self.neighborhood not in ("ellipsoid", "cube", "scale_cube"):
            raise ValueError(
                "neighborhood: expected 'ellipsoid', 'cube' or 'scale_cube', got "
                f"{self.neighborhood!r}"
            )
        self._check_gaussianformer_options()
        k = self.cutoff_sigma
        if isinstance(k, bool) or not isinstance(k, int | float) or not k > 0:  # NaN fails
            raise ValueError(
                f"cutoff_sigma: expected a positive number (inf: the whole grid), got {k!r}"
            )
        if self.neighborhood == "cube":
            if self.nbh is None:
                raise ValueError("nbh: required with neighborhood='cube' (official: 4 or 5)")
            if not isinstance(self.nbh, int) or isinstance(self.nbh, bool) or self.nbh < 0:
                raise ValueError(f"nbh: expected an int >= 0, got {self.nbh!r}")
        if (
            isinstance(self.chunk_size, bool)
            or not isinstance(self.chunk_size, int)
            or self.chunk_size < 1
        ):
            raise ValueError(f"chunk_size: expected a positive int, got {self.chunk_size!r}")

    def _check_gaussianformer_options(self) -> None:
        k = self.scale_multiplier
        if self.neighborhood == "scale_cube":
            if k is None:
                raise ValueError(
                    "scale_multiplier: required with neighborhood='scale_cube' "
                    "(GaussianFormer: 3, GaussianFormer-2: 4)"
                )
            if isinstance(k, bool) or not isinstance(k, int | float) or not k > 0:  # NaN fails
                raise ValueError(
                    f"scale_multiplier: expected a positive number (inf: the whole grid), got {k!r}"
                )
        elif k is not None:
            raise ValueError(
                f"scale_multiplier: only used with neighborhood='scale_cube', got {k!r} with "
                f"neighborhood={self.neighborhood!r}"
            )
        if self.feature_weight not in (None, "kernel", "opacity_kernel"):
            raise ValueError(
                "feature_weight: expected None, 'kernel' or 'opacity_kernel', got "
                f"{self.feature_weight!r}"
            )
        if not isinstance(self.opacity_in_density, bool):
            raise ValueError(
                f"opacity_in_density: expected True or False, got {self.opacity_in_density!r}"
            )
        value = self.empty_value
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            raise ValueError(f"empty_value: expected a finite number, got {value!r}")
        t = self.empty_threshold
        if isinstance(t, bool) or not isinstance(t, int | float) or not 0 <= t < math.inf:
            raise ValueError(f"empty_threshold: expected a finite number >= 0, got {t!r}")

    @property
    def opacity_weights_features(self) -> bool:
        """Whether the feature weight includes the opacity: ``feature_weight`` if given,
        else ``False`` in additive mode (``sum g f``) and ``True`` in probabilistic mode
        (mixture weight ``o N``)."""
        if self.feature_weight is None:
            return self.mode == "probabilistic"
        return self.feature_weight == "opacity_kernel"


def _check_values(fields: dict[str, Tensor]) -> None:
    """Raise ``ValueError`` naming the field on non-finite values, scales <= 0, zero-norm
    quaternions or opacities outside [0, 1]; one host sync when everything is valid."""
    scales, quats, opacities = fields["scales"], fields["quats"], fields["opacities"]
    outside = (opacities < 0) | (opacities > 1)
    non_positive = scales <= 0
    zero_norm = torch.linalg.vector_norm(quats, dim=-1) <= QUATERNION_EPS

    def scales_error() -> Exception:
        message = (
            f"scales: {int(non_positive.sum())} of {scales.numel()} values are <= 0 (e.g. "
            f"{scales[non_positive][0].item():.6g}); voxelize needs positive standard "
            "deviations (its precisions use 1/s^2)"
        )
        if bool((scales < 0).all()):
            message += (
                "; every value is negative, which looks like log-scales: use "
                'GaussianSet.from_tensors(..., scale_space="log")'
            )
        return ValueError(message)

    def quats_error() -> Exception:
        return ValueError(
            f"quats: {int(zero_norm.sum())} of {quats.shape[:-1].numel()} quaternions have "
            f"zero norm (<= {QUATERNION_EPS:g}) and encode no rotation"
        )

    def opacities_error() -> Exception:
        count = int(outside.sum())
        message = (
            f"opacities: {count} of {opacities.numel()} values lie outside [0, 1] "
            f"(e.g. {opacities[outside][0].item():.6g})"
        )
        if count == opacities.numel():
            message += (
                "; every value lies outside [0, 1], which looks like logits: use "
                'GaussianSet.from_tensors(..., opacity_space="logit")'
            )
        return ValueError(message)

    run_checks(
        [finite_check(name, t) for name, t in fields.items()]
        + [
            (~non_positive.any(), "scales: values are <= 0", scales_error),
            (~zero_norm.any(), "quats: quaternions have zero norm", quats_error),
            (~outside.any(), "opacities: values lie outside [0, 1]", opacities_error),
        ]
    )


def _check_size(
    b: int,
    grid: VoxelGrid,
    channels: int,
    dtype: torch.dtype,
    out_dtype: torch.dtype,
    chunk: int,
    per_chunk_element: int,
    retained: int,
) -> None:
    """:func:`check_memory` on the output grids, one chunk's buffers and (under autograd)
    the per-pair indices kept for backward, before any of them is allocated."""
    x, y, z = grid.shape
    voxels = b * x * y * z
    nbytes = voxels * (channels + 2) * dtype.itemsize + chunk * per_chunk_element + retained
    if out_dtype != dtype:  # the cast back to the input dtype
        nbytes += voxels * (channels + 1) * out_dtype.itemsize
    check_memory(
        "voxelize",
        nbytes,
        f"B = {b} grids of {x} x {y} x {z} voxels x ({channels} + 2) channels in {dtype}, "
        f"chunks of {chunk} (Gaussian, voxel) pairs",
    )


def _grid_float64(grid: VoxelGrid, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """The grid's lower corner, voxel size and largest index per axis, float64 ``(3,)``."""
    lower = torch.tensor(grid.lower, dtype=torch.float64, device=device)
    size = torch.tensor(grid.voxel_size, dtype=torch.float64, device=device)
    top = torch.tensor(grid.shape, dtype=torch.float64, device=device) - 1
    return lower, size, top


def _clip_to_grid(low: Tensor, high: Tensor, top: Tensor) -> tuple[Tensor, Tensor]:
    """Float64 index ranges clamped to ``[-1, shape]`` before the int64 conversion (no
    overflow whatever their size; empty where high < low)."""
    low = torch.minimum(low.clamp_min(0), top + 1)
    high = torch.minimum(high.clamp_min(-1), top)
    return low.long(), high.long()


def _ellipsoid_boxes(
    means: Tensor,  # (M, 3)
    rotations: Tensor,  # (M, 3, 3)
    scales: Tensor,  # (M, 3)
    grid: VoxelGrid,
    cutoff_sigma: float,
) -> tuple[Tensor, Tensor]:
    """Inclusive per-axis voxel index ranges ``(M, 3)`` low / high of the voxels whose centres
    lie in the axis-aligned box of each Gaussian's ``cutoff_sigma`` ellipsoid, clipped to the
    grid (empty where high < low).

    Computed in float64 and clamped to ``[-1, shape]`` in floating point before the integer
    conversion, so huge scales, huge ``cutoff_sigma`` (``inf``: the whole grid) or far
    means never overflow int64.
    """
    lower, size, top = _grid_float64(grid, means.device)
    if math.isinf(cutoff_sigma):
        low = torch.zeros_like(means, dtype=torch.float64)
        high = top.expand_as(low)
    else:
        position = (means.double() - lower) / size  # voxel units; centre of voxel i: i + 0.5
        # sqrt(Sigma_jj) = |row j of R diag(s)| (inf where it overflows: the whole axis)
        std = (rotations.double() * scales.double().unsqueeze(-2)).square().sum(-1).sqrt()
        half = cutoff_sigma * std / size
        # voxel i is inside iff |i + 0.5 - position| <= half; NaN (inf - inf) -> whole axis
        low = torch.ceil(position - half - 0.5)
        high = torch.floor(position + half - 0.5)
        low = torch.where(low.isnan(), 0.0, low)
        high = torch.where(high.isnan(), top, high)
    return _clip_to_grid(low, high, top)


def _scale_cube_boxes(
    means: Tensor,  # (M, 3)
    scales: Tensor,  # (M, 3)
    grid: VoxelGrid,
    scale_multiplier: float,
) -> tuple[Tensor, Tensor]:
    """GaussianFormer's cubes as inclusive per-axis index ranges ``(M, 3)`` low / high:
    ``floor((mu - lower) / voxel) +- r`` with ``r = max(1, ceil(k max(s) / voxel))`` per
    axis, clipped to the grid (empty where high < low: cubes wholly outside it).

    Computed in float64 and clamped to ``[-1, shape]`` in floating point before the integer
    conversion (huge scales or ``k = inf``: the whole grid; far means: no voxel).
    """
    lower, size, top = _grid_float64(grid, means.device)
    if math.isinf(scale_multiplier):
        low = torch.zeros_like(means, dtype=torch.float64)
        high = top.expand_as(low)
    else:
        home = torch.floor((means.double() - lower) / size)  # finite: means are finite
        largest = scales.double().amax(-1, keepdim=True)  # (M, 1)
        radius = torch.ceil(scale_multiplier * largest / size).clamp_min(1)  # may be inf
        low, high = home - radius, home + radius
    return _clip_to_grid(low, high, top)


def _pair_quadratic(
    means: Tensor,  # (M, 3)
    whitening: Tensor,  # (M, 9): diag(1/s) R^T, row-major
    owner: Tensor,  # (P,) Gaussian of each pair
    centres: Tensor,  # (P, 3) voxel centre of each pair
) -> Tensor:
    """Per-pair Mahalanobis quadratic ``|diag(1/s) R^T d|^2`` ``(P,)``.

    A sum of squares: non-negative and free of the cancellation of ``d^T P d`` for
    needle-like Gaussians. Whitened offsets are clamped to ``+-sqrt(max) / 2`` (NaN from
    overflowing products counts as far), so the quadratic (then g = 0) and every gradient
    stay finite, whatever the scales and means.
    """
    d = centres - means[owner]
    u = (whitening[owner].view(-1, 3, 3) * d.unsqueeze(-2)).sum(-1)  # (P, 3)
    far = math.sqrt(torch.finfo(u.dtype).max) / 2  # 3 far^2 and 2 far stay finite
    u = torch.nan_to_num(u, nan=far).clamp(-far, far)
    return u.square().sum(-1)


@dataclasses.dataclass(frozen=True)
class _Kernel:
    """Which per-pair terms are summed: the mode and where the opacity enters."""

    probabilistic: bool
    opacity_features: bool  # feature weight o g / o N (else g / N)
    opacity_density: bool  # density from o g (else g)

    @classmethod
    def of(cls, config: VoxelizerConfig) -> _Kernel:
        return cls(
            config.mode == "probabilistic",
            config.opacity_weights_features,
            config.opacity_in_density,
        )


def _kernel_terms(
    quadratic: Tensor,  # (P,)
    opacity: Tensor,  # (P,) opacity of each pair's Gaussian
    features: Tensor,  # (P, C) features of each pair's Gaussian
    log_normaliser: Tensor,  # (P,) clamped log of (2 pi)^(-3/2) sqrt(det P) of each pair
    kernel: _Kernel,
) -> tuple[Tensor, Tensor, Tensor]:
    """Per-pair density term, feature term and feature weight (additive: ``g`` or ``o g``;
    probabilistic: the mixture weight ``N`` or ``o N``)."""
    # d^T P d >= 0: rounding below 0 is clamped, NaN (inf - inf: a far pair) counts as far
    quadratic = torch.where(quadratic.isnan(), math.inf, quadratic.clamp_min(0))
    g = torch.exp(-0.5 * quadratic)
    occupancy = opacity * g if kernel.opacity_density else g
    if not kernel.probabilistic:
        weight = opacity * g if kernel.opacity_features else g
        return occupancy, weight.unsqueeze(-1) * features, weight
    # log(1 - x): kept finite (and its gradient) where x nears 1; x = 1 exactly (o = 1 or
    # opacity unused, at the mean) saturates the voxel: occupancy exactly 1
    survival = torch.log1p(-occupancy.clamp(max=1 - torch.finfo(g.dtype).eps))
    survival = torch.where(occupancy >= 1, _SATURATED_LOG, survival)
    weight = torch.exp(log_normaliser - 0.5 * quadratic)
    if kernel.opacity_features:
        weight = opacity * weight
    return survival, weight.unsqueeze(-1) * features, weight


def _pair_terms(
    means: Tensor,
    whitening: Tensor,
    opacities: Tensor,  # (M,)
    features: Tensor,  # (M, C)
    owner: Tensor,
    centres: Tensor,
    log_normaliser: Tensor,  # (M,)
    kernel: _Kernel,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_kernel_terms` of the (Gaussian ``owner``, voxel centre) pairs."""
    quadratic = _pair_quadratic(means, whitening, owner, centres)
    return _kernel_terms(
        quadratic, opacities[owner], features[owner], log_normaliser[owner], kernel
    )


@float32_under_autocast()
@typechecked
def voxelize(
    gaussians: GaussianSet,
    grid: VoxelGrid,
    *,
    features: Float[Tensor, "B N C"] | None = None,
    mode: Mode = "additive",
    neighborhood: Neighborhood = "ellipsoid",
    cutoff_sigma: float = 3.0,
    nbh: int | None = None,
    chunk_size: int = 1 << 21,
    scale_multiplier: float | int | None = None,
    feature_weight: FeatureWeight | None = None,
    opacity_in_density: bool = True,
    empty_value: float | int = 0.0,
    empty_threshold: float = _TINY_WEIGHT,
) -> VoxelOutput:
    """Splat ``(B, N)`` Gaussians into ``grid``: ``g_i(x) = exp(-0.5 d^T P_i d)`` at voxel centres.

    Args:
        gaussians: batch shape ``(B,)`` (B = 0 and N = 0 give empty / zero grids).
        grid: the voxel grid, ``(X, Y, Z)`` voxels.
        features: ``(B, N, C)`` in the Gaussians' dtype; defaults to ``gaussians.features``
            (none: C = 0).
        mode: ``"additive"`` (official DeGO / GaussianFlowOcc): density =
            clamp(sum o_i g_i, 0, 1), features = sum w_i f_i with w_i = g_i.
            ``"probabilistic"`` (GaussianFormer-2 with opacity): density =
            1 - prod(1 - o_i g_i) (in log space), features = sum p_i f_i / sum p_i with the
            mixture weight p_i = o_i N(x; mu_i, Sigma_i).
        neighborhood: ``"ellipsoid"``: every voxel whose centre lies in the axis-aligned
            box of the ``cutoff_sigma`` ellipsoid (half-extent ``k sqrt(Sigma_jj)``), so no
            voxel with Mahalanobis distance <= k is missed, rotated Gaussians included.
            ``"cube"``: the official fixed ``(2 nbh + 1)^3`` cube around
            ``floor((mu - lower) / voxel)``. ``"scale_cube"``: GaussianFormer's cube
            ``floor((mu - lower) / voxel) +- r`` with ``r = max(1, ceil(k max(s) / voxel))``
            voxels, ``k = scale_multiplier``, ``max(s)`` the largest of the three scales
            (rotation ignored); with per-axis voxel sizes r is computed per axis with that
            axis's size (GaussianFormer has one size). Cubes are clipped to the grid, so
            means outside it give their partial coverage (GaussianFormer asserts).
        cutoff_sigma: k of the ellipsoid neighbourhood, > 0; ``math.inf``: the whole grid.
        nbh: half-width of the cube neighbourhood (official: 4; its evaluation uses 5).
        chunk_size: (Gaussian, voxel) pairs evaluated at once; bounds peak memory
            (about ``chunk_size * (56 + (27 + 2 C) * 4)`` bytes in float32), whatever N
            and the box sizes are.
        scale_multiplier: k of ``"scale_cube"`` (GaussianFormer 3, GaussianFormer-2 4), a
            positive number, ``math.inf``: the whole grid; required with ``"scale_cube"``
            and rejected with the other neighbourhoods.
        feature_weight: the weight w_i of the features. ``"kernel"``: g_i (additive) or
            N(x; mu_i, Sigma_i) (probabilistic: an equal-weight mixture).
            ``"opacity_kernel"``: o_i g_i (additive, GaussianFormer's ``sum o g s``) or
            o_i N(x; mu_i, Sigma_i) (probabilistic, GaussianFormer-2). ``None`` (default):
            ``"kernel"`` in additive and ``"opacity_kernel"`` in probabilistic mode.
        opacity_in_density: ``True`` (default): the density uses o_i g_i as above.
            ``False``: g_i instead, i.e. clamp(sum g_i, 0, 1) (additive) or GaussianFormer-2's
            1 - prod(1 - g_i) (probabilistic: exactly 1 at any Gaussian's mean, whatever
            its opacity); the opacity then only weights the features (if at all).
        empty_value: the value of every feature channel at *empty* voxels, those whose summed
            feature weight ``W(x) = sum_i w_i`` (over the pairs evaluated) is
            <= ``empty_threshold``: no Gaussian reaches them, or only with negligible weight.
            GaussianFormer-2 uses 1/17 (on its 17 non-empty classes). A finite number.
        empty_threshold: the threshold on W(x) above, a finite number >= 0 (default 1e-30;
            GaussianFormer-2: 1e-9). Elsewhere features are ``sum w f`` (additive) and
            ``sum w f / W`` (probabilistic).

    Returns:
        ``VoxelOutput`` with ``density (B, X, Y, Z)`` in [0, 1] and ``features
        (B, X, Y, Z, C)``, in the input dtype (float16 / bfloat16 are computed in float32).

    Raises:
        ValueError: naming the field, for NaN / inf in any Gaussian field or the features,
            scales <= 0, zero-norm quaternions or opacities outside [0, 1]; a bad option
            (naming it); or when the output grids and chunk buffers would exceed dego's
            memory limit (:func:`dego.set_memory_limit`).
        TypeError: ``features`` of another dtype than the Gaussians.

    Gaussians partly or wholly outside the grid contribute where they overlap it; extreme
    but finite scales, means, ``cutoff_sigma`` and ``scale_multiplier`` never overflow the
    box arithmetic. Zero-opacity (padding) Gaussians contribute nothing unless
    ``feature_weight="kernel"`` (then to the features) or ``opacity_in_density=False``
    (then to the density). Differentiable w.r.t. means, quats, scales, opacities and
    features.
    """
    config = VoxelizerConfig(
        mode,
        neighborhood,
        cutoff_sigma,
        nbh,
        chunk_size,
        scale_multiplier,
        feature_weight,
        opacity_in_density,
        empty_value,
        empty_threshold,
    )
    return _voxelize(gaussians, grid, features, config)


def _voxelize(
    gaussians: GaussianSet, grid: VoxelGrid, features: Tensor | None, config: VoxelizerConfig
) -> VoxelOutput:
    if len(gaussians.batch_shape) != 1:
        raise ValueError(
            f"gaussians: expected batch shape (B,), got {tuple(gaussians.batch_shape)}; "
            "flatten extra axes with GaussianSet.flatten_batch()"
        )
    b, n = gaussians.batch_shape[0], gaussians.num_gaussians
    out_dtype, device = gaussians.dtype, gaussians.device
    features = gaussians.features if features is None else features
    if features is None:
        features = gaussians.means.new_zeros(b, n, 0)
    if tuple(features.shape[:2]) != (b, n):
        raise ValueError(f"features: expected shape ({b}, {n}, C), got {tuple(features.shape)}")
    check_dtype("features", features, out_dtype, "gaussians")
    if features.device != device:
        raise ValueError(f"features: on device {features.device} but gaussians are on {device}")
    dtype = compute_dtype(out_dtype)  # float16 / bfloat16 -> float32
    fields = {
        "means": gaussians.means,
        "quats": gaussians.quats,
        "scales": gaussians.scales,
        "opacities": gaussians.opacities,
        "features": features,
    }
    fields = {name: value.to(dtype) for name, value in fields.items()}
    _check_values(fields)

    m, channels = b * n, features.shape[-1]
    means = fields["means"].reshape(m, 3)
    quats = fields["quats"].reshape(m, 4)
    scales = fields["scales"].reshape(m, 3).clamp_min(_scale_floor(dtype))
    opacities = fields["opacities"].reshape(m)
    flat_features = fields["features"].reshape(m, channels)
    bound = _log_normaliser_bound(dtype)
    log_normaliser = (-1.5 * math.log(2 * math.pi) - scales.log().sum(-1)).clamp(-bound, bound)

    if config.neighborhood == "cube":
        # float64 from the input-dtype quats and scales: in float32 the rounding of these
        # entries is the largest error of the cube on grids whose centres are exact
        precision = scaled_rotation_gram(quats.double(), scales.double().reciprocal())
        rows, cols = (0, 1, 2, 0, 0, 1), (0, 1, 2, 1, 2, 2)  # xx, yy, zz, xy, xz, yz
        precision6 = precision[:, rows, cols]
        out = _voxelize_cube(
            (b, n),
            grid,
            means,
            precision6,
            opacities,
            flat_features,
            log_normaliser,
            config,
            out_dtype,
        )
    else:
        rotations = rotation_matrices(quats)
        whitening = (rotations / scales.unsqueeze(-2)).transpose(-1, -2).reshape(m, 9)
        with torch.no_grad():
            if config.neighborhood == "scale_cube":
                assert config.scale_multiplier is not None  # VoxelizerConfig requires it
                boxes = _scale_cube_boxes(
                    means.detach(), scales.detach(), grid, float(config.scale_multiplier)
                )
            else:
                boxes = _ellipsoid_boxes(
                    means.detach(),
                    rotations.detach(),
                    scales.detach(),
                    grid,
                    config.cutoff_sigma,
                )
        out = _voxelize_boxes(
            (b, n),
            grid,
            boxes,
            means,
            whitening,
            opacities,
            flat_features,
            log_normaliser,
            config,
            out_dtype,
        )
    if out_dtype == dtype:
        return out
    return VoxelOutput(density=out.density.to(out_dtype), features=out.features.to(out_dtype))


# Data-dependent by nature (the number of (Gaussian, voxel) pairs): run eagerly under
# torch.compile, as one graph break, rather than recompiling for every pair count.
@torch._dynamo.disable(recursive=True)
def _voxelize_boxes(
    bn: tuple[int, int],
    grid: VoxelGrid,
    boxes: tuple[Tensor, Tensor],  # (M, 3) inclusive low / high voxel indices, in the grid
    means: Tensor,  # (M, 3)
    whitening: Tensor,  # (M, 9)
    opacities: Tensor,  # (M,)
    features: Tensor,  # (M, C)
    log_normaliser: Tensor,  # (M,)
    config: VoxelizerConfig,
    out_dtype: torch.dtype,
) -> VoxelOutput:
    """Per-Gaussian index boxes (ellipsoid or scale cube): pairs enumerated in fixed-size
    ranges of the running pair count."""
    (b, n), (x, y, z) = bn, grid.shape
    dtype, device = means.dtype, means.device
    channels = features.shape[-1]
    kernel = _Kernel.of(config)
    differentiable = _requiring_grad(means, whitening, opacities, features, log_normaliser)
    grad_needed = bool(differentiable)
    low, high = boxes
    with torch.no_grad():
        extent = (high - low + 1).clamp(min=0)  # (M, 3)
        counts = extent.prod(-1)
        ends = torch.cumsum(counts, 0)
    total = int(ends[-1]) if ends.numel() else 0
    chunk = min(config.chunk_size, total)
    _check_size(
        b,
        grid,
        channels,
        dtype,
        out_dtype,
        chunk,
        56 + (27 + 2 * channels) * dtype.itemsize,
        total * (16 + 3 * dtype.itemsize) if grad_needed else 0,
    )
    lower = torch.tensor(grid.lower, dtype=dtype, device=device)
    size = torch.tensor(grid.voxel_size, dtype=dtype, device=device)
    num_voxels = b * x * y * z
    density = torch.zeros(num_voxels, dtype=dtype, device=device)
    accumulated = torch.zeros(num_voxels, channels, dtype=dtype, device=device)
    weights = torch.zeros(num_voxels, dtype=dtype, device=device)
    for first in range(0, total, max(chunk, 1)):  # bounded chunks of pairs
        with torch.no_grad():
            pair = torch.arange(first, min(first + chunk, total), device=device)
            owner = torch.searchsorted(ends, pair, right=True)
            local = pair - (ends[owner] - counts[owner])
            ey, ez = extent[owner, 1], extent[owner, 2]
            index = low[owner] + torch.stack(
                [local // (ey * ez), (local // ez) % ey, local % ez], -1
            )
            batch = owner // n  # n >= 1 whenever there are pairs
            voxel = ((batch * x + index[:, 0]) * y + index[:, 1]) * z + index[:, 2]
            centres = lower + (index.to(dtype) + 0.5) * size
        args = (means, whitening, opacities, features, owner, centres, log_normaliser, kernel)
        if grad_needed:
            terms = checkpoint(_pair_terms, *args, use_reentrant=False)
        else:
            terms = _pair_terms(*args)
        density.index_add_(0, voxel, terms[0])
        accumulated.index_add_(0, voxel, terms[1])
        weights.index_add_(0, voxel, terms[2])
    return _finish(density, accumulated, weights, kernel, config, (b, x, y, z), differentiable)


def _requiring_grad(*inputs: Tensor) -> tuple[Tensor, ...]:
    """The inputs that require grad, none when grad mode is off."""
    if not torch.is_grad_enabled():
        return ()
    return tuple(t for t in inputs if t.requires_grad)


def _finish(
    density: Tensor,
    accumulated: Tensor,
    weights: Tensor,  # summed feature weights W(x)
    kernel: _Kernel,
    config: VoxelizerConfig,
    shape: tuple[int, ...],
    differentiable: tuple[Tensor, ...],  # the inputs requiring grad (empty: no link)
) -> VoxelOutput:
    """Density from its sum; features ``empty_value`` where ``W <= empty_threshold``, else
    ``sum w f`` (additive) or ``sum w f / W`` (probabilistic).

    An output that no pair reached (no Gaussians, no (Gaussian, voxel) pair, B = 0) is still
    linked to every input in ``differentiable``, by an exact zero: it requires grad
    whenever an input does, and backward gives zero gradients.
    """
    reached = (weights > config.empty_threshold).unsqueeze(-1)
    if kernel.probabilistic:
        density = -torch.expm1(density)  # 1 - prod(1 - x), accurate for small densities
        # the divisor is 1 where unused, so the discarded branch's gradient stays finite
        accumulated = accumulated / torch.where(reached, weights.unsqueeze(-1), 1.0)
    else:
        density = density.clamp(0, 1)
    accumulated = torch.where(reached, accumulated, float(config.empty_value))
    if differentiable and not (density.requires_grad and accumulated.requires_grad):
        # a sum over no element: exactly 0 (whatever the values), zero gradient to each input
        zero = sum((t.flatten()[:0].sum() for t in differentiable), density.new_zeros(()))
        density = density if density.requires_grad else density + zero
        accumulated = accumulated if accumulated.requires_grad else accumulated + zero
    return VoxelOutput(
        density=density.view(*shape), features=accumulated.view(*shape, accumulated.shape[-1])
    )


def _cube_quadratics(
    means: Tensor,  # (n, 3)
    precisions: Tensor,  # (n, 6) float64: xx, yy, zz, xy, xz, yz
    cell: Tensor,  # (n, 3) long, voxel index of each mean (may be off-grid)
    axis_centres: tuple[Tensor, Tensor, Tensor],  # float64 voxel centres along x, y, z
    r: Tensor,  # (K,) offsets -nbh..nbh
    reach: tuple[float, float, float],  # (nbh + 1) voxels per axis, metres
) -> Tensor:
    """``(n, K, K, K)`` float64 quadratics ``d^T P d`` over each Gaussian's cube.

    ``d`` is formed per axis in float64, as (the grid's float64 centre) - (mean): the
    official code forms it in float32, where ``lower + (i + 0.5) * voxel`` is up to 4.6e-6 m
    off on the Occ3D grid (0.4 is no float32 number) and the difference of two numbers
    near 40 m loses another ~2e-6 m; those two dominate its float32 error. The quadratic
    form is then separable into (n, K) and (n, K, K) terms broadcast together, so nothing
    is gathered per (Gaussian, voxel) pair. Off-grid cube cells get clamped (meaningless)
    values: the caller drops them. ``d`` is clamped to ``+-reach``, which no in-grid cell of
    the cube exceeds, so far means cannot overflow the products (or their gradients).
    """
    d = []
    for a, centres in enumerate(axis_centres):
        index = (cell[:, a, None] + r).clamp(0, centres.shape[0] - 1)
        offset = centres[index] - means[:, a, None].double()
        d.append(offset.clamp(-reach[a], reach[a]))
    dx, dy, dz = d
    p = precisions.double()
    xy = p[:, 0, None, None] * (dx * dx)[:, :, None] + p[:, 1, None, None] * (dy * dy)[:, None]
    xy = xy + 2 * p[:, 3, None, None] * dx[:, :, None] * dy[:, None, :]
    xz = 2 * p[:, 4, None, None] * dx[:, :, None] * dz[:, None, :]
    yz = (
        p[:, 2, None, None] * (dz * dz)[:, None, :]
        + 2 * p[:, 5, None, None] * dy[:, :, None] * dz[:, None, :]
    )
    return (xy[..., None] + xz[:, :, None, :]) + yz[:, None, :, :]


def _cube_pair_terms(
    means: Tensor,  # (n, 3) this chunk's Gaussians
    precisions: Tensor,  # (n, 6)
    opacities: Tensor,  # (n,)
    features: Tensor,  # (n, C)
    log_normaliser: Tensor,  # (n,)
    cell: Tensor,  # (n, 3)
    local: Tensor,  # (P,) Gaussian of each kept pair, in the chunk
    flat: Tensor,  # (P,) its index into the flattened (n, K, K, K) quadratics
    axis_centres: tuple[Tensor, Tensor, Tensor],
    r: Tensor,
    reach: tuple[float, float, float],
    kernel: _Kernel,
) -> tuple[Tensor, Tensor, Tensor]:
    quadratic = _cube_quadratics(means, precisions, cell, axis_centres, r, reach)
    quadratic = quadratic.flatten()[flat]
    return _kernel_terms(
        quadratic.to(means.dtype),
        opacities[local],
        features[local],
        log_normaliser[local],
        kernel,
    )


# Data-dependent by nature (the number of (Gaussian, voxel) pairs): run eagerly under
# torch.compile, as one graph break, rather than recompiling for every pair count.
@torch._dynamo.disable(recursive=True)
def _voxelize_cube(
    bn: tuple[int, int],
    grid: VoxelGrid,
    means: Tensor,  # (M, 3)
    precision6: Tensor,  # (M, 6) float64
    opacities: Tensor,  # (M,)
    features: Tensor,  # (M, C)
    log_normaliser: Tensor,  # (M,)
    config: VoxelizerConfig,
    out_dtype: torch.dtype,
) -> VoxelOutput:
    """The official fixed-cube neighbourhood: quadratics of all ``(2 nbh + 1)^3`` cells of a
    bounded number of Gaussians at once, negligible and off-grid pairs dropped, the rest
    reduced with ``index_add_``."""
    (b, n), (x, y, z) = bn, grid.shape
    assert config.nbh is not None  # VoxelizerConfig requires it for the cube
    dtype, device = means.dtype, means.device
    channels = features.shape[-1]
    kernel = _Kernel.of(config)
    probabilistic = kernel.probabilistic
    r = torch.arange(-config.nbh, config.nbh + 1, device=device)
    cube_size = r.shape[0] ** 3
    per_chunk = max(1, config.chunk_size // cube_size)
    differentiable = _requiring_grad(means, precision6, opacities, features, log_normaliser)
    grad_needed = bool(differentiable)
    _check_size(
        b,
        grid,
        channels,
        dtype,
        out_dtype,
        min(per_chunk, b * n) * cube_size,
        49 + (5 + 2 * channels) * dtype.itemsize,
        b * n * cube_size * 24 if grad_needed else 0,
    )
    lower = torch.tensor(grid.lower, dtype=dtype, device=device)
    size = torch.tensor(grid.voxel_size, dtype=dtype, device=device)
    shape = torch.tensor(grid.shape, device=device)
    offsets = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    offsets_flat = (offsets[:, 0] * y + offsets[:, 1]) * z + offsets[:, 2]
    # float64 centres (the grid's own, lower + (i + 0.5) * voxel, in float64); the home voxel
    # below stays the official float32 floor((mu - lower) / voxel)
    lower64, size64, _ = _grid_float64(grid, device)
    axis_centres = tuple(
        lower64[a]
        + (torch.arange(grid.shape[a], device=device, dtype=torch.float64) + 0.5) * size64[a]
        for a in range(3)
    )
    reach = tuple((config.nbh + 1) * v for v in grid.voxel_size)
    with torch.no_grad():
        # home voxel, clamped in floating point to just outside the reach of the cube before
        # the integer conversion (a cell that far has no in-grid cube cell either way)
        cell = torch.floor((means.detach() - lower) / size)
        cell = torch.minimum(cell.clamp_min(-config.nbh - 1), shape + config.nbh).long()
        batch = torch.arange(b * n, device=device) // max(n, 1)
        cell_flat = batch * (x * y * z) + (cell[:, 0] * y + cell[:, 1]) * z + cell[:, 2]

    num_voxels = b * x * y * z
    density = torch.zeros(num_voxels, dtype=dtype, device=device)
    accumulated = torch.zeros(num_voxels, channels, dtype=dtype, device=device)
    weights = torch.zeros(num_voxels, dtype=dtype, device=device)
    for start in range(0, b * n, per_chunk):  # bounded chunks of Gaussians
        part = slice(start, start + per_chunk)
        with torch.no_grad():
            quadratic = _cube_quadratics(
                means[part].detach(), precision6[part].detach(), cell[part], axis_centres, r, reach
            )
            axis_ok = [
                ((cell[part, a, None] + r) >= 0) & ((cell[part, a, None] + r) < shape[a])
                for a in range(3)
            ]
            keep = (
                axis_ok[0][:, :, None, None]
                & axis_ok[1][:, None, :, None]
                & axis_ok[2][:, None, None, :]
            )
            # In probabilistic mode a tiny kernel can still carry a large normalised mixture
            # weight, so only the additive mode skips negligible pairs (NaN: far, skipped).
            if not probabilistic:
                keep &= quadratic < _NEGLIGIBLE_QUADRATIC
            flat = keep.flatten().nonzero().squeeze(1)
            local = flat // cube_size
            voxel = cell_flat[start + local] + offsets_flat[flat % cube_size]
        if grad_needed:
            inputs = (means, precision6, opacities, features, log_normaliser, cell)
            terms = checkpoint(
                _cube_pair_terms,
                *(t[part] for t in inputs),
                local,
                flat,
                axis_centres,
                r,
                reach,
                kernel,
                use_reentrant=False,
            )
        else:  # the screening quadratics are the values: no recomputation
            terms = _kernel_terms(
                quadratic.flatten()[flat].to(dtype),
                opacities[part][local],
                features[part][local],
                log_normaliser[part][local],
                kernel,
            )
        density.index_add_(0, voxel, terms[0])
        accumulated.index_add_(0, voxel, terms[1])
        weights.index_add_(0, voxel, terms[2])
    return _finish(density, accumulated, weights, kernel, config, (b, x, y, z), differentiable)


class GaussianVoxelizer(nn.Module):
    """Module form of :func:`voxelize`: holds the grid and settings (the keyword options of
    :func:`voxelize`, e.g. ``neighborhood="scale_cube", scale_multiplier=3``);
    ``forward(gaussians, features=None)`` voxelises."""

    def __init__(self, grid: VoxelGrid | None = None, **config: object) -> None:
        super().__init__()
        self.grid = VoxelGrid.occ3d() if grid is None else grid
        self.config = VoxelizerConfig(**config)  # type: ignore[arg-type]

    @typechecked
    def forward(
        self, gaussians: GaussianSet, features: Float[Tensor, "B N C"] | None = None
    ) -> VoxelOutput:
        return _voxelize(gaussians, self.grid, features, self.config)

    def extra_repr(self) -> str:
        fields = ", ".join(
            f"{f.name}={getattr(self.config, f.name)!r}" for f in dataclasses.fields(self.config)
        )
        return f"grid={self.grid}, {fields}"


__all__ = [
    "FeatureWeight",
    "GaussianVoxelizer",
    "Neighborhood",
    "VoxelOutput",
    "VoxelizerConfig",
    "voxelize",
]
