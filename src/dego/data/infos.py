"""mmdet3d-style nuScenes infos pickles -> :class:`~dego.data.Keyframe` (no code runs).

Layouts read (all through :func:`dego.data.load_pickle`, the restricted unpickler):

- ``{"infos": [...], "metadata": {...}}`` (mmdet3d 0.x, BEVDet, SparseOcc,
  GaussianFlowOcc): ``token``, ``timestamp``, ``lidar2ego_translation`` (3),
  ``lidar2ego_rotation`` (wxyz, 4), ``ego2global_translation``, ``ego2global_rotation``
  and the scene from ``scene_name``, else ``scene_token``, else ``""``;
- ``{"data_list": [...], "metainfo": ...}`` (mmdet3d 1.x): ``token``, ``timestamp``,
  ``ego2global`` (4x4) and ``lidar_points["lidar2ego"]`` (4x4);
- a bare list of either kind of info dict.

Timestamps: ints are microseconds; floats below 1e12 are seconds (mmdet3d 1.x divides
by 1e6) and are rounded to microseconds, larger integral floats are microseconds.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dego._typing import typechecked
from dego.data.keyframes import (
    Keyframe,
    checked_numbers,
    checked_quaternion,
    keyframe_pose_matrices,
)
from dego.data.safe_pickle import load_pickle

PathLike = str | os.PathLike[str]

__all__ = ["load_infos"]

_LEGACY_KEYS = (
    "token",
    "timestamp",
    "lidar2ego_translation",
    "lidar2ego_rotation",
    "ego2global_translation",
    "ego2global_rotation",
)
_SECONDS_BELOW = 1e12  # nuScenes times are ~1.5e9 s, ~1.5e15 us


@typechecked
def load_infos(path: PathLike) -> tuple[Keyframe, ...]:
    """Keyframes of an mmdet3d-style nuScenes infos pickle, in the file's order.

    Args:
        path: the ``.pkl`` file (``nuscenes_infos_val.pkl``,
            ``bevdetv2-nuscenes_infos_val.pkl``, mmdet3d 1.x ``nuscenes_infos_val.pkl``).

    Returns:
        One :class:`Keyframe` per info entry, in file order.

    Raises:
        FileNotFoundError: naming ``path`` (missing, or not a regular file: a FIFO is
            refused without blocking).
        dego.data.UnsafePickleError: the file names a global other than plain containers
            and numpy (nothing is executed).
        ValueError: naming the file, the entry (``infos[i]`` / ``data_list[i]``) and the
            field for a missing key, a non-finite or wrongly shaped pose, a bad timestamp;
            naming the token for duplicates; for an empty list or an unknown layout.
    """
    file = Path(path)
    data = load_pickle(file)
    if isinstance(data, Mapping):
        if "infos" in data:
            label, entries = "infos", data["infos"]
        elif "data_list" in data:
            label, entries = "data_list", data["data_list"]
        else:
            raise ValueError(
                f"{file}: expected a dict with 'infos' (mmdet3d 0.x) or 'data_list' "
                f"(mmdet3d 1.x), got keys {sorted(map(str, data))[:10]}"
            )
    else:
        label, entries = "infos", data
    if not isinstance(entries, list | tuple):
        raise ValueError(f"{file}: {label}: expected a list of dicts, got {type(entries).__name__}")
    if not entries:
        raise ValueError(f"{file}: {label}: the infos list is empty")

    tokens: list[str] = []
    scenes: list[str] = []
    stamps: list[int] = []
    lidar: list[Any] = []
    ego: list[Any] = []
    matrix_layout: bool | None = None
    seen: dict[str, int] = {}
    for i, info in enumerate(entries):
        where = f"{file}: {label}[{i}]"
        if not isinstance(info, Mapping):
            raise ValueError(f"{where}: expected a dict, got {type(info).__name__}")
        is_matrix = "lidar2ego_translation" not in info and (
            "ego2global" in info or "lidar_points" in info
        )
        if matrix_layout is None:
            matrix_layout = is_matrix
        elif matrix_layout != is_matrix:
            raise ValueError(
                f"{where}: mixes the mmdet3d 1.x (ego2global 4x4) and 0.x "
                "(ego2global_translation/rotation) layouts"
            )
        if is_matrix:
            _require(info, ("token", "timestamp", "ego2global", "lidar_points"), where)
            points = info["lidar_points"]
            if not isinstance(points, Mapping) or "lidar2ego" not in points:
                raise ValueError(f"{where}: missing key 'lidar_points.lidar2ego'")
            lidar.append(
                checked_numbers(points["lidar2ego"], (4, 4), f"{where}: lidar_points.lidar2ego")
            )
            ego.append(checked_numbers(info["ego2global"], (4, 4), f"{where}: ego2global"))
        else:
            _require(info, _LEGACY_KEYS, where)
            lidar.append(
                (
                    checked_numbers(
                        info["lidar2ego_translation"], (3,), f"{where}: lidar2ego_translation"
                    ),
                    checked_quaternion(info["lidar2ego_rotation"], f"{where}: lidar2ego_rotation"),
                )
            )
            ego.append(
                (
                    checked_numbers(
                        info["ego2global_translation"], (3,), f"{where}: ego2global_translation"
                    ),
                    checked_quaternion(
                        info["ego2global_rotation"], f"{where}: ego2global_rotation"
                    ),
                )
            )
        token = info["token"]
        if not isinstance(token, str) or not token:
            raise ValueError(f"{where}: token: expected a non-empty str, got {token!r}")
        if token in seen:
            raise ValueError(
                f"{file}: duplicate token {token!r} in {label}[{seen[token]}] and {label}[{i}]"
            )
        seen[token] = i
        tokens.append(token)
        scenes.append(_scene(info, where))
        stamps.append(_timestamp(info["timestamp"], f"{where}: timestamp"))

    if matrix_layout:
        lidar2ego = torch.from_numpy(np.stack(lidar))
        ego2global = torch.from_numpy(np.stack(ego))
        for name, stack in (("lidar_points.lidar2ego", lidar2ego), ("ego2global", ego2global)):
            bad = ~torch.isclose(
                stack[:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-6
            ).all(-1)
            if bool(bad.any()):
                i = int(bad.nonzero()[0])
                raise ValueError(
                    f"{file}: {label}[{i}]: {name}: last row is {stack[i, 3].tolist()}, "
                    "expected [0, 0, 0, 1]"
                )
    else:
        lidar2ego = keyframe_pose_matrices(
            np.stack([t for t, _ in lidar]), np.stack([q for _, q in lidar])
        )
        ego2global = keyframe_pose_matrices(
            np.stack([t for t, _ in ego]), np.stack([q for _, q in ego])
        )
    return tuple(
        Keyframe(token, scene, stamp, lidar2ego[i].clone(), ego2global[i].clone())
        for i, (token, scene, stamp) in enumerate(zip(tokens, scenes, stamps, strict=True))
    )


def _require(info: Mapping[str, Any], keys: tuple[str, ...], where: str) -> None:
    for key in keys:
        if key not in info:
            raise ValueError(f"{where}: missing key {key!r}")


def _scene(info: Mapping[str, Any], where: str) -> str:
    for key in ("scene_name", "scene_token"):
        value = info.get(key)
        if value is not None and value != "":
            if not isinstance(value, str):
                raise ValueError(f"{where}: {key}: expected a str, got {value!r}")
            return value
    return ""


def _timestamp(value: Any, where: str) -> int:
    if isinstance(value, bool | np.bool_):
        raise ValueError(f"{where}: expected an int (microseconds), got {value!r}")
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        value = float(value)
        if math.isfinite(value):
            if abs(value) < _SECONDS_BELOW:
                return round(value * 1e6)
            if value.is_integer():
                return int(value)
    raise ValueError(f"{where}: expected microseconds (int) or seconds (float), got {value!r}")
