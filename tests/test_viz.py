"""Pictures: palette colours, BEV reduction, PNG output, orientation, errors, missing matplotlib."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from jaxtyping import TypeCheckError

import dego.viz
from dego import CLASS_NAMES, FREE_LABEL, PALETTE, VoxelGrid
from dego.viz import (
    add_class_legend,
    bev_labels,
    camera_panels,
    colorize_labels,
    compare_bev,
    plot_bev,
    plot_occupancy_3d,
    save_figure,
)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
GRID = VoxelGrid((-8.0, -8.0, -1.0), (8.0, 8.0, 2.2), 0.4)  # (40, 40, 8)
DRIVEABLE, SIDEWALK, VEGETATION, CAR, BUS, TERRAIN = 11, 13, 16, 4, 3, 14


@pytest.fixture
def mpl() -> object:
    return pytest.importorskip("matplotlib")


def scene() -> torch.Tensor:
    """Road with a sidewalk on the right, a car ahead (+x), a bus on the left (+y), a tree."""
    labels = torch.full(GRID.shape, FREE_LABEL, dtype=torch.long)
    labels[:, :, 0] = DRIVEABLE
    labels[:, :8, 0] = SIDEWALK  # y < -4.8 m: right of the ego
    labels[30:36, 18:22, 1:4] = CAR  # x in [4, 6.4) m, y around 0
    labels[18:22, 32:38, 1:6] = BUS  # x around 0, y in [4.8, 7.2) m
    labels[2:6, 2:6, 1:7] = VEGETATION
    return labels


def read_png(path: Path) -> np.ndarray:
    """The PNG at ``path`` as ``(H, W, 3)`` uint8, after checking the file signature."""
    from matplotlib.image import imread

    assert path.is_file()
    assert path.read_bytes()[:8] == PNG_SIGNATURE
    rgba = imread(path)
    return np.round(rgba[..., :3] * 255).astype(np.uint8)


def colours_of(rgb: np.ndarray) -> set[tuple[int, int, int]]:
    return {tuple(c) for c in np.unique(rgb.reshape(-1, 3), axis=0).tolist()}


def centroid(rgb: np.ndarray, label: int) -> tuple[float, float]:
    """Mean (row, column) of the pixels drawn in ``label``'s palette colour."""
    rows, cols = np.nonzero((rgb == np.array(PALETTE[label], dtype=np.uint8)).all(-1))
    assert rows.size, f"no pixel of {CLASS_NAMES[label]}"
    return float(rows.mean()), float(cols.mean())


def axes_centre(ax: object, height: int) -> tuple[float, float]:
    """(row, column) in the saved PNG of the centre of ``ax`` (saved at the figure's dpi)."""
    box = ax.get_window_extent()
    return height - (box.y0 + box.y1) / 2, (box.x0 + box.x1) / 2


# ----------------------------------------------------------------- pure (no matplotlib)


def test_colorize_maps_every_label_to_the_paper_palette() -> None:
    labels = torch.arange(18)
    out = colorize_labels(labels)
    assert out.dtype == torch.uint8 and out.shape == (18, 3)
    assert out.tolist() == [list(c) for c in PALETTE]
    assert out[FREE_LABEL].tolist() == [255, 255, 255]

    grid = np.arange(18, dtype=np.uint8).reshape(3, 2, 3)[::-1]  # uint8, negative stride
    out_np = colorize_labels(grid)
    assert isinstance(out_np, np.ndarray) and out_np.dtype == np.uint8
    assert out_np.shape == (3, 2, 3, 3)
    np.testing.assert_array_equal(out_np, np.array(PALETTE, dtype=np.uint8)[grid])

    custom = colorize_labels(torch.tensor([4, 17, 0]), free_label=0, free_color=(1, 2, 3))
    assert custom.tolist() == [list(PALETTE[4]), list(PALETTE[17]), [1, 2, 3]]


