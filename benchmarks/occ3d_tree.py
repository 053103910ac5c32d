"""A synthetic Occ3D-nuScenes release for the evaluation benchmark: ground truth in the
release layout, SparseOcc-style predictions and an mmdet3d-style infos file.

Each scene is a straight street (road, sidewalks, terrain, building blocks of varying
height, trees, parked cars and trucks, pedestrians, barriers, cones, bicycles) that the
ego drives along at about 8 m/s; a keyframe every 0.5 s sees the 200 x 200 x 16 window
of the street around the ego, as nuScenes keyframes do (40 per scene). Predictions
perturb the ground truth (missed voxels, confused classes, thickened surfaces).
"""

from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import torch

from dego import Occ3DLabels, save_occ3d_labels
from dego.classes import FREE_LABEL
from dego.data import LABELS_FILENAME

VOXEL = 0.4
STEP_VOXELS = 10  # 4 m between keyframes
LIDAR2EGO_TRANSLATION = [0.943713, 0.0, 1.84023]  # nuScenes LIDAR_TOP
LIDAR2EGO_ROTATION = [0.7071067811865476, 0.0, 0.0, -0.7071067811865476]  # yaw -90 deg


def street(length: int, generator: torch.Generator) -> torch.Tensor:
    """``(length, 200, 16)`` uint8 labels of one street along x."""

    def randint(low: int, high: int) -> int:
        return int(torch.randint(low, high, (1,), generator=generator))

    world = torch.full((length, 200, 16), FREE_LABEL, dtype=torch.uint8)
    world[:, :, 0] = 14  # terrain
    world[:, 80:120, 0:2] = 11  # road
    world[:, 70:80, 0:2] = 13  # sidewalks
    world[:, 120:130, 0:2] = 13
    x = 0
    while x < length:  # building blocks with gaps, on both sides
        width, height = randint(15, 40), randint(6, 15)
        for y0, y1 in ((52, 64), (136, 148)):
            if randint(0, 4):
                world[x : x + width, y0:y1, 0:height] = 15
        x += width + randint(2, 10)
    for x in range(randint(0, 10), length - 8, randint(18, 30)):  # trees
        for y in (66, 132):
            world[x : x + 2, y : y + 2, 2:6] = 16
            world[x - 3 : x + 5, y - 3 : y + 5, 6:11] = 16
    objects = [  # label, size in voxels, lateral range
        (4, (11, 5, 4), (82, 115)),  # cars
        (10, (20, 6, 8), (82, 112)),  # trucks
        (7, (2, 2, 5), (71, 79)),  # pedestrians
        (7, (2, 2, 5), (121, 129)),
        (1, (1, 6, 3), (80, 118)),  # barriers
        (8, (1, 1, 2), (80, 118)),  # traffic cones
        (2, (4, 1, 3), (71, 129)),  # bicycles
    ]
    for _ in range(length // 4):
        label, (sx, sy, sz), (y_low, y_high) = objects[randint(0, len(objects))]
        x0, y0 = randint(0, length - sx), randint(y_low, y_high - sy)
        world[x0 : x0 + sx, y0 : y0 + sy, 2 : 2 + sz] = label
    return world


def perturb(semantics: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """An imperfect prediction: 10% of occupied voxels missed, 5% confused, surfaces
    grown by one voxel in 20% of the columns."""
    occupied = semantics != FREE_LABEL
    draw = torch.rand((3, *semantics.shape), generator=generator)
    pred = semantics.clone()
    pred[occupied & (draw[0] < 0.10)] = FREE_LABEL
    confused = occupied & (draw[1] < 0.05)
    pred[confused] = torch.randint(0, FREE_LABEL, semantics.shape, generator=generator)[
        confused
    ].to(torch.uint8)
    below = pred[:, :, :-1]
    grow = (pred[:, :, 1:] == FREE_LABEL) & (below != FREE_LABEL) & (draw[2, :, :, 1:] < 0.2)
    pred[:, :, 1:] = torch.where(grow, below, pred[:, :, 1:])
    return pred


def _quaternion_yaw(yaw: float) -> list[float]:
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


def write_tree(root: Path, scenes: int, frames: int, seed: int = 0) -> tuple[Path, Path, Path]:
    """Write ``root/gt/gts/<scene>/<token>/labels.npz``, ``root/pred/<token>.npz`` (key
    ``pred``) and ``root/nuscenes_infos_val.pkl``; returns the three paths."""
    generator = torch.Generator().manual_seed(seed)
    gt_root, pred_root = root / "gt", root / "pred"
    pred_root.mkdir(parents=True, exist_ok=True)
    infos = []
    for s in range(scenes):
        scene_name, scene_token = f"scene-{s + 1:04d}", f"{seed:04d}scene{s:024d}"
        world = street(200 + STEP_VOXELS * frames, generator)
        heading = 0.02 * (s - scenes / 2)  # the street's direction in the world
        for f in range(frames):
            token = f"{seed:04d}{s:04d}sample{f:018d}"
            semantics = world[STEP_VOXELS * f : STEP_VOXELS * f + 200].clone()
            occupied = semantics != FREE_LABEL
            seen = torch.rand(semantics.shape, generator=generator) < 0.7
            labels = Occ3DLabels(semantics, occupied | seen, occupied | (seen & ~seen.roll(1, 0)))
            save_occ3d_labels(gt_root / "gts" / scene_name / token / LABELS_FILENAME, labels)
            pred = perturb(semantics, generator)
            np.savez_compressed(pred_root / f"{token}.npz", pred=pred.numpy())
            along = STEP_VOXELS * VOXEL * f
            infos.append(
                {
                    "token": token,
                    "scene_token": scene_token,
                    "scene_name": scene_name,
                    "timestamp": 1_533_000_000_000_000 + s * 100_000_000 + f * 500_000,
                    "lidar_path": f"samples/LIDAR_TOP/{token}.pcd.bin",
                    "lidar2ego_translation": LIDAR2EGO_TRANSLATION,
                    "lidar2ego_rotation": LIDAR2EGO_ROTATION,
                    "ego2global_translation": [
                        400.0 + along * math.cos(heading),
                        1100.0 + 300.0 * s + along * math.sin(heading),
                        0.0,
                    ],
                    "ego2global_rotation": _quaternion_yaw(heading),
                    "gt_boxes": np.zeros((0, 7), dtype=np.float32),
                }
            )
    infos_path = root / "nuscenes_infos_val.pkl"
    with infos_path.open("wb") as file:
        pickle.dump({"infos": infos, "metadata": {"version": "v1.0-trainval"}}, file, protocol=4)
    return gt_root, pred_root, infos_path
