"""cast_rays / generate_lidar_rays: analytic rays, the DVR quirks, and exact agreement with
the scalar reference in tests/reference/ray.py."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dego import _march_numba, raycast
from dego.grid import VoxelGrid
from dego.raycast import MAX_STEPS, cast_product, cast_rays, generate_lidar_rays, observed_voxels
from tests.reference.ray import (
    REFERENCE_MAX_STEPS,
    cast_all,
    reference_lidar_rays,
    to_voxel_units,
    traverse,
)

FREE = 17
CAR, BUS, PED = 4, 3, 7
SQRT2, SQRT3 = math.sqrt(2.0), math.sqrt(3.0)

KERNELS = ["torch", "numba"] if _march_numba.available() else ["torch"]


@pytest.fixture(params=KERNELS, autouse=True)
def kernel(request, monkeypatch) -> str:
    """Every test here runs with both CPU traversals: the torch loop and the compiled kernel."""
    monkeypatch.setattr(raycast, "CPU_KERNEL", request.param)
    return request.param


def unit_grid(shape: tuple[int, int, int], size: float = 1.0) -> VoxelGrid:
    """A grid at the origin: voxel (i, j, k) spans [i, i+1) * size, so metres / size are
    voxel units exactly (for sizes that are powers of two)."""
    return VoxelGrid((0.0, 0.0, 0.0), tuple(n * size for n in shape), size)


def free(shape: tuple[int, int, int]) -> torch.Tensor:
    return torch.full(shape, FREE, dtype=torch.int64)


def cast(labels, origins, directions, grid, free_label: int = FREE):
    """``cast_rays`` on plain lists; returns (distances float32 ndarray, labels list)."""
    distance, label = cast_rays(
        torch.as_tensor(labels),
        torch.tensor(origins, dtype=torch.float32).reshape(-1, 3),
        torch.tensor(directions, dtype=torch.float32).reshape(-1, 3),
        grid,
        free_label,
    )
    assert distance.dtype == torch.float32 and label.dtype == torch.int64
    return distance.numpy(), label.tolist()


def metres(voxel_units: float, size: float = 1.0) -> np.float32:
    """What the reference reports for an exit distance in voxel units."""
    return np.float32(voxel_units) * np.float32(size)


# ---------------------------------------------------------------------------------------
# MAX_STEPS and the ray pattern
# ---------------------------------------------------------------------------------------


def test_max_steps_is_the_kernels() -> None:
    assert MAX_STEPS == REFERENCE_MAX_STEPS == 1000


def test_generate_lidar_rays_pattern() -> None:
    rays = generate_lidar_rays()
    assert rays.shape == (14040, 3) and rays.dtype == torch.float32
    np.testing.assert_array_equal(rays.numpy(), reference_lidar_rays())
    norms = torch.linalg.vector_norm(rays.double(), dim=-1)
    assert torch.allclose(norms, torch.ones_like(norms), atol=1e-6)

    grid = rays.double().reshape(39, 360, 3)  # row p * 360 + a
    pitch = torch.asin(grid[..., 2])
    # one pitch per row of 360, constant along the row
    assert torch.allclose(pitch, pitch[:, :1].expand(-1, 360), atol=1e-6)
    pitches = pitch[:, 0]
    assert pitches[0].item() == pytest.approx(-(math.pi / 2 - math.atan(1)), abs=1e-6)
    assert pitches[0].item() == pytest.approx(math.radians(-45), abs=1e-6)
    for k in range(1, 11):  # -(pi/2 - atan(k)) for k = 1..10
        assert pitches[k - 1].item() == pytest.approx(-(math.pi / 2 - math.atan(k)), abs=1e-6)
    steps = pitches.diff()
    assert bool((steps > 0).all())
    last_step = -(math.pi / 2 - math.atan(10)) + (math.pi / 2 - math.atan(9))
    assert torch.allclose(steps[9:], torch.full_like(steps[9:], last_step), atol=1e-6)
    assert pitches[-1].item() >= 0.21 > pitches[-2].item()
    assert math.degrees(pitches[-1].item()) == pytest.approx(12.55, abs=0.01)

    azimuth = torch.rad2deg(torch.atan2(grid[..., 1], grid[..., 0])) % 360
    expected = torch.arange(360, dtype=torch.float64).expand(39, -1)
    error = (azimuth - expected + 180) % 360 - 180
    assert error.abs().max().item() < 1e-4
    # row 0: pitch -45 degrees, azimuth 0
    np.testing.assert_allclose(
        rays[0].numpy(), [math.sqrt(0.5), 0.0, -math.sqrt(0.5)], atol=1e-7, rtol=0
    )
    np.testing.assert_allclose(rays[90].numpy(), [0.0, math.sqrt(0.5), -math.sqrt(0.5)], atol=1e-7)


# ---------------------------------------------------------------------------------------
# axis-aligned rays: hit voxel, exit distance and label known analytically
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("size", [1.0, 0.5, 0.4])
def test_axis_aligned_hit_reports_the_exit_distance(size: float) -> None:
    grid = unit_grid((6, 1, 1), size)
    labels = free((6, 1, 1))
    labels[4] = CAR
    centre = [0.5 * size] * 3  # voxel 0's centre: 0.5 voxel units on every axis
    distance, label = cast(labels, [centre], [[1.0, 0.0, 0.0]], grid)
    # enters voxel 4 at 3.5 voxels, exits it at 4.5: the exit distance is reported
    assert label == [CAR]
    assert distance[0] == metres(4.5, size)


def test_the_six_axis_directions() -> None:
    grid = unit_grid((3, 3, 3))
    labels = free((3, 3, 3))
    faces = {(2, 1, 1): 1, (0, 1, 1): 2, (1, 2, 1): 3, (1, 0, 1): 5, (1, 1, 2): 6, (1, 1, 0): 8}
    for voxel, value in faces.items():
        labels[voxel] = value
    directions = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    distance, label = cast(labels, [[1.5, 1.5, 1.5]], directions, grid)
    assert label == [1, 2, 3, 5, 6, 8]
    np.testing.assert_array_equal(distance, np.full(6, metres(1.5)))  # exit of the face voxel


def test_occupied_origin_voxel_is_hit_at_its_exit() -> None:
    grid = unit_grid((4, 4, 4))
    labels = free((4, 4, 4))
    labels[1, 1, 1] = PED
    distance, label = cast(labels, [[1.25, 1.5, 1.5]], [[1, 0, 0], [-1, 0, 0]], grid)
    assert label == [PED, PED]
    np.testing.assert_array_equal(distance, [metres(0.75), metres(0.25)])


def test_label_is_read_at_the_hit_and_any_non_free_value_is_occupied() -> None:
    grid = unit_grid((5, 1, 1))
    labels = free((5, 1, 1))
    labels[2] = 0  # "others" is occupied too
    labels[3] = CAR
    distance, label = cast(labels, [[0.5, 0.5, 0.5]], [[2.0, 0.0, 0.0]], grid)
    assert label == [0] and distance[0] == metres(2.5)  # direction length does not matter


def test_ray_with_no_hit_reports_the_last_in_grid_voxel() -> None:
    grid = unit_grid((4, 3, 2), 0.4)
    labels = free((4, 3, 2))
    labels[0, 0, 0] = CAR  # behind the rays: irrelevant
    distance, label = cast(
        labels, [[0.6, 0.6, 0.2]], [[1, 0, 0], [0, 1, 0], [0, 0, 1]], grid
    )  # origin voxel units (1.5, 1.5, 0.5)
    assert label == [FREE, FREE, FREE]
    np.testing.assert_array_equal(distance, [metres(2.5, 0.4), metres(1.5, 0.4), metres(1.5, 0.4)])


def test_anisotropic_voxels_report_metric_distances() -> None:
    # not a SparseOcc case (its grid is isotropic): distances are metres along the ray
    grid = VoxelGrid((0.0, 0.0, 0.0), (2.0, 2.0, 1.0), (0.5, 1.0, 0.25))  # (4, 2, 4)
    distance, label = cast(free((4, 2, 4)), [[0.25, 0.5, 0.125]], [[1, 0, 0], [0, 1, 0]], grid)
    assert label == [FREE, FREE]
    np.testing.assert_array_equal(distance, [np.float32(1.75), np.float32(1.5)])


def test_custom_free_label() -> None:
    grid = unit_grid((4, 1, 1))
    labels = torch.zeros(4, 1, 1, dtype=torch.int64)  # 0 is free here
    labels[2] = FREE  # 17 is occupied then
    distance, label = cast(labels, [[0.5, 0.5, 0.5]], [[1, 0, 0]], grid, free_label=0)
    assert label == [FREE] and distance[0] == metres(2.5)


# ---------------------------------------------------------------------------------------
# corners and edges: the tie-break order
# ---------------------------------------------------------------------------------------


def path_of(direction, origin=(0.5, 0.5, 0.5), shape=(3, 3, 3)):
    """Voxels visited (in order) by the scalar reference, with exit parameters."""
    start, unit = to_voxel_units(origin, direction, (0.0, 0.0, 0.0), 1.0)
    return traverse(start, unit, shape)


def test_reference_tie_break_paths() -> None:
    """The tie-break ``X if tX < tY and tX < tZ; Z if tX < tY; Y if tY < tZ; else Z``
    makes exact corner and edge crossings step Z before Y before X."""
    # three-way tie at a corner: Z, then Y, then X
    assert [v for v, _ in path_of((1, 1, 1))] == [
        (0, 0, 0), (0, 0, 1), (0, 1, 1), (1, 1, 1), (1, 1, 2), (1, 2, 2), (2, 2, 2)
    ]  # fmt: skip
    # edges: (x, y) ties go Y first, (x, z) and (y, z) ties go Z first
    assert [v for v, _ in path_of((1, 1, 0))][:3] == [(0, 0, 0), (0, 1, 0), (1, 1, 0)]
    assert [v for v, _ in path_of((1, 0, 1))][:3] == [(0, 0, 0), (0, 0, 1), (1, 0, 1)]
    assert [v for v, _ in path_of((0, 1, 1))][:3] == [(0, 0, 0), (0, 0, 1), (0, 1, 1)]
    # the same with negative steps from the far corner
    assert [v for v, _ in path_of((-1, -1, -1), origin=(2.5, 2.5, 2.5))][:4] == [
        (2, 2, 2), (2, 2, 1), (2, 1, 1), (1, 1, 1)
    ]  # fmt: skip


CORNER_PATH = [  # direction (1, 1, 1) from (0.5, 0.5, 0.5): voxel, exit parameter / sqrt(3)
    ((0, 0, 0), 0.5), ((0, 0, 1), 0.5), ((0, 1, 1), 0.5), ((1, 1, 1), 1.5),
    ((1, 1, 2), 1.5), ((1, 2, 2), 1.5), ((2, 2, 2), 2.5),
]  # fmt: skip


@pytest.mark.parametrize(("voxel", "exit_over_sqrt3"), CORNER_PATH)
def test_ray_through_voxel_corners(voxel: tuple[int, int, int], exit_over_sqrt3: float) -> None:
    grid = unit_grid((3, 3, 3))
    labels = free((3, 3, 3))
    labels[voxel] = CAR
    distance, label = cast(labels, [[0.5, 0.5, 0.5]], [[1, 1, 1]], grid)
    assert label == [CAR]
    assert distance[0] == metres(exit_over_sqrt3 * SQRT3)


@pytest.mark.parametrize("voxel", [(1, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 1), (2, 1, 1)])
def test_corner_neighbours_off_the_tie_path_are_missed(voxel: tuple[int, int, int]) -> None:
    grid = unit_grid((3, 3, 3))
    labels = free((3, 3, 3))
    labels[voxel] = CAR
    distance, label = cast(labels, [[0.5, 0.5, 0.5]], [[1, 1, 1]], grid)
    assert label == [FREE]  # no hit: last voxel (2, 2, 2)
    assert distance[0] == metres(2.5 * SQRT3)


@pytest.mark.parametrize(
    ("direction", "on_path", "off_path"),
    [
        ((1, 1, 0), (0, 1, 0), (1, 0, 0)),  # x/y tie: Y first
        ((1, 0, 1), (0, 0, 1), (1, 0, 0)),  # x/z tie: Z first
        ((0, 1, 1), (0, 0, 1), (0, 1, 0)),  # y/z tie: Z first
        ((-1, 1, 0), (1, 1, 0), (0, 0, 0)),  # negative x, from (1.5, 0.5, 0.5)
    ],
)
def test_ray_through_voxel_edges(direction, on_path, off_path) -> None:
    grid = unit_grid((3, 3, 3))
    origin = [1.5, 0.5, 0.5] if direction[0] < 0 else [0.5, 0.5, 0.5]
    labels = free((3, 3, 3))
    labels[on_path] = BUS
    distance, label = cast(labels, [origin], [direction], grid)
    assert label == [BUS] and distance[0] == metres(0.5 * SQRT2)
    labels = free((3, 3, 3))
    labels[off_path] = BUS
    _, label = cast(labels, [origin], [direction], grid)
    assert label == [FREE]


# ---------------------------------------------------------------------------------------
# rays from outside the grid, rays that never enter, truncation toward zero
# ---------------------------------------------------------------------------------------


def test_ray_starting_outside_enters_the_grid() -> None:
    grid = unit_grid((3, 1, 1), 0.5)
    labels = free((3, 1, 1))
    labels[1] = CAR
    # origin at -2.5 voxels; voxel 1 is exited at x = 2, i.e. 4.5 voxels along the ray
    distance, label = cast(labels, [[-1.25, 0.25, 0.25]], [[1, 0, 0]], grid)
    assert label == [CAR] and distance[0] == metres(4.5, 0.5)
    # from the far side, through the upper face
    distance, label = cast(labels, [[3.25, 0.25, 0.25]], [[-1, 0, 0]], grid)  # 6.5 voxels
    assert label == [CAR] and distance[0] == metres(5.5, 0.5)


@pytest.mark.parametrize("corner_label", [FREE, CAR])
def test_rays_that_never_enter_keep_the_placeholders(corner_label: int) -> None:
    grid = unit_grid((3, 3, 3), 0.4)
    labels = free((3, 3, 3))
    labels[0, 0, 0] = corner_label
    labels[2, 2, 2] = BUS
    origins = [[-1.0, 0.6, 0.6], [0.6, 5.0, 0.6]]  # before the grid in x; beside it in y
    directions = [[-1, 0, 0], [0, 0, 1], [1, 0, 0]]
    distance, label = cast(labels, origins, directions, grid)
    # distance -1 voxel (-voxel_size metres) and the label of voxel (0, 0, 0); only the
    # first origin's +x ray enters (and hits voxel (0, 1, 1), free -> no hit)
    never = -np.float32(0.4)
    np.testing.assert_array_equal(distance, [never, never, metres(5.5, 0.4), never, never, never])
    assert label == [corner_label] * 2 + [FREE] + [corner_label] * 3


def test_truncation_toward_zero_differs_from_floor() -> None:
    grid = unit_grid((3, 3, 3))
    labels = free((3, 3, 3))
    labels[0, 0, 0] = CAR
    # x = -0.5 truncates to voxel 0 (floor would give -1): the ray starts "inside" voxel
    # (0, 0, 0) and, going -x, exits it at t = (0 - (-0.5)) / -1 = -0.5.
    distance, label = cast(labels, [[-0.5, 0.5, 0.5]], [[-1, 0, 0]], grid)
    assert label == [CAR] and distance[0] == metres(-0.5)
    # free there: still recorded, so "no hit" at -0.5 with its label (not the placeholder)
    labels[0, 0, 0] = FREE
    labels[1, 1, 1] = BUS
    distance, label = cast(labels, [[-0.5, 0.5, 0.5]], [[-1, 0, 0]], grid)
    assert label == [FREE] and distance[0] == metres(-0.5)
    # y = -0.5 truncates to row 0: a ray that passes beside the grid walks through it
    labels = free((3, 3, 3))
    labels[0, 0, 0] = CAR
    distance, label = cast(labels, [[-2.5, -0.5, 0.5]], [[1, 0, 0]], grid)
    assert label == [CAR] and distance[0] == metres(3.5)
    # at exactly -1.0 truncation gives -1 again: never enters
    distance, label = cast(labels, [[-2.5, -1.0, 0.5]], [[1, 0, 0]], grid)
    assert label == [CAR] and distance[0] == metres(-1.0)  # placeholders


def test_step_limit() -> None:
    """At most MAX_STEPS + 1 = 1001 loop iterations: a ray 1000.5 voxels before the grid
    reaches voxel 0 on its last iteration, one at 1001.5 never does."""
    grid = unit_grid((4, 1, 1))
    labels = free((4, 1, 1))
    labels[0] = CAR
    origins = [[-MAX_STEPS - 0.5, 0.5, 0.5], [-MAX_STEPS - 1.5, 0.5, 0.5]]
    distance, label = cast(labels, origins, [[1, 0, 0]], grid)
    assert label == [CAR, CAR]  # the second is the voxel-(0, 0, 0) placeholder
    np.testing.assert_array_equal(distance, [metres(MAX_STEPS + 1.5), metres(-1.0)])
    # voxel 0 free, voxel 1 occupied: voxel 1 is beyond the step limit -> no hit at voxel 0
    labels = free((4, 1, 1))
    labels[1] = CAR
    distance, label = cast(labels, origins[:1], [[1, 0, 0]], grid)
    assert label == [FREE] and distance[0] == metres(MAX_STEPS + 1.5)
    # one voxel closer, voxel 1 is reached
    distance, label = cast(labels, [[-MAX_STEPS + 0.5, 0.5, 0.5]], [[1, 0, 0]], grid)
    assert label == [CAR] and distance[0] == metres(MAX_STEPS + 1.5)


# ---------------------------------------------------------------------------------------
# exact agreement with the scalar reference
# ---------------------------------------------------------------------------------------

DIAGONALS = [d for d in itertools.product((-1.0, 0.0, 1.0), repeat=3) if any(d)]


@st.composite
def ray_problems(draw):
    shape = tuple(draw(st.integers(1, 5)) for _ in range(3))
    if draw(st.booleans()):  # voxel units exact in float32: exact corner and edge ties
        size = draw(st.sampled_from([1.0, 0.5, 0.25]))
        lower = tuple(draw(st.sampled_from([0.0, -1.0, -2.0, -40.0])) for _ in range(3))
    else:
        size = draw(st.sampled_from([0.4, 0.3]))
        lower = tuple(draw(st.sampled_from([0.0, -2.6, 0.7, -40.0])) for _ in range(3))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    density = draw(st.sampled_from([0.0, 0.05, 0.3, 0.8, 1.0]))
    labels = rng.integers(0, 17, shape)
    labels[rng.random(shape) >= density] = FREE
    extent = np.asarray(shape, dtype=np.float64)
    k = draw(st.integers(1, 3))
    kind = draw(st.sampled_from(["uniform", "lattice", "near"]))
    if kind == "uniform":  # anywhere within two grid extents (often outside)
        units = rng.uniform(-1.0, 2.0, (k, 3)) * extent
    elif kind == "lattice":  # on voxel faces, edges, corners and centres, incl. negative
        units = rng.integers(-6, 2 * int(extent.max()) + 6, (k, 3)) / rng.choice([1, 2, 4])
    else:  # just below zero, where truncation toward zero differs from floor
        units = rng.uniform(-1.5, 1.0, (k, 3)) * rng.choice([1.0, 0.1])
    origins = (np.asarray(lower) + units * size).astype(np.float32)
    r = draw(st.integers(1, 6))
    mode = draw(st.sampled_from(["random", "axis", "diagonal", "mixed"]))
    directions = rng.normal(size=(r, 3))
    if mode in ("axis", "diagonal", "mixed"):
        picks = rng.integers(0, len(DIAGONALS), r)
        lattice = np.asarray([DIAGONALS[i] for i in picks])
        if mode == "axis":
            lattice = np.eye(3)[rng.integers(0, 3, r)] * rng.choice([-1.0, 1.0], (r, 1))
        scale = rng.choice([1.0, 0.5, 2.0, 3.0], (r, 1))
        if mode == "mixed":
            directions = np.where(rng.random((r, 1)) < 0.5, lattice * scale, directions)
        else:
            directions = lattice * scale
    return labels, origins, directions.astype(np.float32), lower, size, shape


@st.composite
def tie_problems(draw):
    """Exact grids, origins at voxel centres or corners (same fraction on every axis) and
    diagonal directions: every crossing is an exact edge or corner tie."""
    shape = tuple(draw(st.integers(2, 5)) for _ in range(3))
    size = draw(st.sampled_from([1.0, 0.5, 0.25]))
    lower = tuple(draw(st.sampled_from([0.0, -1.0, -40.0])) for _ in range(3))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    labels = rng.integers(0, 17, shape)
    labels[rng.random(shape) >= draw(st.sampled_from([0.2, 0.5, 0.8]))] = FREE
    k = draw(st.integers(1, 3))
    fraction = draw(st.sampled_from([0.0, 0.5, 0.25]))
    units = rng.integers(-1, max(shape) + 1, (k, 3)) + fraction
    origins = (np.asarray(lower) + units * size).astype(np.float32)
    diagonal = [d for d in DIAGONALS if sum(map(abs, d)) >= 2]
    directions = np.asarray([diagonal[i] for i in rng.integers(0, len(diagonal), 8)])
    directions = directions * rng.choice([1.0, 0.5, 2.0], (8, 1))
    return labels, origins, directions.astype(np.float32), lower, size, shape


def power_of_two_scaled(directions: np.ndarray) -> np.ndarray:
    """The caster's first step: each direction times ``2^-round(log2 |d|)`` (exact)."""
    norm = np.linalg.norm(directions.astype(np.float64), axis=-1, keepdims=True)
    scaled = directions * np.exp2(-np.round(np.log2(norm)))
    assert np.array_equal(scaled / np.exp2(-np.round(np.log2(norm))), directions)  # exact
    return scaled.astype(directions.dtype)


