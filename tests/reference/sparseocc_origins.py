"""An independent, plain-numpy statement of SparseOcc's RayIoU ray-origin rules
(``loaders/ego_pose_dataset.py``, ``EgoPoseDataset``), written from the rules, for tests.

- group the infos by ``scene_name``, keeping the given order within a scene;
- for a reference info, every info of its scene (itself included) gives the translation
  of ``inv(G_ref L_ref) (G_cur L_cur)`` as float32 (its own is exactly 0), mapped to the
  reference ego frame with ``L_ref`` in float64;
- keep ``|x| < 39`` and ``|y| < 39``; more than 8 left: ``round(linspace(0, n - 1, 8))``.

Matrices are built as the nuScenes devkit's ``transform_matrix`` does (the inverse as
``R^T``, ``-R^T t``), with its own quaternion code.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def quaternion_to_matrix(q: Any) -> np.ndarray:
    """``(3, 3)`` rotation of a wxyz quaternion, normalised first."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(np.asarray(q, np.float64))
    return np.array(
        [
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
        ]
    )


def transform_matrix(translation: Any, rotation: Any, inverse: bool = False) -> np.ndarray:
    """``(4, 4)`` pose from a translation and a wxyz quaternion, or its inverse."""
    r = quaternion_to_matrix(rotation)
    t = np.asarray(translation, dtype=np.float64)
    out = np.eye(4)
    if inverse:
        out[:3, :3] = r.T
        out[:3, 3] = -(r.T @ t)
    else:
        out[:3, :3] = r
        out[:3, 3] = t
    return out


def sparseocc_origins(
    infos: list[dict[str, Any]], max_origins: int = 8, xy_limit: float = 39.0
) -> dict[str, tuple[np.ndarray, int]]:
    """``{token: ((K, 3) origins, number of candidates inside the limit)}``."""
    scenes: dict[str, list[dict[str, Any]]] = {}
    for info in infos:
        scenes.setdefault(info["scene_name"], []).append(info)
    out = {}
    for info in infos:
        frames = scenes[info["scene_name"]]
        ref_ego_from_lidar = transform_matrix(
            info["lidar2ego_translation"], info["lidar2ego_rotation"]
        )
        ref_lidar_from_global = transform_matrix(
            info["lidar2ego_translation"], info["lidar2ego_rotation"], inverse=True
        ) @ transform_matrix(
            info["ego2global_translation"], info["ego2global_rotation"], inverse=True
        )
        kept = []
        for other in frames:
            if other["token"] == info["token"]:
                local = np.zeros(3, dtype=np.float32)
            else:
                global_from_cur = transform_matrix(
                    other["ego2global_translation"], other["ego2global_rotation"]
                ) @ transform_matrix(other["lidar2ego_translation"], other["lidar2ego_rotation"])
                local = (ref_lidar_from_global @ global_from_cur)[:3, 3].astype(np.float32)
            point = (
                ref_ego_from_lidar[:3, :3] @ local.astype(np.float64) + ref_ego_from_lidar[:3, 3]
            )
            if abs(point[0]) < xy_limit and abs(point[1]) < xy_limit:
                kept.append(point)
        count = len(kept)
        if count > max_origins:
            picks = np.round(np.linspace(0, count - 1, max_origins)).astype(np.int64)
            kept = [kept[int(k)] for k in picks]
        out[info["token"]] = (np.stack(kept), count)
    return out
