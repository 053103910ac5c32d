"""First-hit voxel ray casting (Amanatides-Woo), vectorised over rays, in pure torch.

The rules are those of the DVR kernel behind SparseOcc's RayIoU
(``reference/metrics-protocol-facts.md`` section 3), so that RayIoU numbers match:

- positions are taken to voxel units as ``float32((p - lower) / voxel_size)``, computed in
  float64 from float64 origins, float32 directions and the float32 grid bounds and voxel
  size, rounded once; the ray's end point is ``origin + direction`` and only its
  direction matters;
- traversal state is float64; it starts in voxel ``trunc(origin)`` (truncation toward
  zero, also for origins outside the grid) and includes that voxel;
- ``step = +1 if d >= 0 else -1``; ``tMax = (next boundary - o) / d`` (``inf`` where
  d = 0); ties go ``X if tMaxX < tMaxY and tMaxX < tMaxZ``, ``Z if tMaxX < tMaxY`` (else),
  ``Y if tMaxY < tMaxZ``, else ``Z``;
- each in-grid voxel's distance is the ray parameter where the ray *exits* it;
- the hit is the first in-grid voxel whose label is not ``free_label``; with no hit, the
  last in-grid voxel's exit distance and label; a ray that never enters the grid keeps
  the reference's placeholders: distance -1 voxel (``-voxel_size`` metres) and the label
  of voxel (0, 0, 0);
- traversal stops when the ray leaves the grid after having been inside, or after 1000
  steps.

Every ray advances one voxel per iteration of a bounded loop (at most 1001 iterations);
rays that finish drop out, and rays that cannot reach the grid are resolved up front.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from dego._typing import typechecked
from dego.classes import FREE_LABEL
from dego.grid import VoxelGrid

MAX_STEPS = 1000
"""The reference kernel's step limit (it records at most MAX_STEPS + 1 voxels per ray)."""

_OUTSIDE = -1  # label of the padding ring around the grid (labels are >= 0)


def generate_lidar_rays() -> Float[Tensor, "14040 3"]:
    """SparseOcc's RayIoU ray pattern: 39 pitches x 360 azimuths, unit float32 directions.

    Pitches are ``-(pi/2 - atan(k))`` for k = 1..10, continued with the last step until
    the pitch reaches 0.21 rad; azimuths 0..359 degrees. Row ``p * 360 + a``.
    """
    pitches = [-(math.pi / 2 - math.atan(k)) for k in range(1, 11)]
    while pitches[-1] < 0.21:
        pitches.append(pitches[-1] + (pitches[-1] - pitches[-2]))
    pitch = np.asarray(pitches)[:, None]
    azimuth = np.deg2rad(np.arange(0, 360, 1))[None, :]
    rays = np.stack(
        np.broadcast_arrays(
            np.cos(pitch) * np.cos(azimuth), np.cos(pitch) * np.sin(azimuth), np.sin(pitch)
        ),
        -1,
    )
    return torch.from_numpy(rays.reshape(-1, 3).astype(np.float32))


def _entry_possible(origin: Tensor, direction: Tensor, shape: Tensor) -> Tensor:
    """Rays (voxel units, float64) that touch the grid box grown by one voxel: the only
    ones that can ever visit an in-grid voxel."""
    low, high = -1.0 - origin, shape.double() + 1.0 - origin
    inverse = 1.0 / direction
    t0, t1 = low * inverse, high * inverse
    near = torch.minimum(t0, t1)
    far = torch.maximum(t0, t1)
    # an axis with d = 0 constrains nothing if the origin lies within its slab, else all
    parallel = direction == 0
    inside_slab = (origin > -1.0) & (origin < shape.double() + 1.0)
    near = torch.where(parallel, torch.where(inside_slab, -math.inf, math.inf), near)
    far = torch.where(parallel, torch.where(inside_slab, math.inf, -math.inf), far)
    enter, leave = near.max(-1).values, far.min(-1).values
    return (enter <= leave) & (leave >= 0)