@pytest.mark.slow
@settings(max_examples=40)
@given(st.one_of(ray_problems(), tie_problems()))
def test_matches_the_scalar_reference_exactly(problem) -> None:
    """Bit for bit, given the directions the caster uses: scaled by a power of two to a
    length in [1/sqrt(2), sqrt(2)) (unit rays, SparseOcc's, are used unchanged)."""
    labels, origins, directions, lower, size, shape = problem
    upper = tuple(lo + n * size for lo, n in zip(lower, shape, strict=True))
    grid = VoxelGrid(lower, upper, size)
    assert grid.shape == shape
    distance, label = cast_rays(
        torch.from_numpy(labels), torch.from_numpy(origins), torch.from_numpy(directions), grid
    )
    expected_distance, expected_label = cast_all(
        labels, origins, power_of_two_scaled(directions), lower, size, free_label=FREE
    )
    np.testing.assert_array_equal(label.numpy(), expected_label)
    np.testing.assert_array_equal(distance.numpy(), expected_distance)


def test_matches_the_scalar_reference_on_lidar_rays() -> None:
    """A small Occ3D-like grid and a subsample of the real ray pattern from a few origins,
    including one outside the grid and one with negative voxel coordinates."""
    grid = VoxelGrid((-4.0, -4.0, -1.0), (4.0, 4.0, 1.4), 0.4)
    rng = np.random.default_rng(7)
    labels = rng.integers(0, 17, grid.shape)
    labels[rng.random(grid.shape) < 0.93] = FREE
    origins = np.asarray(
        [[0.9858, 0.0, 1.8402], [-4.1, -4.3, -0.2], [3.0, -2.2, 0.1]], dtype=np.float32
    )
    rays = generate_lidar_rays().numpy()[::113]
    distance, label = cast_rays(
        torch.from_numpy(labels), torch.from_numpy(origins), torch.from_numpy(rays), grid
    )
    expected_distance, expected_label = cast_all(labels, origins, rays, grid.lower, 0.4)
    np.testing.assert_array_equal(label.numpy(), expected_label)
    np.testing.assert_array_equal(distance.numpy(), expected_distance)
    assert (expected_label != FREE).any() and (expected_distance < 0).any()


