"""Small ground-truth trees in every benchmark's layout, with predictions, made from
procedural street scenes: try ``dego eval --benchmark NAME`` end to end before any
download (``dego data write-tree --benchmark NAME OUT``).

Each scene is a straight street (road, sidewalks, terrain, building blocks, trees, parked
cars and trucks, pedestrians, barriers, cones, bicycles) that the ego drives along at
8 m/s; a keyframe every 0.5 s sees the window of the street around the ego. The street is
drawn in Occ3D-nuScenes labels at 0.4 m and resampled (nearest voxel centre) onto each
benchmark's grid and label ids; predictions perturb the ground truth (missed voxels,
confused classes, thickened surfaces). Benchmarks on nuScenes keyframes also get an
mmdet3d-style infos file whose poses give the RayIoU origins.
"""

from __future__ import annotations

import dataclasses
import math
import pickle
from pathlib import Path

import numpy as np
import torch

from dego._typing import typechecked
from dego.classes import FREE_LABEL
from dego.evaluation.benchmarks import OCC3D_TO_OPENOCC, Benchmark, get_benchmark
from dego.evaluation.layouts import layout_of
from dego.grid import VoxelGrid

VOXEL = 0.4
STEP_VOXELS = 10  # 4 m between keyframes
LIDAR2EGO_TRANSLATION = [0.943713, 0.0, 1.84023]  # nuScenes LIDAR_TOP
LIDAR2EGO_ROTATION = [0.7071067811865476, 0.0, 0.0, -0.7071067811865476]  # yaw -90 deg

# Occ3D-nuScenes id -> each benchmark's id (free last)
_TO_WAYMO = (0, 0, 8, 1, 1, 1, 9, 2, 7, 1, 1, 13, 14, 14, 14, 10, 11, 23)
_TO_NUPLAN = (8, 6, 3, 2, 2, 2, 3, 4, 5, 2, 2, 1, 1, 1, 1, 1, 1, 0)
_TO_SURROUNDOCC = (*range(17), 255)  # 255: no row (empty)
_DYNAMIC = (2, 3, 4, 5, 6, 7, 9, 10)  # Occ3D ids that move (OpenOcc v2 flow)


@dataclasses.dataclass(frozen=True)
class BenchmarkTree:
    """What :func:`write_benchmark_tree` wrote: the ground-truth root (``--gt``), the
    predictions (``--pred``) and, for nuScenes benchmarks, the infos file (``--infos``)."""

    benchmark: str
    gt: Path
    pred: Path
    infos: Path | None
    samples: int


def street(length: int, generator: torch.Generator) -> torch.Tensor:
    """``(length, 200, 16)`` uint8 Occ3D-nuScenes labels of one street along x."""

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
        (0, (2, 2, 2), (60, 140)),  # others
        (12, (6, 6, 1), (66, 134)),  # other flat
    ]
    for _ in range(length // 4):
        label, (sx, sy, sz), (y_low, y_high) = objects[randint(0, len(objects))]
        x0, y0 = randint(0, length - sx), randint(y_low, y_high - sy)
        world[x0 : x0 + sx, y0 : y0 + sy, 2 : 2 + sz] = label
    return world


def perturb(
    semantics: torch.Tensor, generator: torch.Generator, free: int, classes: int
) -> torch.Tensor:
    """An imperfect prediction: 10% of occupied voxels missed, 5% confused with a random
    class, surfaces grown by one voxel in 20% of the columns."""
    occupied = semantics != free
    draw = torch.rand((3, *semantics.shape), generator=generator)
    pred = semantics.clone()
    pred[occupied & (draw[0] < 0.10)] = free
    confused = occupied & (draw[1] < 0.05)
    pred[confused] = torch.randint(0, classes, semantics.shape, generator=generator)[confused].to(
        pred.dtype
    )
    below = pred[:, :, :-1]
    grow = (pred[:, :, 1:] == free) & (below != free) & (draw[2, :, :, 1:] < 0.2)
    pred[:, :, 1:] = torch.where(grow, below, pred[:, :, 1:])
    return pred


def resample(window: torch.Tensor, grid: VoxelGrid, fill: int) -> torch.Tensor:
    """An Occ3D-grid window resampled onto ``grid`` by nearest voxel centre (``fill``
    outside the window)."""
    source = VoxelGrid.occ3d()
    centres = [
        torch.tensor([grid.lower[a] + (i + 0.5) * grid.voxel_size[a] for i in range(n)])
        for a, n in enumerate(grid.shape)
    ]
    index = [
        torch.floor((c - source.lower[a]) / source.voxel_size[a]).long()
        for a, c in enumerate(centres)
    ]
    inside = [(i >= 0) & (i < n) for i, n in zip(index, source.shape, strict=True)]
    clamped = [i.clamp(0, n - 1) for i, n in zip(index, source.shape, strict=True)]
    out = window[clamped[0][:, None, None], clamped[1][None, :, None], clamped[2][None, None, :]]
    keep = inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]
    return torch.where(keep, out.long(), torch.tensor(fill)).to(torch.int64)