def test_colorize_keeps_the_device(device: torch.device) -> None:
    labels = torch.tensor([[4, 17], [11, 16]], device=device, dtype=torch.int32)
    out = colorize_labels(labels)
    assert out.device.type == device.type
    assert out.cpu().tolist() == [
        [list(PALETTE[4]), list(PALETTE[17])],
        [list(PALETTE[11]), list(PALETTE[16])],
    ]


def test_colorize_bad_inputs() -> None:
    with pytest.raises(ValueError, match=r"labels: expected Occ3D labels in \[0, 17\].*\[0, 18\]"):
        colorize_labels(torch.tensor([0, 18]))
    with pytest.raises(ValueError, match=r"labels: .*\[-1, 3\]"):
        colorize_labels(np.array([-1, 3]))
    with pytest.raises(TypeCheckError, match="parameter 'labels'"):
        colorize_labels(torch.tensor([0.0, 1.0]))
    with pytest.raises(TypeCheckError, match="parameter 'labels'"):
        colorize_labels(torch.tensor([True]))
    with pytest.raises(ValueError, match="free_label"):
        colorize_labels(torch.tensor([0]), free_label=18)
    with pytest.raises(ValueError, match="free_color"):
        colorize_labels(torch.tensor([0]), free_color=(256, 0, 0))


def test_bev_picks_the_highest_occupied_voxel() -> None:
    labels = torch.full((2, 3, 4), FREE_LABEL, dtype=torch.uint8)
    labels[0, 0] = torch.tensor([11, 17, 4, 17])  # car over road, free gap between
    labels[0, 1] = torch.tensor([11, 16, 16, 7])  # pedestrian on top of a column
    labels[0, 2] = torch.tensor([17, 17, 17, 17])  # empty column
    labels[1, 0] = torch.tensor([13, 17, 17, 17])  # ground only
    labels[1, 1] = torch.tensor([17, 17, 17, 15])  # floating top voxel
    labels[1, 2] = torch.tensor([0, 0, 0, 0])  # "others" is occupied, not free
    expected = [[4, 7, 17], [13, 15, 0]]
    out = bev_labels(labels)
    assert out.dtype == torch.uint8 and out.tolist() == expected

    out_np = bev_labels(labels.numpy().astype(np.int16))
    assert isinstance(out_np, np.ndarray) and out_np.dtype == np.int16
    assert out_np.tolist() == expected

    batched = bev_labels(torch.stack([labels, labels.flip(-1)]).long())
    assert batched.shape == (2, 2, 3) and batched[0].tolist() == expected
    assert batched[1].tolist() == [[11, 11, 17], [13, 15, 0]]

    as_free_zero = bev_labels(labels.long(), free_label=0)  # label 0 is empty space now
    assert as_free_zero[1, 2].item() == 0 and as_free_zero[0, 2].item() == 17


@given(st.integers(1, 4), st.integers(1, 4), st.integers(1, 5), st.integers(0, 2**31 - 1))
def test_bev_matches_a_loop_reference(x: int, y: int, z: int, seed: int) -> None:
    generator = torch.Generator().manual_seed(seed)
    labels = torch.randint(0, 18, (x, y, z), generator=generator)
    labels[torch.rand(x, y, z, generator=generator) < 0.6] = FREE_LABEL
    expected = torch.full((x, y), FREE_LABEL, dtype=torch.long)
    for i in range(x):
        for j in range(y):
            for k in range(z):
                if labels[i, j, k] != FREE_LABEL:
                    expected[i, j] = labels[i, j, k]
    assert torch.equal(bev_labels(labels), expected)


def test_bev_bad_inputs() -> None:
    with pytest.raises(TypeCheckError, match="parameter 'labels'"):
        bev_labels(torch.zeros(3, 3, dtype=torch.long))
    with pytest.raises(TypeCheckError, match="parameter 'labels'"):
        bev_labels(torch.zeros(3, 3, 2))
    with pytest.raises(ValueError, match=r"labels: expected Occ3D labels"):
        bev_labels(torch.full((2, 2, 2), 255, dtype=torch.uint8))
    with pytest.raises(ValueError, match="labels: the z axis is empty"):
        bev_labels(torch.zeros(2, 2, 0, dtype=torch.long))


