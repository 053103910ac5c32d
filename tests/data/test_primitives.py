"""Primitives: analytic signed distances, ray hits against hand-computed parameters, the
voxel rasterizer (hand-counted and brute force), rigid motions and the rotation helpers."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dego.data import primitives as primitives_module
from dego.data.primitives import (
    BOX,
    CYLINDER,
    ELLIPSOID,
    Primitives,
    axis_to_matrix,
    yaw_matrix,
)
from dego.grid import VoxelGrid

FREE = 17
INF = math.inf
EYE = torch.eye(3)


def solid(kind: int, center, size, rotation=None, label: int = 4) -> Primitives:
    """One solid of ``kind`` (identity rotation unless given)."""
    rot = EYE if rotation is None else torch.as_tensor(rotation, dtype=torch.float32)
    return Primitives.make(
        kind, torch.tensor([center], dtype=torch.float32), rot[None], torch.tensor([size]), label
    )


def yaw(degrees: float) -> torch.Tensor:
    return yaw_matrix(torch.tensor(math.radians(degrees)))


def sdf(solids: Primitives, points) -> torch.Tensor:
    """Signed distance of every point to solid 0."""
    pts = torch.as_tensor(points, dtype=torch.float32).reshape(-1, 3)
    return solids.signed_distance(torch.zeros(pts.shape[0], dtype=torch.long), pts)


def hit(solids: Primitives, origin, direction) -> float:
    """Ray parameter of solid 0's first hit, through the batched private entry point."""
    t = solids._hit_parameter(
        torch.zeros(1, dtype=torch.long),
        torch.tensor([origin], dtype=torch.float32),
        torch.tensor([direction], dtype=torch.float32),
    )
    return float(t[0])


def close(values: torch.Tensor, expected) -> None:
    torch.testing.assert_close(
        values, torch.tensor(expected, dtype=torch.float32), atol=2e-5, rtol=1e-5
    )


# -- construction ----------------------------------------------------------------------
def test_make_cat_empty() -> None:
    boxes = Primitives.make(
        BOX, torch.zeros(3, 3, dtype=torch.float64), EYE.expand(3, 3, 3), torch.ones(3, 3), 5, 0.5
    )
    assert len(boxes) == 3
    assert boxes.centers.dtype == boxes.rotations.dtype == boxes.sizes.dtype == torch.float32
    assert boxes.kinds.tolist() == [BOX] * 3 and boxes.labels.tolist() == [5] * 3
    assert boxes.labels.dtype == boxes.kinds.dtype == torch.long
    assert boxes.shades.tolist() == [0.5] * 3
    empty = Primitives.empty()
    assert len(empty) == 0 and len(Primitives.cat([])) == 0
    both = Primitives.cat([boxes, empty, solid(CYLINDER, (1, 2, 3), (1, 1, 1), label=7)])
    assert len(both) == 4 and both.kinds.tolist() == [BOX] * 3 + [CYLINDER]
    assert both.labels.tolist() == [5, 5, 5, 7]
    assert both.centers[3].tolist() == [1.0, 2.0, 3.0]


# -- signed distances ------------------------------------------------------------------
def test_box_signed_distance() -> None:
    box = solid(BOX, (1, 2, 3), (1, 2, 0.5))
    points = [
        (1, 2, 3),  # centre: -min(half sizes)
        (2, 2, 3),  # on the +x face
        (1, 0, 3),  # on the -y face
        (1.5, 2.5, 3.5),  # on the top face
        (4, 2, 3),  # outside along x
        (1, 2, -1),  # outside along -z
        (3, 5, 4.5),  # outside past a corner: (1, 1, 1)
        (1, 2, 3.3),  # inside, 0.2 below the top
    ]
    close(sdf(box, points), [-0.5, 0, 0, 0, 2, 3.5, math.sqrt(3), -0.2])


def test_rotated_box_signed_distance() -> None:
    # yaw 90 degrees: local x (half size 1) is world y, local y (half size 2) is world -x
    box = solid(BOX, (1, 2, 3), (1, 2, 0.5), yaw(90))
    close(sdf(box, [(1, 5, 3), (4, 2, 3), (1, 2, 3), (1, -1, 3)]), [2, 1, -0.5, 2])
    # a box yawed 45 degrees: its vertical edge is sqrt(2) from the centre along x
    diamond = solid(BOX, (0, 0, 0), (1, 1, 1), yaw(45))
    close(sdf(diamond, [(math.sqrt(2), 0, 0), (2 * math.sqrt(2), 0, 0)]), [0, math.sqrt(2)])


