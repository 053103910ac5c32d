"""A scalar, obviously-correct first-hit ray caster: one ray at a time, plain Python.

Written from the SparseOcc / DVR rules (``reference/metrics-protocol-facts.md`` section 3,
``lib/dvr/dvr.cu: render_forward_cuda_kernel``), not from ``dego.raycast``; it is slow
and only meant for small grids and a few rays in the tests.

- Positions go to voxel units in float32: ``(p - lower) / size`` for the origin and
  ``((p + direction) - lower) / size`` for the end point (``p + direction`` in float32),
  then both are widened to float64.
- The direction is ``(end - start) / |end - start|`` in float64.
- Traversal (Amanatides-Woo) starts in voxel ``int(start)`` (truncation toward zero),
  ``step = +1 if d >= 0 else -1``, ``tMax = (next boundary - o) / d`` (``inf`` if d = 0),
  ties go ``X if tMaxX < tMaxY and tMaxX < tMaxZ``, ``Z`` (else, if tMaxX < tMaxY),
  ``Y if tMaxY < tMaxZ``, else ``Z``.
- Every in-grid voxel records the ray parameter where the ray exits it; the loop stops
  once the ray leaves the grid after having been inside, or after MAX_STEPS + 1
  iterations.
- Hit: the first recorded voxel whose label is not free (its exit distance), else the last
  recorded voxel; nothing recorded: distance -1 and the label of voxel (0, 0, 0).
- Metres: ``float32(d) * float32(voxel_size)`` (isotropic grids only).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

REFERENCE_MAX_STEPS = 1000  # dvr.cu's MAX_STEP


def traverse(
    start: Sequence[float],
    direction: Sequence[float],
    shape: Sequence[int],
    max_steps: int = REFERENCE_MAX_STEPS,
) -> list[tuple[tuple[int, int, int], float]]:
    """The in-grid voxels a ray visits, in order, each with its exit parameter (voxel units).

    ``start`` (float64, voxel units) and the unit ``direction`` (float64) are used as given.
    """
    o = [float(v) for v in start]
    d = [float(v) for v in direction]
    voxel = [int(v) for v in o]  # int() truncates toward zero, like C's int(double)
    step = [1 if v >= 0 else -1 for v in d]
    t_max = [
        ((voxel[a] + (1 if step[a] > 0 else 0)) - o[a]) / d[a] if d[a] != 0 else math.inf
        for a in range(3)
    ]
    t_delta = [step[a] / d[a] if d[a] != 0 else math.inf for a in range(3)]

    recorded: list[tuple[tuple[int, int, int], float]] = []
    was_inside = False
    steps = 0
    while True:
        inside = all(0 <= voxel[a] < shape[a] for a in range(3))
        current = (voxel[0], voxel[1], voxel[2])
        if inside:
            was_inside = True
        elif was_inside:
            break
        tx, ty, tz = t_max
        # the kernel's tie-break, verbatim: X only if strictly first, Z wins every Z tie
        axis = (0 if tx < tz else 2) if tx < ty else (1 if ty < tz else 2)
        exit_t = t_max[axis]
        voxel[axis] += step[axis]
        t_max[axis] += t_delta[axis]
        if inside:
            recorded.append((current, exit_t))
        steps += 1
        if steps > max_steps:
            break
    return recorded


def to_voxel_units(
    origin: Sequence[float],
    direction: Sequence[float],
    lower: Sequence[float],
    voxel_size: float,
) -> tuple[list[float], list[float]]:
    """``(start, unit direction)`` in voxel units, float64, from metres: SparseOcc computes
    ``(p - lower) / size`` in float64 (float64 origins, float32 rays, the float32 lower
    bound and voxel size promoted) and rounds to float32 once."""
    o64 = np.asarray(origin, dtype=np.float64)
    d64 = np.asarray(direction, dtype=np.float32).astype(np.float64)
    lower64 = np.asarray(lower, dtype=np.float32).astype(np.float64)
    size64 = np.float64(np.float32(voxel_size))
    start32 = ((o64 - lower64) / size64).astype(np.float32)
    end32 = (((d64 + o64) - lower64) / size64).astype(np.float32)
    start = [float(v) for v in start32]
    end = [float(v) for v in end32]
    r = [end[a] - start[a] for a in range(3)]
    length = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
    return start, [r[a] / length for a in range(3)]


def cast_one(
    labels: np.ndarray,
    origin: Sequence[float],
    direction: Sequence[float],
    lower: Sequence[float],
    voxel_size: float,
    free_label: int = 17,
) -> tuple[np.float32, int]:
    """First hit of one ray: ``(distance in metres as float32, label)``."""
    start, unit = to_voxel_units(origin, direction, lower, voxel_size)
    recorded = traverse(start, unit, labels.shape)
    if not recorded:
        voxel_units, label = -1.0, int(labels[0, 0, 0])
    else:
        last_voxel, voxel_units = recorded[-1]  # no hit: the last in-grid voxel
        label = int(labels[last_voxel])
        for v, t in recorded:
            if int(labels[v]) != free_label:
                voxel_units, label = t, int(labels[v])
                break
    return np.float32(voxel_units) * np.float32(voxel_size), label


def cast_all(
    labels: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
    lower: Sequence[float],
    voxel_size: float,
    free_label: int = 17,
) -> tuple[np.ndarray, np.ndarray]:
    """Every direction from every origin, origin-major (ray ``k R + r``), like ``cast_rays``."""
    distances, hit_labels = [], []
    for origin in origins:
        for direction in directions:
            d, label = cast_one(labels, origin, direction, lower, voxel_size, free_label)
            distances.append(d)
            hit_labels.append(label)
    return np.asarray(distances, dtype=np.float32), np.asarray(hit_labels, dtype=np.int64)


def reference_lidar_rays() -> np.ndarray:
    """The 14040 SparseOcc ray directions (39 pitches x 360 azimuths), float32, row-by-row
    as ``loaders/ray_metrics.py: generate_lidar_rays`` builds them."""
    pitches = [-(math.pi / 2 - math.atan(k + 1)) for k in range(10)]
    while pitches[-1] < 0.21:  # continue with the last step (re-taken each time)
        pitches.append(pitches[-1] + (pitches[-1] - pitches[-2]))
    rays = []
    for pitch in pitches:
        for azimuth_deg in np.arange(0, 360, 1):
            azimuth = np.deg2rad(azimuth_deg)
            rays.append(
                (
                    np.cos(pitch) * np.cos(azimuth),
                    np.cos(pitch) * np.sin(azimuth),
                    np.sin(pitch),
                )
            )
    return np.asarray(rays, dtype=np.float32)


def reference_counts(
    samples: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    directions: np.ndarray,
    lower: Sequence[float],
    voxel_size: float,
    thresholds: Sequence[float] = (1.0, 2.0, 4.0),
    num_classes: int = 18,
    free_label: int = 17,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SparseOcc's ``main`` + ``calc_metrics`` on ``(pred, gt, origins)`` samples:
    ``(gt_cnt (C,), pred_cnt (C,), tp_cnt (T, C))`` as int64.

    Rays whose gt label is free are dropped; the L1 depth error is taken in float32 and
    compared strictly with each threshold.
    """
    gt_cnt = np.zeros(num_classes, dtype=np.int64)
    pred_cnt = np.zeros(num_classes, dtype=np.int64)
    tp_cnt = np.zeros((len(thresholds), num_classes), dtype=np.int64)
    for pred, gt, origins in samples:
        pred_d, pred_l = cast_all(pred, origins, directions, lower, voxel_size, free_label)
        gt_d, gt_l = cast_all(gt, origins, directions, lower, voxel_size, free_label)
        valid = gt_l != free_label
        pred_d, pred_l, gt_d, gt_l = pred_d[valid], pred_l[valid], gt_d[valid], gt_l[valid]
        l1_error = np.abs(pred_d - gt_d)
        assert l1_error.dtype == np.float32
        for j, threshold in enumerate(thresholds):
            tp_dist_mask = l1_error < np.float32(threshold)
            for c in range(num_classes):
                cls_mask_pred = pred_l == c
                cls_mask_gt = gt_l == c
                if j == 0:
                    gt_cnt[c] += cls_mask_gt.sum()
                    pred_cnt[c] += cls_mask_pred.sum()
                tp_cnt[j, c] += (cls_mask_gt & cls_mask_pred & tp_dist_mask).sum()
    return gt_cnt, pred_cnt, tp_cnt


