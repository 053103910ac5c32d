"""Axis-aligned voxel grids in the ego frame (x forward, y left, z up, metres)."""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Iterable, Sequence

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from dego._policy import check_memory, compute_dtype
from dego._typing import typechecked

_WHOLE_VOXEL_TOLERANCE = 1e-6
# Above 2**53 voxels an axis count is no longer exact in float64.
_MAX_VOXELS_PER_AXIS = 2.0**53
# Float indices are clamped to +-2**62 before the int64 cast (which is undefined for
# NaN, inf and values beyond int64); such indices stay far outside any grid.
_INDEX_LIMIT = 2.0**62

Triple = tuple[float, float, float]


def _as_triple(name: str, value: float | Sequence[float]) -> Triple:
    """``value`` (one number or three) as three finite floats; errors name ``name``."""
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        values: tuple[float, ...] = (float(value),) * 3
    elif isinstance(value, (str, bytes, bool)) or not isinstance(value, Iterable):
        raise TypeError(
            f"{name}: expected a number or 3 numbers (x, y, z), got {type(value).__name__}"
        )
    else:
        try:
            items = list(value)
        except TypeError:  # e.g. a 0-d tensor
            raise TypeError(
                f"{name}: expected a number or 3 numbers (x, y, z), got {value!r}"
            ) from None
        if len(items) != 3:
            raise ValueError(f"{name}: expected 3 values (x, y, z), got {len(items)}")
        try:
            if any(isinstance(v, (str, bytes, bool)) for v in items):
                raise TypeError
            values = tuple(float(v) for v in items)
        except (TypeError, ValueError):
            raise TypeError(f"{name}: expected 3 numbers (x, y, z), got {items!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{name}: values must be finite, got {values}")
    return values  # type: ignore[return-value]