def test_cylinder_signed_distance() -> None:
    cyl = solid(CYLINDER, (0, 0, 0), (1, 1, 2))
    points = [
        (0, 0, 0),  # centre: -min(r, h)
        (1, 0, 0),  # side
        (0.6, 0.8, 1.5),  # side, off-axis
        (0, 0, 2),  # cap
        (3, 0, 0),  # outside the side
        (0, 0, -5),  # outside the cap
        (2, 0, 3),  # past the rim: (1, 1)
        (0, 0.5, 0),  # inside, 0.5 from the side
    ]
    close(sdf(cyl, points), [-1, 0, 0, 0, 2, 3, math.sqrt(2), -0.5])
    # the axis along world x
    lying = solid(CYLINDER, (5, 0, 0), (1, 1, 2), axis_to_matrix(torch.tensor([1.0, 0, 0])))
    close(sdf(lying, [(10, 0, 0), (5, 4, 0), (5, 0, -1), (3, 0, 0.5)]), [3, 3, 0, 0])


def test_ellipsoid_signed_distance() -> None:
    ell = solid(ELLIPSOID, (0, 0, 0), (3, 2, 1))
    a = 0.7
    points = [
        (0, 0, 0),  # centre: -min(radii)
        (3, 0, 0),
        (0, -2, 0),
        (0, 0, 1),  # surface points on the axes
        (3 * math.cos(a), 2 * math.sin(a), 0),  # and off the axes
        (3 * math.cos(a) * 0.6, 0, 0.8),  # (x/3)^2 + (z/1)^2 = 0.36 * cos^2 + 0.64 < 1 ...
        (5, 0, 0),
        (0, 4.5, 0),
        (0, 0, -4),  # outside along the axes: exact
        (0, 1, 0),  # inside along an axis
    ]
    d = sdf(ell, points)
    close(d[[0, 1, 2, 3, 4, 6, 7, 8, 9]], [-1, 0, 0, 0, 0, 2, 2.5, 3, -1])
    assert d[5] < 0
    # rotated: yaw 90 degrees puts the 3 m radius along world y
    turned = solid(ELLIPSOID, (1, 1, 1), (3, 2, 1), yaw(90))
    close(sdf(turned, [(1, 4, 1), (3, 1, 1), (1, 6, 1)]), [0, 0, 2])


def test_ellipsoid_distance_is_a_lower_bound_outside() -> None:
    """Outside, the ellipsoid's signed distance never exceeds the distance to any point of
    its surface (so rasterizing with a margin never misses a voxel it should mark)."""
    g = torch.Generator().manual_seed(0)
    radii = torch.tensor([2.0, 0.5, 0.3])
    ell = solid(ELLIPSOID, (0, 0, 0), radii.tolist())
    u = torch.rand(4000, generator=g) * math.pi
    v = torch.rand(4000, generator=g) * 2 * math.pi
    surface = torch.stack(
        [torch.sin(u) * torch.cos(v), torch.sin(u) * torch.sin(v), torch.cos(u)], -1
    )
    surface = surface * radii
    points = torch.randn(500, 3, generator=g) * 2
    d = sdf(ell, points)
    nearest = torch.cdist(points, surface).min(-1).values
    outside = d > 0
    assert outside.sum() > 100
    assert bool((d[outside] <= nearest[outside] + 1e-5).all())
    # the sign is right everywhere
    inside = ((points / radii).square().sum(-1) < 1).float()
    assert torch.equal((d < 0).float(), inside)


# -- ray hits --------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("origin", "direction", "expected"),
    [
        ((0, 0, 0), (1, 0, 0), 4.0),
        ((0, 0, 0), (2, 0, 0), 2.0),  # t in units of the direction
        ((5, -10, 0), (0, 1, 0), 9.0),
        ((5, 0, 10), (0, 0, -1), 9.0),
        ((0, 0, 0), (1, 0.2, 0), 4.0),  # oblique, through the -x face
        ((5, 0, 0), (1, 0, 0), 0.0),  # starts inside
        ((5.5, 0.5, -0.5), (0, 0, -1), 0.0),
        ((0, 0, 0), (-1, 0, 0), INF),  # points away
        ((0, 2, 0), (1, 0, 0), INF),  # parallel to a face, outside its slab
        ((0, 0, 0), (1, 1, 0), INF),  # passes beside
        ((7, 0, 0), (1, 0, 0), INF),  # behind the origin
    ],
)
def test_box_hit(origin, direction, expected) -> None:
    box = solid(BOX, (5, 0, 0), (1, 1, 1))
    assert hit(box, origin, direction) == pytest.approx(expected, abs=1e-5)