@pytest.mark.slow
@settings(max_examples=30)
@given(st.one_of(ray_problems(), tie_problems()), st.integers(0, 2**32 - 1))
def test_one_traversal_through_several_grids_equals_separate_casts(problem, seed) -> None:
    """RayIoU casts prediction and ground truth together (the rays are shared); each grid's
    hits are exactly those of a cast through that grid alone."""
    labels, origins, directions, lower, size, shape = problem
    upper = tuple(lo + n * size for lo, n in zip(lower, shape, strict=True))
    grid = VoxelGrid(lower, upper, size)
    rng = np.random.default_rng(seed)
    other = np.where(rng.random(shape) < 0.3, rng.integers(0, 17, shape), labels)
    grids = [torch.from_numpy(labels), torch.from_numpy(other), torch.from_numpy(labels)]
    o, d = torch.from_numpy(origins), torch.from_numpy(directions)
    distance, label = cast_product(grids, o, d, grid, FREE, "test")
    for i, labels_i in enumerate(grids):
        alone_distance, alone_label = cast_rays(labels_i, o, d, grid)
        assert torch.equal(label[i], alone_label)
        assert torch.equal(distance[i], alone_distance)


@pytest.mark.slow
@settings(max_examples=20)
@given(ray_problems())
def test_compiled_kernel_and_torch_loop_agree_exactly(problem) -> None:
    """The two CPU traversals give bit-identical hits, in both precision modes."""
    if "numba" not in KERNELS:
        pytest.skip("numba is not installed")
    labels, origins, directions, lower, size, shape = problem
    upper = tuple(lo + n * size for lo, n in zip(lower, shape, strict=True))
    grid = VoxelGrid(lower, upper, size)
    for dtype in (torch.float32, torch.float64):
        o = torch.from_numpy(origins).to(dtype)
        d = torch.from_numpy(directions).to(dtype)
        results = {}
        for name in ("torch", "numba"):
            raycast.CPU_KERNEL = name
            results[name] = cast_rays(torch.from_numpy(labels), o, d, grid)
        assert torch.equal(results["torch"][0], results["numba"][0])
        assert torch.equal(results["torch"][1], results["numba"][1])


