"""RayIoU and lidar_origins: analytic single-ray scoring, agreement with SparseOcc's recipe
(tests/reference/ray.py), pooling and state handling, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dego import _march_numba, raycast
from dego.grid import VoxelGrid
from dego.metrics import RayIoU, RayIoUReport, lidar_origins
from dego.raycast import generate_lidar_rays
from tests.helpers.rayiou import FREE, SMALL_GRID, SMALL_RAYS, random_scene
from tests.reference.ray import reference_counts, reference_origins, transform

OTHERS, BUS, CAR, PED = 0, 3, 4, 7


@pytest.fixture(params=["torch", "numba"] if _march_numba.available() else ["torch"], autouse=True)
def kernel(request, monkeypatch) -> str:
    """Every test here runs with both CPU traversals: the torch loop and the compiled kernel."""
    monkeypatch.setattr(raycast, "CPU_KERNEL", request.param)
    return request.param


def line_grid(n: int = 10, size: float = 0.4) -> VoxelGrid:
    """``(n, 1, 1)`` voxels along x starting at the origin."""
    return VoxelGrid((0.0, 0.0, 0.0), (n * size, size, size), size)


def line(n: int = 10, **occupied: int) -> torch.Tensor:
    labels = torch.full((n, 1, 1), FREE, dtype=torch.int64)
    for voxel, label in occupied.items():
        labels[int(voxel[1:])] = label
    return labels


def single_ray_metric(size: float = 0.4, n: int = 10, **kw) -> tuple[RayIoU, torch.Tensor]:
    """A RayIoU casting one +x ray from voxel 0's centre of a line grid."""
    metric = RayIoU(grid=line_grid(n, size), rays=torch.tensor([[1.0, 0.0, 0.0]]), **kw)
    return metric, torch.tensor([[size / 2, size / 2, size / 2]])


def assert_nan_except(values: torch.Tensor, present: dict[int, float]) -> None:
    for c, v in enumerate(values.tolist()):
        if c in present:
            assert v == pytest.approx(present[c]), (c, v)
        elif c != FREE:
            assert math.isnan(v), (c, v)


# ---------------------------------------------------------------------------------------
# analytic single-ray scoring
# ---------------------------------------------------------------------------------------


def test_prediction_one_voxel_behind_is_a_true_positive_at_every_threshold() -> None:
    metric, origin = single_ray_metric()
    metric.update(line(v6=CAR), line(v5=CAR), origin)  # 0.4 m apart: < 1 m
    assert metric.gt_count[CAR] == metric.pred_count[CAR] == 1
    assert metric.true_positives[:, CAR].tolist() == [1, 1, 1]
    report = metric.compute()
    assert report.at == (1.0, 1.0, 1.0) and report.rayiou == 1.0
    assert_nan_except(report.per_class[0], {CAR: 1.0})


def test_prediction_three_voxels_behind_misses_the_one_metre_threshold() -> None:
    metric, origin = single_ray_metric()
    metric.update(line(v8=CAR), line(v5=CAR), origin)  # 1.2 m apart
    assert metric.true_positives[:, CAR].tolist() == [0, 1, 1]
    report = metric.compute()
    # at 1 m the ray is a false negative and a false positive for car: 0 / (1 + 1 - 0)
    assert report.per_class[:, CAR].tolist() == [0.0, 1.0, 1.0]
    assert report.at == (0.0, 1.0, 1.0)
    assert report.rayiou == pytest.approx(2 / 3)


@pytest.mark.parametrize(
    ("gt_voxel", "pred_voxel", "expected_tp"),
    [
        (3, 5, [0, 1, 1]),  # 1.0 m exactly: not < 1
        (3, 7, [0, 0, 1]),  # 2.0 m exactly
        (0, 8, [0, 0, 0]),  # 4.0 m exactly
        (3, 1, [0, 1, 1]),  # in front of the gt: |error| = 1.0
        (3, 2, [1, 1, 1]),  # 0.5 m in front
    ],
)
def test_thresholds_are_strict(gt_voxel: int, pred_voxel: int, expected_tp: list[int]) -> None:
    metric, origin = single_ray_metric(size=0.5)  # distances exact in binary
    metric.update(line(**{f"v{pred_voxel}": CAR}), line(**{f"v{gt_voxel}": CAR}), origin)
    assert metric.true_positives[:, CAR].tolist() == expected_tp


