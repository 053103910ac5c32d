"""Integer labels of any dtype: every function that takes label grids gives identical results
for uint8 (as Occ3D ships them), int8, int16, int32 and int64, refuses bool and floating
labels with a TypeError, and handles labels that could collide with internal sentinels
(-1, 255) as its docstring says."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dego.classes import FREE_LABEL
from dego.data.occ3d import Occ3DLabels, load_occ3d_labels, save_occ3d_labels
from dego.grid import VoxelGrid
from dego.metrics import OccupancyMetrics, RayIoU, confusion_matrix, per_class_iou
from dego.raycast import cast_rays, generate_lidar_rays, observed_voxels
from dego.viz import bev_labels, colorize_labels

INT_DTYPES = (torch.uint8, torch.int8, torch.int16, torch.int32, torch.int64)
NP_DTYPES = (np.uint8, np.int8, np.int16, np.int32, np.int64)
GRID = VoxelGrid((-2.0, -2.0, -1.0), (2.0, 2.0, 0.6), 0.4)  # (10, 10, 4)
RAYS = generate_lidar_rays()[::97]  # 145 rays
ORIGINS = torch.tensor([[0.1, -0.3, 0.2], [-2.5, 1.0, 0.4]])


def occ3d_labels(seed: int, shape: tuple[int, ...] = GRID.shape, free: float = 0.7) -> np.ndarray:
    """int64 Occ3D-range labels 0..17, mostly free."""
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, FREE_LABEL, shape)
    labels[rng.random(shape) < free] = FREE_LABEL
    return labels


dtypes = st.sampled_from(INT_DTYPES)
seeds = st.integers(0, 2**32 - 1)


def as_dtype(labels: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
    return torch.from_numpy(labels).to(dtype)


# ---------------------------------------------------------------------------------------
# identical results for every integer dtype
# ---------------------------------------------------------------------------------------


@settings(max_examples=10)
@given(seeds, dtypes)
def test_cast_rays_and_observed_voxels_do_not_depend_on_the_label_dtype(seed, dtype) -> None:
    labels = occ3d_labels(seed)
    distance, label = cast_rays(as_dtype(labels, dtype), ORIGINS, RAYS, GRID)
    expected = cast_rays(torch.from_numpy(labels), ORIGINS, RAYS, GRID)
    assert torch.equal(distance, expected[0]) and torch.equal(label, expected[1])
    assert label.dtype == torch.int64
    origins = ORIGINS[torch.arange(RAYS.shape[0]) % 2]
    seen = observed_voxels(as_dtype(labels, dtype), origins, RAYS, GRID)
    assert torch.equal(seen, observed_voxels(torch.from_numpy(labels), origins, RAYS, GRID))


@settings(max_examples=20)
@given(seeds, dtypes, dtypes, st.sampled_from([None, 255, -1, 1000]), st.booleans())
def test_confusion_and_occupancy_metrics_do_not_depend_on_the_label_dtype(
    seed, pred_dtype, gt_dtype, ignore, numpy
) -> None:
    info = torch.iinfo(gt_dtype)
    if ignore is not None and not info.min <= ignore <= info.max:
        ignore = None  # this dtype cannot hold that ignore label
    rng = np.random.default_rng(seed)
    gt, pred = occ3d_labels(seed, (2, 6, 5, 3)), occ3d_labels(seed + 1, (2, 6, 5, 3))
    if ignore is not None:
        gt[rng.random(gt.shape) < 0.2] = ignore
    mask = rng.random(gt.shape) < 0.8
    inputs = as_dtype(pred, pred_dtype), as_dtype(gt, gt_dtype)
    if numpy:
        inputs = tuple(t.numpy() for t in inputs)
    kwargs = {"ignore_label": ignore}
    matrix = confusion_matrix(*inputs, mask, **kwargs)
    # the recipe, on int64 values: skip ignored and masked-out voxels, count (gt, pred)
    keep = mask & (gt != ignore) if ignore is not None else mask
    expected = np.zeros((18, 18), np.int64)
    np.add.at(expected, (gt[keep], pred[keep]), 1)
    np.testing.assert_array_equal(matrix.numpy(), expected)
    metric = OccupancyMetrics(protocol="occ3d", ignore_label=ignore)
    metric.update(*inputs, mask)
    np.testing.assert_array_equal(metric.confusion.numpy(), expected)
    torch.testing.assert_close(
        per_class_iou(matrix.to(torch.int32)), per_class_iou(matrix), rtol=0, atol=0, equal_nan=True
    )


@settings(max_examples=8)
@given(seeds, dtypes, dtypes)
def test_rayiou_does_not_depend_on_the_label_dtype(seed, pred_dtype, gt_dtype) -> None:
    gt, pred = occ3d_labels(seed), occ3d_labels(seed + 1)
    metric, reference = RayIoU(grid=GRID, rays=RAYS), RayIoU(grid=GRID, rays=RAYS)
    metric.update(as_dtype(pred, pred_dtype), as_dtype(gt, gt_dtype).numpy(), ORIGINS)
    reference.update(torch.from_numpy(pred), torch.from_numpy(gt), ORIGINS)
    for name in ("gt_count", "pred_count", "true_positives"):
        assert torch.equal(getattr(metric, name), getattr(reference, name)), name


@settings(max_examples=20)
@given(seeds, dtypes, st.booleans())
def test_pure_viz_functions_do_not_depend_on_the_label_dtype(seed, dtype, numpy) -> None:
    labels = occ3d_labels(seed, (3, 4, 5))
    typed = as_dtype(labels, dtype)
    given_labels = typed.numpy() if numpy else typed
    bev = bev_labels(given_labels)
    expected = bev_labels(torch.from_numpy(labels))
    np.testing.assert_array_equal(np.asarray(bev), expected.numpy())
    assert bev.dtype == given_labels.dtype  # the input's dtype and type are kept
    rgb = colorize_labels(given_labels)
    np.testing.assert_array_equal(np.asarray(rgb), colorize_labels(torch.from_numpy(labels)))


@pytest.mark.slow
@pytest.mark.parametrize("dtype", NP_DTYPES)
def test_plot_bev_and_compare_bev_do_not_depend_on_the_label_dtype(dtype) -> None:
    pytest.importorskip("matplotlib")
    from dego.viz import compare_bev, plot_bev

    labels = occ3d_labels(3, (6, 5, 4))
    picture = plot_bev(labels.astype(dtype)).images[0].get_array()
    np.testing.assert_array_equal(picture, plot_bev(labels).images[0].get_array())
    figure = compare_bev(labels.astype(dtype), torch.from_numpy(labels).to(torch.int64))
    left, right = (ax.images[0].get_array() for ax in figure.axes[:2])
    np.testing.assert_array_equal(left, right)


@settings(max_examples=10)
@given(seeds, st.sampled_from(NP_DTYPES), st.booleans())
def test_occ3d_io_does_not_depend_on_the_label_dtype(
    tmp_path_factory: pytest.TempPathFactory, seed: int, dtype: type, as_tensor: bool
) -> None:
    rng = np.random.default_rng(seed)
    shape = (4, 5, 3)
    semantics = occ3d_labels(seed, shape)
    masks = [(rng.random(shape) < 0.5).astype(dtype) for _ in range(2)]
    arrays = [semantics.astype(dtype), *masks]
    if as_tensor:
        arrays = [torch.from_numpy(a) for a in arrays]
    labels = Occ3DLabels.from_arrays(*arrays)
    assert labels.semantics.dtype == torch.uint8
    np.testing.assert_array_equal(labels.semantics.numpy(), semantics)
    folder = tmp_path_factory.mktemp("occ3d")
    round_trip = load_occ3d_labels(save_occ3d_labels(folder / "a.npz", labels), expected_shape=None)
    assert torch.equal(round_trip.semantics, labels.semantics)
    assert torch.equal(round_trip.mask_camera, labels.mask_camera)
    # a file that stores semantics in this dtype reads the same
    path = folder / "b.npz"
    np.savez_compressed(
        path, semantics=semantics.astype(dtype), mask_lidar=masks[1], mask_camera=masks[0]
    )
    loaded = load_occ3d_labels(path, expected_shape=None)
    assert torch.equal(loaded.semantics, labels.semantics)
    assert torch.equal(loaded.mask_lidar, labels.mask_lidar)


# ---------------------------------------------------------------------------------------
# bool and floating labels: TypeError naming the argument
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.bool, torch.float32, torch.float64, torch.float16])
def test_bool_and_floating_labels_are_refused(dtype: torch.dtype) -> None:
    labels = torch.from_numpy(occ3d_labels(0)).to(dtype)
    ints = torch.from_numpy(occ3d_labels(0))
    with pytest.raises(TypeError, match="labels"):
        cast_rays(labels, ORIGINS, RAYS, GRID)
    with pytest.raises(TypeError, match="labels"):
        observed_voxels(labels, ORIGINS[:1], RAYS[:1], GRID)
    with pytest.raises(TypeError, match="gt"):
        confusion_matrix(ints, labels)
    with pytest.raises(TypeError, match="pred"):
        OccupancyMetrics().update(labels, ints, None)
    with pytest.raises(TypeError, match="gt"):
        RayIoU(grid=GRID, rays=RAYS).update(ints, labels, ORIGINS)
    with pytest.raises(TypeError, match="labels"):
        bev_labels(labels)
    with pytest.raises(TypeError, match="labels"):
        colorize_labels(labels)
    with pytest.raises(TypeError, match="semantics: expected integer labels"):
        Occ3DLabels.from_arrays(labels, ints == 0, ints == 1)


# ---------------------------------------------------------------------------------------
# labels that could collide with sentinels
# ---------------------------------------------------------------------------------------


@settings(max_examples=10)
@given(seeds, st.sampled_from([torch.int8, torch.int16, torch.int32, torch.int64]))
def test_negative_labels_are_ordinary_occupied_labels_for_the_ray_caster(seed, dtype) -> None:
    """The caster once padded its grid with -1 and mistook -1 labels for outside voxels:
    every value but free_label is now occupied and returned as stored."""
    labels = occ3d_labels(seed)
    negative = torch.from_numpy(np.where(labels == 5, -1, labels)).to(dtype)
    distance, label = cast_rays(negative, ORIGINS, RAYS, GRID)
    expected_distance, expected_label = cast_rays(torch.from_numpy(labels), ORIGINS, RAYS, GRID)
    assert torch.equal(distance, expected_distance)
    assert torch.equal(label, torch.where(expected_label == 5, -1, expected_label))
    origins = ORIGINS[torch.arange(RAYS.shape[0]) % 2]
    seen = observed_voxels(negative, origins, RAYS, GRID)
    assert torch.equal(seen, observed_voxels(torch.from_numpy(labels), origins, RAYS, GRID))
    # -1 as the free label works as well
    free_minus_one = torch.from_numpy(np.where(labels == FREE_LABEL, -1, labels)).to(dtype)
    distance, label = cast_rays(free_minus_one, ORIGINS, RAYS, GRID, free_label=-1)
    assert torch.equal(distance, expected_distance)
    assert torch.equal(label, torch.where(expected_label == FREE_LABEL, -1, expected_label))


@pytest.mark.parametrize("extremes", [(True, False), (False, True), (True, True)])
def test_int64_extremes_are_labels_too(extremes: tuple[bool, bool]) -> None:
    """The padding value is chosen outside the labels' range; with both int64 extremes
    present the caster falls back to an in-grid mask. Results never change."""
    labels = occ3d_labels(6)
    info = torch.iinfo(torch.int64)
    mapping = {}
    if extremes[0]:
        mapping[3] = info.min
    if extremes[1]:
        mapping[4] = info.max
    extreme = torch.from_numpy(labels).clone()
    for value, new in mapping.items():
        extreme[extreme == value] = new
    distance, label = cast_rays(extreme, ORIGINS, RAYS, GRID)
    expected_distance, expected_label = cast_rays(torch.from_numpy(labels), ORIGINS, RAYS, GRID)
    for value, new in mapping.items():
        expected_label = torch.where(expected_label == value, new, expected_label)
    assert torch.equal(distance, expected_distance) and torch.equal(label, expected_label)


def test_255_in_uint8_labels_is_occupied_for_the_ray_caster() -> None:
    labels = occ3d_labels(4)
    with_255 = torch.from_numpy(np.where(labels == 7, 255, labels)).to(torch.uint8)
    distance, label = cast_rays(with_255, ORIGINS, RAYS, GRID)
    expected_distance, expected_label = cast_rays(torch.from_numpy(labels), ORIGINS, RAYS, GRID)
    assert torch.equal(distance, expected_distance)
    assert torch.equal(label, torch.where(expected_label == 7, 255, expected_label))


@pytest.mark.parametrize("dtype", [torch.int8, torch.int16, torch.int64])
def test_ignore_label_minus_one_works_in_update(dtype: torch.dtype) -> None:
    gt = torch.tensor([[[4, -1, -1, 17, 3]]], dtype=dtype)
    pred = torch.tensor([[[4, 4, 17, 17, 2]]], dtype=dtype)
    metric = OccupancyMetrics(protocol="occ3d", ignore_label=-1)
    metric.update(pred, gt, None)
    assert int(metric.confusion.sum()) == 3  # the two -1 voxels are skipped
    assert int(metric.confusion[4, 4]) == int(metric.confusion[17, 17]) == 1
    assert int(metric.confusion[3, 2]) == 1
    with pytest.raises(ValueError, match=r"pred: label -1 is out of range"):
        metric.update(gt, pred, None)  # the ignore label is no prediction
    with pytest.raises(ValueError, match=r"gt: label -2 is out of range; expected 0\.\.17 or"):
        metric.update(pred, torch.full_like(gt, -2), None)


def test_ignore_label_that_the_dtype_cannot_hold_is_no_ignore_label() -> None:
    gt = torch.tensor([[[4, 17, 3]]], dtype=torch.uint8)
    for ignore in (-1, 255, 1000, None):
        matrix = confusion_matrix(gt, gt, ignore_label=ignore)
        assert int(matrix.sum()) == 3 and int(matrix.trace()) == 3


@pytest.mark.parametrize("bad", [18, 200, 255, -1, -128])
def test_out_of_range_labels_name_the_argument_and_the_value(bad: int) -> None:
    dtype = torch.int16
    gt = torch.tensor([[[4, 17, 3]]], dtype=dtype)
    wrong = gt.clone()
    wrong[0, 0, 1] = bad
    ignore = None  # no ignore label: every value outside 0..17 is out of range
    with pytest.raises(ValueError, match=rf"gt: label {bad} is out of range"):
        confusion_matrix(gt, wrong, ignore_label=ignore)
    with pytest.raises(ValueError, match=rf"pred: label {bad} is out of range"):
        OccupancyMetrics(ignore_label=ignore).update(wrong, gt, None)
    ray_gt = torch.from_numpy(occ3d_labels(1)).to(dtype)
    ray_bad = ray_gt.clone()
    ray_bad[1, 2, 3] = bad
    with pytest.raises(ValueError, match=rf"pred: labels must lie in 0\.\.17, found {bad}"):
        RayIoU(grid=GRID, rays=RAYS).update(ray_bad, ray_gt, ORIGINS)
    with pytest.raises(ValueError, match=r"labels: expected Occ3D labels in \[0, 17\]"):
        bev_labels(ray_bad)
    with pytest.raises(ValueError, match="semantics"):
        Occ3DLabels.from_arrays(ray_bad, ray_gt == 0, ray_gt == 1)


def test_ignore_label_must_be_an_int_outside_the_classes() -> None:
    for bad, match in ((3, "collides"), (2.5, "expected an int"), (True, "expected an int")):
        with pytest.raises(ValueError, match=f"ignore_label: .*{match}"):
            OccupancyMetrics(ignore_label=bad)  # type: ignore[arg-type]
        # a float is a wrong type: the run-time type check refuses it, naming the argument
        error = TypeError if isinstance(bad, float) else ValueError
        match = "ignore_label" if isinstance(bad, float) else f"ignore_label: .*{match}"
        with pytest.raises(error, match=match):
            confusion_matrix(torch.zeros(2, dtype=torch.uint8), torch.zeros(2), ignore_label=bad)  # type: ignore[arg-type]
    assert OccupancyMetrics(ignore_label=np.int64(-1)).ignore_label == -1


def test_occ3d_semantics_outside_uint8_or_the_classes_are_refused() -> None:
    labels = occ3d_labels(2, (3, 3, 3))
    mask = np.ones((3, 3, 3), bool)
    for bad in (-1, 18, 300):
        wrong = labels.astype(np.int16)
        wrong[0, 0, 0] = bad
        with pytest.raises(ValueError, match=rf"semantics: labels range over .*{bad}"):
            Occ3DLabels.from_arrays(wrong, mask, mask)


def test_numpy_inputs_in_foreign_byte_order_or_read_only() -> None:
    gt = occ3d_labels(5, (4, 4, 2))
    swapped = gt.astype(">i4")
    frozen = gt.astype(np.uint8)
    frozen.flags.writeable = False
    reference = confusion_matrix(gt, gt)
    assert torch.equal(confusion_matrix(swapped, frozen), reference)


def test_a_file_path_is_kept_in_tmp(tmp_path: Path) -> None:
    """save/load of uint8 labels holding every class keeps every value."""
    semantics = np.arange(18, dtype=np.uint8).reshape(3, 3, 2)
    labels = Occ3DLabels.from_arrays(semantics, semantics > 3, semantics > 9)
    loaded = load_occ3d_labels(save_occ3d_labels(tmp_path / "x.npz", labels), expected_shape=None)
    np.testing.assert_array_equal(loaded.semantics.numpy(), semantics)