@pytest.mark.slow
@pytest.mark.parametrize("chunk", [1, 4, 7, 10_000])
def test_chunking_does_not_change_the_hits(chunk, monkeypatch) -> None:
    """Blocks of whole origins (R <= CHUNK_RAYS) and flat blocks (R > CHUNK_RAYS) give
    the hits of one block, for cast_rays and observed_voxels."""
    grid = VoxelGrid((-4.0, -4.0, -1.0), (4.0, 4.0, 1.4), 0.4)
    rng = np.random.default_rng(3)
    labels = torch.from_numpy(np.where(rng.random(grid.shape) < 0.9, FREE, 4))
    origins = torch.tensor([[0.1, 0.2, 0.3], [-3.9, 2.0, -0.5], [5.0, 0.0, 0.0]])
    rays = generate_lidar_rays()[::1400]  # 11 rays
    expected = cast_rays(labels, origins, rays, grid)
    paired_o, paired_d = origins.repeat_interleave(len(rays), 0), rays.repeat(3, 1)
    seen = observed_voxels(labels, paired_o, paired_d, grid)
    monkeypatch.setattr(raycast, "CHUNK_RAYS", chunk)
    got = cast_rays(labels, origins, rays, grid)
    assert torch.equal(got[0], expected[0]) and torch.equal(got[1], expected[1])
    assert torch.equal(observed_voxels(labels, paired_o, paired_d, grid), seen)