def test_wrong_class_at_the_right_depth() -> None:
    metric, origin = single_ray_metric()
    metric.update(line(v5=BUS), line(v5=CAR), origin)
    report = metric.compute()
    assert metric.true_positives.sum() == 0
    assert report.per_class[:, CAR].tolist() == [0.0] * 3  # gt car, never matched
    assert report.per_class[:, BUS].tolist() == [0.0] * 3  # predicted, absent from gt
    assert report.at == (0.0, 0.0, 0.0)


def test_prediction_that_hits_nothing() -> None:
    metric, origin = single_ray_metric()
    metric.update(line(), line(v5=CAR), origin)
    report = metric.compute()
    assert metric.pred_count.tolist() == [0] * FREE + [1]  # counted as a free prediction
    assert report.per_class[:, CAR].tolist() == [0.0] * 3
    assert report.per_class[:, FREE].tolist() == [0.0] * 3  # never averaged
    assert report.at == (0.0, 0.0, 0.0)


def test_rays_whose_gt_hits_free_are_not_scored() -> None:
    grid = VoxelGrid((0.0, 0.0, 0.0), (5.0, 1.0, 1.0), 1.0)
    metric = RayIoU(grid=grid, rays=torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]))
    gt = torch.full((5, 1, 1), FREE)
    gt[4] = CAR
    pred = gt.clone()
    pred[0] = BUS  # the -x ray: gt hits nothing, pred hits a bus -> ignored, no FP
    metric.update(pred, gt, torch.tensor([[2.5, 0.5, 0.5]]))
    assert metric.gt_count.sum() == metric.pred_count.sum() == 1
    assert metric.pred_count[BUS] == 0
    report = metric.compute()
    assert_nan_except(report.per_class[0], {CAR: 1.0})
    # no scored ray at all: compute refuses
    empty = RayIoU(grid=grid, rays=torch.tensor([[-1.0, 0.0, 0.0]]))
    empty.update(pred, gt, torch.tensor([[2.5, 0.5, 0.5]]))
    with pytest.raises(RuntimeError, match="no scored ray"):
        empty.compute()


def test_absent_classes_are_nan_and_left_out_of_the_mean() -> None:
    # four rays from the centre of a 5 x 5 x 1 grid of 1 m voxels, all at depth 2.5 m
    grid = VoxelGrid((0.0, 0.0, 0.0), (5.0, 5.0, 1.0), 1.0)
    rays = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])
    gt = torch.full((5, 5, 1), FREE)
    gt[4, 2, 0], gt[0, 2, 0], gt[2, 4, 0] = CAR, CAR, PED  # (2, 0, 0) stays free
    pred = gt.clone()
    pred[0, 2, 0] = BUS
    metric = RayIoU(grid=grid, rays=rays)
    metric.update(pred, gt, torch.tensor([[2.5, 2.5, 0.5]]))
    report = metric.compute()
    # car: gt 2, pred 1, tp 1 -> 1/2; bus: predicted only -> 0; pedestrian 1; others NaN
    for row in report.per_class:
        assert_nan_except(row, {CAR: 0.5, BUS: 0.0, PED: 1.0})
    assert report.at == pytest.approx((0.5, 0.5, 0.5))
    assert report.rayiou == pytest.approx(0.5)
    # a custom class set averages only those classes
    metric = RayIoU(grid=grid, rays=rays, class_ids=[CAR, PED, OTHERS])
    metric.update(pred, gt, torch.tensor([[2.5, 2.5, 0.5]]))
    assert metric.compute().at == pytest.approx((0.75, 0.75, 0.75))
    # no averaged class present at all: NaN
    metric = RayIoU(grid=grid, rays=rays, class_ids=[OTHERS])
    metric.update(pred, gt, torch.tensor([[2.5, 2.5, 0.5]]))
    report = metric.compute()
    assert all(math.isnan(v) for v in report.at) and math.isnan(report.rayiou)


