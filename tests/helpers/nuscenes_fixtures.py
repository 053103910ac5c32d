"""Fabricated nuScenes keyframes written in the real formats: mmdet3d infos pickles
(0.x ``infos``, 1.x ``data_list``) and the nuScenes JSON tables, from one set of poses.

Poses are realistic: the ego drives 3-5 m between keyframes along a curve (sometimes
standing still), with small pitch/roll; LIDAR_TOP sits near (0.94, 0, 1.84) with nuScenes'
~-90 deg yaw plus a small per-scene offset. Scenes are long enough that more than 8
frames lie within 39 m of a reference and others lie beyond it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from tests.reference.sparseocc_origins import transform_matrix

SCENE_LENGTHS = (24, 17, 1)


@dataclasses.dataclass(frozen=True)
class FakeFrame:
    token: str
    scene_token: str
    scene_name: str
    timestamp: int
    lidar_t: tuple[float, float, float]
    lidar_q: tuple[float, float, float, float]  # wxyz
    ego_t: tuple[float, float, float]
    ego_q: tuple[float, float, float, float]


def _token(rng: np.random.Generator) -> str:
    return "".join(f"{b:02x}" for b in rng.integers(0, 256, 16))


def _quaternion(yaw: float, pitch: float, roll: float) -> tuple[float, float, float, float]:
    """wxyz of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def make_frames(seed: int = 0, lengths: tuple[int, ...] = SCENE_LENGTHS) -> list[FakeFrame]:
    """Keyframes of ``len(lengths)`` scenes, scene by scene, each in temporal order."""
    rng = np.random.default_rng(seed)
    frames = []
    for s, length in enumerate(lengths):
        scene_token = _token(rng)
        name = f"scene-{rng.integers(1, 1200):04d}"
        lidar_t = (
            0.94 + rng.normal(0, 0.02),
            rng.normal(0, 0.02),
            1.84 + rng.normal(0, 0.02),
        )
        lidar_q = _quaternion(
            -math.pi / 2 + rng.normal(0, 0.01), rng.normal(0, 0.003), rng.normal(0, 0.003)
        )
        x, y = 400.0 + 700.0 * s + rng.uniform(-50, 50), 1100.0 + rng.uniform(-50, 50)
        heading = rng.uniform(-math.pi, math.pi)
        curvature = rng.uniform(-0.02, 0.02)
        stamp = int(1_531_000_000_000_000 + rng.integers(0, 10**12))
        for i in range(length):
            if i:
                step = 0.0 if rng.random() < 0.1 else rng.uniform(3.0, 5.0)
                heading += curvature * step
                x += step * math.cos(heading)
                y += step * math.sin(heading)
                stamp += int(500_000 + rng.integers(-2000, 2000))
            z = 0.3 * math.sin(0.05 * i) + rng.normal(0, 0.01)
            ego_q = _quaternion(heading, rng.normal(0, 0.01), rng.normal(0, 0.01))
            frames.append(
                FakeFrame(_token(rng), scene_token, name, stamp, lidar_t, lidar_q, (x, y, z), ego_q)
            )
    return frames


# ----------------------------------------------------------------------------------------
# infos pickles
# ----------------------------------------------------------------------------------------


def _as(value: tuple[float, ...], i: int) -> Any:
    """Vary the container as real files do: list, tuple or numpy array."""
    return [list(value), tuple(value), np.array(value)][i % 3]


