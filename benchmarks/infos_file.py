"""A realistic mmdet3d nuScenes infos pickle (v1.0 layout), generated from a seed.

The file :func:`write_infos` writes has the layout of ``nuscenes_infos_val.pkl`` as
mmdet3d 0.x's ``tools/create_data.py nuscenes`` writes it, with BEVFormer's additions
(``prev``, ``next``, ``can_bus``, ``frame_idx``, ``scene_token``) and Occ3D's
``occ_path``: the file BEVFormer, SparseOcc, FlashOcc and GaussianFormer read.
Values are random (seeded, ``numpy.random.default_rng``); keys, types, shapes, dtypes,
counts and the objects shared between entries are the converter's.

``{"infos": [info, ...], "metadata": {"version": "v1.0-trainval"}}``, ``samples`` infos
(6,019 by default: the val split) in scenes of 40 keyframes (``scene-0001``...), each
``info`` a dict, in the converter's key order:

=========================  ===============================================================
``lidar_path``             str, ``./data/nuscenes/samples/LIDAR_TOP/<log>__LIDAR_TOP__<t>.pcd.bin``
``token``                  str, 32 hex digits (the sample token)
``prev``, ``next``         str, the neighbouring sample tokens, ``""`` at a scene's ends
``can_bus``                ndarray float64 (18,)
``frame_idx``              int, index of the keyframe in its scene
``sweeps``                 list of ``sweeps`` dicts (10 by default; none for the first
                           keyframe of a scene: nothing precedes it), each: ``data_path``
                           (str, ``./data/nuscenes/sweeps/LIDAR_TOP/...``), ``type``
                           (``"lidar"``), ``sample_data_token`` (str), ``sensor2ego_translation``
                           (list of 3 float), ``sensor2ego_rotation`` (list of 4 float),
                           ``ego2global_translation`` (3 float), ``ego2global_rotation``
                           (4 float), ``timestamp`` (int, microseconds),
                           ``sensor2lidar_rotation`` (ndarray float64 (3, 3), Fortran order:
                           the converter stores ``R.T``), ``sensor2lidar_translation``
                           (ndarray float64 (3,))
``cams``                   dict of the 6 cameras ``CAM_FRONT``, ``CAM_FRONT_RIGHT``,
                           ``CAM_FRONT_LEFT``, ``CAM_BACK``, ``CAM_BACK_LEFT``,
                           ``CAM_BACK_RIGHT``, each a sweep's keys (``type`` the camera's
                           name, ``data_path`` ``./data/nuscenes/samples/<CAM>/...jpg``) and
                           ``cam_intrinsic`` (ndarray float64 (3, 3))
``scene_token``            str, 32 hex digits
``lidar2ego_translation``  list of 3 float; ``lidar2ego_rotation`` list of 4 float
``ego2global_translation`` list of 3 float; ``ego2global_rotation`` list of 4 float
``timestamp``              int, microseconds
``gt_boxes``               ndarray float64 (n, 7): x, y, z, w, l, h, yaw
``gt_names``               ndarray ``<U`` (n,): mmdet3d's 10 class names and the unmapped
                           nuScenes categories (``movable_object.debris``...); the width is
                           the sample's longest name, as ``np.array(names)`` makes it
``gt_velocity``            ndarray float64 (n, 2), about 3 % NaN (no neighbouring annotation)
``num_lidar_pts``          ndarray int64 (n,); ``num_radar_pts`` ndarray int64 (n,)
``valid_flag``             ndarray bool (n,): ``num_lidar_pts + num_radar_pts > 0``
``occ_path``               str, ``./data/occ3d/gts/scene-XXXX/<token>``
=========================  ===============================================================

n, the boxes of a sample, is uniform in 20-50: 35 on average, as in nuScenes
(1,166,187 annotations over 34,149 trainval keyframes). As in the converter, the calibration
lists (``lidar2ego_*``, the sweeps' ``sensor2ego_*``, each camera's ``sensor2ego_*``) are
one list object per scene and sensor (``nusc.get`` returns the table's record), and the
last sweep of a keyframe is the previous keyframe's lidar frame, whose ego pose lists it
shares; the pickle stores those as memo references.

Protocol: mmcv's and mmengine's ``dump`` (what ``create_data.py`` calls) default to
protocol 2; converters that call ``pickle.dump`` directly (BEVDet/FlashOcc's
``create_data_bevdet.py``) write Python's default, 4 since Python 3.8. At the defaults
(6,019 samples, 10 sweeps, seed 0) the file is 87.6 MB at protocol 4 and 115.2 MB at
protocol 2 (array bytes go through ``_codecs.encode`` as latin-1 text there).

    python benchmarks/infos_file.py OUT [--samples 6019] [--sweeps 10] [--protocol 2]
                                        [--seed 0]
"""

