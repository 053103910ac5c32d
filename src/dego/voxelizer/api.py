"""The voxelizer's entry points: :func:`voxelize` and its module form :class:`GaussianVoxelizer`."""

from __future__ import annotations

import dataclasses
import sys

from jaxtyping import Float
from torch import Tensor, nn

from dego._options import build_config, config_from
from dego._policy import float32_under_autocast
from dego._typing import typechecked
from dego.gaussians import GaussianSet
from dego.grid import VoxelGrid
from dego.voxelizer.boxes import voxelize_boxes
from dego.voxelizer.cube import voxelize_cube
from dego.voxelizer.inputs import flatten_inputs
from dego.voxelizer.output import VoxelOutput
from dego.voxelizer.types import (
    TINY_WEIGHT,
    FeatureWeight,
    Mode,
    Neighborhood,
    VoxelizerConfig,
    VoxelizerOptions,
)

if sys.version_info >= (3, 11):
    from typing import Unpack
else:  # Python 3.10: typing_extensions, a dependency of torch
    from typing_extensions import Unpack


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
    empty_threshold: float = TINY_WEIGHT,
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
    config = config_from(VoxelizerConfig, locals())
    return _voxelize(gaussians, grid, features, config)


def _voxelize(
    gaussians: GaussianSet, grid: VoxelGrid, features: Tensor | None, config: VoxelizerConfig
) -> VoxelOutput:
    flat = flatten_inputs(gaussians, features)
    if config.neighborhood == "cube":
        out = voxelize_cube(flat, grid, config)
    else:
        out = voxelize_boxes(flat, grid, config)
    if flat.out_dtype == flat.dtype:
        return out
    return VoxelOutput(
        density=out.density.to(flat.out_dtype), features=out.features.to(flat.out_dtype)
    )


class GaussianVoxelizer(nn.Module):
    """Module form of :func:`voxelize`: holds the grid and a :class:`VoxelizerConfig`;
    ``forward(gaussians, features=None)`` voxelises.

    Args:
        grid: the voxel grid (default: :meth:`VoxelGrid.occ3d`).
        config: the settings (default: the defaults of :func:`voxelize`).
        **overrides: keyword options of :func:`voxelize` applied on top of ``config``, e.g.
            ``neighborhood="scale_cube", scale_multiplier=3``.

    Raises:
        TypeError: ``config`` is not a :class:`VoxelizerConfig`, or an unknown option
            (with the closest valid name).
        ValueError: a bad option value, naming the option.
    """

    @typechecked
    def __init__(
        self,
        grid: VoxelGrid | None = None,
        config: VoxelizerConfig | None = None,
        **overrides: Unpack[VoxelizerOptions],
    ) -> None:
        super().__init__()
        self.grid = VoxelGrid.occ3d() if grid is None else grid
        self.config = build_config("GaussianVoxelizer()", VoxelizerConfig, config, overrides)

    @typechecked
    def forward(
        self, gaussians: GaussianSet, features: Float[Tensor, "B N C"] | None = None
    ) -> VoxelOutput:
        return _voxelize(gaussians, self.grid, features, self.config)

    @typechecked
    def extra_repr(self) -> str:
        fields = ", ".join(
            f"{f.name}={getattr(self.config, f.name)!r}" for f in dataclasses.fields(self.config)
        )
        return f"grid={self.grid}, {fields}"
