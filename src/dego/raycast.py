"""First-hit voxel ray casting (Amanatides-Woo), vectorised over rays, in pure torch.

The rules are those of the DVR kernel behind SparseOcc's RayIoU
(docs/rayiou.md, "The rules"), so that RayIoU numbers match:

- positions are taken to voxel units as ``float32((p - lower) / voxel_size)``, computed in
  float64 from the origins as given, float32 directions and the float32 grid bounds and
  voxel size, rounded once; the ray's end point is ``origin + direction`` and only its
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

Precision. The traversal itself is always float64, as in the reference kernel. What the
dtype of the inputs selects is the rounding *before* it:

- **SparseOcc mode** (float32 directions, with float32 or float64 origins; float16 and
  bfloat16 inputs are computed this way): the voxel coordinates of the start and end
  points are rounded to float32 as above, and distances are returned in float32 (half
  inputs: in their dtype). This reproduces the reference kernel bit for bit.
- **float64 mode** (float64 origins and directions): no float32 rounding anywhere; float64
  distances. It differs from SparseOcc mode only through the reference's float32 voxel
  coordinates, which turn the direction by up to about ``2^-23 |p| / |d|`` (voxel units):
  on the RayIoU benchmark (8 origins x 14,040 rays through an Occ3D-sized street scene)
  distances differ by at most 1.3e-3 m (about 1e-4 relative; 99.9% of rays within
  3e-4 m), no label differs and RayIoU is identical; in general a ray that clips a voxel
  edge or corner can change voxel (``docs/rayiou.md``).

Directions are first scaled by the exact power of two ``2^-round(log2 |d|)``, which
brings their length into ``[1/sqrt(2), sqrt(2))`` without turning them: unit directions
(SparseOcc's) are used unchanged, a direction and any power-of-two multiple of it give
identical results, and any length works, from 1e-20 to 1e20 in float32 and far beyond in
float64 (before, a direction much shorter than the float32 spacing of the origin's voxel
coordinates gave NaN distances).

Two traversals give identical hits (the tests compare them bit for bit):

- **torch** (CUDA, and CPU without numba): every ray advances one voxel per iteration of
  a bounded loop (at most 1001 iterations), over chunks of at most ``2^20`` rays; rays
  that finish drop out, and rays that cannot reach the grid are resolved up front.
- **compiled CPU kernel** (``dego._march_numba``, with numba installed: the ``eval``
  extra): one loop per ray, in parallel over rays on ``torch.get_num_threads()``
  threads, each ray stopping at its hit; several times faster (docs/performance.md).
  :data:`CPU_KERNEL` chooses.

Several label grids on the same rays (RayIoU's prediction and ground truth) are traversed
together: a ray stops once it has hit in every grid.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Iterator, Sequence
from typing import NamedTuple

import numpy as np
import torch
from jaxtyping import Bool, Float, Integer
from torch import Tensor

from dego import _march_numba
from dego._compile import eager_only
from dego._policy import check_dtype, check_memory, compute_dtype, finite_check, run_checks
from dego._typing import typechecked
from dego.classes import FREE_LABEL
from dego.grid import VoxelGrid

MAX_STEPS = 1000
"""The reference kernel's step limit (it records at most MAX_STEPS + 1 voxels per ray)."""

CHUNK_RAYS = 1 << 20
"""Rays traversed together; longer casts loop over chunks of this many rays."""

WORK_BYTES_PER_RAY = 800
"""Working memory of the traversal per ray of a chunk (measured peak about 650 bytes)."""


@typechecked
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
    """Rays (voxel units, float64) that touch the grid box grown by one voxel within
    ``MAX_STEPS`` steps: the only ones that can ever visit an in-grid voxel."""
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
    # a step moves one voxel along one axis: a start more than MAX_STEPS + 2 voxels from
    # the grown box on any axis cannot reach the grid (this also keeps trunc() in range)
    reach = float(MAX_STEPS + 2)
    near_enough = ((origin > -1.0 - reach) & (origin < shape.double() + 1.0 + reach)).all(-1)
    return (enter <= leave) & (leave >= 0) & near_enough