def test_cpu_kernel_choice(monkeypatch) -> None:
    monkeypatch.setattr(raycast, "CPU_KERNEL", "torch")
    assert raycast.cpu_kernel() == "torch"
    monkeypatch.setattr(raycast, "CPU_KERNEL", "auto")
    assert raycast.cpu_kernel() == ("numba" if _march_numba.available() else "torch")
    monkeypatch.setattr(raycast, "CPU_KERNEL", "cuda")
    with pytest.raises(ValueError, match=r"CPU_KERNEL: expected 'auto', 'numba' or 'torch'"):
        cast_rays(free((2, 2, 2)), torch.zeros(1, 3), torch.ones(1, 3), unit_grid((2, 2, 2)))
    monkeypatch.setattr(_march_numba, "available", lambda: False)
    monkeypatch.setattr(raycast, "CPU_KERNEL", "auto")
    assert raycast.cpu_kernel() == "torch"
    monkeypatch.setattr(raycast, "CPU_KERNEL", "numba")
    with pytest.raises(ImportError, match=r"numba is not installed"):
        raycast.cpu_kernel()


def test_wide_label_values_use_the_int64_kernel() -> None:
    """Labels beyond uint8 (negative, 255+, int64 extremes) are hit and returned as stored."""
    grid = unit_grid((4, 1, 1))
    info = torch.iinfo(torch.int64)
    for value in (-1, 300, info.min, info.max):
        labels = free((4, 1, 1))
        labels[2] = value
        distance, label = cast(labels, [[0.5, 0.5, 0.5]], [[1, 0, 0]], grid)
        assert label == [value] and distance[0] == metres(2.5)