def test_rotated_box_hit() -> None:
    diamond = solid(BOX, (5, 0, 0), (1, 1, 1), yaw(45))
    assert hit(diamond, (0, 0, 0), (1, 0, 0)) == pytest.approx(5 - math.sqrt(2), abs=1e-5)
    assert hit(diamond, (5, -5, 0.5), (0, 1, 0)) == pytest.approx(5 - math.sqrt(2), abs=1e-5)
    assert hit(diamond, (0, 1.5, 0), (1, 0, 0)) == INF  # passes beside the corner
    # local z along world -x: half sizes (1, 2, 3) lie along world (-y, z, -x)
    tilted = solid(BOX, (10, 0, 0), (1, 2, 3), axis_to_matrix(torch.tensor([-1.0, 0, 0])))
    assert hit(tilted, (0, 0, 0), (1, 0, 0)) == pytest.approx(7.0, abs=1e-5)
    assert hit(tilted, (10, 0, 5), (0, 0, -1)) == pytest.approx(3.0, abs=1e-5)
    assert hit(tilted, (10, -5, 0), (0, 1, 0)) == pytest.approx(4.0, abs=1e-5)


@pytest.mark.parametrize(
    ("origin", "direction", "expected"),
    [
        ((0, 0, 0), (1, 0, 0), 4.0),  # the side
        ((0, 0, 1.5), (0.5, 0, 0), 8.0),
        ((5, 0, 10), (0, 0, -1), 8.0),  # along the axis, inside the circle: the cap
        ((5.5, 0.5, -10), (0, 0, 1), 8.0),
        ((5, -5, 5), (0, 1, -1), 4.0),  # oblique, enters through the side
        ((5, -5, 7.5), (0, 1, -1), 5.5),  # oblique, enters through the cap
        ((0, 0, 3), (1, 0, -0.5), 4.0),
        ((5, 0, 1), (0, 1, 0), 0.0),  # starts inside
        ((7, 0, 10), (0, 0, -1), INF),  # along the axis, outside the circle
        ((0, 0, 3), (1, 0, 0), INF),  # parallel to the caps, above them
        ((0, 0, 0), (-1, 0, 0), INF),
        ((0, 1.5, 0), (1, 0, 0), INF),
    ],
)
def test_cylinder_hit(origin, direction, expected) -> None:
    cyl = solid(CYLINDER, (5, 0, 0), (1, 1, 2))
    assert hit(cyl, origin, direction) == pytest.approx(expected, abs=1e-5)


def test_rotated_cylinder_hit() -> None:
    lying = solid(CYLINDER, (5, 0, 0), (1, 1, 2), axis_to_matrix(torch.tensor([1.0, 0, 0])))
    assert hit(lying, (0, 0, 0), (1, 0, 0)) == pytest.approx(3.0, abs=1e-5)  # the cap
    assert hit(lying, (5, -10, 0), (0, 1, 0)) == pytest.approx(9.0, abs=1e-5)  # the side
    assert hit(lying, (5, 0, 10), (0, 0, -1)) == pytest.approx(9.0, abs=1e-5)
    assert hit(lying, (8, -10, 0), (0, 1, 0)) == INF  # beyond the cap
    tilted = solid(CYLINDER, (0, 0, 0), (1, 1, 3), axis_to_matrix(torch.tensor([1.0, 1, 0])))
    assert hit(tilted, (-10, -10, 0), (1, 1, 0)) == pytest.approx(10 - 3 / math.sqrt(2), abs=1e-5)


@pytest.mark.parametrize(
    ("origin", "direction", "expected"),
    [
        ((0, 0, 0), (1, 0, 0), 3.0),
        ((0, 0, 0), (4, 0, 0), 0.75),
        ((5, -10, 0), (0, 1, 0), 9.0),
        ((5, 0, -3), (0, 0, 1), 2.0),
        ((5, 0, 0), (0, 1, 0), 0.0),  # starts inside
        ((6.9, 0, 0), (-1, 0, 0), 0.0),
        ((0, 2, 0), (1, 0, 0), INF),
        ((0, 0, 0), (-1, 0, 0), INF),
        ((5, -10, 0), (0, -1, 0), INF),
    ],
)
def test_ellipsoid_hit(origin, direction, expected) -> None:
    ell = solid(ELLIPSOID, (5, 0, 0), (2, 1, 1))
    assert hit(ell, origin, direction) == pytest.approx(expected, abs=1e-5)


def test_rotated_and_offset_ellipsoid_hit() -> None:
    turned = solid(ELLIPSOID, (5, 0, 0), (2, 1, 1), yaw(90))
    assert hit(turned, (0, 0, 0), (1, 0, 0)) == pytest.approx(4.0, abs=1e-5)
    assert hit(turned, (5, -10, 0), (0, 1, 0)) == pytest.approx(8.0, abs=1e-5)
    ball = solid(ELLIPSOID, (0, 0, 0), (1, 1, 1))
    assert hit(ball, (-5, 0.6, 0), (1, 0, 0)) == pytest.approx(4.2, abs=1e-5)