def _label_grid(name: str, labels: Tensor, grid: VoxelGrid) -> Tensor:
    """``labels`` (any integer dtype) as int64, checked against ``grid``."""
    if labels.dtype == torch.bool or labels.is_floating_point() or labels.is_complex():
        raise TypeError(f"{name}: expected integer labels, got dtype {labels.dtype}")
    if tuple(labels.shape) != grid.shape:
        raise ValueError(f"{name}: shape {tuple(labels.shape)} does not match grid {grid.shape}")
    wide = labels.to(torch.int64)
    if labels.dtype == torch.uint64 and wide.numel() and bool((wide < 0).any()):
        raise ValueError(f"{name}: uint64 labels above {torch.iinfo(torch.int64).max}")
    return wide


def _ray_mode(origins: Tensor, directions: Tensor) -> tuple[torch.dtype, bool]:
    """``(dtype of the returned distances, SparseOcc mode?)``; ``TypeError`` for mixed
    dtypes other than SparseOcc's own float64 origins with float32 directions."""
    if origins.dtype == torch.float64 and directions.dtype == torch.float32:
        return torch.float32, True
    check_dtype("directions", directions, origins.dtype, "origins")
    return directions.dtype, compute_dtype(directions.dtype) != torch.float64


def _check_rays(origins: Tensor, directions: Tensor) -> None:
    zero = (directions == 0).all(-1)

    def zero_error() -> Exception:
        first = int(zero.nonzero()[0, 0])
        return ValueError(
            f"directions: {int(zero.sum())} of {directions.shape[0]} directions are zero "
            f"vectors (first: row {first}); expected non-zero directions"
        )

    run_checks(
        [
            finite_check("origins", origins),
            finite_check("directions", directions),
            (~zero.any(), "directions: zero vectors; expected non-zero directions", zero_error),
        ]
    )


def _voxel_rays(
    origins: Tensor, directions: Tensor, grid: VoxelGrid, sparseocc: bool
) -> tuple[Tensor, Tensor, Tensor]:
    """Origins (metres) and non-zero directions, ``(..., 3)`` and broadcastable against
    each other (paired ``(N, 3)``, or ``(K, 1, 3)`` with ``(1, R, 3)`` for every direction
    from every origin), -> float64 voxel-unit starts, unit directions and metres per
    unit of ray parameter (module docstring), flattened to ``(N, 3)``, ``(N, 3)``,
    ``(N,)``. Work that depends on only one of them is done at its own size."""
    device = origins.device
    o64 = origins.to(dtype=torch.float64)
    d64 = directions.to(device=device, dtype=torch.float64)
    if sparseocc:
        # an exact power of two: unit directions stay as they are, none is turned
        norm = torch.linalg.vector_norm(d64, dim=-1, keepdim=True)
        d64 = d64 * torch.exp2(-torch.round(torch.log2(norm)))
        lower = torch.tensor(grid.lower, dtype=torch.float32, device=device).double()
        size = torch.tensor(grid.voxel_size, dtype=torch.float32, device=device).double()
        # voxel units computed in float64 and rounded to float32 once, as the reference does
        start = ((o64 - lower) / size).float().double()
        end = (((d64 + o64) - lower) / size).float().double()
        delta = end - start
        length = torch.linalg.vector_norm(delta, dim=-1, keepdim=True)
        usable = (length > 0) & torch.isfinite(length)
        unit = delta / torch.where(usable, length, 1.0)
        if not bool(usable.all()):
            # origins so far out that float32 swallows a one-metre step (where the
            # reference gives NaN) keep their unrounded direction; they rarely reach the
            # grid anyway
            exact = d64 / size
            exact = exact / torch.linalg.vector_norm(exact, dim=-1, keepdim=True)
            unit = torch.where(usable, unit, exact)
    else:
        lower = torch.tensor(grid.lower, dtype=torch.float64, device=device)
        size = torch.tensor(grid.voxel_size, dtype=torch.float64, device=device)
        start = (o64 - lower) / size
        scaled = d64 / d64.abs().amax(-1, keepdim=True) / size  # no overflow, no underflow
        unit = scaled / torch.linalg.vector_norm(scaled, dim=-1, keepdim=True)
    # metres per unit of ray parameter (voxel units along a unit voxel-space direction)
    metres = torch.linalg.vector_norm(unit * size, dim=-1)
    shape = torch.broadcast_shapes(origins.shape, directions.shape)
    return (
        start.expand(shape).reshape(-1, 3),
        unit.expand(shape).reshape(-1, 3),
        metres.expand(shape[:-1]).reshape(-1),
    )


