"""The label and palette checks behind every picture: Occ3D labels in [0, 17], the free
label and its colour, the palette as a lookup table, a grid's extents, the classes present.

Label arguments take any integer dtype (uint8 as Occ3D ships them, int8 ... int64; the
pictures do not depend on it). Values outside [0, 17], such as -1 or 255, raise a
``ValueError`` naming the argument and the range found; bool and floating labels raise a
``TypeError`` (jaxtyping's ``TypeCheckError``) naming the argument. Empty grids and
batches give empty results.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from dego._checks import check_int
from dego.classes import NUM_CLASSES, PALETTE
from dego.grid import VoxelGrid

RGB = tuple[int, int, int]
WHITE: RGB = (255, 255, 255)


def _check_free(free_label: int, free_color: RGB) -> None:
    check_int("free_label", free_label)
    if not 0 <= free_label < NUM_CLASSES:
        raise ValueError(
            f"free_label: expected a label in [0, {NUM_CLASSES - 1}], got {free_label}"
        )
    if any(isinstance(c, bool) or not 0 <= c <= 255 for c in free_color):
        raise ValueError(f"free_color: expected three ints in [0, 255], got {free_color}")


def _label_tensor(name: str, labels: Tensor | np.ndarray) -> Tensor:
    """``labels`` as int64 (a tensor stays on its device), checked to lie in [0, 17]."""
    if isinstance(labels, Tensor):
        index = labels.detach().long()
    else:
        index = torch.from_numpy(np.array(labels, dtype=np.int64))  # copy: read-only/strided ok
    if index.numel():
        low, high = (int(v) for v in torch.aminmax(index))
        if low < 0 or high >= NUM_CLASSES:
            raise ValueError(
                f"{name}: expected Occ3D labels in [0, {NUM_CLASSES - 1}], "
                f"got values in [{low}, {high}]"
            )
    return index


def _unit_rgb(rgb: RGB) -> tuple[float, float, float]:
    """0-255 RGB as matplotlib's 0-1 floats."""
    r, g, b = (v / 255.0 for v in rgb)
    return r, g, b


def _palette_lut(free_label: int, free_color: RGB) -> Tensor:
    lut = torch.tensor(PALETTE, dtype=torch.uint8)
    lut[free_label] = torch.tensor(free_color, dtype=torch.uint8)
    return lut


def _extents(
    grid: VoxelGrid | None, shape: tuple[int, ...]
) -> tuple[list[tuple[float, float]], str]:
    """Per-axis ``(low, high)`` and unit for a grid of ``shape`` (2 or 3 axes)."""
    if grid is None:
        occ3d = VoxelGrid.occ3d()
        if shape != occ3d.shape[: len(shape)]:
            return [(0.0, float(n)) for n in shape], "voxel"
        grid = occ3d
    elif grid.shape[: len(shape)] != shape:
        raise ValueError(
            f"grid: its shape {grid.shape} does not match the labels' shape {shape}; "
            "pass the VoxelGrid the labels live on"
        )
    return [(grid.lower[a], grid.upper[a]) for a in range(len(shape))], "m"


def _present_classes(labels: Tensor, free_label: int) -> list[int]:
    return [int(c) for c in torch.unique(labels) if int(c) != free_label]