def test_intersect_nearest_and_ties() -> None:
    near = solid(BOX, (5, 0, 0), (1, 1, 1), label=1)
    far = solid(CYLINDER, (10, 0, 0), (1, 1, 1), label=2)
    twin = solid(ELLIPSOID, (5, 0, 0), (1, 1, 1), label=3)  # same entry point as ``near``
    origins = torch.tensor([[0.0, 0, 0], [20, 0, 0], [0, 5, 0], [5, 0, 0], [10, 0, 0]])
    directions = torch.tensor([[1.0, 0, 0], [-1, 0, 0], [1, 0, 0], [1, 0, 0], [-1, 0, 0]])
    t, index = Primitives.cat([far, near]).intersect(origins, directions)
    close(t, [4, 9, INF, 0, 0])
    assert index.tolist() == [1, 0, -1, 1, 0]
    t, index = Primitives.cat([near, far]).intersect(origins, directions)
    assert index.tolist() == [0, 1, -1, 0, 1]
    # equal t: the later (higher index) solid wins, for entry hits and for starts inside
    for order, winner in (([near, twin], 1), ([twin, near], 1)):
        t, index = Primitives.cat([*order, far]).intersect(origins[[0, 3]], directions[[0, 3]])
        close(t, [4, 0])
        assert index.tolist() == [winner, winner]
    same = Primitives.cat([near, solid(BOX, (5, 0, 0), (1, 1, 1), label=9)])
    t, index = same.intersect(origins[:1], directions[:1])
    assert index.tolist() == [1] and same.labels[index].tolist() == [9]


def test_intersect_empty() -> None:
    t, index = Primitives.empty().intersect(torch.zeros(4, 3), torch.ones(4, 3))
    assert t.tolist() == [INF] * 4 and index.tolist() == [-1] * 4
    t, index = solid(BOX, (0, 0, 0), (1, 1, 1)).intersect(torch.zeros(0, 3), torch.zeros(0, 3))
    assert t.shape == (0,) and index.shape == (0,)


def random_solids(n: int, seed: int, spread: float = 6.0) -> Primitives:
    g = torch.Generator().manual_seed(seed)
    kinds = torch.randint(0, 3, (n,), generator=g)
    axes = torch.randn(n, 3, generator=g)
    rotations = axis_to_matrix(axes) @ yaw_matrix(torch.rand(n, generator=g) * 6.3)
    sizes = 0.2 + torch.rand(n, 3, generator=g) * 1.5
    sizes[:, 1] = torch.where(kinds == CYLINDER, sizes[:, 0], sizes[:, 1])
    return Primitives(
        kinds,
        (torch.rand(n, 3, generator=g) * 2 - 1) * spread,
        rotations,
        sizes,
        torch.randint(0, 17, (n,), generator=g),
        torch.rand(n, generator=g),
    )


def brute_force_intersect(solids: Primitives, origins, directions):
    """Every ray against every solid, no screening: nearest, highest index on ties."""
    r, p = origins.shape[0], len(solids)
    owner = torch.arange(p).repeat(r)
    t = solids._hit_parameter(
        owner, origins.repeat_interleave(p, 0), directions.repeat_interleave(p, 0)
    ).view(r, p)
    best = t.min(-1).values
    winner = torch.where(t == best[:, None], torch.arange(p), -1).max(-1).values
    return best, torch.where(torch.isfinite(best), winner, -1)


@pytest.mark.parametrize("chunk", [None, 7, 64])
def test_intersect_matches_brute_force(chunk, monkeypatch) -> None:
    """Bounding-sphere screening and chunking never change the answer."""
    if chunk is not None:
        monkeypatch.setattr(primitives_module, "_PAIR_CHUNK", chunk)
    solids = random_solids(25, seed=1)
    g = torch.Generator().manual_seed(2)
    origins = (torch.rand(300, 3, generator=g) * 2 - 1) * 9
    directions = torch.randn(300, 3, generator=g) * (0.2 + torch.rand(300, 1, generator=g))
    t, index = solids.intersect(origins, directions)
    best, winner = brute_force_intersect(solids, origins, directions)
    assert torch.equal(t, best) and torch.equal(index, winner)
    assert 30 < int((index >= 0).sum()) < 300  # hits, misses and starts inside
    assert int((t == 0).sum()) > 0


