"""RayIoU.sync across two real processes (gloo backend, CPU)."""

from __future__ import annotations

import datetime
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from dego.grid import VoxelGrid
from dego.metrics import RayIoU
from tests.helpers.rayiou import SMALL_GRID, SMALL_RAYS, random_scene
from tests.helpers.sync_checks import assert_refused_on_every_rank

SEEDS = list(range(4))
COUNTS = ("gt_count", "pred_count", "true_positives")


def _worker(rank: int, world_size: int, init_file: str, out_dir: str) -> None:
    dist.init_process_group(
        "gloo", init_method=f"file://{init_file}", rank=rank, world_size=world_size
    )
    try:
        metric = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
        for seed in SEEDS[rank::world_size]:  # each rank sees half of the data
            metric.update(*random_scene(seed))
        local = {name: getattr(metric, name).clone() for name in COUNTS}
        report = metric.sync().compute()
        again = metric.sync().compute()  # syncing twice must not double-count
        torch.save(
            {
                "per_class": report.per_class,
                "at": torch.tensor(report.at, dtype=torch.float64),
                "rayiou": report.rayiou,
                "again_per_class": again.per_class,
                "local_unchanged": all(
                    torch.equal(local[name], getattr(metric, name)) for name in COUNTS
                ),
                "local_is_partial": bool(local["gt_count"].sum() > 0),
            },
            Path(out_dir) / f"rank{rank}.pt",
        )
    finally:
        dist.destroy_process_group()


@pytest.mark.slow
def test_two_process_sync_equals_single_process(tmp_path: Path) -> None:
    if not dist.is_available():
        pytest.skip("torch.distributed is not available in this build")
    single = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    for seed in SEEDS:
        single.update(*random_scene(seed))
    expected = single.compute()

    mp.spawn(_worker, args=(2, str(tmp_path / "init"), str(tmp_path)), nprocs=2, join=True)
    for rank in range(2):
        result = torch.load(tmp_path / f"rank{rank}.pt", weights_only=True)
        np.testing.assert_array_equal(result["per_class"].numpy(), expected.per_class.numpy())
        np.testing.assert_array_equal(result["again_per_class"].numpy(), expected.per_class.numpy())
        np.testing.assert_array_equal(result["at"].numpy(), np.asarray(expected.at))
        assert result["rayiou"] == expected.rayiou
        assert result["local_unchanged"] and result["local_is_partial"]


# ---------------------------------------------------------------------------------------
# differently configured ranks: sync refuses on every rank
# ---------------------------------------------------------------------------------------

SHIFTED_GRID = VoxelGrid((-3.6, -4.0, -1.0), (4.4, 4.0, 1.4), 0.4)  # SMALL_GRID's shape
MISMATCHES = {  # case: (rank 0's configuration, rank 1's)
    "thresholds": ({}, {"thresholds": (0.5, 1.0, 2.0)}),
    "grid": ({}, {"grid": SHIFTED_GRID}),
    # a (T, C) count of another shape: never reaches the all_reduce
    "threshold_count": ({}, {"thresholds": (1.0, 2.0)}),
}


def _mismatch_worker(rank: int, world_size: int, init_file: str, out_dir: str) -> None:
    dist.init_process_group(
        "gloo",
        init_method=f"file://{init_file}",
        rank=rank,
        world_size=world_size,
        timeout=datetime.timedelta(seconds=60),  # a collective left waiting fails the test
    )
    try:
        results = {}
        for case, configs in MISMATCHES.items():  # every case in one process group, in turn
            metric = RayIoU(**{"grid": SMALL_GRID, "rays": SMALL_RAYS, **configs[rank]})
            metric.update(*random_scene(rank, grid=metric.grid))
            try:
                results[case] = f"no error: rayiou {metric.sync().compute().rayiou}"
            except Exception as err:  # the test reports what was raised
                results[case] = f"{type(err).__name__}: {err}"
            results[case + "/config"] = repr(metric._config())
        # after the refusals the group still works: a well-configured sync pools both ranks
        metric = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
        metric.update(*random_scene(rank))
        results["after"] = metric.sync().compute().per_class
        torch.save(results, Path(out_dir) / f"rank{rank}.pt")
    finally:
        dist.destroy_process_group()


@pytest.mark.slow
def test_sync_of_differently_configured_ranks_raises_on_every_rank(tmp_path: Path) -> None:
    if not dist.is_available():
        pytest.skip("torch.distributed is not available in this build")
    merged = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    for rank in range(2):
        part = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
        part.update(*random_scene(rank))
        merged.merge(part)

    mp.spawn(_mismatch_worker, args=(2, str(tmp_path / "init"), str(tmp_path)), nprocs=2, join=True)
    results = [torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in range(2)]
    assert_refused_on_every_rank(results, MISMATCHES, merged.compute().per_class)
    assert "thresholds [1.0, 2.0, 4.0] vs [0.5, 1.0, 2.0]" in results[0]["thresholds"]
    assert "vs [[-3.6, -4.0, -1.0], [4.4, 4.0, 1.4]" in results[0]["grid"]
    assert "thresholds [1.0, 2.0] vs [1.0, 2.0, 4.0]" in results[1]["threshold_count"]