# ---------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------


def test_bad_input() -> None:
    grid = unit_grid((3, 3, 3))
    labels = free((3, 3, 3))
    origin, direction = torch.tensor([[0.5, 0.5, 0.5]]), torch.tensor([[1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"labels: shape .* does not match grid"):
        cast_rays(free((3, 3, 2)), origin, direction, grid)
    with pytest.raises(ValueError, match="origins: 1 of 3 values are not finite"):
        cast_rays(labels, torch.tensor([[math.inf, 0.0, 0.0]]), direction, grid)
    with pytest.raises(ValueError, match="directions: 1 of 2 directions are zero vectors"):
        cast_rays(labels, origin, torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), grid)
    with pytest.raises(ValueError, match="directions: 1 of 3 values are not finite"):
        cast_rays(labels, origin, torch.tensor([[math.nan, 1.0, 0.0]]), grid)
    with pytest.raises(ValueError, match="directions: 1 of 3 values are not finite"):
        observed_voxels(labels, origin, torch.tensor([[-math.inf, 1.0, 0.0]]), grid)
    with pytest.raises(TypeError, match="labels"):  # float labels (jaxtyping's TypeCheckError)
        cast_rays(labels.float(), origin, direction, grid)
    with pytest.raises(TypeError, match="labels"):
        cast_rays(labels.bool(), origin, direction, grid)
    with pytest.raises(TypeError):
        cast_rays(labels, origin[0], direction, grid)


def test_empty_inputs_give_empty_results() -> None:
    grid = unit_grid((3, 3, 3))
    labels = free((3, 3, 3))
    origin, direction = torch.tensor([[0.5, 0.5, 0.5]]), torch.tensor([[1.0, 0.0, 0.0]])
    for origins, directions in ((origin[:0], direction), (origin, direction[:0])):
        for dtype in (torch.float32, torch.float64):
            distance, label = cast_rays(labels, origins.to(dtype), directions.to(dtype), grid)
            assert distance.shape == label.shape == (0,)
            assert distance.dtype == dtype and label.dtype == torch.int64
    seen = observed_voxels(labels, origin[:0], direction[:0], grid)
    assert seen.shape == grid.shape and not bool(seen.any())


def test_origins_outside_the_grid_are_allowed() -> None:
    grid = unit_grid((3, 3, 3))
    origins = torch.tensor([[100.0, -50.0, 7.0], [-1e4, 0.5, 0.5]])
    labels = free((3, 3, 3))
    labels[0, 0, 0] = BUS
    distance, label = cast_rays(labels, origins, torch.eye(3), grid)
    # the second origin's +x ray would reach the grid, but only after 10^4 > MAX_STEPS steps
    assert distance.tolist() == [-1.0] * 6 and label.tolist() == [BUS] * 6


# ---------------------------------------------------------------------------------------
# devices
# ---------------------------------------------------------------------------------------


def test_cpu_and_device_agree(device: torch.device) -> None:
    grid = VoxelGrid((-4.0, -4.0, -1.0), (4.0, 4.0, 1.4), 0.4)
    rng = np.random.default_rng(3)
    labels = torch.from_numpy(rng.integers(0, 18, grid.shape))
    origins = torch.tensor([[0.9858, 0.0, 1.8402], [-5.0, 1.0, 0.3], [-0.1, -0.2, -0.05]])
    rays = generate_lidar_rays()[::29]
    d_cpu, l_cpu = cast_rays(labels, origins, rays, grid)
    d_dev, l_dev = cast_rays(labels.to(device), origins.to(device), rays.to(device), grid)
    assert d_dev.device.type == device.type
    assert torch.equal(d_dev.cpu(), d_cpu) and torch.equal(l_dev.cpu(), l_cpu)


def test_observed_voxels_stop_at_and_include_the_first_occupied_voxel() -> None:
    grid = VoxelGrid((0.0, 0.0, 0.0), (4.0, 2.0, 1.0), 1.0)  # (4, 2, 1)
    labels = torch.full(grid.shape, 17, dtype=torch.long)
    labels[2, 0, 0] = 4
    origins = torch.tensor([[0.5, 0.5, 0.5], [0.5, 1.5, 0.5], [9.0, 9.0, 9.0]])
    directions = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    seen = observed_voxels(labels, origins, directions, grid)
    expected = torch.zeros(grid.shape, dtype=torch.bool)
    expected[:3, 0, 0] = True  # up to and including the hit; nothing behind it
    expected[:, 1, 0] = True  # a ray through free space sees its whole row
    assert torch.equal(seen, expected)
    empty = observed_voxels(labels, origins[:0], directions[:0], grid)
    assert empty.shape == grid.shape and not bool(empty.any())
    with pytest.raises(ValueError, match="labels"):
        observed_voxels(labels[:2], origins, directions, grid)


# ---------------------------------------------------------------------------------------
# direction lengths: tiny, huge, any power of two
# ---------------------------------------------------------------------------------------

SMALL_OCC3D = VoxelGrid((-4.0, -4.0, -1.0), (4.0, 4.0, 1.4), 0.4)  # (20, 20, 6)


def small_scene(seed: int = 11) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, 17, SMALL_OCC3D.shape)
    labels[rng.random(SMALL_OCC3D.shape) < 0.9] = FREE
    return torch.from_numpy(labels)