def test_never_entering_rays_are_scored_with_the_placeholders() -> None:
    """SparseOcc keeps distance -1 voxel and the label of voxel (0, 0, 0) for rays that never
    enter the grid, so such rays are scored when gt's voxel (0, 0, 0) is occupied."""
    grid = VoxelGrid((0.0, 0.0, 0.0), (2.0, 2.0, 2.0), 1.0)
    metric = RayIoU(grid=grid, rays=torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]))
    gt = torch.full((2, 2, 2), FREE)
    gt[0, 0, 0] = CAR
    metric.update(gt.clone(), gt, torch.tensor([[-10.0, 0.5, 0.5]]))  # beside the grid
    assert metric.gt_count[CAR] == 2 and metric.true_positives[:, CAR].tolist() == [2, 2, 2]


def test_identical_prediction_scores_one_for_every_present_class() -> None:
    rng = np.random.default_rng(0)
    gt = rng.integers(0, 17, SMALL_GRID.shape)
    gt[rng.random(SMALL_GRID.shape) < 0.85] = FREE
    metric = RayIoU(grid=SMALL_GRID, rays=generate_lidar_rays()[::7])  # 2006 rays
    metric.update(gt.copy(), gt, np.array([[0.9858, 0.0, 1.8402], [-1.0, 2.0, 0.3]]))
    report = metric.compute()
    present = {c: 1.0 for c in range(FREE) if metric.gt_count[c] > 0}
    assert len(present) >= 10
    for row in report.per_class:
        assert_nan_except(row, present)
    assert report.at == (1.0, 1.0, 1.0) and report.rayiou == 1.0
    assert torch.equal(metric.gt_count, metric.pred_count)


# ---------------------------------------------------------------------------------------
# agreement with SparseOcc's recipe (scalar casting + calc_metrics)
# ---------------------------------------------------------------------------------------


@pytest.mark.slow
@settings(max_examples=12)
@given(
    st.lists(st.integers(0, 10_000), min_size=1, max_size=2),
    st.sampled_from([0.6, 0.9]),
    st.sampled_from([(1.0, 2.0, 4.0), (0.5, 0.8)]),
)
def test_counts_match_the_reference_recipe(
    seeds: list[int], free_fraction: float, thresholds: tuple[float, ...]
) -> None:
    grid = VoxelGrid((-2.0, -2.0, -1.0), (2.0, 2.0, 0.6), 0.4)
    rays = generate_lidar_rays()[::331]  # 43 rays
    samples = [random_scene(s, grid, free_fraction) for s in seeds]
    metric = RayIoU(grid=grid, rays=rays, thresholds=thresholds)
    for pred, gt, origins in samples:
        metric.update(pred, gt, origins)
    gt_cnt, pred_cnt, tp_cnt = reference_counts(
        samples, rays.numpy(), grid.lower, 0.4, thresholds=thresholds
    )
    np.testing.assert_array_equal(metric.gt_count.numpy(), gt_cnt)
    np.testing.assert_array_equal(metric.pred_count.numpy(), pred_cnt)
    np.testing.assert_array_equal(metric.true_positives.numpy(), tp_cnt)
    if gt_cnt.sum():
        with np.errstate(invalid="ignore", divide="ignore"):
            iou = tp_cnt / (gt_cnt + pred_cnt - tp_cnt)
        report = metric.compute()
        np.testing.assert_array_equal(report.per_class.numpy(), iou)
        expected_at = [
            np.nanmean(row[:FREE]) if not np.isnan(row[:FREE]).all() else np.nan for row in iou
        ]
        np.testing.assert_allclose(report.at, expected_at, rtol=1e-15)
        if not np.isnan(iou[:, :FREE]).all():
            assert report.rayiou == pytest.approx(float(np.nanmean(iou[:, :FREE])), rel=1e-15)


# ---------------------------------------------------------------------------------------
# pooling and state
# ---------------------------------------------------------------------------------------