def test_without_matplotlib_plots_raise_a_helpful_import_error(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    # a fresh copy of dego.viz imports without matplotlib (dego.viz itself is left alone)
    spec = importlib.util.spec_from_file_location("viz_without_matplotlib", dego.viz.__file__)
    viz = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(viz)
    labels = scene()
    assert viz.colorize_labels(labels).shape == (*GRID.shape, 3)
    assert viz.bev_labels(labels).shape == GRID.shape[:2]
    calls = [
        lambda: viz.plot_bev(labels),
        lambda: viz.plot_occupancy_3d(labels),
        lambda: viz.compare_bev(labels, labels),
        lambda: viz.camera_panels(depth=torch.ones(1, 4, 4)),
        lambda: viz.add_class_legend(object()),
        lambda: viz.save_figure(object(), "never.png"),
        lambda: plot_bev(labels),  # the installed module too
    ]
    for call in calls:
        with pytest.raises(ImportError, match=r'pip install -e "\.\[viz\]"'):
            call()


@pytest.mark.slow
def test_every_picture_module_imports_in_a_process_without_matplotlib() -> None:
    """The modules of dego.viz, imported for the first time with matplotlib blocked: each
    imports, and each drawing function raises the one install hint."""
    import subprocess

    code = """
import sys
sys.modules["matplotlib"] = None
import torch
import dego.viz as viz
from dego.viz import bev, cameras, colors, legend, occupancy_3d
labels = torch.zeros(4, 4, 2, dtype=torch.long)
assert viz.colorize_labels(labels).shape == (4, 4, 2, 3)
failures = []
for call in (
    lambda: bev.plot_bev(labels),
    lambda: bev.compare_bev(labels, labels),
    lambda: occupancy_3d.plot_occupancy_3d(labels),
    lambda: cameras.camera_panels(depth=torch.ones(1, 4, 4)),
    lambda: legend.add_class_legend(object()),
    lambda: viz.new_figure((2.0, 2.0)),
    lambda: viz.save_figure(object(), "never.png"),
):
    try:
        call()
        failures.append("no error")
    except ImportError as error:
        if 'pip install -e ".[viz]"' not in str(error):
            failures.append(str(error))
print(failures)
"""
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "[]"


# ----------------------------------------------------------------- pictures


@pytest.mark.slow
def test_plot_bev_writes_a_png_in_the_palette(mpl: object, tmp_path: Path) -> None:
    ax = plot_bev(scene(), grid=GRID, title="scene")
    path = save_figure(ax.figure, tmp_path / "bev.png")
    assert path == tmp_path / "bev.png"
    colours = colours_of(read_png(path))
    assert len(colours) >= 6
    for label in (DRIVEABLE, SIDEWALK, CAR, BUS, VEGETATION):
        assert PALETTE[label] in colours, CLASS_NAMES[label]
    assert ax.get_title() == "scene"
    assert ax.get_xlim() == (8.0, -8.0) and ax.get_ylim() == (-8.0, 8.0)  # metres, y to the left


def test_plot_bev_orientation_x_up_and_y_left(mpl: object, tmp_path: Path) -> None:
    labels = torch.full(GRID.shape, FREE_LABEL, dtype=torch.long)
    labels[36, 19:21, 2] = CAR  # one column ahead of the ego: x = +6.6 m, y ~ 0
    labels[19:21, 36, 2] = BUS  # one column to the left: x ~ 0, y = +6.6 m
    ax = plot_bev(labels, grid=GRID)
    rgb = read_png(save_figure(ax.figure, tmp_path / "orientation.png"))
    centre_row, centre_col = axes_centre(ax, rgb.shape[0])
    half = ax.get_window_extent().height / 2
    car_row, car_col = centroid(rgb, CAR)
    bus_row, bus_col = centroid(rgb, BUS)
    assert car_row < centre_row - 0.5 * half  # ahead = upper half
    assert abs(car_col - centre_col) < 0.1 * half
    assert bus_col < centre_col - 0.5 * half  # left = left half
    assert abs(bus_row - centre_row) < 0.1 * half


def test_plot_bev_greys_the_columns_outside_the_mask_and_outlines_the_rest(
    mpl: object, tmp_path: Path
) -> None:
    labels = torch.full(GRID.shape, FREE_LABEL, dtype=torch.long)
    labels[..., 0] = CAR  # every column a car, so the veil's grey is easy to tell apart
    mask = torch.zeros(GRID.shape, dtype=torch.bool)
    mask[20:, :, 3] = True  # scored: the front half (x > 0), one voxel per column suffices
    ax = plot_bev(labels, grid=GRID, mask=mask)
    rgb = read_png(save_figure(ax.figure, tmp_path / "masked.png")).astype(int)
    centre_row, centre_col = axes_centre(ax, rgb.shape[0])
    quarter = int(ax.get_window_extent().height / 4)
    front = rgb[int(centre_row) - quarter, int(centre_col)]  # x > 0: scored, the car colour
    row, col = int(centre_row) + quarter, int(centre_col)
    back = rgb[row - 6 : row + 7, col - 6 : col + 7].reshape(-1, 3)  # x < 0: veiled, hatched
    assert tuple(front) == PALETTE[CAR]
    alpha = dego.viz.UNSCORED_RGBA[3]
    veiled = (1 - alpha) * np.array(PALETTE[CAR]) + alpha * 255 * np.array(
        dego.viz.UNSCORED_RGBA[:3]
    )
    grey = np.abs(back - veiled).max(axis=1) <= 2
    assert grey.mean() > 0.4  # mostly the veil's grey ...
    assert (back[~grey].sum(axis=1) < veiled.sum() - 60).any()  # ... crossed by dark hatching
    assert len(ax.collections) == 2  # the hatching and the outline of the scored region
    # a 2D map gives the same veil; all scored: no veil, no outline
    again = plot_bev(labels, grid=GRID, mask=mask.any(-1).numpy())
    assert len(again.collections) == 2
    full = plot_bev(labels, grid=GRID, mask=torch.ones(GRID.shape, dtype=torch.bool))
    assert len(full.collections) == 0
    with pytest.raises(TypeCheckError, match="mask"):  # not the labels' columns
        plot_bev(labels, grid=GRID, mask=torch.ones(3, 3, dtype=torch.bool))
    with pytest.raises(TypeCheckError, match="mask"):  # a float mask
        plot_bev(labels, grid=GRID, mask=torch.ones(GRID.shape))


def test_compare_bev_with_a_mask_names_the_grey_in_its_legend(mpl: object) -> None:
    labels = scene()
    mask = torch.zeros(GRID.shape, dtype=torch.bool)
    mask[10:30, 10:30] = True
    fig = compare_bev(labels, labels, grid=GRID, mask=mask)
    names = [t.get_text() for t in fig.legends[0].get_texts()]
    assert names[-1] == "not scored"
    assert fig.legends[0].get_patches()[-1].get_hatch() == dego.viz.UNSCORED_HATCH
    assert all(len(ax.collections) == 2 for ax in fig.axes)  # hatching, outline
    plain = compare_bev(labels, labels, grid=GRID)
    assert "not scored" not in [t.get_text() for t in plain.legends[0].get_texts()]


def test_plot_bev_inputs_numpy_2d_existing_axes_and_device(
    mpl: object, tmp_path: Path, device: torch.device
) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 3))
    left, right = fig.subplots(1, 2)
    bev = bev_labels(scene().numpy().astype(np.uint8))
    assert plot_bev(bev, ax=left) is left  # (X, Y) map, voxel units (not the Occ3D shape)
    assert left.get_xlabel() == "y [voxel] (left)"
    assert plot_bev(scene().to(device), grid=GRID, ax=right) is right
    rgb = read_png(save_figure(right, tmp_path / "nested" / "dir" / "two.png"))
    assert {PALETTE[CAR], PALETTE[BUS]} <= colours_of(rgb)

    occ3d = torch.full((200, 200, 16), FREE_LABEL)
    occ3d[100:110, 95:105, :3] = CAR
    assert plot_bev(occ3d).get_xlim() == (40.0, -40.0)  # the Occ3D grid by default