def legacy_info(frame: FakeFrame, i: int, scene_keys: tuple[str, ...]) -> dict[str, Any]:
    """One mmdet3d 0.x / BEVDet info dict, irrelevant keys included."""
    rng = np.random.default_rng(i)
    cams = {
        cam: {
            "data_path": f"./data/nuscenes/samples/{cam}/n015-{i}.jpg",
            "type": cam,
            "sample_data_token": f"{cam}-{frame.token}",
            "sensor2ego_translation": [1.7, 0.01, 1.5],
            "sensor2ego_rotation": [0.5, -0.5, 0.5, -0.5],
            "ego2global_translation": list(frame.ego_t),
            "ego2global_rotation": list(frame.ego_q),
            "timestamp": frame.timestamp + 12,
            "sensor2lidar_rotation": rng.normal(size=(3, 3)),
            "sensor2lidar_translation": rng.normal(size=3),
            "cam_intrinsic": np.array([[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0, 0, 1]]),
        }
        for cam in ("CAM_FRONT", "CAM_BACK")
    }
    info: dict[str, Any] = {
        "lidar_path": f"./data/nuscenes/samples/LIDAR_TOP/n015-{i}.pcd.bin",
        "token": frame.token,
        "sweeps": [
            {
                "data_path": f"./data/nuscenes/sweeps/LIDAR_TOP/{i}-{k}.pcd.bin",
                "type": "lidar",
                "sample_data_token": f"sweep-{k}-{frame.token}",
                "sensor2lidar_rotation": np.eye(3),
                "sensor2lidar_translation": np.zeros(3),
                "timestamp": frame.timestamp - 50_000 * (k + 1),
            }
            for k in range(2)
        ],
        "cams": cams,
        "lidar2ego_translation": _as(frame.lidar_t, i),
        "lidar2ego_rotation": _as(frame.lidar_q, i + 1),
        "ego2global_translation": _as(frame.ego_t, i + 2),
        "ego2global_rotation": _as(frame.ego_q, i),
        "timestamp": frame.timestamp if i % 2 else np.int64(frame.timestamp),
        "gt_boxes": rng.normal(size=(3, 7)),
        "gt_names": np.array(["car", "pedestrian", "barrier"]),
        "gt_velocity": rng.normal(size=(3, 2)),
        "num_lidar_pts": np.array([12, 3, 40]),
        "valid_flag": np.array([True, True, False]),
        "occ_path": f"./data/nuscenes/gts/{frame.scene_name}/{frame.token}",
        "lidar_score": np.float64(0.5),
    }
    for key in scene_keys:
        info[key] = frame.scene_name if key == "scene_name" else frame.scene_token
    return info


def matrix(translation: tuple[float, ...], rotation: tuple[float, ...]) -> np.ndarray:
    return transform_matrix(np.array(translation), np.array(rotation))


def v2_info(frame: FakeFrame, i: int) -> dict[str, Any]:
    """One mmdet3d 1.x ``data_list`` entry (timestamps in seconds)."""
    return {
        "sample_idx": i,
        "token": frame.token,
        "timestamp": frame.timestamp / 1e6,
        "ego2global": matrix(frame.ego_t, frame.ego_q).tolist(),
        "images": {"CAM_FRONT": {"img_path": f"{i}.jpg", "cam2img": [[1266.4, 0, 816.3]] * 3}},
        "lidar_points": {
            "num_pts_feats": 5,
            "lidar_path": f"n015-{i}.pcd.bin",
            "lidar2ego": matrix(frame.lidar_t, frame.lidar_q).tolist(),
        },
        "instances": [{"bbox_3d": [0.0] * 7, "bbox_label_3d": 0}],
    }


def write_infos(
    path: Path,
    frames: list[FakeFrame],
    *,
    protocol: int = 2,
    layout: str = "infos",
    scene_keys: tuple[str, ...] = ("scene_token", "scene_name"),
) -> Path:
    """Pickle ``frames`` as mmdet3d's converters do (mmcv dumps with protocol 2)."""
    if layout == "data_list":
        data: Any = {
            "metainfo": {"dataset": "nuscenes", "version": "v1.0-trainval", "info_version": "1.1"},
            "data_list": [v2_info(f, i) for i, f in enumerate(frames)],
        }
    else:
        infos = [legacy_info(f, i, scene_keys) for i, f in enumerate(frames)]
        data = (
            infos
            if layout == "bare"
            else {"infos": infos, "metadata": {"version": "v1.0-trainval"}}
        )
    with path.open("wb") as stream:
        pickle.dump(data, stream, protocol=protocol)
    return path


def reference_infos(frames: list[FakeFrame]) -> list[dict[str, Any]]:
    """Plain info dicts for the SparseOcc reference (scene_name set)."""
    return [
        {
            "token": f.token,
            "scene_name": f.scene_name,
            "lidar2ego_translation": list(f.lidar_t),
            "lidar2ego_rotation": list(f.lidar_q),
            "ego2global_translation": list(f.ego_t),
            "ego2global_rotation": list(f.ego_q),
        }
        for f in frames
    ]


