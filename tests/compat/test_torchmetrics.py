"""dego.compat.torchmetrics: OccupancyMetric and RayIoUMetric agree with dego's own classes
(update, forward, compute, report), in a MetricCollection, across two real processes and in
a Lightning run; conflicting configurations never share counts silently."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

torchmetrics = pytest.importorskip("torchmetrics")  # the wheel stage has no extra: skip

import torch  # noqa: E402
import torch.distributed as dist  # noqa: E402
import torch.multiprocessing as mp  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from torchmetrics import MetricCollection  # noqa: E402

from dego import OccupancyMetrics  # noqa: E402
from dego.compat.torchmetrics import OccupancyMetric, RayIoUMetric  # noqa: E402
from dego.metrics import RayIoU  # noqa: E402
from tests.helpers.metrics import random_sample  # noqa: E402
from tests.helpers.rayiou import SMALL_GRID, SMALL_RAYS, random_scene  # noqa: E402

FREE = 17


def as_value(value: float, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return torch.tensor(value, dtype=dtype)


def assert_same(actual: torch.Tensor, expected: float) -> None:
    torch.testing.assert_close(actual, as_value(expected), rtol=0, atol=0, equal_nan=True)


def dego_scores(samples, protocol: str = "weak"):
    metric = OccupancyMetrics(protocol)
    for sample in samples:
        metric.update(*sample)
    return metric.compute()


def without_others(seed: int, shape=(6, 5, 4)):
    """A sample whose gt has no others (0), other_flat (12) or ignore voxels, on which the weak
    and occ3d protocols count exactly the same."""
    pred, gt, mask = random_sample(seed, shape)
    gt[(gt == 0) | (gt == 12)] = FREE
    return pred, gt, mask


# ---------------------------------------------------------------------------------------
# agreement with dego's classes
# ---------------------------------------------------------------------------------------


@settings(max_examples=25)
@given(
    st.lists(st.integers(0, 10_000), min_size=1, max_size=3),
    st.sampled_from(["weak", "occ3d", "surroundocc"]),
    st.sampled_from(["miou", "iou", "hcm", "iou/car"]),
)
def test_forward_update_and_compute_equal_occupancy_metrics(
    seeds: list[int], protocol: str, value: str
) -> None:
    samples = [random_sample(s) for s in seeds]
    metric, pooled = OccupancyMetric(protocol, value=value), OccupancyMetrics(protocol)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no voxel predicted free" on tiny grids
        for sample in samples:
            batch = metric(*sample)  # forward: update + this batch's value
            assert batch.shape == () and batch.dtype == torch.float32
            assert_same(batch, dego_scores([sample], protocol).as_dict()[value])
            pooled.update(*sample)
        expected = pooled.compute()
        assert_same(metric.compute(), expected.as_dict()[value])
        report = metric.report()
    assert torch.equal(metric.confusion, pooled.confusion)
    assert torch.equal(metric.geometric, pooled.geometric)
    np.testing.assert_array_equal(report.per_class.numpy(), expected.per_class.numpy())
    np.testing.assert_equal(report.as_dict(), expected.as_dict())  # NaN == NaN here
    assert metric.update_count == len(samples)


def test_dict_values_and_dtype() -> None:
    samples = [random_sample(s, shape=(8, 8, 4)) for s in range(3)]
    expected = dego_scores(samples).as_dict()
    every, per_class = OccupancyMetric(value="all"), OccupancyMetric(value="per_class")
    for sample in samples:
        every.update(*sample)
        per_class.update(*sample)
    got = every.compute()
    assert list(got) == list(expected)
    for key, value in expected.items():
        assert_same(got[key], value)
    assert list(per_class.compute()) == [k for k in expected if k.startswith("iou/")]
    precise = OccupancyMetric().set_dtype(torch.float64)  # the values' dtype
    for sample in samples:
        precise.update(*sample)
    assert precise.confusion.dtype == torch.int64  # the counts stay int64
    assert precise.compute().dtype == torch.float64
    assert precise.compute().item() == expected["miou"]


def test_rayiou_metric_equals_rayiou() -> None:
    scenes = [random_scene(s) for s in range(3)]
    metric = RayIoUMetric(grid=SMALL_GRID, rays=SMALL_RAYS)
    thresholds = RayIoUMetric(grid=SMALL_GRID, rays=SMALL_RAYS, value="per_threshold")
    pooled = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    for scene in scenes:
        single = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
        single.update(*scene)
        assert_same(metric(*scene), single.compute().rayiou)  # forward: the sample's value
        thresholds.update(*scene)
        pooled.update(*scene)
    expected = pooled.compute()
    assert_same(metric.compute(), expected.rayiou)
    per_threshold = thresholds.compute()
    assert list(per_threshold) == ["rayiou@1", "rayiou@2", "rayiou@4"]
    for got, at in zip(per_threshold.values(), expected.at, strict=True):
        assert_same(got, at)
    report = metric.report()
    np.testing.assert_array_equal(report.per_class.numpy(), expected.per_class.numpy())
    np.testing.assert_equal(report.as_dict(), expected.as_dict())
    for name in ("gt_count", "pred_count", "true_positives"):
        assert torch.equal(getattr(metric, name), getattr(pooled, name))
    assert set(metric.state_dict()) == set()  # neither counts nor rays


def test_runs_on_the_device(device: torch.device) -> None:
    sample = [torch.from_numpy(a).to(device) for a in random_sample(6)]
    metric = OccupancyMetric("weak", device=device)
    batch = metric(*sample)
    assert metric.confusion.device.type == batch.device.type == device.type
    assert_same(metric.compute().cpu(), dego_scores([[a.cpu() for a in sample]]).miou)
    rays = RayIoUMetric(grid=SMALL_GRID, rays=SMALL_RAYS).to(device)
    pred, gt, origins = (torch.from_numpy(a).to(device) for a in random_scene(2))
    rays.update(pred, gt, origins)
    on_cpu = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    on_cpu.update(*random_scene(2))
    assert rays.true_positives.device.type == device.type
    assert torch.equal(rays.true_positives.cpu(), on_cpu.true_positives)


def test_metric_collection_with_both_metrics_and_reset() -> None:
    pred, gt, origins = random_scene(4)
    mask = np.random.default_rng(0).random(gt.shape) < 0.8
    collection = MetricCollection(
        {
            "occupancy": OccupancyMetric("weak", value="all"),  # a dict: flattened
            "rayiou": RayIoUMetric(grid=SMALL_GRID, rays=SMALL_RAYS),
        },
        prefix="val/",
    )
    # positional arguments go to every metric, keywords to the metrics whose update has them
    batch = collection(pred, gt, mask=mask, origins=origins)
    occupancy = dego_scores([(pred, gt, mask)])
    rays = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    rays.update(pred, gt, origins)
    assert_same(batch["val/miou"], occupancy.miou)
    assert_same(batch["val/rayiou"], rays.compute().rayiou)
    assert_same(batch["val/iou/car"], occupancy.as_dict()["iou/car"])
    collection.update(pred, gt, mask=mask, origins=origins)
    result = collection.compute()
    assert_same(result["val/miou"], occupancy.miou)  # the same sample twice: same scores
    assert_same(result["val/rayiou"], rays.compute().rayiou)
    assert set(result) == {"val/miou", "val/rayiou", *(f"val/{k}" for k in occupancy.as_dict())}
    assert int(collection["occupancy"].confusion.sum()) == 2 * occupancy_count(pred, gt, mask)

    collection.reset()
    for metric in collection.values():
        for name, default in metric._defaults.items():  # zero counts, own fingerprint
            assert torch.equal(getattr(metric, name), default), name
    single = collection["occupancy"]
    assert int(single.confusion.sum()) == 0
    with (
        pytest.warns(UserWarning, match="before the ``update``"),  # torchmetrics' warning
        pytest.raises(RuntimeError, match="no voxel has been evaluated"),
    ):
        single.compute()
    single.update(pred, gt, mask)  # usable again
    assert_same(single.compute()["miou"], occupancy.miou)


def occupancy_count(pred, gt, mask) -> int:
    metric = OccupancyMetrics("weak")
    metric.update(pred, gt, mask)
    return int(metric.confusion.sum())


# ---------------------------------------------------------------------------------------
# conflicting configurations
# ---------------------------------------------------------------------------------------


def test_auto_compute_groups_share_only_identical_configurations() -> None:
    """weak and occ3d count the same on these samples, so torchmetrics' state comparison alone
    would merge them; the configuration fingerprint keeps them apart, while two values of
    one configuration share their counts."""
    samples = [without_others(s) for s in range(3)]
    collection = MetricCollection(
        {
            "weak": OccupancyMetric("weak"),
            "weak_iou": OccupancyMetric("weak", value="iou"),
            "occ3d": OccupancyMetric("occ3d"),
        }
    )
    for sample in samples:
        collection.update(*sample)
    assert torch.equal(collection["weak"].confusion, collection["occ3d"].confusion)
    groups = sorted(sorted(members) for members in collection.compute_groups.values())
    assert groups == [["occ3d"], ["weak", "weak_iou"]]
    result = collection.compute()
    assert_same(result["weak"], dego_scores(samples, "weak").miou)
    assert_same(result["occ3d"], dego_scores(samples, "occ3d").miou)
    assert_same(result["weak_iou"], dego_scores(samples, "weak").iou)


@pytest.mark.parametrize("step", ["update", "forward"])
def test_an_explicit_compute_group_of_two_configurations_raises(step: str) -> None:
    collection = MetricCollection(
        {"weak": OccupancyMetric("weak"), "occ3d": OccupancyMetric("occ3d")},
        compute_groups=[["weak", "occ3d"]],
    )
    getattr(collection, step)(*random_sample(0))
    with pytest.raises(
        ValueError, match=r"counts of another configuration.*protocol 'weak' vs 'occ3d'"
    ):
        collection.compute()
    ray_collection = MetricCollection(
        {
            "a": RayIoUMetric(grid=SMALL_GRID, rays=SMALL_RAYS),
            "b": RayIoUMetric(grid=SMALL_GRID, rays=SMALL_RAYS, thresholds=(0.5, 1.0, 2.0)),
        },
        compute_groups=[["a", "b"]],
    )
    getattr(ray_collection, step)(*random_scene(1))
    with pytest.raises(ValueError, match=r"thresholds \[1\.0, 2\.0, 4\.0\] vs \[0\.5"):
        ray_collection.compute()


@pytest.mark.skipif(
    not hasattr(torchmetrics.Metric, "merge_state"), reason="torchmetrics < 1.4: no merge_state"
)
def test_merge_state_checks_the_configuration() -> None:
    a, b = OccupancyMetric("weak"), OccupancyMetric("weak")
    a.update(*random_sample(0))
    b.update(*random_sample(1))
    a.merge_state(b)
    assert_same(a.compute(), dego_scores([random_sample(0), random_sample(1)]).miou)
    mixed = OccupancyMetric("occ3d")
    mixed.update(*random_sample(2))
    mixed.merge_state(b)
    with pytest.raises(ValueError, match="protocol 'weak' vs 'occ3d'"):
        mixed.compute()


def test_state_dict_checks_the_configuration() -> None:
    a = OccupancyMetric("weak")
    a.update(*random_sample(0))
    a.persistent(True)  # torchmetrics' switch: the states go into state_dict
    state = a.state_dict()
    assert set(state) == {"confusion", "geometric", "config_fingerprint"}
    restored = OccupancyMetric("weak")
    restored.load_state_dict(state)
    assert torch.equal(restored.confusion, a.confusion)
    refusing = OccupancyMetric("occ3d")
    refusing.persistent(True)
    with pytest.raises(ValueError, match="state_dict: saved configuration"):
        refusing.load_state_dict(state)
    assert int(refusing.confusion.sum()) == 0
    lenient = OccupancyMetric("occ3d")  # not persistent: foreign counts ignored, with a warning
    with pytest.warns(UserWarning, match="the saved counts are ignored"):
        lenient.load_state_dict(state)
    assert int(lenient.confusion.sum()) == 0


def test_states_stay_out_of_a_models_state_dict() -> None:
    class Model(torch.nn.Module):
        def __init__(self, with_metrics: bool) -> None:
            super().__init__()
            self.head = torch.nn.Linear(2, 2)
            if with_metrics:
                self.miou = OccupancyMetric("weak")
                self.rayiou = RayIoUMetric(grid=SMALL_GRID, rays=SMALL_RAYS)

    model = Model(with_metrics=True)
    model.miou.update(*random_sample(0))
    state = model.state_dict()
    assert set(state) == {"head.weight", "head.bias"}
    Model(with_metrics=False).load_state_dict(state, strict=True)
    model.miou.persistent(True)
    assert "miou.confusion" in model.state_dict()


# ---------------------------------------------------------------------------------------
# bad input: the errors of dego's classes
# ---------------------------------------------------------------------------------------


def test_bad_input_names_the_argument() -> None:
    pred, gt, mask = random_sample(7)
    bad_gt = gt.copy()
    bad_gt[0, 0, 0] = 18
    metric = OccupancyMetric()
    with pytest.raises(ValueError, match=r"gt: label 18 is out of range; expected 0\.\.17"):
        metric.update(pred, bad_gt, mask)
    with pytest.raises(ValueError, match=r"gt: label 18 is out of range"):
        metric(pred, bad_gt, mask)  # forward too
    with pytest.raises(TypeError, match=r"pred: expected integer labels, got dtype torch\.float"):
        metric.update(pred.astype(np.float32), gt, mask)
    with pytest.raises(ValueError, match="mask: a uint8 mask must hold only 0 and 1"):
        metric.update(pred, gt, mask.astype(np.uint8) * 3)
    with pytest.raises(ValueError, match="gt: expected a label grid"):
        metric.update(pred[0, 0], gt[0, 0])
    with pytest.raises(TypeError):
        metric.update(pred.tolist(), gt)
    assert int(metric.confusion.sum()) == 0  # nothing was counted
    rays = RayIoUMetric(grid=SMALL_GRID, rays=SMALL_RAYS)
    pred, gt, origins = random_scene(0)
    with pytest.raises(ValueError, match=r"origins: expected \(K, 3\)"):
        rays.update(pred, gt, origins[:, :2])
    with pytest.raises(ValueError, match="pred: expected shape"):
        rays.update(pred[:-1], gt, origins)
    with pytest.raises(ValueError, match=r"gt: labels must lie in 0\.\.17, found 255"):
        rays.update(pred, np.full_like(gt, 255), origins)


@pytest.mark.parametrize("protocol", ["occ3d", "weak"])
def test_an_omitted_camera_mask_is_refused_as_by_dego(protocol: str) -> None:
    pred, gt, _ = random_sample(12)
    metric = OccupancyMetric(protocol)
    with pytest.raises(ValueError, match=r"mask: .*camera mask.*mask=None"):
        metric.update(pred, gt)
    with pytest.raises(ValueError, match=r"mask: .*camera mask.*mask=None"):
        metric(pred, gt)  # forward too
    assert int(metric.confusion.sum()) == 0  # nothing was counted
    own = OccupancyMetrics(protocol)
    own.update(pred, gt, mask=None)
    batch = metric(pred, gt, mask=None)  # explicit: every voxel
    assert_same(batch, own.compute().miou)
    assert torch.equal(metric.confusion, own.confusion)
    surroundocc = OccupancyMetric("surroundocc")  # no camera mask in its protocol
    surroundocc.update(pred, gt)
    assert int(surroundocc.confusion.sum()) > 0


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: OccupancyMetric("nusc"), "protocol: expected one of"),
        (lambda: OccupancyMetric(ignore_label=3), "ignore_label: 3 collides"),
        (lambda: OccupancyMetric(value="mIoU"), "value: expected 'miou'"),
        (lambda: OccupancyMetric(value="iou/others"), "value:"),  # not evaluated under weak
        (lambda: RayIoUMetric(thresholds=(0.0,)), "thresholds: expected positive"),
        (lambda: RayIoUMetric(rays=SMALL_RAYS, value="rayiou@3"), "value: expected 'rayiou'"),
        (lambda: OccupancyMetric(dist_sync_on_step=1), "dist_sync_on_step"),  # torchmetrics'
    ],
)
def test_bad_configuration(make, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        make()


# ---------------------------------------------------------------------------------------
# two real processes (gloo): torchmetrics' sync
# ---------------------------------------------------------------------------------------

OCC_SEEDS = list(range(6))
RAY_SEEDS = list(range(4))


def _ddp_worker(rank: int, world_size: int, init_file: str, out_dir: str) -> None:
    dist.init_process_group(
        "gloo", init_method=f"file://{init_file}", rank=rank, world_size=world_size
    )
    try:
        adapter, own = OccupancyMetric("weak"), OccupancyMetrics("weak")
        for seed in OCC_SEEDS[rank::world_size]:  # each rank sees half of the data
            adapter.update(*random_sample(seed))
            own.update(*random_sample(seed))
        ray_adapter = RayIoUMetric(grid=SMALL_GRID, rays=SMALL_RAYS)
        ray_own = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
        for seed in RAY_SEEDS[rank::world_size]:
            ray_adapter.update(*random_scene(seed))
            ray_own.update(*random_scene(seed))
        local = adapter.confusion.clone()
        value, report = adapter.compute(), adapter.report()
        mixed = OccupancyMetric("weak" if rank == 0 else "occ3d")  # a rank configured wrongly
        mixed.update(*random_sample(rank))
        try:
            mixed.compute()
            error = ""
        except ValueError as err:
            error = str(err)
        # issue 38: another metric on each rank (states of other names and shapes, on which
        # gloo's gather aborted): refused on every rank before any state is gathered
        other = OccupancyMetric("weak") if rank == 0 else RayIoUMetric(grid=SMALL_GRID)
        try:
            other.compute()
            kind_error = ""
        except ValueError as err:
            kind_error = str(err)
        torch.save(
            {
                "value": value,
                "per_class": report.per_class,
                "own_per_class": own.sync().compute().per_class,
                "ray_value": ray_adapter.compute(),
                "ray_per_class": ray_adapter.report().per_class,
                "ray_own_per_class": ray_own.sync().compute().per_class,
                "local_unchanged": torch.equal(local, adapter.confusion),
                "error": error,
                "kind_error": kind_error,
            },
            Path(out_dir) / f"rank{rank}.pt",
        )
    finally:
        dist.destroy_process_group()


@pytest.mark.slow
def test_two_process_sync_equals_dego_sync_and_single_process(tmp_path: Path) -> None:
    if not dist.is_available():
        pytest.skip("torch.distributed is not available in this build")
    single = OccupancyMetric("weak")
    for seed in OCC_SEEDS:
        single.update(*random_sample(seed))
    ray_single = RayIoUMetric(grid=SMALL_GRID, rays=SMALL_RAYS)
    for seed in RAY_SEEDS:
        ray_single.update(*random_scene(seed))
    expected, ray_expected = single.report(), ray_single.report()

    mp.spawn(_ddp_worker, args=(2, str(tmp_path / "init"), str(tmp_path)), nprocs=2, join=True)
    for rank in range(2):
        result = torch.load(tmp_path / f"rank{rank}.pt", weights_only=True)
        for key in ("per_class", "own_per_class"):
            np.testing.assert_array_equal(result[key].numpy(), expected.per_class.numpy())
        for key in ("ray_per_class", "ray_own_per_class"):
            np.testing.assert_array_equal(result[key].numpy(), ray_expected.per_class.numpy())
        assert torch.equal(result["value"], single.compute())
        assert torch.equal(result["ray_value"], ray_single.compute())
        assert result["local_unchanged"]  # torchmetrics restores the local states
        # both ranks refuse before pooling, each naming the other rank's configuration
        assert "sync: the ranks of the process group hold OccupancyMetric" in result["error"]
        assert result["kind_error"].startswith("sync: the ranks of the process group hold")
    rank1 = torch.load(tmp_path / "rank1.pt", weights_only=True)
    assert "protocol 'occ3d' vs 'weak'" in rank1["error"]
    rank0 = torch.load(tmp_path / "rank0.pt", weights_only=True)
    assert "rank 1 has a RayIoUMetric" in rank0["kind_error"]


# ---------------------------------------------------------------------------------------
# Lightning
# ---------------------------------------------------------------------------------------


def test_lightning_logs_the_metrics(tmp_path: Path) -> None:
    lightning = pytest.importorskip("lightning")
    from torch.utils.data import DataLoader, TensorDataset

    samples = [random_sample(s) for s in range(4)]
    tensors = [torch.from_numpy(np.stack([s[i] for s in samples])) for i in range(3)]
    loader = DataLoader(TensorDataset(*tensors), batch_size=2)

    class Module(lightning.LightningModule):
        def __init__(self) -> None:
            super().__init__()
            self.weight = torch.nn.Parameter(torch.zeros(1))
            self.miou = OccupancyMetric("weak")
            self.scores = MetricCollection(
                {"iou": OccupancyMetric("weak", value="iou"), "occ3d": OccupancyMetric("occ3d")},
                prefix="val/",
            )
            self.everything = OccupancyMetric("weak", value="all")

        def training_step(self, batch, batch_idx):
            return (self.weight**2).sum()

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.1)

        def validation_step(self, batch, batch_idx):
            pred, gt, mask = batch
            self.miou(pred, gt, mask)
            self.log("val/miou", self.miou)  # the Metric object: pooled over the epoch
            self.scores.update(pred, gt, mask)
            self.log_dict(self.scores)
            self.everything.update(pred, gt, mask)

        def on_validation_epoch_end(self):
            self.log_dict({f"val/all/{k}": v for k, v in self.everything.compute().items()})
            self.everything.reset()

    trainer = lightning.Trainer(
        accelerator="cpu",
        max_epochs=1,
        limit_train_batches=1,
        limit_val_batches=2,
        num_sanity_val_steps=0,
        enable_checkpointing=False,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=tmp_path,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Lightning's advice on workers and such
        trainer.fit(Module(), train_dataloaders=loader, val_dataloaders=loader)
    logged = trainer.callback_metrics
    weak, occ3d = dego_scores(samples, "weak"), dego_scores(samples, "occ3d")
    assert_same(logged["val/miou"], weak.miou)
    assert_same(logged["val/iou"], weak.iou)
    assert_same(logged["val/occ3d"], occ3d.miou)
    assert_same(logged["val/all/hcm"], weak.hcm)
    assert_same(logged["val/all/iou/car"], weak.as_dict()["iou/car"])
