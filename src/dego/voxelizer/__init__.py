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

Modules: ``types`` (the options: :class:`VoxelizerConfig` and the ``Literal`` aliases),
``output`` (:class:`VoxelOutput`), ``inputs`` (input and value checks), ``records`` (the
flattened inputs and the per-voxel sums), ``kernels`` (per-pair terms), ``boxes`` (the
ellipsoid and scale-cube neighbourhoods), ``cube`` (the official cube) and ``api``
(:func:`voxelize`, :class:`GaussianVoxelizer`).
"""

from dego.voxelizer.api import GaussianVoxelizer, voxelize
from dego.voxelizer.output import VoxelOutput
from dego.voxelizer.types import (
    FeatureWeight,
    Mode,
    Neighborhood,
    VoxelizerConfig,
    VoxelizerOptions,
)

__all__ = [
    "FeatureWeight",
    "GaussianVoxelizer",
    "Mode",
    "Neighborhood",
    "VoxelOutput",
    "VoxelizerConfig",
    "VoxelizerOptions",
    "voxelize",
]
