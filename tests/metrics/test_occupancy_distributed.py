"""OccupancyMetrics.sync across two real processes (gloo backend, CPU)."""

from __future__ import annotations

import datetime
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from dego import OccupancyMetrics
from tests.helpers.metrics import random_sample
from tests.helpers.sync_checks import assert_refused_on_every_rank

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


# ---------------------------------------------------------------------------------------
# differently configured ranks: sync refuses on every rank
# ---------------------------------------------------------------------------------------

MISMATCHES = {  # case: (rank 0's configuration, rank 1's)
    "protocol": ({"protocol": "occ3d"}, {"protocol": "weak"}),
    "ignore_label": ({"ignore_label": 255}, {"ignore_label": 254}),
    # different count shapes: never reach the all_reduce
    "num_classes": (
        {"protocol": "occ3d"},
        {"protocol": "occ3d", "num_classes": 5, "free_label": 4},
    ),
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
            metrics = OccupancyMetrics(**configs[rank])
            if metrics.num_classes == 18:
                metrics.update(*random_sample(rank))
            try:
                results[case] = f"no error: miou {metrics.sync().compute().miou}"
            except Exception as err:  # the test reports what was raised
                results[case] = f"{type(err).__name__}: {err}"
            results[case + "/config"] = repr(metrics._config())
        # after the refusals the group still works: a well-configured sync pools both ranks
        metrics = OccupancyMetrics("occ3d")
        metrics.update(*random_sample(rank))
        results["after"] = metrics.sync().compute().per_class
        torch.save(results, Path(out_dir) / f"rank{rank}.pt")
    finally:
        dist.destroy_process_group()


@pytest.mark.slow
def test_sync_of_differently_configured_ranks_raises_on_every_rank(tmp_path: Path) -> None:
    if not dist.is_available():
        pytest.skip("torch.distributed is not available in this build")
    merged = OccupancyMetrics("occ3d")
    for rank in range(2):
        part = OccupancyMetrics("occ3d")
        part.update(*random_sample(rank))
        merged.merge(part)

    mp.spawn(_mismatch_worker, args=(2, str(tmp_path / "init"), str(tmp_path)), nprocs=2, join=True)
    results = [torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in range(2)]
    assert_refused_on_every_rank(results, MISMATCHES, merged.compute().per_class)
    assert "protocol 'occ3d' vs 'weak'" in results[0]["protocol"]
    assert "protocol 'weak' vs 'occ3d'" in results[1]["protocol"]
    assert "ignore_label 254 vs 255" in results[1]["ignore_label"]
    assert "num_classes 18 vs 5" in results[0]["num_classes"]
