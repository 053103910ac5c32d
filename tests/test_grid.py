"""VoxelGrid: geometry, index round trips and validation."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from jaxtyping import TypeCheckError

import dego
from dego import VoxelGrid


def test_occ3d_grid() -> None:
    grid = VoxelGrid.occ3d()
    assert grid.shape == (200, 200, 16)
    assert grid.num_voxels == 640_000
    assert grid.lower == (-40.0, -40.0, -1.0) and grid.upper == (40.0, 40.0, 5.4)
    centers = grid.centers()
    assert centers.shape == (200, 200, 16, 3) and centers.dtype == torch.float32
    torch.testing.assert_close(centers[0, 0, 0], torch.tensor([-39.8, -39.8, -0.8]))
    torch.testing.assert_close(centers[-1, -1, -1], torch.tensor([39.8, 39.8, 5.2]))
    torch.testing.assert_close(
        centers[3, 7, 2], torch.tensor([-38.6, -37.0, 0.0]), atol=1e-6, rtol=0
    )


def test_per_axis_voxel_size() -> None:
    grid = VoxelGrid((0, 0, 0), (4, 2, 1), (0.5, 0.25, 1.0))
    assert grid.shape == (8, 8, 1)
    assert grid.centers(dtype=torch.float64)[1, 2, 0].tolist() == [0.75, 0.625, 0.5]


grids = st.builds(
    lambda lo, counts, sizes: VoxelGrid(
        lo, [a + n * s for a, n, s in zip(lo, counts, sizes, strict=True)], sizes
    ),
    st.tuples(*[st.integers(-50, 50).map(lambda v: v / 4)] * 3),
    st.tuples(*[st.integers(1, 300)] * 3),
    st.tuples(*[st.sampled_from([0.05, 0.1, 0.2, 0.25, 0.4, 0.5, 1.0, 2.0])] * 3),
)


@given(grids, st.data())
def test_world_to_index_inverts_index_to_world(grid: VoxelGrid, data: st.DataObject) -> None:
    index = torch.tensor(
        [[data.draw(st.integers(-5, n + 5)) for n in grid.shape] for _ in range(6)],
        dtype=torch.long,
    )
    for dtype in (torch.float32, torch.float64):
        world = grid.index_to_world(index, dtype=dtype)
        assert world.dtype == dtype
        assert torch.equal(grid.world_to_index(world), index)
    inside = grid.contains_index(index)
    assert torch.equal(inside, grid.contains(grid.index_to_world(index, dtype=torch.float64)))


@given(grids, st.integers(0, 2**31 - 1))
def test_contains_agrees_with_index_range(grid: VoxelGrid, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    lo, hi = (
        torch.tensor(grid.lower, dtype=torch.float64),
        torch.tensor(grid.upper, dtype=torch.float64),
    )
    points = lo - 1 + torch.rand(64, 3, generator=g, dtype=torch.float64) * (hi - lo + 2)
    inside = grid.contains(points)
    assert torch.equal(inside, grid.contains_index(grid.world_to_index(points)))


def test_half_open_bounds_and_batched_points(dtype: torch.dtype, device: torch.device) -> None:
    grid = VoxelGrid.occ3d()
    points = torch.tensor(
        [[[-40.0, -40.0, -1.0], [40.0, 0.0, 0.0]], [[0.0, 0.0, 5.4], [39.9, 39.9, 5.3]]],
        dtype=dtype,
        device=device,
    )
    assert grid.contains(points).tolist() == [[True, False], [False, True]]
    index = grid.world_to_index(points)
    assert index.dtype == torch.long and index.device.type == device.type
    assert index[0, 0].tolist() == [0, 0, 0] and index[1, 1].tolist() == [199, 199, 15]


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (((0, 0, 0), (0, 1, 1), 0.5), "lower must be < upper"),
        (((0, 0, 0), (-1, 1, 1), 0.5), "lower must be < upper"),
        (((0, 0, 0), (1, 1, 1), 0.0), "voxel_size: must be positive"),
        (((0, 0, 0), (1, 1, 1), (0.5, -0.5, 0.5)), "voxel_size: must be positive"),
        (((0, 0, 0), (1, 1, 1), 0.3), "voxel_size: the x extent 1 m is not a whole number"),
        (((0, 0, 0), (1, 1, 1.1), 0.5), "voxel_size: the z extent"),
        (((0, 0), (1, 1, 1), 0.5), "lower: expected 3 values"),
        (((0, 0, float("nan")), (1, 1, 1), 0.5), "lower: values must be finite"),
    ],
)
def test_invalid_grids_are_rejected(args: tuple, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        VoxelGrid(*args)


def test_whole_voxel_tolerance_accepts_float_rounding() -> None:
    assert VoxelGrid((-40, -40, -1), (40, 40, 5.4), (0.4, 0.4, 0.4)).shape == (200, 200, 16)
    assert VoxelGrid((0, 0, 0), (0.3, 0.3, 0.3), 0.1).shape == (3, 3, 3)


def test_bad_tensor_arguments_name_the_parameter() -> None:
    grid = VoxelGrid.occ3d()
    with pytest.raises(TypeCheckError, match="parameter 'points'"):
        grid.world_to_index(torch.zeros(4, 2))
    with pytest.raises(TypeCheckError, match="parameter 'points'"):
        grid.contains(torch.zeros(4, 3, dtype=torch.long))
    with pytest.raises(TypeCheckError, match="parameter 'index'"):
        grid.index_to_world(torch.zeros(4, 3))


# -- edge values (issue 17) -----------------------------------------------------------
_NON_FINITE = st.sampled_from([float("nan"), float("inf"), float("-inf")])
_GOOD = {"lower": (0.0, 0.0, 0.0), "upper": (4.0, 4.0, 4.0), "voxel_size": 0.5}


@given(
    st.sampled_from(["lower", "upper", "voxel_size"]),
    _NON_FINITE,
    st.one_of(st.none(), st.integers(0, 2)),
)
def test_non_finite_bounds_name_the_argument(name: str, bad: float, axis: int | None) -> None:
    # axis None: a scalar for all three axes; else one bad value in a per-axis triple.
    value: float | list[float]
    if axis is None:
        value = bad
    else:
        good = _GOOD[name]
        value = list(good) if isinstance(good, tuple) else [good] * 3
        value[axis] = bad
    with pytest.raises(ValueError, match=rf"^{name}: values must be finite"):
        VoxelGrid(**{**_GOOD, name: value})


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"upper": 1e-9}, ValueError, "voxel_size: the x extent .* is less than one"),
        ({"lower": -1e308, "upper": 1e308}, ValueError, "voxel_size: the x extent .* at most"),
        ({"voxel_size": 1e-300}, ValueError, r"voxel_size: the x extent .* at most 2\*\*53"),
        ({"lower": "0"}, TypeError, "lower: expected a number or 3 numbers"),
        ({"upper": None}, TypeError, "upper: expected a number or 3 numbers"),
        ({"voxel_size": True}, TypeError, "voxel_size: expected a number or 3 numbers"),
        ({"voxel_size": (0.5, "0.5", 0.5)}, TypeError, "voxel_size: expected 3 numbers"),
        ({"lower": (0, 0, 0, 0)}, ValueError, "lower: expected 3 values"),
        ({"lower": torch.tensor(0.0)}, TypeError, "lower: expected a number or 3 numbers"),
    ],
)
def test_degenerate_and_non_numeric_grids(kwargs: dict, error: type, match: str) -> None:
    with pytest.raises(error, match=match):
        VoxelGrid(**{**_GOOD, **kwargs})


def test_numpy_and_tensor_bounds_are_accepted() -> None:
    np = pytest.importorskip("numpy")
    grid = VoxelGrid(np.float32(-1.0), torch.tensor([1.0, 1.0, 1.0]), np.array([0.5, 0.5, 0.5]))
    assert grid.shape == (4, 4, 4) and grid.lower == (-1.0, -1.0, -1.0)


@given(
    st.lists(
        st.one_of(
            st.floats(allow_nan=True, allow_infinity=True, width=32),
            st.sampled_from([1e30, -1e30, 3e38]),
        ),
        min_size=3,
        max_size=3,
    ),
    st.sampled_from([torch.float16, torch.bfloat16, torch.float32, torch.float64]),
)
def test_world_to_index_is_defined_for_any_point(coords: list[float], dtype: torch.dtype) -> None:
    grid = VoxelGrid.occ3d()
    point = torch.tensor([coords], dtype=dtype)
    index = grid.world_to_index(point)
    assert index.dtype == torch.long and (index.abs() <= 2**62).all()
    # A point is inside exactly when its index is (NaN coordinates are neither).
    assert torch.equal(grid.contains(point), grid.contains_index(index))


def test_centers_go_through_the_memory_guard() -> None:
    grid = VoxelGrid(0.0, 1.0, 0.01)  # 10^6 voxels
    with (
        dego.memory_limit(1000),
        pytest.raises(ValueError, match=r"VoxelGrid.centers: .*100 x 100 x 100 voxels"),
    ):
        grid.centers()
