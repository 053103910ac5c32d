"""The few nuScenes JSON tables RayIoU needs -> :class:`~dego.data.Keyframe` (no devkit).

:func:`load_nuscenes_keyframes` reads ``<root>/<version>/{scene, sample, sample_data,
ego_pose, calibrated_sensor, sensor}.json`` with the standard library. Each sample's
LIDAR_TOP key frame (the ``sample_data`` row with that ``sample_token``,
``is_key_frame`` true and a ``calibrated_sensor`` whose ``sensor`` has channel
``LIDAR_TOP``) gives ``ego2global`` (its ``ego_pose``) and ``lidar2ego`` (its
``calibrated_sensor``); rotations are wxyz quaternions, normalised. Only dict indexes
are built, so the ~2.6M rows of v1.0-trainval's ``sample_data`` are scanned once.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from dego._typing import typechecked
from dego.data.keyframes import (
    Keyframe,
    checked_numbers,
    checked_quaternion,
    keyframe_pose_matrices,
)

PathLike = str | os.PathLike[str]

__all__ = ["load_nuscenes_keyframes"]

_TABLES = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor")
_CHANNEL = "LIDAR_TOP"


@typechecked
def load_nuscenes_keyframes(root: PathLike, version: str = "v1.0-trainval") -> tuple[Keyframe, ...]:
    """Every sample of a nuScenes release as a :class:`Keyframe` (LIDAR_TOP poses).

    Args:
        root: the nuScenes data root (holding ``<version>/``).
        version: ``"v1.0-trainval"``, ``"v1.0-mini"``, ``"v1.0-test"``, ...

    Returns:
        Keyframes grouped by scene in ``scene.json`` order and, within a scene, in
        temporal order (``first_sample_token`` then ``next``); ``scene`` is the scene's
        name and ``timestamp`` the sample's (microseconds).

    Raises:
        FileNotFoundError: naming the missing root, version directory or table.
        ValueError: naming the table and token for a dangling reference, a sample without
            a LIDAR_TOP key frame (or with two), a broken ``next`` chain, a missing field
            or an unreadable table.
    """
    base = Path(root)
    if not base.is_dir():
        raise FileNotFoundError(f"root: {base} is not a directory")
    folder = base / version
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no nuScenes tables for version {version!r} here")
    tables = {name: _read_table(folder / f"{name}.json") for name in _TABLES}

    sensors = _index(tables["sensor"], "sensor")
    calibrated = _index(tables["calibrated_sensor"], "calibrated_sensor")
    lidar_calibrations = set()
    for token, row in calibrated.items():
        sensor = _get(sensors, _field(row, "sensor_token", "calibrated_sensor", token), "sensor")
        if sensor.get("channel") == _CHANNEL:
            lidar_calibrations.add(token)

    # one pass over sample_data: the LIDAR_TOP key frames, by sample token
    lidar_frames: dict[str, Mapping[str, Any]] = {}
    for row in tables["sample_data"]:
        if not isinstance(row, Mapping) or not row.get("is_key_frame"):
            continue
        sd_token = _field(row, "token", "sample_data", "?")
        cs_token = _field(row, "calibrated_sensor_token", "sample_data", sd_token)
        if cs_token not in calibrated:
            raise ValueError(
                f"sample_data.json: row {sd_token!r} references calibrated_sensor {cs_token!r}, "
                "which is not in calibrated_sensor.json"
            )
        if cs_token not in lidar_calibrations:
            continue
        sample_token = _field(row, "sample_token", "sample_data", sd_token)
        if sample_token in lidar_frames:
            raise ValueError(
                f"sample_data.json: sample {sample_token!r} has two {_CHANNEL} key frames "
                f"({lidar_frames[sample_token]['token']!r} and {sd_token!r})"
            )
        lidar_frames[sample_token] = row

    samples = _index(tables["sample"], "sample")
    ego_poses = _index(tables["ego_pose"], "ego_pose")
    order: list[tuple[str, str]] = []  # (sample token, scene name)
    for scene in tables["scene"]:
        if not isinstance(scene, Mapping):
            raise ValueError("scene.json: expected a list of objects")
        scene_token = _field(scene, "token", "scene", "?")
        name = _field(scene, "name", "scene", scene_token)
        token = _field(scene, "first_sample_token", "scene", scene_token)
        where = f"scene.json: scene {scene_token!r} first_sample_token"
        visited: set[str] = set()
        while token:
            if token not in samples:
                raise ValueError(f"{where} {token!r} is not in sample.json")
            if token in visited:
                raise ValueError(
                    f"sample.json: the next chain of scene {name!r} loops at {token!r}"
                )
            visited.add(token)
            sample = samples[token]
            owner = _field(sample, "scene_token", "sample", token)
            if owner != scene_token:
                raise ValueError(
                    f"sample.json: sample {token!r} belongs to scene {owner!r}, but is linked "
                    f"from scene {scene_token!r}"
                )
            order.append((token, name))
            where = f"sample.json: sample {token!r} next"
            token = _field(sample, "next", "sample", token)
    if len(order) != len(samples):
        linked = {token for token, _ in order}
        missing = next(token for token in samples if token not in linked)
        raise ValueError(
            f"sample.json: sample {missing!r} is not reachable from its scene's "
            f"first_sample_token ({len(samples) - len(order)} of {len(samples)} samples)"
        )

    stamps: list[int] = []
    lidar_t, lidar_q, ego_t, ego_q = [], [], [], []
    for token, _ in order:
        frame = lidar_frames.get(token)
        if frame is None:
            raise ValueError(
                f"sample_data.json: sample {token!r} has no {_CHANNEL} key frame "
                "(is_key_frame true, LIDAR_TOP calibrated_sensor)"
            )
        sd_token = frame["token"]
        cs_token = frame["calibrated_sensor_token"]
        pose_token = _field(frame, "ego_pose_token", "sample_data", sd_token)
        translation, rotation = _pose(calibrated[cs_token], "calibrated_sensor", cs_token)
        lidar_t.append(translation)
        lidar_q.append(rotation)
        translation, rotation = _pose(
            _get(ego_poses, pose_token, "ego_pose"), "ego_pose", pose_token
        )
        ego_t.append(translation)
        ego_q.append(rotation)
        stamp = _field(samples[token], "timestamp", "sample", token)
        if isinstance(stamp, bool) or not isinstance(stamp, int):
            raise ValueError(
                f"sample.json: sample {token!r} timestamp: expected an int, got {stamp!r}"
            )
        stamps.append(stamp)
    if not order:
        return ()
    lidar2ego = keyframe_pose_matrices(np.stack(lidar_t), np.stack(lidar_q))
    ego2global = keyframe_pose_matrices(np.stack(ego_t), np.stack(ego_q))
    return tuple(
        Keyframe(token, scene, stamps[i], lidar2ego[i].clone(), ego2global[i].clone())
        for i, (token, scene) in enumerate(order)
    )


def _read_table(path: Path) -> list[Any]:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing nuScenes table")
    try:
        with path.open("rb") as stream:
            rows = json.load(stream)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a readable JSON table ({exc})") from None
    except RecursionError:  # e.g. "[" * 100000: nesting deeper than the parser's stack
        raise ValueError(f"{path}: not a readable JSON table (nested too deeply)") from None
    if not isinstance(rows, list):
        raise ValueError(f"{path}: expected a JSON list of objects, got {type(rows).__name__}")
    return rows


def _index(rows: list[Any], table: str) -> dict[str, Mapping[str, Any]]:
    """``{token: row}``; ``ValueError`` naming the table for non-objects or duplicates."""
    index: dict[str, Mapping[str, Any]] = {}
    for row in rows:
        if not isinstance(row, Mapping):
            raise ValueError(f"{table}.json: expected a list of objects, got {row!r:.80}")
        token = _field(row, "token", table, "?")
        if token in index:
            raise ValueError(f"{table}.json: duplicate token {token!r}")
        index[token] = row
    return index


def _field(row: Mapping[str, Any], key: str, table: str, token: str) -> Any:
    try:
        return row[key]
    except KeyError:
        raise ValueError(f"{table}.json: row {token!r} has no field {key!r}") from None


def _get(index: Mapping[str, Mapping[str, Any]], token: Any, table: str) -> Mapping[str, Any]:
    try:
        return index[token]
    except (KeyError, TypeError):
        raise ValueError(
            f"{table}.json: token {token!r} is referenced but not in the table"
        ) from None


def _pose(row: Mapping[str, Any], table: str, token: str) -> tuple[np.ndarray, np.ndarray]:
    """``(3,)`` translation and ``(4,)`` wxyz rotation of an ego_pose / calibrated_sensor row."""
    where = f"{table}.json: {token!r}"
    translation = checked_numbers(
        _field(row, "translation", table, token), (3,), f"{where}: translation"
    )
    rotation = checked_quaternion(_field(row, "rotation", table, token), f"{where}: rotation")
    return translation, rotation