# ----------------------------------------------------------------------------------------
# nuScenes JSON tables
# ----------------------------------------------------------------------------------------


def make_tables(frames: list[FakeFrame], seed: int = 1) -> dict[str, list[dict[str, Any]]]:
    """The six tables, rows shuffled; camera rows and lidar sweeps mixed in."""
    rng = np.random.default_rng(seed)
    lidar_sensor, cam_sensor = _token(rng), _token(rng)
    sensor = [
        {"token": cam_sensor, "channel": "CAM_FRONT", "modality": "camera"},
        {"token": lidar_sensor, "channel": "LIDAR_TOP", "modality": "lidar"},
    ]
    calibrated, ego_pose, sample_data, sample, scene = [], [], [], [], []
    by_scene: dict[str, list[FakeFrame]] = {}
    for f in frames:
        by_scene.setdefault(f.scene_token, []).append(f)
    for scene_token, group in by_scene.items():
        cam_cs, lidar_cs = _token(rng), _token(rng)
        calibrated.append(
            {
                "token": cam_cs,
                "sensor_token": cam_sensor,
                "translation": [1.70, 0.02, 1.51],
                "rotation": [0.4998, -0.5030, 0.4997, -0.4975],
                "camera_intrinsic": [[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0, 0, 1]],
            }
        )
        calibrated.append(
            {
                "token": lidar_cs,
                "sensor_token": lidar_sensor,
                "translation": list(group[0].lidar_t),
                "rotation": list(group[0].lidar_q),
                "camera_intrinsic": [],
            }
        )
        scene.append(
            {
                "token": scene_token,
                "log_token": _token(rng),
                "nbr_samples": len(group),
                "first_sample_token": group[0].token,
                "last_sample_token": group[-1].token,
                "name": group[0].scene_name,
                "description": "fabricated",
            }
        )
        for i, f in enumerate(group):
            sample.append(
                {
                    "token": f.token,
                    "timestamp": f.timestamp,
                    "prev": group[i - 1].token if i else "",
                    "next": group[i + 1].token if i + 1 < len(group) else "",
                    "scene_token": scene_token,
                }
            )
            rows = [  # (channel cs, key frame, ego pose, time offset)
                (lidar_cs, True, (f.ego_t, f.ego_q), 0),
                (cam_cs, True, (tuple(np.add(f.ego_t, 0.3)), f.ego_q), 12),
                (lidar_cs, False, (tuple(np.add(f.ego_t, 1.1)), f.ego_q), -50_000),
                (lidar_cs, False, (tuple(np.add(f.ego_t, 2.2)), f.ego_q), -100_000),
                (cam_cs, False, (tuple(np.add(f.ego_t, 0.7)), f.ego_q), -80_000),
            ]
            for cs, key, (t, q), dt in rows:
                pose_token = _token(rng)
                ego_pose.append(
                    {
                        "token": pose_token,
                        "timestamp": f.timestamp + dt,
                        "rotation": list(q),
                        "translation": list(t),
                    }
                )
                sample_data.append(
                    {
                        "token": _token(rng),
                        "sample_token": f.token,
                        "ego_pose_token": pose_token,
                        "calibrated_sensor_token": cs,
                        "timestamp": f.timestamp + dt,
                        "fileformat": "pcd" if cs == lidar_cs else "jpg",
                        "is_key_frame": key,
                        "height": 0,
                        "width": 0,
                        "filename": f"samples/{f.token}-{dt}",
                        "prev": "",
                        "next": "",
                    }
                )
    for rows in (calibrated, ego_pose, sample_data, sample):
        order = rng.permutation(len(rows))
        rows[:] = [rows[k] for k in order]
    return {
        "scene": scene,
        "sample": sample,
        "sample_data": sample_data,
        "ego_pose": ego_pose,
        "calibrated_sensor": calibrated,
        "sensor": sensor,
    }


def write_tables(
    root: Path, tables: dict[str, list[dict[str, Any]]], version: str = "v1.0-trainval"
) -> Path:
    folder = root / version
    folder.mkdir(parents=True, exist_ok=True)
    for name, rows in tables.items():
        (folder / f"{name}.json").write_text(json.dumps(rows, indent=0))
    return root
