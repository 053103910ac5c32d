"""nuScenes keyframes: a sample's token, scene, time and the two poses RayIoU needs.

A :class:`Keyframe` comes from an mmdet3d-style infos pickle (:func:`dego.data.load_infos`)
or from the nuScenes JSON tables (:func:`dego.data.load_nuscenes_keyframes`); both
build the 4x4 matrices the same way (``R`` of the normalised wxyz quaternion, as
pyquaternion does, and the translation).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import torch
from jaxtyping import Float64
from torch import Tensor

from dego.metrics.rayiou import pose_matrices

__all__ = ["Keyframe"]


@dataclasses.dataclass(frozen=True, eq=False)
class Keyframe:
    """One nuScenes sample (a LIDAR_TOP key frame).

    Fields:
        token: the nuScenes sample token.
        scene: the scene name (``"scene-0003"``) if known, else the scene token, else ``""``.
        timestamp: microseconds.
        lidar2ego: ``(4, 4)`` float64, LIDAR_TOP sensor frame -> ego frame.
        ego2global: ``(4, 4)`` float64, ego frame -> global frame.
    """

    token: str
    scene: str
    timestamp: int
    lidar2ego: Float64[Tensor, "4 4"]
    ego2global: Float64[Tensor, "4 4"]

    def __post_init__(self) -> None:
        if not isinstance(self.token, str) or not self.token:
            raise ValueError(f"token: expected a non-empty str, got {self.token!r}")
        if not isinstance(self.scene, str):
            raise ValueError(f"scene: expected a str, got {type(self.scene).__name__}")
        if isinstance(self.timestamp, bool) or not isinstance(self.timestamp, int):
            raise ValueError(f"timestamp: expected an int (microseconds), got {self.timestamp!r}")
        for name in ("lidar2ego", "ego2global"):
            _check_matrix(name, getattr(self, name), f"Keyframe {self.token!r}")


def _check_matrix(name: str, value: Any, where: str) -> None:
    if not isinstance(value, Tensor):
        raise TypeError(f"{where}: {name}: expected a torch.Tensor, got {type(value).__name__}")
    if value.dtype != torch.float64 or tuple(value.shape) != (4, 4):
        raise ValueError(
            f"{where}: {name}: expected a (4, 4) float64 tensor, got {tuple(value.shape)} "
            f"{value.dtype}"
        )
    rows = value.tolist()
    if not all(math.isfinite(v) for row in rows for v in row):
        raise ValueError(f"{where}: {name}: holds non-finite values")
    if any(abs(v - e) > 1e-6 for v, e in zip(rows[3], (0.0, 0.0, 0.0, 1.0), strict=True)):
        raise ValueError(f"{where}: {name}: last row is {rows[3]}, expected [0, 0, 0, 1]")


def checked_numbers(value: Any, shape: tuple[int, ...], where: str) -> np.ndarray:
    """``value`` (list, tuple, numpy array) as a finite float64 array of ``shape``."""
    if isinstance(value, str | bytes | dict) or value is None:
        raise ValueError(f"{where}: expected {_shape_text(shape)} numbers, got {value!r:.80}")
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"{where}: expected {_shape_text(shape)} numbers, got {value!r:.80}"
        ) from None
    if array.shape != shape:
        raise ValueError(f"{where}: expected shape {shape}, got {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{where}: holds non-finite values ({array.tolist()})")
    return array


def _shape_text(shape: tuple[int, ...]) -> str:
    return "x".join(str(s) for s in shape)


def checked_quaternion(value: Any, where: str) -> np.ndarray:
    """A wxyz quaternion ``(4,)``; zero or non-finite ones raise ``ValueError``."""
    quat = checked_numbers(value, (4,), where)
    if not math.isfinite(norm := float(np.linalg.norm(quat))) or norm < 1e-12:
        raise ValueError(f"{where}: the quaternion {quat.tolist()} has no direction (norm 0)")
    return quat


def keyframe_pose_matrices(translations: np.ndarray, rotations: np.ndarray) -> Tensor:
    """``(N, 4, 4)`` float64 poses from ``(N, 3)`` translations and ``(N, 4)`` wxyz quaternions.

    The quaternions are normalised first (as pyquaternion's ``rotation_matrix``).
    """
    rotations = rotations / np.linalg.norm(rotations, axis=-1, keepdims=True)
    return pose_matrices(
        "poses", torch.from_numpy(np.concatenate([translations, rotations], axis=-1))
    )