class _PaddedLabels(NamedTuple):
    """A label grid padded by one voxel on every side, flattened, for clamped lookups."""

    labels: Tensor  # ((X + 2) (Y + 2) (Z + 2),) int64
    outside: int  # the padding ring's value: one no voxel of the grid holds
    inside: Tensor | None  # bool in-grid mask like ``labels``, only if no such value exists
    strides: Tensor  # (3,) int64
    shape: Tensor  # (3,) int64, X Y Z
    corner: Tensor  # () int64, the label of voxel (0, 0, 0)


def _pad(labels: Tensor) -> _PaddedLabels:
    """Pad with a value that no label has (below the smallest or above the largest), so
    that every label value, -1 included, stays a label; a separate in-grid mask only when
    the labels hold both int64 extremes."""
    low, high = (int(v) for v in torch.aminmax(labels))
    info = torch.iinfo(torch.int64)
    outside = low - 1 if low > info.min else high + 1 if high < info.max else 0
    pad = (1, 1, 1, 1, 1, 1)
    padded = torch.nn.functional.pad(labels, pad, value=outside).reshape(-1)
    inside = None
    if low == info.min and high == info.max:
        ones = torch.ones(labels.shape, dtype=torch.bool, device=labels.device)
        inside = torch.nn.functional.pad(ones, pad).reshape(-1)
    _, y, z = labels.shape
    strides = torch.tensor([(y + 2) * (z + 2), z + 2, 1], device=labels.device)
    shape = torch.tensor(labels.shape, device=labels.device)
    return _PaddedLabels(padded, outside, inside, strides, shape, labels[0, 0, 0])


def _march(
    grids: Sequence[_PaddedLabels],  # G label grids of one shape, traversed together
    origin: Tensor,  # (N, 3) float64 voxel units
    unit: Tensor,  # (N, 3) float64 unit directions
    free_label: int,
    visited: Tensor | None = None,  # (X + 2) (Y + 2) (Z + 2) bool, marked in place
) -> tuple[Tensor, Tensor]:
    """Amanatides-Woo traversal of every ray through every grid at once; ``(G, N)`` first
    hits ``(distance in voxel units, label)`` with the reference's placeholders. A ray
    stops when it has hit in every grid or leaves the grid. With ``visited`` (the padded
    grid, flattened; one grid only), every voxel a ray passes up to and including its
    hit is marked."""
    device = origin.device
    n, count = origin.shape[0], len(grids)
    first = grids[0]  # the grids share their geometry: in-grid tests use the first one
    shape = first.shape
    labels = torch.stack([grid.labels for grid in grids])  # (G, P)
    # never entered: the reference's placeholders, -1 voxel and the label of voxel (0, 0, 0)
    distance = torch.full((count, n), -1.0, dtype=torch.float64, device=device)
    hit = torch.stack([grid.corner for grid in grids])[:, None].expand(count, n).clone()

    rays = _entry_possible(origin, unit, shape).nonzero().squeeze(1)
    origin, unit = origin[rays], unit[rays]
    voxel = torch.trunc(origin).long()
    step = torch.where(unit >= 0, 1, -1)
    boundary = voxel.double() + (step > 0).double()
    t_max = torch.where(unit != 0, (boundary - origin) / unit, math.inf)
    t_delta = torch.where(unit != 0, step.double() / unit, math.inf)
    was_inside = torch.zeros(rays.shape, dtype=torch.bool, device=device)
    alive = torch.ones((count, rays.shape[0]), dtype=torch.bool, device=device)
    last_t = torch.full((count, rays.shape[0]), -1.0, dtype=torch.float64, device=device)
    last_label = hit[:, rays]
    low, high = torch.full_like(shape, -1), shape

    def flush(done: Tensor) -> None:
        distance[:, rays[done]] = last_t[:, done]
        hit[:, rays[done]] = last_label[:, done]

    for iteration in range(MAX_STEPS + 1):
        index = ((torch.maximum(torch.minimum(voxel, high), low) + 1) * first.strides).sum(-1)
        label = labels[:, index]  # (G, N)
        inside = label[0] != first.outside if first.inside is None else first.inside[index]
        update = inside & alive
        if visited is not None:
            visited[index[update[0]]] = True
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
            # outside on an axis and stepping away along it: can never (re-)enter the grid
            away = ((voxel < 0) & (step < 0)) | ((voxel >= shape) & (step > 0))
            alive = alive & ~away.any(-1)
            moving = alive.any(0)
            live = int(moving.sum())
            if live == 0:
                break
            if live < 0.75 * moving.numel():
                flush(~moving)
                state = (rays, voxel, step, t_max, t_delta, was_inside)
                rays, voxel, step, t_max, t_delta, was_inside = (t[moving] for t in state)
                alive, last_t, last_label = (
                    alive[:, moving],
                    last_t[:, moving],
                    last_label[:, moving],
                )
    flush(torch.ones_like(was_inside))
    return distance, hit


