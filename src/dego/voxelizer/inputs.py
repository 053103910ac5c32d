"""The voxelizer's input checks: shapes, dtypes and devices, Gaussian values, memory.

:func:`flatten_inputs` checks the inputs and flattens them into a
:class:`~dego.voxelizer.records.FlatGaussians`; :func:`_check_values` holds every value
check's wording; :func:`check_size` checks the buffers against dego's memory limit.
"""

from __future__ import annotations

import math

from torch import Tensor

from dego._policy import (
    check_dtype,
    check_memory,
    compute_dtype,
    finite_check,
    gaussian_value_checks,
    run_checks,
)
from dego.gaussians import GaussianSet
from dego.grid import VoxelGrid
from dego.voxelizer.kernels import log_normaliser_bound, scale_floor
from dego.voxelizer.records import FlatGaussians


def _check_values(fields: dict[str, Tensor]) -> None:
    """Raise ``ValueError`` naming the field on non-finite values, scales <= 0, zero-norm
    quaternions or opacities outside [0, 1]; one host sync when everything is valid."""
    run_checks(
        [finite_check(name, t) for name, t in fields.items()]
        + gaussian_value_checks(
            "",
            scales=fields["scales"],
            opacities=fields["opacities"],
            quats=fields["quats"],
            scales_needed_for="; voxelize needs positive standard deviations (its "
            "precisions use 1/s^2)",
        )
    )


def flatten_inputs(gaussians: GaussianSet, features: Tensor | None) -> FlatGaussians:
    """Check ``(B, N)`` Gaussians and their ``(B, N, C)`` features (default: their own; none:
    C = 0) and flatten them into ``B * N`` rows in the compute dtype."""
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

    m = b * n
    scales = fields["scales"].reshape(m, 3).clamp_min(scale_floor(dtype))
    bound = log_normaliser_bound(dtype)
    log_normaliser = (-1.5 * math.log(2 * math.pi) - scales.log().sum(-1)).clamp(-bound, bound)
    return FlatGaussians(
        batch_size=b,
        num_gaussians=n,
        means=fields["means"].reshape(m, 3),
        quats=fields["quats"].reshape(m, 4),
        scales=scales,
        opacities=fields["opacities"].reshape(m),
        features=fields["features"].reshape(m, features.shape[-1]),
        log_normaliser=log_normaliser,
        out_dtype=out_dtype,
    )


def check_size(
    flat: FlatGaussians,
    grid: VoxelGrid,
    chunk: int,
    per_chunk_element: int,
    retained: int,
    detail: str = "",
) -> None:
    """:func:`check_memory` on the output grids, one chunk's buffers (``chunk`` elements of
    ``per_chunk_element`` bytes) and (under autograd) the ``retained`` bytes of per-pair
    indices kept for backward (and any other table), before any of them is allocated;
    ``detail`` is added to the sizes the message names."""
    b, channels, dtype, out_dtype = flat.batch_size, flat.channels, flat.dtype, flat.out_dtype
    x, y, z = grid.shape
    voxels = b * x * y * z
    nbytes = voxels * (channels + 2) * dtype.itemsize + chunk * per_chunk_element + retained
    if out_dtype != dtype:  # the cast back to the input dtype
        nbytes += voxels * (channels + 1) * out_dtype.itemsize
    check_memory(
        "voxelize",
        nbytes,
        f"B = {b} grids of {x} x {y} x {z} voxels x ({channels} + 2) channels in {dtype}, "
        f"chunks of {chunk} (Gaussian, voxel) pairs{detail}",
    )
