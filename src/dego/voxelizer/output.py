"""The voxelizer's result, :class:`VoxelOutput`.

No ``from __future__ import annotations`` here: the field annotations are objects, so
:mod:`dego._serialization` resolves them whatever ``__module__`` says, and ``__module__``
is ``"dego.voxelizer"``, the name pickles and ``torch.load(weights_only=True)`` allowlists
have always used.
"""

import dataclasses

import torch
from jaxtyping import Float, Int
from torch import Tensor

from dego import _serialization
from dego._typing import check_tensor_fields, typechecked
from dego.classes import FREE_LABEL


@dataclasses.dataclass(frozen=True)
class VoxelOutput(_serialization.DictForm):
    """Voxelised Gaussians.

    Attributes:
        density: ``(B, X, Y, Z)`` occupancy in [0, 1].
        features: ``(B, X, Y, Z, C)`` aggregated features (C may be 0).
    """

    density: Float[Tensor, "B X Y Z"]
    features: Float[Tensor, "B X Y Z C"]

    def __post_init__(self) -> None:
        check_tensor_fields(self)

    @typechecked
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


# The public (and pickled) name: dego.voxelizer.VoxelOutput, as before the package split.
VoxelOutput.__module__ = "dego.voxelizer"

__all__ = ["VoxelOutput"]