def test_merge_equals_one_instance_fed_both() -> None:
    (p1, g1, o1), (p2, g2, o2) = random_scene(1), random_scene(2)
    both = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    both.update(p1, g1, o1)
    both.update(p2, g2, o2)
    first, second = (
        RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS),
        RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS),
    )
    first.update(p1, g1, o1)
    second.update(p2, g2, o2)
    assert first.merge(second) is first
    for name in ("gt_count", "pred_count", "true_positives"):
        assert torch.equal(getattr(first, name), getattr(both, name)), name
    np.testing.assert_array_equal(
        first.compute().per_class.numpy(), both.compute().per_class.numpy()
    )
    # pooled, not averaged per sample
    assert int(both.gt_count.sum()) == int(first.gt_count.sum()) > 0


def test_state_dict_round_trip_reset_and_config_checks() -> None:
    metric = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS).persistent()  # counts in state_dict
    metric.update(*random_scene(3))
    state = metric.state_dict()
    assert set(state) == {"gt_count", "pred_count", "true_positives", "_extra_state"}
    assert state["true_positives"].dtype == torch.int64 and state["true_positives"].shape == (3, 18)
    assert RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS).state_dict() == {}  # the default
    restored = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS).persistent()
    restored.load_state_dict(state)
    for name in ("gt_count", "pred_count", "true_positives"):
        assert torch.equal(getattr(restored, name), getattr(metric, name))
    assert restored.compute().rayiou == metric.compute().rayiou

    for kwargs in (
        {"thresholds": (1.0, 2.0)},
        {"grid": VoxelGrid((-4.0, -4.0, -1.0), (4.0, 4.0, 1.8), 0.4)},
        {"class_ids": [1, 2, 3]},
        {"free_label": 0},
    ):
        other = RayIoU(rays=SMALL_RAYS, **{"grid": SMALL_GRID, **kwargs}).persistent()
        with pytest.raises(ValueError, match="configuration"):
            other.load_state_dict(state)
        with pytest.raises(ValueError, match="other: configuration"):
            metric.merge(RayIoU(rays=SMALL_RAYS, **{"grid": SMALL_GRID, **kwargs}))
    with pytest.raises(TypeError, match="other: expected RayIoU"):
        metric.merge(object())  # type: ignore[arg-type]

    metric.reset()
    assert int(metric.gt_count.sum()) == int(metric.pred_count.sum()) == 0
    assert int(metric.true_positives.sum()) == 0
    with pytest.raises(RuntimeError, match="no scored ray"):
        metric.compute()
    metric.update(*random_scene(3))  # usable again, same counts as before
    assert torch.equal(metric.true_positives, restored.true_positives)


def test_a_refused_state_dict_or_merge_leaves_the_counts_untouched() -> None:
    metric = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS).persistent()
    metric.update(*random_scene(3))
    other = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS, thresholds=(1.0, 2.0, 3.0)).persistent()
    other.update(*random_scene(5))
    before = [t.clone() for t in (other.gt_count, other.pred_count, other.true_positives)]
    with pytest.raises(ValueError, match="configuration"):
        other.load_state_dict(metric.state_dict())
    after = (other.gt_count, other.pred_count, other.true_positives)
    assert all(torch.equal(a, b) for a, b in zip(before, after, strict=True))


def test_the_ray_pattern_is_part_of_the_configuration() -> None:
    metric = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS).persistent()
    metric.update(*random_scene(3))
    turned = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS.flip(0)).persistent()
    with pytest.raises(ValueError, match="other: configuration"):
        metric.merge(turned)
    with pytest.raises(ValueError, match="configuration"):
        turned.load_state_dict(metric.state_dict())


def test_bool_labels_are_refused_and_integer_origins_accepted() -> None:
    metric = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    pred, gt, origins = random_scene(9)
    with pytest.raises(TypeError, match="pred: expected an integer label grid"):
        metric.update(torch.from_numpy(pred).bool(), gt, origins)
    with pytest.raises(TypeError, match="origins"):
        metric.update(pred, gt, torch.ones(1, 3, dtype=torch.bool))
    as_float, as_int = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS), metric
    as_float.update(pred, gt, torch.tensor([[1.0, -2.0, 0.0]]))
    as_int.update(pred, gt, torch.tensor([[1, -2, 0]]))
    assert torch.equal(as_float.true_positives, as_int.true_positives)