def _march_compiled(
    labels: np.ndarray,  # (G, X, Y, Z) integer, C-contiguous (see _kernel_labels)
    origin: Tensor,  # (N, 3) float64 voxel units, on the CPU
    unit: Tensor,  # (N, 3) float64 unit directions
    free_label: int,
) -> tuple[Tensor, Tensor]:
    """:func:`_march` (without ``visited``) in the compiled CPU kernel; identical results."""
    units, hits = _march_numba.first_hits(
        labels,
        origin.numpy(),
        unit.numpy(),
        labels[:, 0, 0, 0].astype(np.int64),
        free_label,
        MAX_STEPS,
        torch.get_num_threads(),
    )
    return torch.from_numpy(units), torch.from_numpy(hits)


CPU_KERNEL = os.environ.get("DEGO_CPU_KERNEL", "auto")
"""How CPU casts are traversed: ``"auto"`` (the compiled kernel when numba is installed,
else torch), ``"numba"`` (the compiled kernel; ``ImportError`` without numba) or
``"torch"`` (the vectorised torch loop, as on CUDA). Both give identical hits. The
environment variable ``DEGO_CPU_KERNEL`` sets the default."""


def cpu_kernel() -> str:
    """The traversal CPU casts use now: ``"numba"`` or ``"torch"`` (resolves ``"auto"``)."""
    choice = CPU_KERNEL
    if choice not in ("auto", "numba", "torch"):
        raise ValueError(
            f"dego.raycast.CPU_KERNEL: expected 'auto', 'numba' or 'torch', got {choice!r}"
        )
    if choice == "numba" and not _march_numba.available():
        raise ImportError(
            'dego.raycast.CPU_KERNEL is "numba" but numba is not installed '
            '(pip install -e ".[eval]" in your dego clone)'
        )
    if choice == "auto":
        return "numba" if _march_numba.available() else "torch"
    return choice


def _kernel_labels(labels: Sequence[Tensor]) -> np.ndarray:
    """The grids as one C-contiguous ``(G, X, Y, Z)`` array of the narrowest integer type
    that holds every label (uint8 for label sets such as Occ3D's)."""
    stacked = torch.stack(list(labels))
    if stacked.dtype != torch.uint8:
        low, high = (int(v) for v in torch.aminmax(stacked))
        stacked = stacked.to(torch.uint8 if 0 <= low and high <= 255 else torch.int64)
    return np.ascontiguousarray(stacked.numpy())


def cast_bytes(num_rays: int, grid: VoxelGrid, out_bytes_per_ray: int) -> int:
    """Estimated peak bytes of casting ``num_rays`` rays through ``grid``."""
    x, y, z = grid.shape
    padded = (x + 2) * (y + 2) * (z + 2) * (8 + 1 + 1)  # labels, in-grid mask, visited
    return num_rays * out_bytes_per_ray + min(num_rays, CHUNK_RAYS) * WORK_BYTES_PER_RAY + padded


def cast_sizes(num_rays: int, grid: VoxelGrid) -> str:
    return f"{num_rays} rays through a {grid.shape[0]} x {grid.shape[1]} x {grid.shape[2]} grid"