LIDAR_ORIGINS = torch.tensor([[0.9858, 0.0, 1.8402], [-4.3, 2.0, 0.1], [3.1, -2.9, -0.7]])
SOME_RAYS = generate_lidar_rays()[::37]  # 380 rays


@pytest.mark.slow
@settings(max_examples=25)
@given(
    st.integers(-100, 100),
    st.sampled_from([torch.float32, torch.float64]),
    st.integers(0, 2**32 - 1),
)
def test_any_power_of_two_length_gives_identical_hits(exponent, dtype, seed) -> None:
    """Directions are scaled by an exact power of two before use: a direction and 2^j
    times it give bit-identical results, from 2^-100 (~8e-31) to 2^100 (~1e30)."""
    rng = np.random.default_rng(seed)
    directions = torch.from_numpy(rng.normal(size=(64, 3))).to(dtype)
    labels = small_scene(seed % 7)
    origins = LIDAR_ORIGINS.to(dtype)
    expected = cast_rays(labels, origins, directions, SMALL_OCC3D)
    distance, label = cast_rays(labels, origins, directions * 2.0**exponent, SMALL_OCC3D)
    assert torch.equal(distance, expected[0]) and torch.equal(label, expected[1])
    assert bool(torch.isfinite(distance).all())


@pytest.mark.parametrize("scale", [1e-8, 1e-20, 1e8, 1e20])
def test_tiny_and_huge_directions_work(scale: float) -> None:
    """A length-1e-8 direction once gave NaN distances (the end point origin + direction
    rounded onto the origin); now every length gives the unit direction's hits, up to the
    float32 rounding of the scaled direction itself (scales that push a component out of
    float32's normal range change the input itself)."""
    labels = small_scene()
    distance, label = cast_rays(labels, LIDAR_ORIGINS, SOME_RAYS * scale, SMALL_OCC3D)
    expected_distance, expected_label = cast_rays(labels, LIDAR_ORIGINS, SOME_RAYS, SMALL_OCC3D)
    assert bool(torch.isfinite(distance).all())
    same = label == expected_label
    assert float(same.float().mean()) >= 0.99
    torch.testing.assert_close(distance[same], expected_distance[same], rtol=1e-4, atol=1e-4)
    # float64 mode: lengths far beyond float32's range too
    for big in (scale, 1e-200, 1e200):
        d64, l64 = cast_rays(labels, LIDAR_ORIGINS.double(), SOME_RAYS.double() * big, SMALL_OCC3D)
        reference = cast_rays(labels, LIDAR_ORIGINS.double(), SOME_RAYS.double(), SMALL_OCC3D)
        assert torch.equal(l64, reference[1])
        torch.testing.assert_close(d64, reference[0], rtol=1e-12, atol=1e-12)


def test_origins_far_away_keep_the_placeholders() -> None:
    """Origins whose voxel coordinates float32 cannot separate from a one-metre step, or
    beyond float32's range, are far beyond MAX_STEPS: placeholders, never NaN."""
    labels = small_scene()
    origins = torch.tensor(
        [[1e7, 0.0, 0.0], [-1e30, 1e30, 0.0], [1e300, 0.0, -1e300]], dtype=torch.float64
    )
    distance, label = cast_rays(labels, origins, SOME_RAYS, SMALL_OCC3D)
    assert torch.equal(distance, torch.full_like(distance, -np.float32(0.4)))
    assert bool((label == labels[0, 0, 0]).all())