def test_plot_bev_bad_inputs(mpl: object) -> None:
    with pytest.raises(TypeCheckError, match="parameter 'labels'"):
        plot_bev(torch.zeros(4, dtype=torch.long))
    with pytest.raises(TypeCheckError, match="parameter 'labels'"):
        plot_bev(torch.zeros(2, 2, 2, 2, dtype=torch.long))
    with pytest.raises(ValueError, match="labels: expected Occ3D labels"):
        plot_bev(torch.full((3, 3, 2), 20))
    with pytest.raises(ValueError, match="grid: its shape"):
        plot_bev(torch.zeros(4, 4, 3, dtype=torch.long), grid=GRID)


@pytest.mark.slow
def test_plot_occupancy_3d_writes_a_png_in_the_palette(mpl: object, tmp_path: Path) -> None:
    ax = plot_occupancy_3d(scene(), grid=GRID, title="3d")
    rgb = read_png(save_figure(ax.figure, tmp_path / "occ.png"))
    colours = colours_of(rgb)
    assert len(colours) >= 6
    for label in (DRIVEABLE, SIDEWALK, CAR, BUS, VEGETATION):  # their tops keep the palette
        assert PALETTE[label] in colours, CLASS_NAMES[label]
    # default view: looking forward from behind the ego; the car (+x) is further up the
    # picture than the bus, which is on the left (+y)
    car_row, car_col = centroid(rgb, CAR)
    bus_row, bus_col = centroid(rgb, BUS)
    assert car_row < bus_row and bus_col < car_col