@pytest.mark.slow
@pytest.mark.parametrize("block", [1, 3, 32, 1000])
@pytest.mark.parametrize("chunk", [None, 40])
def test_intersect_ray_blocks_match_brute_force(block, chunk, monkeypatch) -> None:
    """Screening blocks of consecutive rays as cones never changes the answer: bundles from
    shared origins (camera-like, origins inside some bounding spheres), scattered rays,
    short and long directions, and zero directions (never hit)."""
    monkeypatch.setattr(primitives_module, "_RAY_BLOCK", block)
    if chunk is not None:
        monkeypatch.setattr(primitives_module, "_PAIR_CHUNK", chunk)
    solids = Primitives.cat(
        [random_solids(20, seed=4), solid(BOX, (0.0, 0.0, -3.0), (40.0, 40.0, 1.0), label=11)]
    )
    g = torch.Generator().manual_seed(5)
    u, v = torch.meshgrid(
        torch.linspace(-0.6, 0.6, 23), torch.linspace(-0.4, 0.4, 9), indexing="ij"
    )
    fan = torch.stack([torch.ones_like(u), u, v], -1).reshape(-1, 3)
    origins = torch.cat(
        [
            torch.tensor([-8.0, 0.5, 0.0]).expand(fan.shape[0], 3),
            torch.tensor([0.0, 0.0, 0.0]).expand(fan.shape[0], 3),  # inside the ground's sphere
            (torch.rand(150, 3, generator=g) * 2 - 1) * 9,
            torch.zeros(3, 3),
        ]
    )
    directions = torch.cat(
        [
            fan,
            -fan * 0.01,
            torch.randn(150, 3, generator=g) * (0.2 + torch.rand(150, 1, generator=g)),
            torch.zeros(3, 3),
        ]
    )
    t, index = solids.intersect(origins, directions)
    best, winner = brute_force_intersect(solids, origins, directions)
    best[-3:], winner[-3:] = INF, -1  # a zero direction hits nothing
    assert torch.equal(t, best) and torch.equal(index, winner)
    assert 100 < int((index >= 0).sum()) < origins.shape[0] - 50
    assert int((index == len(solids) - 1).sum()) > 20  # the ground, from inside its sphere


@settings(max_examples=30)
@given(st.integers(0, 2**31 - 1), st.integers(1, 8))
def test_hits_agree_with_signed_distances(seed: int, n: int) -> None:
    """The two independent evaluations agree: a ray's first hit is on the surface of the
    solid it names, and no solid contains a point of the ray before it."""
    solids = random_solids(n, seed, spread=3.0)
    g = torch.Generator().manual_seed(seed + 1)
    origins = (torch.rand(64, 3, generator=g) * 2 - 1) * 8
    directions = torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=-1)
    t, index = solids.intersect(origins, directions)
    hits = torch.isfinite(t)
    # on the surface of the named solid (0 for starts inside: the origin is inside)
    at = origins + t.where(hits, 0.0)[:, None] * directions
    d = solids.signed_distance(index.clamp_min(0), at)
    entering = hits & (t > 0)
    assert bool((d[entering].abs() < 2e-3).all())
    assert bool((d[hits & (t == 0)] < 1e-4).all())
    # no solid contains a sample of the ray before its hit (or up to 30 m for misses)
    reach = torch.where(hits, t, 30.0)
    s = torch.linspace(0.0, 0.995, 60)
    samples = origins[:, None] + (s[None, :, None] * reach[:, None, None]) * directions[:, None]
    samples = samples[t > 0].reshape(-1, 3)
    owner = torch.arange(n).repeat(samples.shape[0])
    inside = solids.signed_distance(owner, samples.repeat_interleave(n, 0)).view(-1, n)
    assert bool((inside.min(-1).values > -2e-3).all())


# -- rasterization ---------------------------------------------------------------------
UNIT_GRID = VoxelGrid((0.0, 0.0, 0.0), (4.0, 4.0, 4.0), 1.0)  # centres 0.5 .. 3.5


@pytest.mark.parametrize(
    ("margin", "count"),
    [(0.0, 1), (0.45, 1), (0.6, 7), (0.8, 19), (0.9, 27)],  # centre, faces, edges, corners
)
def test_rasterize_hand_counted_cube(margin: float, count: int) -> None:
    cube = solid(BOX, (1.5, 1.5, 1.5), (0.5, 0.5, 0.5), label=3)
    labels = cube.rasterize(UNIT_GRID, margin)
    assert labels.shape == (4, 4, 4) and labels.dtype == torch.uint8
    marked = labels != FREE
    assert int(marked.sum()) == count
    assert set(labels.unique().tolist()) == {3, FREE}
    i = torch.arange(4)
    offsets = (i[:, None, None] - 1) ** 2 + (i[None, :, None] - 1) ** 2 + (i[None, None] - 1) ** 2
    expected = offsets <= {1: 0, 7: 1, 19: 2, 27: 3}[count]
    assert torch.equal(marked, expected)