def _check_grid_labels(labels: Tensor, grid: VoxelGrid) -> None:
    if tuple(labels.shape) != grid.shape:
        raise ValueError(f"labels: shape {tuple(labels.shape)} does not match grid {grid.shape}")


def _voxel_rays(
    origins: Tensor, directions: Tensor, grid: VoxelGrid
) -> tuple[Tensor, Tensor, Tensor]:
    """Paired ``(N, 3)`` origins (metres) and directions -> float64 voxel-unit starts, unit
    directions and metres per unit of ray parameter, rounded as the reference does."""
    device = origins.device
    o64 = origins.to(dtype=torch.float64)
    d64 = directions.to(device=device, dtype=torch.float32).double()
    if not bool(torch.isfinite(o64).all()):
        raise ValueError("origins: expected finite values")
    if not bool(torch.isfinite(d64).all()) or bool((d64 == 0).all(-1).any()):
        raise ValueError("directions: expected finite, non-zero vectors")
    lower = torch.tensor(grid.lower, dtype=torch.float32, device=device).double()
    size = torch.tensor(grid.voxel_size, dtype=torch.float32, device=device).double()
    # voxel units computed in float64 and rounded to float32 once, as the reference does
    start = ((o64 - lower) / size).float().double()
    end = (((d64 + o64) - lower) / size).float().double()
    delta = end - start
    unit = delta / torch.linalg.vector_norm(delta, dim=-1, keepdim=True)
    # metres per unit of ray parameter (voxel units along a unit voxel-space direction)
    return start, unit, torch.linalg.vector_norm(unit * size, dim=-1)


def _march(
    labels: Tensor,  # (X, Y, Z) int64
    origin: Tensor,  # (N, 3) float64 voxel units
    unit: Tensor,  # (N, 3) float64 unit directions
    free_label: int,
    visited: Tensor | None = None,  # (X + 2) (Y + 2) (Z + 2) bool, marked in place
) -> tuple[Tensor, Tensor]:
    """Amanatides-Woo traversal of every ray; first hits ``(distance in voxel units,
    label)`` with the reference's placeholders. With ``visited`` (the padded grid,
    flattened), every voxel a ray passes up to and including its hit is marked."""
    device = labels.device
    n = origin.shape[0]
    shape = torch.tensor(labels.shape, device=device)
    # never entered: the reference's placeholders, -1 voxel and the label of voxel (0, 0, 0)
    distance = torch.full((n,), -1.0, dtype=torch.float64, device=device)
    hit = labels[0, 0, 0].expand(n).clone()
    # labels padded by one voxel of _OUTSIDE, so a clamped lookup also tells in-grid or not
    padded = torch.nn.functional.pad(labels, (1, 1, 1, 1, 1, 1), value=_OUTSIDE).reshape(-1)
    strides = torch.tensor(
        [(labels.shape[1] + 2) * (labels.shape[2] + 2), labels.shape[2] + 2, 1], device=device
    )

    rays = _entry_possible(origin, unit, shape).nonzero().squeeze(1)
    origin, unit = origin[rays], unit[rays]
    voxel = torch.trunc(origin).long()
    step = torch.where(unit >= 0, 1, -1)
    boundary = voxel.double() + (step > 0).double()
    t_max = torch.where(unit != 0, (boundary - origin) / unit, math.inf)
    t_delta = torch.where(unit != 0, step.double() / unit, math.inf)
    was_inside = torch.zeros(rays.shape, dtype=torch.bool, device=device)
    alive = torch.ones_like(was_inside)
    last_t = torch.full(rays.shape, -1.0, dtype=torch.float64, device=device)
    last_label = hit[rays]
    low, high = torch.full_like(shape, -1), shape

    def flush(done: Tensor) -> None:
        distance[rays[done]] = last_t[done]
        hit[rays[done]] = last_label[done]

    for iteration in range(MAX_STEPS + 1):
        index = ((torch.maximum(torch.minimum(voxel, high), low) + 1) * strides).sum(-1)
        label = padded[index]
        inside = label != _OUTSIDE
        update = inside & alive
        if visited is not None:
            visited[index[update]] = True
        # the axis crossed next (the voxel's exit), with the reference's tie-break
        tx, ty, tz = t_max.unbind(-1)
        axis = torch.where(tx < ty, torch.where(tx < tz, 0, 2), torch.where(ty < tz, 1, 2))
        axis = axis[:, None]
        last_t = torch.where(update, t_max.gather(1, axis).squeeze(1), last_t)
        last_label = torch.where(update, label, last_label)
        alive = alive & ~(was_inside & ~inside) & ~(update & (label != free_label))
        was_inside = was_inside | inside
        voxel = voxel.scatter_add(1, axis, step.gather(1, axis))
        t_max = t_max.scatter_add(1, axis, t_delta.gather(1, axis))
        if iteration % 8 == 7:  # drop finished rays once in a while: compaction costs
            live = int(alive.sum())
            if live == 0:
                break
            if live < 0.75 * alive.numel():
                flush(~alive)
                state = (rays, voxel, step, t_max, t_delta, was_inside, last_t, last_label)
                rays, voxel, step, t_max, t_delta, was_inside, last_t, last_label = (
                    t[alive] for t in state
                )
                alive = alive[alive]
    flush(torch.ones_like(alive))
    return distance, hit


