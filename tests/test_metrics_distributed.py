"""OccupancyMetrics.sync across two real processes (gloo backend, CPU)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from dego import OccupancyMetrics
from tests.test_metrics import random_sample

SEEDS = list(range(6))


def _worker(rank: int, world_size: int, init_file: str, out_dir: str) -> None:
    dist.init_process_group(
        "gloo", init_method=f"file://{init_file}", rank=rank, world_size=world_size
    )
    try:
        metrics = OccupancyMetrics("weak")
        for seed in SEEDS[rank::world_size]:  # each rank sees half of the data
            metrics.update(*random_sample(seed))
        local = metrics.confusion.clone()
        report = metrics.sync().compute()
        again = metrics.sync().compute()  # syncing twice must not double-count
        torch.save(
            {
                "per_class": report.per_class,
                "miou": report.miou,
                "iou": report.iou,
                "again_miou": again.miou,
                "local_unchanged": torch.equal(local, metrics.confusion),
            },
            Path(out_dir) / f"rank{rank}.pt",
        )
    finally:
        dist.destroy_process_group()


@pytest.mark.slow
def test_two_process_sync_equals_single_process(tmp_path: Path) -> None:
    if not dist.is_available():
        pytest.skip("torch.distributed is not available in this build")
    single = OccupancyMetrics("weak")
    for seed in SEEDS:
        single.update(*random_sample(seed))
    expected = single.compute()

    mp.spawn(_worker, args=(2, str(tmp_path / "init"), str(tmp_path)), nprocs=2, join=True)
    for rank in range(2):
        result = torch.load(tmp_path / f"rank{rank}.pt", weights_only=True)
        np.testing.assert_array_equal(result["per_class"].numpy(), expected.per_class.numpy())
        assert result["miou"] == expected.miou == result["again_miou"]
        assert result["iou"] == expected.iou
        assert result["local_unchanged"]