def test_rasterize_hand_counted_box() -> None:
    # x in [1, 3] covers centres 1.5 and 2.5; y, z in [1, 2] cover 1.5; within 0.6 of the
    # faces: x 0.5 and 3.5 (1 each), y 0.5 / 2.5 and z 0.5 / 2.5 beside both core voxels
    box = solid(BOX, (2.0, 1.5, 1.5), (1.0, 0.5, 0.5), label=10)
    labels = box.rasterize(UNIT_GRID, 0.6)
    marked = {tuple(v) for v in (labels != FREE).nonzero().tolist()}
    core = {(1, 1, 1), (2, 1, 1)}
    ends = {(0, 1, 1), (3, 1, 1)}
    sides = {(x, y, z) for x in (1, 2) for (y, z) in ((0, 1), (2, 1), (1, 0), (1, 2))}
    assert marked == core | ends | sides and len(marked) == 12
    assert int(box.rasterize(UNIT_GRID, 0.1).ne(FREE).sum()) == 2


def brute_force_box_labels(grid: VoxelGrid, boxes, margin: float) -> np.ndarray:
    """Axis-aligned boxes ``(label, centre, half sizes)`` in order, per voxel in numpy."""
    centres = grid.centers(dtype=torch.float64).numpy()
    out = np.full(grid.shape, FREE, dtype=np.uint8)
    for label, centre, half in boxes:
        d = np.abs(centres - np.asarray(centre)) - np.asarray(half)
        dist = np.linalg.norm(np.maximum(d, 0), axis=-1) + np.minimum(d.max(-1), 0)
        out[dist <= margin] = label
    return out


def test_rasterize_matches_brute_force_with_overlaps_and_clipping() -> None:
    """Later solids win where they overlap; solids reaching past the grid are clipped; any
    grid origin and anisotropic voxels."""
    grid = VoxelGrid((-1.0, -2.0, -0.5), (3.0, 2.0, 2.5), (0.5, 0.25, 0.5))
    boxes = [
        (11, (1.0, 0.0, -0.6), (5.0, 5.0, 0.5)),  # a ground slab wider than the grid
        (3, (0.3, 0.1, 0.8), (0.9, 0.6, 0.7)),
        (5, (0.9, -0.3, 1.1), (0.6, 0.8, 0.5)),  # overlaps the previous one
        (8, (2.9, 1.9, 2.4), (0.4, 0.3, 0.3)),  # in the far corner, partly outside
        (9, (9.0, 0.0, 0.0), (1.0, 1.0, 1.0)),  # entirely outside
    ]
    solids = Primitives.cat(
        [solid(BOX, c, h, label=label) for label, c, h in boxes]  # identity rotations
    )
    for margin in (0.0, 0.1, 0.3):
        got = solids.rasterize(grid, margin).numpy()
        expected = brute_force_box_labels(grid, boxes, margin)
        np.testing.assert_array_equal(got, expected)
    labels = solids.rasterize(grid, 0.1)
    assert {3, 5, 8, 11} <= set(labels.unique().tolist()) and 9 not in labels.unique()
    # reversed order: the other box wins the overlap
    flipped = Primitives.cat([solid(BOX, c, h, label=label) for label, c, h in boxes[::-1]])
    got = flipped.rasterize(grid, 0.1).numpy()
    np.testing.assert_array_equal(got, brute_force_box_labels(grid, boxes[::-1], 0.1))
    assert not np.array_equal(got, labels.numpy())


def last_solid_within(solids: Primitives, grid: VoxelGrid, margin: float) -> torch.Tensor:
    """Brute force: per voxel centre (flattened), the index of the last solid whose signed
    distance is within ``margin`` (-1 where none)."""
    centres = grid.centers().reshape(-1, 3)
    n = len(solids)
    within = (
        solids.signed_distance(
            torch.arange(n).repeat(centres.shape[0]), centres.repeat_interleave(n, 0)
        )
        .view(-1, n)
        .le(margin)
    )
    return torch.where(within, torch.arange(n), -1).max(-1).values


@pytest.mark.parametrize("chunk", [1, 50, 1000])
def test_rasterize_chunking_is_invisible(chunk, monkeypatch) -> None:
    grid = VoxelGrid((-6.0, -6.0, -6.0), (6.0, 6.0, 6.0), 0.5)
    solids = random_solids(30, seed=3, spread=5.0)
    full = solids.rasterize(grid, 0.1)
    monkeypatch.setattr(primitives_module, "_PAIR_CHUNK", chunk)
    assert torch.equal(solids.rasterize(grid, 0.1), full)
    # and the rule itself: the label of the last solid within the margin of a voxel centre
    last = last_solid_within(solids, grid, 0.1)
    expected = torch.where(last >= 0, solids.labels[last.clamp_min(0)], FREE).to(torch.uint8)
    assert torch.equal(full.reshape(-1), expected)
    assert int((last >= 0).sum()) > 100