def test_sync_is_a_no_op_without_distributed() -> None:
    metric = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    metric.update(*random_scene(4))
    before = metric.true_positives.clone(), metric.gt_count.clone(), metric.pred_count.clone()
    report = metric.compute()
    assert metric.sync() is metric
    assert torch.equal(metric.true_positives, before[0])
    assert torch.equal(metric.gt_count, before[1]) and torch.equal(metric.pred_count, before[2])
    np.testing.assert_array_equal(metric.compute().per_class.numpy(), report.per_class.numpy())


def test_report_dict_and_table() -> None:
    metric = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    metric.update(*random_scene(5))
    report = metric.compute()
    assert isinstance(report, RayIoUReport)
    assert report.thresholds == (1.0, 2.0, 4.0) and report.class_ids == tuple(range(17))
    assert report.per_class.shape == (3, 18) and report.per_class.dtype == torch.float64
    as_dict = report.as_dict()
    assert as_dict["rayiou"] == report.rayiou
    assert [as_dict[f"rayiou@{t}"] for t in ("1", "2", "4")] == list(report.at)
    assert "rayiou@1/car" in as_dict and "rayiou@4/others" in as_dict
    assert not any(k.endswith("/free") for k in as_dict)
    percent = report.table()  # percent like every dego table, and says so
    assert "car" in percent and "MEAN" in percent and str(report) == percent
    assert percent.splitlines()[0].startswith("RayIoU in percent")
    assert f"RayIoU {report.rayiou * 100:.2f} (mean over 17 classes)" in percent
    assert f"{report.at[0] * 100:.2f}" in percent.splitlines()[-2]
    fractions = report.table(percent=False)  # SparseOcc's printout
    assert fractions.splitlines()[0].startswith("RayIoU in fractions")
    assert f"RayIoU {report.rayiou:.3f} (mean over 17 classes)" in fractions
    with pytest.warns(FutureWarning, match=r"RayIoUReport.as_dict\(percent=True\)"):
        assert report.as_dict(percent=True)["rayiou"] == round(100 * report.rayiou, 2)
    assert report.rayiou == pytest.approx(float(np.mean(report.at)))


def test_numpy_and_torch_inputs_of_any_integer_dtype_agree() -> None:
    pred, gt, origins = random_scene(6)
    reference = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    reference.update(pred, gt, origins)
    for dtype in (np.int16, np.int32, np.int64):
        metric = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
        metric.update(
            pred.astype(dtype), torch.from_numpy(gt.astype(dtype)), origins.astype(np.float64)
        )
        assert torch.equal(metric.true_positives, reference.true_positives), dtype


def test_runs_on_the_device(device: torch.device) -> None:
    pred, gt, origins = (torch.from_numpy(a) for a in random_scene(7))
    on_device = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS, device=device)
    on_device.update(pred.to(device), gt.to(device), origins.to(device))
    on_cpu = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    on_cpu.update(pred, gt, origins)
    assert on_device.true_positives.device.type == device.type
    for name in ("gt_count", "pred_count", "true_positives"):
        assert torch.equal(getattr(on_device, name).cpu(), getattr(on_cpu, name)), name
    cpu_state = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    cpu_state.update(pred.to(device), gt.to(device), origins)  # device inputs, CPU state
    assert torch.equal(cpu_state.true_positives, on_cpu.true_positives)


# ---------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------


def test_origins_outside_the_grid_are_allowed() -> None:
    metric = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    pred, gt, _ = random_scene(8)
    metric.update(pred, gt, np.array([[100.0, -300.0, 50.0], [-4.5, 0.0, 0.0]]))


