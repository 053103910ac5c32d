"""The first-hit traversal of :mod:`dego.raycast` as a compiled CPU kernel (numba).

One loop per ray, in parallel over blocks of rays: the same Amanatides-Woo steps, float64
state, tie-break, exit distances, placeholders and step limit as the torch traversal
(``dego.raycast._march``), so the hits are bit-identical (the tests compare them). Every
ray is traversed once for all label grids it is cast through (RayIoU's prediction and
ground truth share rays): it stops when every grid has been hit or it leaves the grid.

numba is an optional dependency (``pip install -e ".[eval]"`` from the clone); it is imported
on first use only. The kernel is compiled on its first call (a few seconds) and cached
on disk (numba's ``cache=True``: next to this file, or numba's user-wide cache when that
is not writable).

The kernel itself is serial and releases the GIL; the blocks run on a thread pool of
``torch.get_num_threads()`` threads. numba's own parallel backends are not used: its
OpenMP layer spin-waits beside torch's (two evaluation processes on two cores ran 10x
slower), its workqueue layer is not thread-safe, and choosing a layer would change the
process-wide setting of the user's own numba code.
"""

from __future__ import annotations

import functools
import itertools
import math
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np


def available() -> bool:
    """Whether numba can be imported."""
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


BLOCKS_PER_THREAD = 4
"""Rays are split into this many blocks per thread (rays finish at different depths)."""


def _kernel_source() -> Callable[..., None]:
    def first_hits(labels, start, unit, free_label, max_steps, begin, stop, out_t, out_label):
        grids, size_x, size_y, size_z = labels.shape
        everyone = (1 << grids) - 1
        reach = max_steps + 3.0  # one voxel of margin, and a step moves one voxel
        for i in range(begin, stop):
            ox, oy, oz = start[i, 0], start[i, 1], start[i, 2]
            if not (
                -reach < ox < size_x + reach
                and -reach < oy < size_y + reach
                and -reach < oz < size_z + reach
            ):
                continue  # too far to reach the grid: the caller's placeholders stay
            dx, dy, dz = unit[i, 0], unit[i, 1], unit[i, 2]
            vx, vy, vz = int(ox), int(oy), int(oz)  # truncation toward zero
            sx = 1 if dx >= 0 else -1
            sy = 1 if dy >= 0 else -1
            sz = 1 if dz >= 0 else -1
            tmx = (vx + (1.0 if sx > 0 else 0.0) - ox) / dx if dx != 0 else math.inf
            tmy = (vy + (1.0 if sy > 0 else 0.0) - oy) / dy if dy != 0 else math.inf
            tmz = (vz + (1.0 if sz > 0 else 0.0) - oz) / dz if dz != 0 else math.inf
            tdx = sx / dx if dx != 0 else math.inf
            tdy = sy / dy if dy != 0 else math.inf
            tdz = sz / dz if dz != 0 else math.inf
            was_inside = False
            alive = everyone
            for _ in range(max_steps + 1):
                inside = 0 <= vx < size_x and 0 <= vy < size_y and 0 <= vz < size_z
                # the axis crossed next (the voxel's exit), with the reference's tie-break
                axis = (0 if tmx < tmz else 2) if tmx < tmy else (1 if tmy < tmz else 2)
                if inside:
                    exit_t = tmx if axis == 0 else (tmy if axis == 1 else tmz)
                    for g in range(grids):
                        if alive & (1 << g):
                            label = labels[g, vx, vy, vz]
                            out_t[g, i] = exit_t
                            out_label[g, i] = label
                            if label != free_label:
                                alive &= ~(1 << g)
                    was_inside = True
                    if alive == 0:
                        break
                elif was_inside:
                    break  # left the grid after having been inside
                elif (
                    (vx < 0 and sx < 0)
                    or (vx >= size_x and sx > 0)
                    or (vy < 0 and sy < 0)
                    or (vy >= size_y and sy > 0)
                    or (vz < 0 and sz < 0)
                    or (vz >= size_z and sz > 0)
                ):
                    break  # outside on an axis and moving away along it: never enters
                if axis == 0:
                    vx += sx
                    tmx += tdx
                elif axis == 1:
                    vy += sy
                    tmy += tdy
                else:
                    vz += sz
                    tmz += tdz

    return first_hits


@functools.cache
def _compiled() -> Callable[..., None]:
    import numba

    source = _kernel_source()
    try:
        return numba.njit(cache=True, nogil=True)(source)
    except RuntimeError:  # no writable cache location: compile per process
        return numba.njit(nogil=True)(source)


_POOL_LOCK = threading.Lock()
_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0


def _forget_pool() -> None:  # a forked child has none of the parent's threads
    global _POOL, _POOL_SIZE
    _POOL, _POOL_SIZE = None, 0


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def _pool(threads: int) -> ThreadPoolExecutor:
    global _POOL, _POOL_SIZE
    with _POOL_LOCK:
        if _POOL is None or _POOL_SIZE != threads:
            if _POOL is not None:
                _POOL.shutdown(wait=False)
            _POOL = ThreadPoolExecutor(threads, thread_name_prefix="dego-raycast")
            _POOL_SIZE = threads
        return _POOL


def first_hits(
    labels: np.ndarray,  # (G, X, Y, Z) integer, C-contiguous
    start: np.ndarray,  # (N, 3) float64 voxel units
    unit: np.ndarray,  # (N, 3) float64 unit directions
    corner: np.ndarray,  # (G,) int64: each grid's label of voxel (0, 0, 0)
    free_label: int,
    max_steps: int,
    threads: int,
) -> tuple[np.ndarray, np.ndarray]:
    """``(G, N)`` float64 exit distances (voxel units) and int64 labels of each ray's
    first hit in each grid, with the reference's placeholders (-1, the corner label)
    for rays that never enter."""
    grids, n = labels.shape[0], start.shape[0]
    out_t = np.full((grids, n), -1.0)
    out_label = np.repeat(corner.astype(np.int64)[:, None], n, axis=1)
    kernel = _compiled()
    args = (labels, start, unit, free_label, max_steps)
    blocks = max(1, min(threads * BLOCKS_PER_THREAD, n // 1024))
    if threads <= 1 or blocks == 1:
        kernel(*args, 0, n, out_t, out_label)
        return out_t, out_label
    bounds = np.linspace(0, n, blocks + 1).astype(np.int64)
    futures = [
        _pool(threads).submit(kernel, *args, int(lo), int(hi), out_t, out_label)
        for lo, hi in itertools.pairwise(bounds)
    ]
    for future in futures:
        future.result()
    return out_t, out_label


__all__: list[str] = []