def test_rasterize_index_is_the_winning_solid() -> None:
    """rasterize_index gives the index of the solid whose label rasterize writes: the last
    solid within the margin (-1 where none), on a hand-counted overlap."""
    grid = UNIT_GRID
    solids = Primitives.cat(
        [
            solid(BOX, (2.0, 2.0, 0.5), (2.0, 2.0, 0.5), label=11),  # the z = 0 layer
            solid(BOX, (1.5, 1.5, 1.0), (0.5, 0.5, 1.0), label=3),  # a column over (1, 1)
            solid(BOX, (9.0, 9.0, 9.0), (0.5, 0.5, 0.5), label=5),  # outside the grid
        ]
    )
    index = solids.rasterize_index(grid, 0.1)
    assert index.shape == (4, 4, 4) and index.dtype == torch.int64
    expected = torch.full((4, 4, 4), -1, dtype=torch.long)
    expected[:, :, 0] = 0
    expected[1, 1, :2] = 1  # the column wins the layer's voxel below it
    assert torch.equal(index, expected)
    labels = torch.where(index >= 0, solids.labels[index.clamp_min(0)], FREE).to(torch.uint8)
    assert torch.equal(solids.rasterize(grid, 0.1), labels)
    assert torch.equal(Primitives.empty().rasterize_index(grid, 0.1), torch.full_like(index, -1))


@pytest.mark.parametrize("chunk", [1, 50, 1000])
def test_rasterize_index_matches_the_rule(chunk, monkeypatch) -> None:
    grid = VoxelGrid((-6.0, -6.0, -6.0), (6.0, 6.0, 6.0), 0.5)
    solids = random_solids(30, seed=6, spread=5.0)
    monkeypatch.setattr(primitives_module, "_PAIR_CHUNK", chunk)
    index = solids.rasterize_index(grid, 0.1)
    last = last_solid_within(solids, grid, 0.1)
    assert torch.equal(index.reshape(-1), last)
    labels = torch.where(last >= 0, solids.labels[last.clamp_min(0)], FREE).to(torch.uint8)
    assert torch.equal(solids.rasterize(grid, 0.1).reshape(-1), labels)


# -- rigid motions ---------------------------------------------------------------------
quaternions = st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: sum(v * v for v in q) > 0.01)
translations = st.tuples(*[st.floats(-20, 20)] * 3)


def quaternion_matrix(q) -> torch.Tensor:
    w, x, y, z = (v / math.sqrt(sum(c * c for c in q)) for v in q)
    return torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
        dtype=torch.float64,
    )


@given(quaternions, translations, st.integers(0, 2**31 - 1))
def test_transformed_is_a_rigid_motion(q, shift, seed: int) -> None:
    rotation = quaternion_matrix(q)
    translation = torch.tensor(shift, dtype=torch.float64)
    solids = random_solids(6, seed)
    moved = solids.transformed(rotation, translation)
    assert torch.equal(moved.kinds, solids.kinds) and torch.equal(moved.sizes, solids.sizes)
    assert torch.equal(moved.labels, solids.labels) and torch.equal(moved.shades, solids.shades)
    assert moved.centers.dtype == moved.rotations.dtype == torch.float32
    g = torch.Generator().manual_seed(seed)
    points = torch.randn(40, 3, generator=g, dtype=torch.float64) * 4
    moved_points = points @ rotation.T + translation
    owner = torch.arange(6).repeat(40)
    before = solids.signed_distance(owner, points.float().repeat_interleave(6, 0))
    after = moved.signed_distance(owner, moved_points.float().repeat_interleave(6, 0))
    torch.testing.assert_close(after, before, atol=2e-4, rtol=1e-4)
    # ray hits are invariant too
    directions = torch.randn(40, 3, generator=g, dtype=torch.float64)
    t0, _ = solids.intersect(points.float(), directions.float())
    t1, _ = moved.intersect(moved_points.float(), (directions @ rotation.T).float())
    finite = torch.isfinite(t0) & torch.isfinite(t1)
    torch.testing.assert_close(t1[finite], t0[finite], atol=1e-3, rtol=1e-3)
    # a miss on one side and a hit on the other only happens for grazing rays
    assert int((torch.isfinite(t0) != torch.isfinite(t1)).sum()) <= 1