@eager_only  # see cast_product
def _traverse(
    labels: Sequence[Tensor],  # G grids (X, Y, Z), any integer dtype, traversed together
    num_rays: int,
    chunks: Iterable[tuple[Tensor, Tensor]],  # broadcastable (origins, directions) blocks
    grid: VoxelGrid,
    free_label: int,
    sparseocc: bool,
    visited: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """``(G, num_rays)`` first hits of every ray in every grid, block by block (each block
    is :func:`_voxel_rays`'s input; together they flatten to the ``num_rays`` rays in
    order): float32 (SparseOcc mode) or float64 metres and int64 labels."""
    device = labels[0].device
    compiled = visited is None and device.type == "cpu" and cpu_kernel() == "numba"
    label_array = _kernel_labels(labels) if compiled else None
    padded = [] if compiled else [_pad(grid_labels.long()) for grid_labels in labels]
    shape = (len(labels), num_rays)
    distance = torch.empty(
        shape, dtype=torch.float32 if sparseocc else torch.float64, device=device
    )
    hit = torch.empty(shape, dtype=torch.int64, device=device)
    begin = 0
    for origins, directions in chunks:
        start, unit, metres = _voxel_rays(origins, directions, grid, sparseocc)
        stop = begin + start.shape[0]
        if label_array is not None:
            units, hit[:, begin:stop] = _march_compiled(label_array, start, unit, free_label)
        else:
            units, hit[:, begin:stop] = _march(padded, start, unit, free_label, visited)
        if sparseocc:  # float32 voxel-unit distances scaled in float32, as the reference does
            distance[:, begin:stop] = units.float() * metres.float()
        else:
            distance[:, begin:stop] = units * metres
        begin = stop
    return distance, hit


def _product_chunks(origins: Tensor, directions: Tensor) -> Iterator[tuple[Tensor, Tensor]]:
    """Every direction from every origin, origin-major, in blocks of at most about
    :data:`CHUNK_RAYS` rays: whole origins ``(k, 1, 3)`` x ``(1, R, 3)`` while R fits,
    else ``(n, 3)`` pairs gathered from the flat ray index."""
    k, r = origins.shape[0], directions.shape[0]
    if k == 0 or r == 0:
        return
    if r <= CHUNK_RAYS:
        per = CHUNK_RAYS // r
        for first in range(0, k, per):
            yield origins[first : first + per, None], directions[None]
        return
    for begin in range(0, k * r, CHUNK_RAYS):
        index = torch.arange(begin, min(begin + CHUNK_RAYS, k * r), device=origins.device)
        yield origins[index // r], directions[index % r]


# Data-dependent by nature (rays retire as they hit): run eagerly under torch.compile, as
# one graph break, rather than letting dynamo split it at every compaction.
@eager_only
def cast_product(
    labels: Sequence[Tensor],
    origins: Tensor,
    directions: Tensor,
    grid: VoxelGrid,
    free_label: int,
    what: str,
    extra_bytes_per_ray: int = 0,
) -> tuple[Tensor, Tensor]:
    """:func:`cast_rays` through each of the G grids ``labels`` (integers, on one device)
    after the checks of its callers: every direction from every origin, origin-major,
    one traversal for all grids; ``(G, K R)`` distances and labels. ``what`` names the
    caller in the memory guard."""
    out_dtype, sparseocc = _ray_mode(origins, directions)
    _check_rays(origins, directions)
    n = origins.shape[0] * directions.shape[0]
    out_bytes = ((4 if sparseocc else 8) + 8) * len(labels) + extra_bytes_per_ray
    check_memory(what, cast_bytes(n, grid, out_bytes), cast_sizes(n, grid))
    device = labels[0].device
    origins, directions = origins.to(device), directions.to(device)
    chunks = _product_chunks(origins, directions)
    distance, hit = _traverse(labels, n, chunks, grid, free_label, sparseocc)
    return distance.to(out_dtype), hit


@typechecked
def cast_rays(
    labels: Integer[Tensor, "X Y Z"],
    origins: Float[Tensor, "K 3"],
    directions: Float[Tensor, "R 3"],
    grid: VoxelGrid,
    free_label: int = FREE_LABEL,
) -> tuple[Float[Tensor, " KR"], Integer[Tensor, " KR"]]:
    """Cast every direction from every origin through a label grid; first hits.

    Args:
        labels: ``(X, Y, Z)`` labels on ``grid``, any integer dtype (uint8 as Occ3D ships
            them, int8 ... int64; results do not depend on the dtype). Every value but
            ``free_label`` is occupied, negative ones (such as -1) and ones above the
            class range (such as 255) included; the hit label is returned as stored.
        origins: ``(K, 3)`` ray origins in metres (grid frame); may lie outside the grid.
            Finite.
        directions: ``(R, 3)`` ray directions, finite and non-zero, of any length (scaled
            by an exact power of two to about 1 before use: see the module docstring).
            Same dtype as ``origins``, or float32 with float64 ``origins`` (SparseOcc's
            convention).
        grid: the voxel grid of ``labels``.
        free_label: the empty label.

    Returns:
        ``hit_distance (K R,)`` metres along the ray (origin-major: ray ``k R + r``;
        negative, ``-voxel_size``, where the ray never enters the grid), in the
        directions' dtype (float32 in SparseOcc mode, float64 for float64 inputs, the
        input dtype for float16 / bfloat16, computed in float32), and ``hit_label (K R,)``
        int64 (usually ``free_label`` where nothing is hit; see the module docstring for
        rays that never enter). K = 0 or R = 0 give empty results.

    Raises:
        TypeError: non-integer (bool, floating) ``labels``; ``origins`` and
            ``directions`` of different floating dtypes (other than float64 / float32).
        ValueError: ``labels`` not of ``grid``'s shape; non-finite ``origins`` or
            ``directions``; a zero direction; an estimated memory need above
            :func:`dego.set_memory_limit`'s limit (checked before allocating).
    """
    labels = _label_grid("labels", labels, grid)
    distance, hit = cast_product([labels], origins, directions, grid, free_label, "cast_rays")
    return distance[0], hit[0]


@typechecked
def observed_voxels(
    labels: Integer[Tensor, "X Y Z"],
    origins: Float[Tensor, "N 3"],
    directions: Float[Tensor, "N 3"],
    grid: VoxelGrid,
    free_label: int = FREE_LABEL,
) -> Bool[Tensor, "X Y Z"]:
    """Voxels seen along rays: every voxel ray i (from ``origins[i]`` along
    ``directions[i]``, paired) passes through, up to and including its first occupied
    voxel, as Occ3D defines its camera and LiDAR visibility masks.

    Same traversal, input rules and errors as :func:`cast_rays` (labels of any integer
    dtype, every value but ``free_label`` occupied; finite origins; finite non-zero
    directions of any length; the same dtype rule; the memory guard). N = 0 gives an
    all-False mask.

    Args:
        labels: ``(X, Y, Z)`` integer labels on ``grid``.
        origins: ``(N, 3)`` ray origins in metres.
        directions: ``(N, 3)`` ray directions, paired with ``origins``.
        grid: the voxel grid of ``labels``.
        free_label: the empty label.

    Returns:
        ``(X, Y, Z)`` bool mask on ``labels``' device.
    """
    labels = _label_grid("labels", labels, grid)
    _, sparseocc = _ray_mode(origins, directions)
    _check_rays(origins, directions)
    n = origins.shape[0]
    check_memory("observed_voxels", cast_bytes(n, grid, 12), cast_sizes(n, grid))
    device = labels.device
    x, y, z = grid.shape
    visited = torch.zeros((x + 2) * (y + 2) * (z + 2), dtype=torch.bool, device=device)
    if n:
        origins, directions = origins.to(device), directions.to(device)
        chunks = (
            (origins[begin : begin + CHUNK_RAYS], directions[begin : begin + CHUNK_RAYS])
            for begin in range(0, n, CHUNK_RAYS)
        )
        _traverse([labels], n, chunks, grid, free_label, sparseocc, visited)
    return visited.view(x + 2, y + 2, z + 2)[1:-1, 1:-1, 1:-1].clone()


__all__ = [
    "CHUNK_RAYS",
    "CPU_KERNEL",
    "MAX_STEPS",
    "cast_rays",
    "cpu_kernel",
    "generate_lidar_rays",
    "observed_voxels",
]