def test_plot_occupancy_3d_culls_hidden_voxels_and_subsamples_deterministically(
    mpl: object,
) -> None:
    labels = torch.full((6, 6, 6), FREE_LABEL)
    labels[1:4, 1:4, 1:4] = CAR  # 27 voxels; the middle one cannot be seen
    ax = plot_occupancy_3d(labels)
    assert ax.collections[0].get_offsets().shape[0] == 26
    assert ax.get_xlabel() == "x [voxel]"
    first = plot_occupancy_3d(scene(), grid=GRID, max_voxels=50).collections[0]
    second = plot_occupancy_3d(scene(), grid=GRID, max_voxels=50).collections[0]
    assert first.get_offsets().shape[0] == 50
    np.testing.assert_array_equal(np.asarray(first._offsets3d), np.asarray(second._offsets3d))
    empty = plot_occupancy_3d(torch.full((3, 3, 3), FREE_LABEL))
    assert empty.collections[0].get_offsets().shape[0] == 0


def test_plot_occupancy_3d_bad_inputs(mpl: object) -> None:
    from matplotlib.figure import Figure

    with pytest.raises(TypeCheckError, match="parameter 'labels'"):
        plot_occupancy_3d(torch.zeros(4, 4, dtype=torch.long))
    with pytest.raises(ValueError, match="max_voxels"):
        plot_occupancy_3d(scene(), max_voxels=0)
    with pytest.raises(ValueError, match="ax: expected a 3D axes"):
        plot_occupancy_3d(scene(), ax=Figure().add_subplot())
    with pytest.raises(ValueError, match="labels: expected Occ3D labels"):
        plot_occupancy_3d(torch.full((2, 2, 2), -1))


@pytest.mark.slow
def test_compare_bev_side_by_side(mpl: object, tmp_path: Path) -> None:
    gt = scene()
    pred = gt.clone()
    pred[30:36, 18:22, 1:] = FREE_LABEL  # the car is missed ...
    pred[:, 8:12, 0] = TERRAIN  # ... and a strip of road is called terrain
    fig = compare_bev(pred.numpy(), gt, grid=GRID)
    rgb = read_png(save_figure(fig, tmp_path / "compare.png"))
    colours = colours_of(rgb)
    assert {PALETTE[c] for c in (CAR, TERRAIN, DRIVEABLE, BUS)} <= colours
    left, right = (ax for ax in fig.axes)
    assert (left.get_title(), right.get_title()) == ("prediction", "ground truth")
    legend_names = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend_names == [
        CLASS_NAMES[c] for c in (BUS, CAR, DRIVEABLE, SIDEWALK, TERRAIN, VEGETATION)
    ]
    assert not compare_bev(pred, gt, titles=("a", "b"), legend=False).legends