@typechecked
def cast_rays(
    labels: Int[Tensor, "X Y Z"],
    origins: Float[Tensor, "K 3"],
    directions: Float[Tensor, "R 3"],
    grid: VoxelGrid,
    free_label: int = FREE_LABEL,
) -> tuple[Float[Tensor, " KR"], Int[Tensor, " KR"]]:
    """Cast every direction from every origin through a label grid; first hits.

    Args:
        labels: ``(X, Y, Z)`` integer labels on ``grid`` (any value but ``free_label``
            is occupied).
        origins: ``(K, 3)`` ray origins in metres (grid frame); may lie outside the grid.
        directions: ``(R, 3)`` ray directions (any non-zero length).
        grid: the voxel grid of ``labels``.
        free_label: the empty label.

    Returns:
        ``hit_distance (K R,)`` float32 metres along the ray (origin-major: ray
        ``k R + r``; negative, ``-voxel_size``, where the ray never enters the grid) and
        ``hit_label (K R,)`` int64 (usually ``free_label`` where nothing is hit; see the
        module docstring for rays that never enter).
    """
    _check_grid_labels(labels, grid)
    if origins.shape[0] == 0:
        raise ValueError("origins: need at least one origin, got K = 0")
    k, r = origins.shape[0], directions.shape[0]
    o64 = origins.to(device=labels.device, dtype=torch.float64)
    start, unit, metres = _voxel_rays(
        o64.repeat_interleave(r, 0), directions.to(labels.device).repeat(k, 1), grid
    )
    distance, hit = _march(labels.long(), start, unit, free_label)
    # float32 voxel-unit distances scaled in float32, as the reference does
    return distance.float() * metres.float(), hit


@typechecked
def observed_voxels(
    labels: Int[Tensor, "X Y Z"],
    origins: Float[Tensor, "N 3"],
    directions: Float[Tensor, "N 3"],
    grid: VoxelGrid,
    free_label: int = FREE_LABEL,
) -> Bool[Tensor, "X Y Z"]:
    """Voxels seen along rays: every voxel ray i (from ``origins[i]`` along
    ``directions[i]``, paired) passes through, up to and including its first occupied
    voxel, as Occ3D defines its camera and LiDAR visibility masks. Same traversal rules as
    :func:`cast_rays`."""
    _check_grid_labels(labels, grid)
    if origins.shape[0] == 0:
        return torch.zeros(grid.shape, dtype=torch.bool, device=labels.device)
    start, unit, _ = _voxel_rays(origins.to(labels.device), directions, grid)
    x, y, z = grid.shape
    visited = torch.zeros((x + 2) * (y + 2) * (z + 2), dtype=torch.bool, device=labels.device)
    _march(labels.long(), start, unit, free_label, visited)
    return visited.view(x + 2, y + 2, z + 2)[1:-1, 1:-1, 1:-1].clone()


__all__ = ["MAX_STEPS", "cast_rays", "generate_lidar_rays", "observed_voxels"]