def quaternion_matrix(wxyz: Sequence[float]) -> np.ndarray:
    """3x3 rotation of a (normalised) wxyz quaternion, as pyquaternion's rotation_matrix."""
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def transform(translation: Sequence[float], wxyz: Sequence[float]) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = quaternion_matrix(wxyz)
    matrix[:3, 3] = translation
    return matrix


def reference_origins(
    ego2global: Sequence[np.ndarray], lidar2ego: Sequence[np.ndarray], reference_index: int
) -> np.ndarray:
    """``EgoPoseDataset.__getitem__``: the scene's LiDAR origins in the reference ego frame,
    ``(K, 3)`` float64, from per-frame 4x4 ego2global / lidar2ego matrices.

    As the reference does: the reference frame's origin is ``[0, 0, 0]`` in its own LiDAR
    frame; every other frame's origin in the reference LiDAR frame is rounded to float32
    before ``lidar2ego[ref]`` takes it to the ego frame; ``|x| < 39 and |y| < 39``; more
    than 8 -> indices ``round(linspace(0, n - 1, 8))``.
    """
    ref_lidar_from_global = np.linalg.inv(ego2global[reference_index] @ lidar2ego[reference_index])
    ref_ego_from_lidar = lidar2ego[reference_index]
    kept = []
    for index in range(len(ego2global)):
        if index == reference_index:
            origin = np.array([0.0, 0.0, 0.0], dtype=np.float32)
        else:
            global_from_curr = ego2global[index] @ lidar2ego[index]
            origin = np.array((ref_lidar_from_global @ global_from_curr)[:3, 3], dtype=np.float32)
        padded = np.ones(4)
        padded[:3] = origin
        origin = ref_ego_from_lidar[:3] @ padded
        if abs(origin[0]) < 39 and abs(origin[1]) < 39:
            kept.append(origin)
    if len(kept) > 8:
        picked = np.round(np.linspace(0, len(kept) - 1, 8)).astype(np.int64)
        kept = [kept[i] for i in picked]
    return np.stack(kept)