from __future__ import annotations

import argparse
import pickle
import time
from pathlib import Path
from typing import Any

import numpy as np

VALIDATION_SAMPLES = 6019  # nuScenes (and Occ3D-nuScenes) val
SCENE_KEYFRAMES = 40
CAMERAS = (
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_FRONT_LEFT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
)
# mmdet3d's class names and the nuScenes categories its NameMapping leaves as they are,
# with roughly the val split's frequencies.
NAMES = (
    "car",
    "pedestrian",
    "barrier",
    "traffic_cone",
    "truck",
    "trailer",
    "bus",
    "construction_vehicle",
    "motorcycle",
    "bicycle",
    "movable_object.pushable_pullable",
    "movable_object.debris",
    "static_object.bicycle_rack",
    "vehicle.emergency.police",
    "human.pedestrian.stroller",
    "animal",
)
_NAME_WEIGHTS = np.array([40, 20, 14, 9, 6, 2, 1.5, 1.2, 1, 1, 1.5, 1, 0.9, 0.3, 0.3, 0.3])
_NAME_P = _NAME_WEIGHTS / _NAME_WEIGHTS.sum()
_LIDAR_PERIOD_US = 50_000  # 20 Hz lidar, keyframes at 2 Hz


def _tokens(rng: np.random.Generator, count: int) -> list[str]:
    """``count`` 32-hex-digit tokens."""
    raw = rng.bytes(16 * count)
    return [raw[i : i + 16].hex() for i in range(0, 16 * count, 16)]