# ---------------------------------------------------------------------------------------
# precision modes and the dtype rule
# ---------------------------------------------------------------------------------------


def test_float32_inputs_match_a_float64_traversal_of_the_same_rounded_coordinates() -> None:
    """The traversal is float64 in both modes: where the float32 voxel coordinates of
    SparseOcc mode are exact (grid at 0 with 1 m voxels, origins and end points exact in
    float32), float32 and float64 inputs give the same hits to float32 output precision."""
    grid = unit_grid((24, 24, 8))
    rng = np.random.default_rng(5)
    labels = torch.from_numpy(np.where(rng.random(grid.shape) < 0.9, FREE, 4))
    origins = torch.from_numpy(rng.integers(0, 24 * 64, (6, 3)) / 64.0)  # exact in float32
    origins[:, 2] /= 3.0
    origins = origins.float().double()
    # directions with few significant bits: origin + direction stays exact in float32
    directions = torch.from_numpy(rng.integers(-512, 513, (500, 3)) / 256.0)
    directions = directions[(directions != 0).any(-1)]
    d32, l32 = cast_rays(labels, origins.float(), directions.float(), grid)
    d64, l64 = cast_rays(labels, origins, directions, grid)
    assert d32.dtype == torch.float32 and d64.dtype == torch.float64
    assert torch.equal(l32, l64)
    torch.testing.assert_close(d32.double(), d64, rtol=1e-6, atol=1e-6)


def test_sparseocc_mode_stays_within_the_documented_bound_of_float64_mode() -> None:
    """SparseOcc's float32 voxel coordinates turn each direction slightly; on Occ3D-like
    scenes distances differ from float64 mode by at most a few millimetres (docs/rayiou.md:
    1.3e-3 m on the RayIoU benchmark), labels almost never."""
    labels = small_scene(3)
    rays = generate_lidar_rays()[::7]
    # origins inside the grid, as RayIoU's are (from just outside, the reference's
    # truncation toward zero lets rays with a ~1e-16 component "start inside" and exit at
    # absurd parameters, -1e15 m, in float64 mode, where SparseOcc mode rounds the
    # component to 0)
    origins = torch.tensor([[0.9858, 0.0, 0.8402], [-3.3, 2.0, 0.1], [3.1, -2.9, -0.7]])
    d32, l32 = cast_rays(labels, origins.double(), rays, SMALL_OCC3D)
    d64, l64 = cast_rays(labels, origins.double(), rays.double(), SMALL_OCC3D)
    same = l32 == l64
    assert float(same.float().mean()) >= 0.999
    error, reference = (d32.double() - d64).abs()[same], d64[same].abs()
    assert float(error.max()) < 2e-3
    assert float((error / reference.clamp_min(0.4)).max()) < 2e-4


@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
def test_half_inputs_are_computed_in_float32_and_returned_in_their_dtype(half) -> None:
    labels = small_scene()
    origins, directions = LIDAR_ORIGINS.to(half), SOME_RAYS.to(half)
    distance, label = cast_rays(labels, origins, directions, SMALL_OCC3D)
    expected_distance, expected_label = cast_rays(
        labels, origins.float(), directions.float(), SMALL_OCC3D
    )
    assert distance.dtype == half and torch.equal(label, expected_label)
    assert torch.equal(distance, expected_distance.to(half))


def test_mixed_float_dtypes() -> None:
    labels = small_scene()
    o32, r32 = LIDAR_ORIGINS, SOME_RAYS
    # SparseOcc's own convention: float64 origins with float32 rays, float32 distances
    distance, _ = cast_rays(labels, o32.double(), r32, SMALL_OCC3D)
    assert distance.dtype == torch.float32
    for origins, directions in ((o32, r32.double()), (o32.half(), r32), (o32, r32.half())):
        with pytest.raises(TypeError, match=r"directions: dtype .* differs from origins"):
            cast_rays(labels, origins, directions, SMALL_OCC3D)
        paired = origins[torch.zeros(directions.shape[0], dtype=torch.long)]
        with pytest.raises(TypeError, match=r"directions: dtype .* differs from origins"):
            observed_voxels(labels, paired, directions, SMALL_OCC3D)


# ---------------------------------------------------------------------------------------
# the memory guard
# ---------------------------------------------------------------------------------------


def test_memory_guard_trips_before_allocating() -> None:
    import dego

    labels = small_scene()
    with dego.memory_limit(1000), pytest.raises(ValueError, match=r"cast_rays: .*memory limit"):
        cast_rays(labels, LIDAR_ORIGINS, SOME_RAYS, SMALL_OCC3D)
    paired = LIDAR_ORIGINS[torch.zeros(SOME_RAYS.shape[0], dtype=torch.long)]
    with (
        dego.memory_limit(1000),
        pytest.raises(ValueError, match=r"observed_voxels: .*380 rays.*memory limit"),
    ):
        observed_voxels(labels, paired, SOME_RAYS, SMALL_OCC3D)
    # 10^12 rays from broadcast views (no memory of their own): refused at the default
    # limit before anything of that size is allocated
    origins = torch.zeros(1, 3).expand(10**6, 3)
    directions = torch.ones(1, 3).expand(10**6, 3)
    with pytest.raises(ValueError, match=r"cast_rays: would need about .* \(1000000000000 rays"):
        cast_rays(labels, origins, directions, SMALL_OCC3D)
    # chunks keep the working memory bounded: the estimate grows with the output only
    with dego.memory_limit(2**30):
        cast_rays(labels, LIDAR_ORIGINS, SOME_RAYS, SMALL_OCC3D)
