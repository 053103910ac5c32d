"""Issue 41 (7): dego's metrics called like torchmetrics' (``metric(pred, gt, mask)``
updates and returns the batch's value) and the adapters' ``plot()``."""

from __future__ import annotations

import pytest
import torch

import dego

SHAPE = (2, 12, 10, 4)


def labels(seed: int) -> torch.Tensor:
    return torch.randint(0, 18, SHAPE, generator=torch.Generator().manual_seed(seed)).to(
        torch.uint8
    )


def same(values: dict[str, float]) -> object:
    """Equal values, NaN (an absent class) equal to NaN."""
    return pytest.approx(values, rel=0, abs=0, nan_ok=True)


def test_calling_occupancy_metrics_updates_and_returns_the_batch_report() -> None:
    metric, whole = dego.OccupancyMetrics("occ3d"), dego.OccupancyMetrics("occ3d")
    mask = torch.rand(SHAPE, generator=torch.Generator().manual_seed(9)) < 0.8
    for seed in range(3):
        pred, gt = labels(seed), labels(10 + seed)
        batch = metric(pred, gt, mask)
        alone = dego.OccupancyMetrics("occ3d")
        alone.update(pred, gt, mask)
        assert batch.as_dict() == same(alone.compute().as_dict())  # this batch's value only
        whole.update(pred, gt, mask)
    assert metric.compute().as_dict() == same(whole.compute().as_dict())  # accumulated
    assert torch.equal(metric.confusion, whole.confusion)
    with pytest.raises(ValueError, match="mask"):  # update's checks and errors
        metric(labels(0), labels(1), torch.ones(3, 3, 3, dtype=torch.bool))


def test_calling_rayiou_updates_and_returns_the_batch_report() -> None:
    metric, whole = dego.RayIoU(), dego.RayIoU()
    grid = torch.full((200, 200, 16), 17, dtype=torch.uint8)
    grid[:, :, 0] = 11
    grid[120:130, 95:105, 1:5] = 4
    pred = grid.clone()
    pred[120:125, 95:105, 1:5] = 17
    origins = torch.tensor([[0.94, 0.0, 1.84]], dtype=torch.float64)
    batch = metric(pred, grid, origins)
    whole.update(pred, grid, origins)
    assert batch.as_dict() == same(whole.compute().as_dict())
    assert metric.compute().as_dict() == same(whole.compute().as_dict())


def test_the_torchmetrics_adapters_plot() -> None:
    pytest.importorskip("torchmetrics")
    pytest.importorskip("matplotlib")
    from dego.compat.torchmetrics import OccupancyMetric

    for value in ("miou", "all"):
        metric = OccupancyMetric("occ3d", value=value)
        metric.update(labels(0), labels(1), None)
        figure, axes = metric.plot()
        assert figure.axes and axes in figure.axes
        figure, _ = metric.plot([metric.compute(), metric.compute()])  # one per epoch
        assert figure.axes
