"""RayIoU.sync across two real processes (gloo backend, CPU)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from dego.metrics import RayIoU
from tests.test_rayiou import SMALL_GRID, SMALL_RAYS, random_scene

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