def test_compare_bev_bad_inputs(mpl: object) -> None:
    with pytest.raises(TypeCheckError, match="parameter 'gt'"):
        compare_bev(scene(), scene()[:, :-1])
    with pytest.raises(ValueError, match="gt: shape"):
        compare_bev(scene(), bev_labels(scene()))
    with pytest.raises(ValueError, match="pred: expected Occ3D labels"):
        compare_bev(scene() + 1, scene())


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [np.uint8, np.int8, np.int16, np.int32, np.int64])
def test_plots_do_not_depend_on_the_label_dtype(mpl: object, dtype: type) -> None:
    labels = scene()[:10, :8, :4].numpy()
    semantics = labels[:2, :, :].transpose(0, 2, 1)  # (V, H, W) = (2, 4, 8)
    ours = camera_panels(semantics=semantics.astype(dtype))
    reference = camera_panels(semantics=torch.from_numpy(semantics))
    for a, b in zip(ours.axes, reference.axes, strict=True):
        np.testing.assert_array_equal(a.images[0].get_array(), b.images[0].get_array())
    ours_3d = plot_occupancy_3d(labels.astype(dtype)).collections[0]
    reference_3d = plot_occupancy_3d(torch.from_numpy(labels)).collections[0]
    np.testing.assert_array_equal(
        np.asarray(ours_3d._offsets3d), np.asarray(reference_3d._offsets3d)
    )


def test_sentinel_labels_are_refused_naming_the_argument(mpl: object) -> None:
    for bad in (torch.full((3, 3, 2), -1, dtype=torch.int8), torch.full((3, 3, 2), 255)):
        with pytest.raises(ValueError, match=r"labels: expected Occ3D labels .* got values"):
            plot_bev(bad.to(torch.uint8) if int(bad[0, 0, 0]) == 255 else bad)
        with pytest.raises(ValueError, match=r"gt: expected Occ3D labels"):
            compare_bev(torch.zeros(3, 3, 2, dtype=torch.int8), bad)
        with pytest.raises(ValueError, match=r"semantics: expected Occ3D labels"):
            camera_panels(semantics=bad)


@pytest.mark.slow
def test_camera_panels_rows_columns_and_colours(mpl: object, tmp_path: Path) -> None:
    views, height, width = 2, 12, 16
    images = torch.zeros(views, 3, height, width, dtype=torch.uint8)
    images[:, 0], images[:, 1], images[:, 2] = 10, 120, 230
    depth = torch.linspace(1.0, 60.0, width).expand(views, height, width).clone()
    depth[:, :2] = 0.0  # nothing rendered: drawn black
    depth[:, 2] = float("inf")
    semantics = torch.full((views, height, width), DRIVEABLE)
    semantics[0, :4] = CAR
    semantics[1, :, :5] = VEGETATION
    semantics[1, -2:] = FREE_LABEL
    fig = camera_panels(images, depth, semantics, max_depth=50, camera_names=("front", "back"))
    rgb = read_png(save_figure(fig, tmp_path / "cameras.png"))
    colours = colours_of(rgb)
    assert len(colours) >= 20  # the depth colour map
    assert {(10, 120, 230), PALETTE[CAR], PALETTE[DRIVEABLE], PALETTE[VEGETATION]} <= colours
    panels = fig.axes[: 3 * views]
    assert [ax.get_ylabel() for ax in panels[::views]] == ["image", "depth", "semantics"]
    assert [ax.get_title() for ax in panels[:views]] == ["front", "back"]
    assert len(fig.axes) == 3 * views + 1  # + the depth colour bar
    legend_names = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend_names == [CLASS_NAMES[c] for c in (CAR, DRIVEABLE, VEGETATION)]