def _quaternion_yaw(yaw: float) -> list[float]:
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


def _remap(labels: torch.Tensor, table: tuple[int, ...]) -> torch.Tensor:
    return torch.tensor(table, dtype=torch.int64)[labels.long()]


def _rows(dense: np.ndarray, empty: int, order: str, generator: torch.Generator) -> np.ndarray:
    """Sparse rows of the non-empty voxels in ``order`` with the label last; a few voxels
    get a second and third row (OpenOccupancy's majority vote decides them)."""
    index = np.argwhere(dense != empty)
    label = dense[tuple(index.T)]
    axes = {"x": 0, "y": 1, "z": 2}
    rows = np.concatenate([index[:, [axes[a] for a in order]], label[:, None]], 1)
    if order == "zyx" and len(rows):
        pick = torch.randint(0, len(rows), (max(1, len(rows) // 200),), generator=generator)
        extra = rows[pick.numpy()].copy()
        extra[:, -1] = (extra[:, -1] % 16) + 1
        rows = np.concatenate([rows, extra, extra])  # outvoted by 2 to 1
    return rows.astype(np.int16)


@typechecked
def write_benchmark_tree(
    benchmark: str,
    out: str | Path,
    *,
    scenes: int = 1,
    frames: int = 2,
    seed: int = 0,
) -> BenchmarkTree:
    """Write a small tree of ``benchmark`` (ground truth in its layout, predictions, and
    for nuScenes benchmarks ``nuscenes_infos_val.pkl``) under ``out``: ``out/gt``,
    ``out/pred``. Deterministic for a seed.

    Raises:
        ValueError: an unknown benchmark, ``scenes`` or ``frames`` below 1.
    """
    spec = get_benchmark(benchmark)
    if scenes < 1 or frames < 1:
        raise ValueError(f"scenes, frames: expected >= 1, got {scenes}, {frames}")
    root = Path(out)
    gt_root, pred_root = root / "gt", root / "pred"
    pred_root.mkdir(parents=True, exist_ok=True)
    generator = torch.Generator().manual_seed(seed)
    layout = layout_of(spec)
    infos = []
    for s in range(scenes):
        scene_name, scene_token = f"scene-{s + 1:04d}", f"{seed:04d}scene{s:024d}"
        world = street(200 + STEP_VOXELS * frames, generator)
        heading = 0.02 * (s - scenes / 2)
        for f in range(frames):
            token = f"{seed:04d}{s:04d}sample{f:018d}"
            window = world[STEP_VOXELS * f : STEP_VOXELS * f + 200].clone()
            scene = scene_name
            if spec.layout == "waymo":
                scene, token = f"{s:03d}", f"{s:03d}_{f:03d}"
            elif spec.layout == "openoccupancy":
                scene = scene_token
            _write_sample(spec, layout, gt_root, pred_root, scene, token, window, generator)
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
    infos_path = None
    if spec.nuscenes:
        infos_path = root / "nuscenes_infos_val.pkl"
        with infos_path.open("wb") as file:
            pickle.dump(
                {"infos": infos, "metadata": {"version": "v1.0-trainval"}}, file, protocol=4
            )
    return BenchmarkTree(spec.name, gt_root, pred_root, infos_path, scenes * frames)


def _write_sample(
    spec: Benchmark,
    layout: object,
    gt_root: Path,
    pred_root: Path,
    scene: str,
    token: str,
    window: torch.Tensor,
    generator: torch.Generator,
) -> None:
    occupied = window != FREE_LABEL
    seen = torch.rand(window.shape, generator=generator) < 0.7
    camera = (occupied | (seen & ~seen.roll(1, 0))).numpy()
    lidar = (occupied | seen).numpy()
    c, free = spec.num_classes, spec.free_label
    write = layout.write  # type: ignore[attr-defined]
    if spec.layout == "occ3d":
        write(
            gt_root,
            scene,
            token,
            {"semantics": window.numpy(), "mask_camera": camera, "mask_lidar": lidar},
        )
        pred = perturb(window, generator, FREE_LABEL, FREE_LABEL)
        np.savez_compressed(pred_root / f"{token}.npz", pred=pred.numpy())
    elif spec.layout == "openocc":
        semantics = _remap(window, OCC3D_TO_OPENOCC)
        dynamic = torch.isin(window, torch.tensor(_DYNAMIC))
        velocity = torch.rand(2, generator=generator) * 4 - 2
        flow = torch.where(dynamic[..., None], velocity, torch.zeros(2)).float()
        write(
            gt_root,
            scene,
            token,
            {"semantics": semantics.to(torch.uint8).numpy(), "flow": flow.numpy()},
        )
        pred = perturb(semantics, generator, free, free)
        noise = torch.randn(flow.shape, generator=generator) * 0.3
        pred_flow = torch.where(pred[..., None] != free, flow + noise, torch.zeros(2))
        np.savez_compressed(
            pred_root / f"{token}.npz",
            pred=pred.to(torch.uint8).numpy(),
            flow=pred_flow.float().numpy(),
        )
    elif spec.layout == "waymo":
        semantics = _remap(window, _TO_WAYMO)
        infov = np.ones(window.shape, dtype=bool)
        infov[:, :20] = False  # outside the cameras' field of view
        write(
            gt_root,
            scene,
            token,
            {
                "voxel_label": semantics.to(torch.uint8).numpy(),
                "origin_voxel_state": lidar.astype(np.uint8),
                "final_voxel_state": camera.astype(np.uint8),
                "infov": infov.astype(np.uint8),
            },
        )
        scored = torch.where(semantics == 23, free, semantics)
        pred = perturb(scored, generator, free, free)
        stored = torch.where(pred == free, 23, pred)  # free stored as 23, as the GT
        np.savez_compressed(pred_root / f"{token}.npz", pred=stored.to(torch.uint8).numpy())
    elif spec.layout in ("surroundocc", "openoccupancy"):
        dense = resample(_remap(window, _TO_SURROUNDOCC), spec.grid, 255)
        order = layout.order  # type: ignore[attr-defined]
        rows = _rows(dense.numpy(), 255, order, generator)
        write(gt_root, scene, token, {"rows": rows})
        occupied = (dense != 255) & (dense != 0)
        target = torch.where(occupied, dense, free)  # noise voxels: the GT ignores them
        pred = perturb(target, generator, free, 17)
        pred = torch.where(pred == 17, free, pred) if free == 0 else pred
        name = f"{token}.npy"
        np.save(pred_root / name, pred.to(torch.uint8).numpy(), allow_pickle=False)
    elif spec.layout == "nuplan":
        # val files sit 8 layers (2 m) lower than the scored grid: the reader moves them up
        stored_grid = VoxelGrid((-50.0, -50.0, -3.0), (50.0, 50.0, 5.0), 0.25)
        stored = resample(_remap(window, _TO_NUPLAN), stored_grid, 0)
        write(gt_root, scene, token, {"labels": stored.to(torch.uint8).numpy()})
        cropped = layout.read(gt_root / f"{token}.npy", spec).semantics  # type: ignore[attr-defined]
        pred = perturb(cropped, generator, free, c)
        np.save(pred_root / f"{token}.npy", pred.to(torch.uint8).numpy(), allow_pickle=False)
    else:  # pragma: no cover - a new layout needs its writer here
        raise ValueError(f"benchmark: no fixture writer for layout {spec.layout!r}")


__all__ = ["BenchmarkTree", "perturb", "resample", "street", "write_benchmark_tree"]