@pytest.mark.slow
def test_bad_update_input() -> None:
    metric = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    pred, gt, origins = random_scene(9)
    with pytest.raises(ValueError, match="at least one origin"):
        metric.update(pred, gt, np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"origins: expected \(K, 3\)"):
        metric.update(pred, gt, origins[0])
    with pytest.raises(ValueError, match="origins: 3 of 3 values are not finite"):
        metric.update(pred, gt, np.full((1, 3), np.nan))
    with pytest.raises(ValueError, match=r"pred: expected shape \(20, 20, 6\)"):
        metric.update(pred[:, :, :5], gt, origins)
    with pytest.raises(ValueError, match="gt: expected shape"):
        metric.update(pred, gt[None], origins)
    for bad in (18, 255):
        wrong = gt.copy()
        wrong[0, 0, 0] = bad
        with pytest.raises(ValueError, match=r"gt: labels must lie in 0\.\.17"):
            metric.update(pred, wrong, origins)
    negative = torch.from_numpy(pred.astype(np.int64))
    negative[1, 2, 3] = -1
    with pytest.raises(ValueError, match=r"pred: labels must lie in 0\.\.17"):
        metric.update(negative, gt, origins)
    with pytest.raises(TypeError, match="gt: expected an integer label grid"):
        metric.update(pred, gt.astype(np.float32), origins)
    with pytest.raises(TypeError):
        metric.update(pred.tolist(), gt, origins)  # type: ignore[arg-type]
    assert int(metric.gt_count.sum()) == 0  # nothing was counted


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"thresholds": (0.0, 1.0)}, "thresholds"),
        ({"thresholds": (-1.0,)}, "thresholds"),
        ({"thresholds": ()}, "thresholds"),
        ({"thresholds": (math.nan,)}, "thresholds"),
        ({"num_classes": 1}, "num_classes"),
        ({"free_label": 18}, "free_label"),
        ({"free_label": -1}, "free_label"),
        ({"class_ids": [3, FREE]}, "class_ids"),
        ({"class_ids": [18]}, "class_ids"),
        ({"class_ids": []}, "class_ids"),
        ({"rays": torch.zeros(0, 3)}, "rays"),
        ({"rays": torch.ones(4, 2)}, "rays"),
        ({"rays": torch.ones(3)}, "rays"),
        ({"rays": torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])}, "rays: 1 of 2 .* zero"),
        ({"rays": torch.tensor([[1e-50, 0.0, 0.0]], dtype=torch.float64)}, "underflow"),
        ({"rays": torch.tensor([[math.nan, 1.0, 0.0]])}, "rays: 1 of 3 values are not finite"),
        ({"rays": torch.tensor([[math.inf, 1.0, 0.0]])}, "rays: .* not finite"),
    ],
)
def test_bad_configuration(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        RayIoU(grid=SMALL_GRID, **kwargs)


def test_integer_rays_are_refused() -> None:
    with pytest.raises(TypeError, match="rays: expected a floating"):
        RayIoU(grid=SMALL_GRID, rays=torch.ones(2, 3, dtype=torch.long))


def test_ray_length_does_not_matter() -> None:
    """Rays of length 1e-8 once gave NaN distances and a RayIoU of 0. Power-of-two
    multiples give identical counts; other lengths the same up to float32 rounding of the
    scaled rays (on this scene: identical)."""
    pred, gt, origins = random_scene(12)
    unit = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    unit.update(pred, gt, origins)
    for scale in (2.0**-27, 2.0**40, 1e-8, 1e8):
        metric = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS * scale)
        metric.update(pred, gt, origins)
        for name in ("gt_count", "pred_count", "true_positives"):
            assert torch.equal(getattr(metric, name), getattr(unit, name)), (scale, name)
    assert unit.compute().rayiou > 0.3


@pytest.mark.parametrize("dtype", [torch.float16, torch.float32, torch.float64, torch.int32])
def test_origins_of_any_real_dtype_are_used_in_float64(dtype: torch.dtype) -> None:
    pred, gt, _ = random_scene(13)
    origins = torch.tensor([[0.5, -1.0, 0.25], [-3.0, 2.0, 0.0]])
    reference, metric = (RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS) for _ in range(2))
    reference.update(pred, gt, origins.to(dtype).double())
    metric.update(pred, gt, origins.to(dtype))
    assert torch.equal(metric.true_positives, reference.true_positives)


def test_memory_guard_trips_before_casting() -> None:
    import dego

    pred, gt, origins = random_scene(14)
    metric = RayIoU(grid=SMALL_GRID, rays=SMALL_RAYS)
    with dego.memory_limit(1000), pytest.raises(ValueError, match=r"RayIoU.update: .*memory limit"):
        metric.update(pred, gt, origins)
    assert int(metric.gt_count.sum()) == 0
    # 10^6 origins x 265 rays: refused at a 1 GiB limit before any ray is cast
    many = torch.zeros(1, 3, dtype=torch.float64).expand(10**6, 3)
    with dego.memory_limit(2**30), pytest.raises(ValueError, match=r"265000000 rays"):
        metric.update(pred, gt, many)