def test_transformed_composes_and_keeps_labels() -> None:
    solids = random_solids(5, seed=4)
    r1, r2 = yaw(30) @ axis_to_matrix(torch.tensor([0.3, 1.0, 0.2])), yaw(-75)
    t1, t2 = torch.tensor([1.0, -2.0, 0.5]), torch.tensor([-4.0, 0.0, 3.0])
    twice = solids.transformed(r1, t1).transformed(r2, t2)
    once = solids.transformed(r2 @ r1, r2 @ t1 + t2)
    torch.testing.assert_close(twice.centers, once.centers, atol=1e-5, rtol=0)
    torch.testing.assert_close(twice.rotations, once.rotations, atol=1e-6, rtol=0)
    identity = solids.transformed(torch.eye(3), torch.zeros(3))
    torch.testing.assert_close(identity.centers, solids.centers)
    torch.testing.assert_close(identity.rotations, solids.rotations)


def test_half_extents_contain_the_solids() -> None:
    solids = random_solids(40, seed=5)
    g = torch.Generator().manual_seed(6)
    points = solids.centers.repeat(100, 1) + torch.randn(4000, 3, generator=g)
    n = len(solids)
    inside = (
        solids.signed_distance(
            torch.arange(n).repeat(points.shape[0]), points.repeat_interleave(n, 0)
        )
        .view(-1, n)
        .le(0)
    )
    rel = (points[:, None] - solids.centers[None]).abs()
    in_box = (rel <= solids.half_extents()[None] + 1e-5).all(-1)
    in_ball = rel.norm(dim=-1) <= solids.bounding_radius()[None] + 1e-5
    assert int(inside.sum()) > 500
    assert bool(in_box[inside].all()) and bool(in_ball[inside].all())


# -- rotation helpers ------------------------------------------------------------------
def assert_rotation(matrices: torch.Tensor, atol: float = 1e-5) -> None:
    eye = torch.eye(3, dtype=matrices.dtype).expand_as(matrices)
    torch.testing.assert_close(matrices.transpose(-1, -2) @ matrices, eye, atol=atol, rtol=0)
    dets = torch.linalg.det(matrices)
    torch.testing.assert_close(dets, torch.ones_like(dets), atol=atol, rtol=0)


@given(st.lists(st.floats(-10, 10), min_size=1, max_size=6))
def test_yaw_matrix_is_a_rotation_about_z(angles) -> None:
    a = torch.tensor(angles, dtype=torch.float64)
    r = yaw_matrix(a)
    assert r.shape == (len(angles), 3, 3) and r.dtype == torch.float64
    assert_rotation(r, 1e-12)
    x = r @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    torch.testing.assert_close(x, torch.stack([a.cos(), a.sin(), torch.zeros_like(a)], -1))
    z = r @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(z, torch.tensor([0.0, 0, 1], dtype=torch.float64).expand_as(z))


def test_yaw_matrix_values() -> None:
    torch.testing.assert_close(
        yaw_matrix(torch.tensor(math.pi / 2)),
        torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]),
        atol=1e-7,
        rtol=0,
    )
    assert yaw_matrix(torch.zeros(2, 3)).shape == (2, 3, 3, 3)


axes = st.tuples(*[st.floats(-5, 5)] * 3).filter(lambda v: sum(c * c for c in v) > 1e-4)


@given(st.lists(axes, min_size=1, max_size=5))
def test_axis_to_matrix_is_a_rotation_taking_z_to_the_axis(vectors) -> None:
    axis = torch.tensor(vectors, dtype=torch.float64)
    r = axis_to_matrix(axis)
    assert r.shape == (len(vectors), 3, 3)
    assert_rotation(r, 1e-10)
    unit = axis / axis.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(r[..., :, 2], unit)  # local +z
    torch.testing.assert_close(
        r @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), unit, atol=1e-12, rtol=0
    )


@pytest.mark.parametrize(
    "axis",
    [v for v in itertools.product([-1.0, 0.0, 1.0], repeat=3) if any(v)]
    + [(0.0, 0.1, 1.0), (1e-3, 0.0, -1.0), (0.44, 0.0, 0.9)],  # near and at the helper switch
)
def test_axis_to_matrix_special_axes(axis) -> None:
    r = axis_to_matrix(torch.tensor(axis))
    assert_rotation(r)
    unit = torch.tensor(axis) / torch.tensor(axis).norm()
    torch.testing.assert_close(r @ torch.tensor([0.0, 0.0, 1.0]), unit, atol=1e-6, rtol=0)


def test_axis_to_matrix_batch_shapes() -> None:
    g = torch.Generator().manual_seed(7)
    axis = torch.randn(2, 4, 3, generator=g)
    r = axis_to_matrix(axis)
    assert r.shape == (2, 4, 3, 3)
    assert_rotation(r)
    # the scale of the axis does not matter
    torch.testing.assert_close(axis_to_matrix(axis * 7.5), r, atol=1e-6, rtol=0)