def _rotations(rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` random rotation matrices (count, 3, 3), float64."""
    q, r = np.linalg.qr(rng.standard_normal((count, 3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    return q * np.sign(np.linalg.det(q))[:, None, None]


def _quaternions(rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` unit quaternions (count, 4), w first, w >= 0."""
    q = rng.standard_normal((count, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def _calibration(rng: np.random.Generator) -> tuple[list[float], list[float]]:
    """One calibrated-sensor record's (translation, rotation) lists."""
    translation = rng.normal(0.0, 1.0, 3) + np.array([0.9, 0.0, 1.8])
    return translation.tolist(), _quaternions(rng, 1)[0].tolist()


def _sensor(
    rng: np.random.Generator,
    path: str,
    kind: str,
    calibration: tuple[list[float], list[float]],
    pose: tuple[list[float], list[float]],
    timestamp: int,
) -> dict[str, Any]:
    """One sweep or camera entry, keys in ``obtain_sensor2top``'s order."""
    return {
        "data_path": path,
        "type": kind,
        "sample_data_token": _tokens(rng, 1)[0],
        "sensor2ego_translation": calibration[0],
        "sensor2ego_rotation": calibration[1],
        "ego2global_translation": pose[0],
        "ego2global_rotation": pose[1],
        "timestamp": timestamp,
        "sensor2lidar_rotation": _rotations(rng, 1)[0].T,  # R.T: Fortran order, as stored
        "sensor2lidar_translation": rng.normal(0.0, 0.5, 3),
    }


def _pose(rng: np.random.Generator, origin: np.ndarray) -> tuple[list[float], list[float]]:
    """One ego_pose record's (translation, rotation) lists near ``origin``."""
    translation = origin + rng.normal(0.0, 2.0, 3) * [1.0, 1.0, 0.0]
    return translation.tolist(), _quaternions(rng, 1)[0].tolist()


def _boxes(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A sample's annotations, as ``_fill_trainval_infos`` turns them into arrays."""
    n = int(rng.integers(20, 51))
    locs = rng.uniform([-50.0, -50.0, -3.0], [50.0, 50.0, 1.0], (n, 3))
    dims = rng.uniform([0.4, 0.4, 0.8], [3.0, 12.0, 4.0], (n, 3))
    rots = rng.uniform(-np.pi, np.pi, (n, 1))
    velocity = rng.normal(0.0, 2.0, (n, 2))
    velocity[rng.random(n) < 0.03] = np.nan
    names = np.array([NAMES[i] for i in rng.choice(len(NAMES), n, p=_NAME_P)])
    lidar = np.array(rng.lognormal(3.0, 2.0, n).astype(np.int64).tolist())
    radar = np.array(rng.poisson(0.8, n).tolist())
    return {
        "gt_boxes": np.concatenate([locs, dims, -rots - np.pi / 2], axis=1),
        "gt_names": names,
        "gt_velocity": velocity.reshape(-1, 2),
        "num_lidar_pts": lidar,
        "num_radar_pts": radar,
        "valid_flag": np.array([(a + b) > 0 for a, b in zip(lidar, radar, strict=True)], bool),
    }


def make_infos(samples: int = VALIDATION_SAMPLES, sweeps: int = 10, seed: int = 0) -> dict:
    """The infos structure (see the module docstring); deterministic for a seed."""
    if samples < 1 or sweeps < 0:
        raise ValueError(f"samples >= 1 and sweeps >= 0 expected, got {samples}, {sweeps}")
    rng = np.random.default_rng(seed)
    tokens = _tokens(rng, samples)
    infos: list[dict[str, Any]] = []
    for start in range(0, samples, SCENE_KEYFRAMES):
        count = min(SCENE_KEYFRAMES, samples - start)
        scene = start // SCENE_KEYFRAMES + 1
        scene_token = _tokens(rng, 1)[0]
        month, day = (int(v) for v in rng.integers([1, 1], [13, 29]))
        log = f"n{(8, 15)[scene % 2]:03d}-2018-{month:02d}-{day:02d}-11-22-45+0800"
        lidar_calibration = _calibration(rng)
        camera_calibration = {camera: _calibration(rng) for camera in CAMERAS}
        origin = rng.uniform(300.0, 2000.0, 3) * [1.0, 1.0, 0.0]
        t0 = 1_532_402_927_647_951 + int(rng.integers(0, 10**10))
        previous_pose: tuple[list[float], list[float]] | None = None
        for frame in range(count):
            index = start + frame
            token, timestamp = tokens[index], t0 + frame * 500_000
            origin = origin + np.array([3.0, 0.5, 0.0])
            pose = _pose(rng, origin)
            swept = []
            for k in range(sweeps if frame else 0):
                t = timestamp - (k + 1) * _LIDAR_PERIOD_US
                swept.append(
                    _sensor(
                        rng,
                        f"./data/nuscenes/{'samples' if k == 9 else 'sweeps'}/LIDAR_TOP/"
                        f"{log}__LIDAR_TOP__{t}.pcd.bin",
                        "lidar",
                        lidar_calibration,
                        previous_pose if previous_pose and k == 9 else _pose(rng, origin),
                        t,
                    )
                )
            cams = {}
            for camera in CAMERAS:
                t = timestamp + int(rng.integers(-40_000, 40_000))
                cams[camera] = _sensor(
                    rng,
                    f"./data/nuscenes/samples/{camera}/{log}__{camera}__{t}.jpg",
                    camera,
                    camera_calibration[camera],
                    _pose(rng, origin),
                    t,
                )
                focal = rng.uniform(1250.0, 1270.0)
                cams[camera]["cam_intrinsic"] = np.array(
                    [[focal, 0.0, rng.uniform(800.0, 830.0)], [0.0, focal, 450.0], [0, 0, 1.0]]
                )
            infos.append(
                {
                    "lidar_path": f"./data/nuscenes/samples/LIDAR_TOP/"
                    f"{log}__LIDAR_TOP__{timestamp}.pcd.bin",
                    "token": token,
                    "prev": tokens[index - 1] if frame else "",
                    "next": tokens[index + 1] if frame + 1 < count else "",
                    "can_bus": rng.normal(0.0, 10.0, 18),
                    "frame_idx": frame,
                    "sweeps": swept,
                    "cams": cams,
                    "scene_token": scene_token,
                    "lidar2ego_translation": lidar_calibration[0],
                    "lidar2ego_rotation": lidar_calibration[1],
                    "ego2global_translation": pose[0],
                    "ego2global_rotation": pose[1],
                    "timestamp": timestamp,
                    **_boxes(rng),
                    "occ_path": f"./data/occ3d/gts/scene-{scene:04d}/{token}",
                }
            )
            previous_pose = pose
    return {"infos": infos, "metadata": {"version": "v1.0-trainval"}}


def write_infos(
    path: str | Path,
    samples: int = VALIDATION_SAMPLES,
    sweeps: int = 10,
    protocol: int = 2,
    seed: int = 0,
) -> Path:
    """Write :func:`make_infos` ``(samples, sweeps, seed)`` to ``path`` with ``pickle``
    ``protocol`` (2 by default: mmcv's ``dump``); returns the path."""
    path = Path(path)
    data = make_infos(samples, sweeps, seed)
    with path.open("wb") as stream:
        pickle.dump(data, stream, protocol=protocol)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("out", type=Path, help="the pickle to write")
    parser.add_argument("--samples", type=int, default=VALIDATION_SAMPLES)
    parser.add_argument("--sweeps", type=int, default=10, help="lidar sweeps per keyframe")
    parser.add_argument("--protocol", type=int, default=2, choices=range(6))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    start = time.perf_counter()
    path = write_infos(args.out, args.samples, args.sweeps, args.protocol, args.seed)
    print(
        f"{path}: {path.stat().st_size / 1e6:.1f} MB ({args.samples} samples, "
        f"{args.sweeps} sweeps, protocol {args.protocol}) in {time.perf_counter() - start:.1f} s"
    )


if __name__ == "__main__":
    main()