# ---------------------------------------------------------------------------------------
# lidar_origins
# ---------------------------------------------------------------------------------------

IDENTITY7 = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]  # translation, wxyz
QZ90 = [math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]  # 90 degrees about z


def poses7(rows) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float64)


def as_matrices(rows) -> torch.Tensor:
    return torch.from_numpy(np.stack([transform(r[:3], r[3:]) for r in rows]))


def test_identity_ego_poses_give_the_lidar2ego_translation() -> None:
    lidar = [0.9858, 0.0, 1.8402, *[0.7071, 0.0071, -0.0034, 0.7071]]  # a nuScenes-like mount
    origins = lidar_origins(poses7([IDENTITY7] * 4), poses7([lidar] * 4), reference_index=1)
    assert origins.shape == (4, 3) and origins.dtype == torch.float64
    np.testing.assert_allclose(origins.numpy(), np.tile(lidar[:3], (4, 1)), rtol=0, atol=1e-12)


def test_hand_built_scene() -> None:
    # ego poses: at the global origin; 10 m ahead; at (0, 5) turned 90 degrees left
    ego = [IDENTITY7, [10.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], [0.0, 5.0, 0.0, *QZ90]]
    # the LiDAR sits 0.9 m ahead and 1.8 m up; its own rotation does not move its origin
    lidar = [[0.9, 0.0, 1.8, *QZ90], [0.9, 0.0, 1.8, 1.0, 0.0, 0.0, 0.0], [0.9, 0.0, 1.8, *QZ90]]
    # LiDAR positions in the world: (0.9, 0, 1.8), (10.9, 0, 1.8), (0, 5.9, 1.8)
    expected = {
        0: [[0.9, 0.0, 1.8], [10.9, 0.0, 1.8], [0.0, 5.9, 1.8]],  # the world frame
        1: [[-9.1, 0.0, 1.8], [0.9, 0.0, 1.8], [-10.0, 5.9, 1.8]],
        # frame 2's ego looks along world +y: world (x, y) -> ego (y - 5, -x)
        2: [[-5.0, -0.9, 1.8], [-5.0, -10.9, 1.8], [0.9, 0.0, 1.8]],
    }
    for ref, points in expected.items():
        from_rows = lidar_origins(poses7(ego), poses7(lidar), ref)
        from_matrices = lidar_origins(as_matrices(ego), as_matrices(lidar), ref)
        # other frames pass through float32 in the reference LiDAR frame, as in SparseOcc
        np.testing.assert_allclose(from_rows.numpy(), points, rtol=0, atol=1e-6)
        np.testing.assert_allclose(from_rows.numpy()[ref], points[ref], rtol=0, atol=1e-15)
        np.testing.assert_allclose(from_matrices.numpy(), from_rows.numpy(), rtol=0, atol=1e-12)
    # negative reference index counts from the end
    np.testing.assert_allclose(
        lidar_origins(poses7(ego), poses7(lidar), -1).numpy(), expected[2], rtol=0, atol=1e-6
    )


def test_xy_filter_is_strict_and_ignores_z() -> None:
    xs = [[0.0, 0.0, 0.0], [39.0, 0.0, 0.0], [-39.0, 0.0, 0.0], [38.999, -38.999, 0.0],
          [0.0, 39.0, 0.0], [0.0, -39.0, 1.0], [1.0, 2.0, 100.0], [0.0, 39.5, -100.0]]  # fmt: skip
    ego = poses7([[*x, 1.0, 0.0, 0.0, 0.0] for x in xs])
    lidar = poses7([IDENTITY7] * len(xs))
    origins = lidar_origins(ego, lidar, 0)
    # 38.999 passes through float32 (SparseOcc rounds other frames' origins)
    kept = [[0.0, 0.0, 0.0], [float(np.float32(38.999)), float(np.float32(-38.999)), 0.0]]
    assert origins.tolist() == [*kept, [1.0, 2.0, 100.0]]
    wider = lidar_origins(ego, lidar, 0, xy_limit=39.5)
    assert wider.shape[0] == 7