@pytest.mark.slow
def test_camera_panels_any_subset_of_rows(mpl: object, tmp_path: Path) -> None:
    depth_only = camera_panels(depth=np.random.default_rng(0).uniform(1, 40, (3, 8, 8)))
    assert len(depth_only.axes) == 3 + 1
    assert depth_only.axes[0].get_ylabel() == "depth"
    images = torch.rand(1, 3, 8, 10, dtype=torch.float64)
    fig = camera_panels(images, semantics=torch.full((1, 4, 5), BUS, dtype=torch.int32))
    rgb = read_png(save_figure(fig, tmp_path / "two_rows.png"))
    assert PALETTE[BUS] in colours_of(rgb)
    assert [ax.get_ylabel() for ax in fig.axes[:2]] == ["image", "semantics"]


def test_camera_panels_bad_inputs(mpl: object) -> None:
    with pytest.raises(ValueError, match="at least one of images, depth, semantics"):
        camera_panels()
    with pytest.raises(TypeCheckError, match="parameter 'depth'"):
        camera_panels(torch.rand(2, 3, 4, 4), torch.rand(3, 4, 4))
    with pytest.raises(TypeCheckError, match="parameter 'images'"):
        camera_panels(torch.rand(2, 4, 4, 4))
    with pytest.raises(ValueError, match=r"images: expected float values in \[0, 1\]"):
        camera_panels(torch.rand(1, 3, 4, 4) * 2)
    with pytest.raises(ValueError, match="images: expected float values"):
        camera_panels(torch.full((1, 3, 4, 4), float("nan")))
    with pytest.raises(ValueError, match="semantics: expected Occ3D labels"):
        camera_panels(semantics=torch.full((1, 4, 4), 18))
    with pytest.raises(ValueError, match="camera_names: expected 2 names"):
        camera_panels(depth=torch.ones(2, 4, 4), camera_names=["front"])
    with pytest.raises(ValueError, match="depth_cmap: unknown"):
        camera_panels(depth=torch.ones(1, 4, 4), depth_cmap="not-a-colormap")
    with pytest.raises(ValueError, match="max_depth"):
        camera_panels(depth=torch.ones(1, 4, 4), max_depth=-1.0)


def test_add_class_legend_on_axes_and_figures(mpl: object) -> None:
    from matplotlib.figure import Figure

    fig = Figure()
    ax = fig.add_subplot()
    everything = add_class_legend(ax)
    assert [t.get_text() for t in everything.get_texts()] == list(CLASS_NAMES[:FREE_LABEL])
    patches = everything.get_patches()
    assert tuple(round(v * 255) for v in patches[CAR].get_facecolor()[:3]) == PALETTE[CAR]
    present = add_class_legend(fig, torch.tensor([[16, 17], [4, 4]]))
    assert fig.legends == [present]
    assert [t.get_text() for t in present.get_texts()] == ["car", "vegetation"]
    chosen = add_class_legend(ax, [16, 4], loc="lower right")
    assert [t.get_text() for t in chosen.get_texts()] == ["vegetation", "car"]
    with pytest.raises(TypeError, match="target: expected a matplotlib Figure or Axes"):
        add_class_legend("not a figure")
    with pytest.raises(ValueError, match="classes: expected Occ3D labels"):
        add_class_legend(ax, [4, 18])


def test_save_figure_checks_its_arguments(mpl: object, tmp_path: Path) -> None:
    ax = plot_bev(scene(), grid=GRID)
    path = save_figure(ax, str(tmp_path / "a" / "b" / "from_axes.png"), dpi=40)
    assert read_png(path).shape[:2] == (200, 200)  # 5 x 5 inches at 40 dpi
    with pytest.raises(ValueError, match=r"path: expected a file name ending in \.png"):
        save_figure(ax.figure, tmp_path / "picture.jpg")
    with pytest.raises(TypeError, match="fig: expected a matplotlib Figure or Axes"):
        save_figure(object(), tmp_path / "x.png")
    with pytest.raises(ValueError, match="dpi"):
        save_figure(ax.figure, tmp_path / "x.png", dpi=0)