@dataclasses.dataclass(frozen=True, init=False)
class VoxelGrid:
    """A regular grid of ``shape = (X, Y, Z)`` voxels spanning ``[lower, upper)``.

    Args:
        lower: ``(x, y, z)`` of the grid's minimum corner, metres.
        upper: ``(x, y, z)`` of the maximum corner, metres; strictly above ``lower``.
        voxel_size: edge length in metres, one value or one per axis; each extent must
            be a whole number of voxels (within 1e-6 voxel), at least 1 and at most 2**53.

    Each argument is one number (used on all three axes) or three. Non-numbers raise
    ``TypeError``; NaN or infinite values, a wrong count, ``voxel_size <= 0``,
    ``lower >= upper`` or an extent that is not a whole number of voxels raise
    ``ValueError`` naming the argument.

    Voxel ``(i, j, k)`` covers ``lower + [i, i+1) * voxel_size`` (per axis) and its
    centre is ``lower + (index + 0.5) * voxel_size``.
    """

    lower: Triple
    upper: Triple
    voxel_size: Triple

    def __init__(
        self,
        lower: float | Sequence[float],
        upper: float | Sequence[float],
        voxel_size: float | Sequence[float],
    ) -> None:
        lo, hi, size = (
            _as_triple("lower", lower),
            _as_triple("upper", upper),
            _as_triple("voxel_size", voxel_size),
        )
        if any(s <= 0 for s in size):
            raise ValueError(f"voxel_size: must be positive, got {size}")
        if any(a >= b for a, b in zip(lo, hi, strict=True)):
            raise ValueError(f"lower must be < upper on every axis, got lower={lo}, upper={hi}")
        for axis, a, b, s in zip("xyz", lo, hi, size, strict=True):
            count = (b - a) / s
            if not math.isfinite(count) or count > _MAX_VOXELS_PER_AXIS:
                raise ValueError(
                    f"voxel_size: the {axis} extent {b - a:g} m holds {count:.6g} voxels of "
                    f"{s:g} m; at most 2**53 per axis"
                )
            if round(count) < 1:
                raise ValueError(
                    f"voxel_size: the {axis} extent {b - a:g} m is less than one {s:g} m voxel"
                )
            if abs(count - round(count)) > _WHOLE_VOXEL_TOLERANCE:
                raise ValueError(
                    f"voxel_size: the {axis} extent {b - a:g} m is not a whole number of "
                    f"{s:g} m voxels ({count:.6g})"
                )
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)
        object.__setattr__(self, "voxel_size", size)

    @classmethod
    def occ3d(cls) -> VoxelGrid:
        """The Occ3D-nuScenes grid: [-40, -40, -1] to [40, 40, 5.4] m at 0.4 m, (200, 200, 16)."""
        return cls((-40.0, -40.0, -1.0), (40.0, 40.0, 5.4), 0.4)

    @classmethod
    def surroundocc(cls) -> VoxelGrid:
        """The SurroundOcc-nuScenes grid (GaussianFormer's): [-50, -50, -5] to [50, 50, 3] m
        at 0.5 m, (200, 200, 16)."""
        return cls((-50.0, -50.0, -5.0), (50.0, 50.0, 3.0), 0.5)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Number of voxels ``(X, Y, Z)`` along x, y, z."""
        return tuple(  # type: ignore[return-value]
            round((b - a) / s)
            for a, b, s in zip(self.lower, self.upper, self.voxel_size, strict=True)
        )

    @property
    def num_voxels(self) -> int:
        return math.prod(self.shape)

    def _tensors(
        self,
        like: Tensor | None = None,
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> tuple[Tensor, Tensor]:
        """``lower`` and ``voxel_size`` as ``(3,)`` tensors matching ``like`` (or dtype/device)."""
        if like is not None:
            # float16 / bfloat16 points are compared in float32 (5.4 is 5.3984 in float16).
            floating = like.is_floating_point()
            dtype = compute_dtype(like.dtype) if floating else torch.get_default_dtype()
            device = like.device
        dtype = dtype or torch.get_default_dtype()
        return (
            torch.tensor(self.lower, dtype=dtype, device=device),
            torch.tensor(self.voxel_size, dtype=dtype, device=device),
        )

    def centers(
        self, *, dtype: torch.dtype | None = None, device: torch.device | str | None = None
    ) -> Float[Tensor, "X Y Z 3"]:
        """World coordinates of every voxel centre, ``(X, Y, Z, 3)``, computed in float64.

        The size (a float64 grid plus the result) goes through dego's memory guard first.
        """
        out_dtype = dtype or torch.get_default_dtype()
        itemsize = torch.empty((), dtype=out_dtype).element_size()
        check_memory(
            "VoxelGrid.centers",
            float(self.num_voxels) * 3 * (8 + itemsize),
            f"{' x '.join(map(str, self.shape))} voxels x 3 coordinates, float64 and {out_dtype}",
        )
        axes = [
            torch.arange(n, dtype=torch.float64, device=device).add_(0.5).mul_(s).add_(a)
            for n, s, a in zip(self.shape, self.voxel_size, self.lower, strict=True)
        ]
        grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)
        return grid.to(out_dtype)

    @typechecked
    def world_to_index(self, points: Float[Tensor, "*batch 3"]) -> Int[Tensor, "*batch 3"]:
        """Integer voxel indices ``floor((p - lower) / voxel_size)``, ``(*, 3)`` int64.

        Points outside the grid give out-of-range indices; use :meth:`contains` or
        :meth:`contains_index` to mask them. So that the int64 cast is always defined,
        indices are clamped to ``[-2**62, 2**62]`` (still outside any grid), and a NaN
        coordinate gives index -1 (outside; :meth:`contains` is False for it too).
        """
        lower, size = self._tensors(points)
        index = torch.floor((points.to(lower.dtype) - lower) / size)
        index = torch.nan_to_num(index, nan=-1.0).clamp(-_INDEX_LIMIT, _INDEX_LIMIT)
        return index.long()

    @typechecked
    def index_to_world(
        self, index: Int[Tensor, "*batch 3"], *, dtype: torch.dtype | None = None
    ) -> Float[Tensor, "*batch 3"]:
        """Centres ``lower + (index + 0.5) * voxel_size`` of voxels ``index`` ``(*, 3)``."""
        lower, size = self._tensors(dtype=torch.float64, device=index.device)
        return ((index.double() + 0.5) * size + lower).to(dtype or torch.get_default_dtype())

    @typechecked
    def contains(self, points: Float[Tensor, "*batch 3"]) -> Bool[Tensor, "*batch"]:
        """Whether each point lies inside the half-open box ``[lower, upper)``."""
        lower, _ = self._tensors(points)
        upper = torch.tensor(self.upper, dtype=lower.dtype, device=lower.device)
        points = points.to(lower.dtype)
        return ((points >= lower) & (points < upper)).all(dim=-1)

    @typechecked
    def contains_index(self, index: Int[Tensor, "*batch 3"]) -> Bool[Tensor, "*batch"]:
        """Whether each integer index lies in ``[0, shape)`` on every axis."""
        shape = torch.tensor(self.shape, device=index.device)
        return ((index >= 0) & (index < shape)).all(dim=-1)


__all__ = ["VoxelGrid"]