def test_subsampling_to_eight_after_filtering() -> None:
    # 26 frames along x; frames 3, 7 and 11 are too far sideways (dropped before subsampling)
    rows = [
        [float(f), 50.0 if f in (3, 7, 11) else 0.0, 0.0, 1.0, 0.0, 0.0, 0.0] for f in range(26)
    ]
    origins = lidar_origins(poses7(rows), poses7([IDENTITY7] * 26), 0)
    kept = [f for f in range(26) if f not in (3, 7, 11)]  # 23 frames
    picked = [kept[i] for i in np.round(np.linspace(0, 22, 8)).astype(int)]
    assert picked == [0, 4, 8, 12, 16, 19, 22, 25]
    assert origins[:, 0].tolist() == [float(f) for f in picked]
    # 20 frames -> round(linspace(0, 19, 8)) = 0, 3, 5, 8, 11, 14, 16, 19
    origins = lidar_origins(poses7(rows[:20]), poses7([IDENTITY7] * 20), 0, xy_limit=100.0)
    assert origins[:, 0].tolist() == [0.0, 3.0, 5.0, 8.0, 11.0, 14.0, 16.0, 19.0]
    # eight or fewer are all kept, in temporal order; max_origins changes the count
    origins = lidar_origins(poses7(rows[:8]), poses7([IDENTITY7] * 8), 5, xy_limit=100.0)
    assert origins[:, 0].tolist() == [float(f) - 5.0 for f in range(8)]
    origins = lidar_origins(poses7(rows[:20]), poses7([IDENTITY7] * 20), 0, 3, xy_limit=100.0)
    assert origins[:, 0].tolist() == [0.0, 10.0, 19.0]  # round(9.5) = 10 (half to even)


def test_matches_the_ego_pose_dataset_recipe() -> None:
    """Random scenes against ``EgoPoseDataset``: equal up to the float32 rounding the
    reference applies to every non-reference origin in the reference LiDAR frame."""
    rng = np.random.default_rng(0)
    frames = 15
    heading = np.cumsum(rng.normal(0, 0.1, frames))
    ego = np.concatenate(
        [
            np.cumsum(rng.normal(3.0, 1.0, (frames, 3)) * [1, 1, 0.01], 0)
            + np.array([600.0, 1600.0, 0.0]),
            np.stack([np.cos(heading / 2), *np.zeros((2, frames)), np.sin(heading / 2)], -1),
        ],
        -1,
    )
    q = rng.normal(size=4)
    lidar = np.tile([0.94, 0.01, 1.84, *(q / np.linalg.norm(q))], (frames, 1))
    for ref in (0, 7, 14):
        origins = lidar_origins(torch.from_numpy(ego), torch.from_numpy(lidar), ref)
        expected = reference_origins(
            [transform(r[:3], r[3:]) for r in ego], [transform(r[:3], r[3:]) for r in lidar], ref
        )
        assert origins.shape == expected.shape and origins.shape[0] <= 8
        np.testing.assert_allclose(origins.numpy(), expected, rtol=0, atol=1e-6)


def test_bad_pose_input() -> None:
    ego, lidar = poses7([IDENTITY7] * 3), poses7([IDENTITY7] * 3)
    with pytest.raises(ValueError, match="ego2global: expected"):
        lidar_origins(ego[:, :3], lidar, 0)
    with pytest.raises(ValueError, match="lidar2ego: expected"):
        lidar_origins(ego, torch.zeros(3, 4, 3, dtype=torch.float64), 0)
    with pytest.raises(ValueError, match="ego2global: 1 values are not finite"):
        lidar_origins(
            ego.index_put(
                (torch.tensor(1), torch.tensor(0)), torch.tensor(torch.nan, dtype=ego.dtype)
            ),
            lidar,
            0,
        )
    with pytest.raises(ValueError, match="lidar2ego: 2 frames"):
        lidar_origins(ego, lidar[:2], 0)
    for index in (3, -4):
        with pytest.raises(IndexError, match="reference_index"):
            lidar_origins(ego, lidar, index)
    with pytest.raises(ValueError, match="max_origins"):
        lidar_origins(ego, lidar, 0, max_origins=0)
