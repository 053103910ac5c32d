"""Occ3D labels as palette colours, and a label grid seen from above as a label map.

Plain torch/numpy: no matplotlib needed.
"""

from __future__ import annotations

from typing import overload

import numpy as np
import torch
from jaxtyping import Integer, UInt8
from torch import Tensor

from dego._typing import typechecked
from dego.classes import FREE_LABEL
from dego.viz._labels import RGB, WHITE, _check_free, _label_tensor, _palette_lut


@overload
def colorize_labels(
    labels: Integer[Tensor, "*shape"], *, free_label: int = ..., free_color: RGB = ...
) -> UInt8[Tensor, "*shape 3"]: ...
@overload
def colorize_labels(
    labels: Integer[np.ndarray, "*shape"], *, free_label: int = ..., free_color: RGB = ...
) -> UInt8[np.ndarray, "*shape 3"]: ...
@typechecked
def colorize_labels(
    labels: Integer[Tensor, "*shape"] | Integer[np.ndarray, "*shape"],
    *,
    free_label: int = FREE_LABEL,
    free_color: RGB = WHITE,
) -> UInt8[Tensor, "*shape 3"] | UInt8[np.ndarray, "*shape 3"]:
    """RGB colours of Occ3D labels in the paper's palette (:data:`dego.PALETTE`).

    Args:
        labels: ``(...)`` integer labels in [0, 17], any shape (a grid, a BEV map, an image).
        free_label: the label drawn as ``free_color`` (Occ3D: 17).
        free_color: RGB (0-255) of free space; white by default.

    Returns:
        ``(..., 3)`` uint8 colours; a tensor on ``labels``' device for a tensor input,
        a numpy array for a numpy input.

    Raises:
        ValueError: a label outside [0, 17], or a bad ``free_label`` / ``free_color``.
    """
    _check_free(free_label, free_color)
    index = _label_tensor("labels", labels)
    lut = _palette_lut(free_label, free_color)
    if isinstance(labels, Tensor):
        return lut.to(index.device)[index]
    return lut[index].numpy()


@overload
def bev_labels(
    labels: Integer[Tensor, "*batch X Y Z"], *, free_label: int = ...
) -> Integer[Tensor, "*batch X Y"]: ...
@overload
def bev_labels(
    labels: Integer[np.ndarray, "*batch X Y Z"], *, free_label: int = ...
) -> Integer[np.ndarray, "*batch X Y"]: ...
@typechecked
def bev_labels(
    labels: Integer[Tensor, "*batch X Y Z"] | Integer[np.ndarray, "*batch X Y Z"],
    *,
    free_label: int = FREE_LABEL,
) -> Integer[Tensor, "*batch X Y"] | Integer[np.ndarray, "*batch X Y"]:
    """Top-down view of a label grid: per ``(x, y)`` column, the label of its highest
    non-free voxel, or ``free_label`` where the whole column is free.

    Args:
        labels: ``(*, X, Y, Z)`` labels in [0, 17], z up (index order x, y, z).
        free_label: the empty-space label (Occ3D: 17).

    Returns:
        ``(*, X, Y)`` labels with ``labels``' dtype and type (tensor on its device, or numpy).
    """
    _check_free(free_label, WHITE)
    index = _label_tensor("labels", labels)
    if index.shape[-1] == 0:
        raise ValueError(f"labels: the z axis is empty (shape {tuple(index.shape)})")
    occupied = index != free_label
    height = torch.arange(1, index.shape[-1] + 1, device=index.device)
    top = torch.where(occupied, height, 0).argmax(dim=-1, keepdim=True)  # highest occupied z
    bev = index.gather(-1, top).squeeze(-1)
    bev = torch.where(occupied.any(dim=-1), bev, free_label)
    if isinstance(labels, Tensor):
        return bev.to(labels.dtype)
    return bev.numpy().astype(labels.dtype, copy=False)
