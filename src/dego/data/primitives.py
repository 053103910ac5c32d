"""Analytic solids for procedural scenes: oriented boxes, cylinders and ellipsoids.

A :class:`Primitives` set holds P solids with a kind, a centre, a rotation (local to
world), local half-extents and a label. It answers, vectorised over solids and
points/rays: signed distances, first ray hits (:meth:`Primitives.intersect`) and a voxel
label grid (:meth:`Primitives.rasterize`, with the winning solid's index from
:meth:`Primitives.rasterize_index`). Where solids overlap, the later one wins.
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from dego._typing import check_tensor_fields, typechecked
from dego.classes import FREE_LABEL
from dego.grid import VoxelGrid

BOX, CYLINDER, ELLIPSOID = 0, 1, 2
"""Kinds. Box: half sizes (hx, hy, hz). Cylinder: axis local z, sizes (r, r, half height).
Ellipsoid: radii (a, b, c)."""

_PAIR_CHUNK = 1 << 22  # (solid, point) or (solid, ray) pairs evaluated at a time
_RAY_BLOCK = 32  # consecutive rays screened together against the solids' bounding spheres


def yaw_matrix(yaw: Tensor) -> Tensor:
    """``(..., 3, 3)`` rotations about +z by ``yaw`` radians."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    zero, one = torch.zeros_like(yaw), torch.ones_like(yaw)
    rows = (c, -s, zero, s, c, zero, zero, zero, one)
    return torch.stack(rows, -1).unflatten(-1, (3, 3))


def axis_to_matrix(axis: Tensor) -> Tensor:
    """``(..., 3, 3)`` rotations taking local +z to the unit vectors ``axis (..., 3)``."""
    z = axis / torch.linalg.vector_norm(axis, dim=-1, keepdim=True)
    helper = torch.where(
        z[..., 2:3].abs() < 0.9,
        torch.tensor([0.0, 0.0, 1.0], dtype=z.dtype).expand_as(z),
        torch.tensor([1.0, 0.0, 0.0], dtype=z.dtype).expand_as(z),
    )
    x = torch.linalg.cross(helper, z)
    x = x / torch.linalg.vector_norm(x, dim=-1, keepdim=True)
    y = torch.linalg.cross(z, x)
    return torch.stack([x, y, z], -1)  # columns: local axes in world coordinates


@dataclasses.dataclass(frozen=True)
class Primitives:
    """P analytic solids (float32 geometry).

    Attributes:
        kinds: ``(P,)`` int64, :data:`BOX`, :data:`CYLINDER` or :data:`ELLIPSOID`.
        centers: ``(P, 3)``.
        rotations: ``(P, 3, 3)`` local -> world (columns = local axes).
        sizes: ``(P, 3)`` half extents (see the kinds).
        labels: ``(P,)`` int64.
        shades: ``(P,)`` brightness factors for rendering, in (0, 1].
    """

    def __post_init__(self) -> None:
        check_tensor_fields(self)

    kinds: Tensor
    centers: Tensor
    rotations: Tensor
    sizes: Tensor
    labels: Tensor
    shades: Tensor

    @staticmethod
    def empty() -> Primitives:
        return Primitives(
            torch.zeros(0, dtype=torch.long),
            torch.zeros(0, 3),
            torch.zeros(0, 3, 3),
            torch.zeros(0, 3),
            torch.zeros(0, dtype=torch.long),
            torch.zeros(0),
        )

    @staticmethod
    @typechecked
    def make(
        kind: int,
        centers: Tensor,
        rotations: Tensor,
        sizes: Tensor,
        label: int | Tensor,
        shade: float | Tensor = 1.0,
    ) -> Primitives:
        """Solids of one kind; ``centers (P, 3)``, ``rotations (P, 3, 3)``, ``sizes (P, 3)``."""
        p = centers.shape[0]
        return Primitives(
            torch.full((p,), kind, dtype=torch.long),
            centers.float(),
            rotations.float(),
            sizes.float(),
            torch.as_tensor(label, dtype=torch.long).expand(p).clone(),
            torch.as_tensor(shade, dtype=torch.float32).expand(p).clone(),
        )

    @staticmethod
    def cat(parts: list[Primitives]) -> Primitives:
        """Concatenate in order (later solids win where they overlap)."""
        if not parts:
            return Primitives.empty()
        return Primitives(
            *(
                torch.cat([getattr(p, f.name) for p in parts])
                for f in dataclasses.fields(Primitives)
            )
        )

    def __len__(self) -> int:
        return self.kinds.shape[0]

    @typechecked
    def transformed(self, rotation: Tensor, translation: Tensor) -> Primitives:
        """The solids under ``x -> rotation @ x + translation`` (a rigid motion)."""
        r, t = rotation.float(), translation.float()
        return dataclasses.replace(
            self, centers=self.centers @ r.T + t, rotations=r @ self.rotations
        )

    def bounding_radius(self) -> Tensor:
        """``(P,)`` radius of a sphere around each centre containing the solid."""
        return torch.linalg.vector_norm(self.sizes, dim=-1)

    def half_extents(self) -> Tensor:
        """``(P, 3)`` world axis-aligned half extents containing each solid."""
        return (self.rotations.abs() @ self.sizes.unsqueeze(-1)).squeeze(-1)

    # -- signed distances -------------------------------------------------------------
    def _local(self, owner: Tensor, points: Tensor) -> Tensor:
        """Points ``(M, 3)`` in the local frames of solids ``owner (M,)``."""
        rel = (points - self.centers[owner]).unsqueeze(-1)
        return (self.rotations[owner].transpose(-1, -2) @ rel).squeeze(-1)

    @typechecked
    def signed_distance(self, owner: Tensor, points: Tensor) -> Tensor:
        """``(M,)`` signed distance of ``points[m]`` to solid ``owner[m]`` (negative
        inside). The ellipsoid's is approximate: exact on its surface, a lower bound
        outside, only its sign is exact inside."""
        q = self._local(owner, points)
        size, kind = self.sizes[owner], self.kinds[owner]
        # box
        d = q.abs() - size
        box = torch.linalg.vector_norm(d.clamp_min(0), dim=-1) + d.max(-1).values.clamp_max(0)
        # cylinder about local z
        dc = torch.stack(
            [torch.linalg.vector_norm(q[:, :2], dim=-1) - size[:, 0], q[:, 2].abs() - size[:, 2]],
            -1,
        )
        cylinder = torch.linalg.vector_norm(dc.clamp_min(0), dim=-1) + dc.max(-1).values.clamp_max(
            0
        )
        # ellipsoid bound: k0 (k0 - 1) / k1
        k0 = torch.linalg.vector_norm(q / size, dim=-1)
        k1 = torch.linalg.vector_norm(q / size.square(), dim=-1)
        ellipsoid = torch.where(k1 > 1e-9, k0 * (k0 - 1) / k1.clamp_min(1e-9), -size.min(-1).values)
        return torch.where(kind == BOX, box, torch.where(kind == CYLINDER, cylinder, ellipsoid))

    # -- ray hits ---------------------------------------------------------------------
    def _hit_parameter(self, owner: Tensor, origins: Tensor, directions: Tensor) -> Tensor:
        """``(M,)`` smallest ``t >= 0`` where ray m (``origins + t directions``) enters
        solid ``owner[m]`` (0 if it starts inside; ``inf`` if it misses)."""
        rot_t = self.rotations[owner].transpose(-1, -2)
        o = (rot_t @ (origins - self.centers[owner]).unsqueeze(-1)).squeeze(-1)
        d = (rot_t @ directions.unsqueeze(-1)).squeeze(-1)
        size, kind = self.sizes[owner], self.kinds[owner]
        t = torch.full_like(o[:, 0], math.inf)
        for k, entry in (
            (BOX, _box_entry),
            (CYLINDER, _cylinder_entry),
            (ELLIPSOID, _ellipsoid_entry),
        ):
            pairs = (kind == k).nonzero().squeeze(1)  # each kind on its own pairs only
            if pairs.numel():
                t[pairs] = entry(o[pairs], d[pairs], size[pairs])
        return t

    @typechecked
    def intersect(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """First hit of each ray ``(R, 3)`` among all solids: ``(t (R,), index (R,))`` with
        ``t`` in units of ``directions`` (``inf`` and index -1 where nothing is hit).
        Ray-solid pairs are screened with (slightly enlarged) bounding spheres first,
        for blocks of consecutive rays (as cones), then for single rays."""
        r = origins.shape[0]
        best = torch.full((r,), math.inf)
        index = torch.full((r,), -1, dtype=torch.long)
        if len(self) == 0 or r == 0:
            return best, index
        centers = self.centers.double()
        reach = self.bounding_radius().double() * (1 + 1e-4) + 1e-4  # enlarged: rounding
        step = max(1, _PAIR_CHUNK // len(self))
        for start in range(0, r, step):
            o, d = origins[start : start + step], directions[start : start + step]
            ray, owner = _near_pairs(centers, reach, o.double(), d.double())
            t = self._hit_parameter(owner, o[ray], d[ray])
            chunk_best = torch.full((o.shape[0],), math.inf).scatter_reduce(
                0, ray, t, "amin", include_self=True
            )
            # the last solid (highest priority) among equal first hits
            winner = torch.full((o.shape[0],), -1, dtype=torch.long).scatter_reduce(
                0, ray[t == chunk_best[ray]], owner[t == chunk_best[ray]], "amax"
            )
            hit = torch.isfinite(chunk_best)
            best[start : start + step] = chunk_best
            index[start : start + step] = torch.where(hit, winner, -1)
        return best, index

    # -- voxels -----------------------------------------------------------------------
    def rasterize_index(self, grid: VoxelGrid, margin: float) -> Tensor:
        """``(X, Y, Z)`` int64 index of the solid each voxel takes: the last solid whose
        signed distance at the voxel centre is <= ``margin``; -1 where there is none."""
        x, y, z = grid.shape
        lower = torch.tensor(grid.lower)
        size = torch.tensor(grid.voxel_size)
        shape = torch.tensor(grid.shape)
        reach = self.half_extents() + margin
        low = torch.ceil((self.centers - reach - lower) / size - 0.5).long().clamp_min(0)
        high = torch.minimum(
            torch.floor((self.centers + reach - lower) / size - 0.5).long(), shape - 1
        )
        extent = (high - low + 1).clamp_min(0)
        counts = extent.prod(-1)
        winner = torch.full((x * y * z,), -1, dtype=torch.long)
        ends = torch.cumsum(counts, 0)
        first = 0
        while first < len(self):
            # solids whose pairs fit in one chunk (at least one solid)
            base = int(ends[first - 1]) if first else 0
            last = int(torch.searchsorted(ends, base + _PAIR_CHUNK, right=True))
            last = max(last, first + 1)
            part = torch.arange(first, last)
            owner = part.repeat_interleave(counts[part])
            offset = torch.arange(owner.shape[0]) - (ends[owner] - counts[owner] - base)
            ey, ez = extent[owner, 1], extent[owner, 2]
            index = low[owner] + torch.stack(
                [offset // (ey * ez), (offset // ez) % ey, offset % ez], -1
            )
            centres = lower + (index.float() + 0.5) * size
            inside = self.signed_distance(owner, centres) <= margin
            flat = (index[:, 0] * y + index[:, 1]) * z + index[:, 2]
            winner.scatter_reduce_(0, flat[inside], owner[inside], "amax")
            first = last
        return winner.view(x, y, z)

    def rasterize(self, grid: VoxelGrid, margin: float) -> Tensor:
        """``(X, Y, Z)`` uint8 labels: a voxel takes the label of the last solid whose
        signed distance at the voxel centre is <= ``margin``; free (17) elsewhere (the
        labels of :meth:`rasterize_index`)."""
        winner = self.rasterize_index(grid, margin)
        labels = torch.where(winner >= 0, self.labels[winner.clamp_min(0)], FREE_LABEL)
        return labels.to(torch.uint8)


def _near_pairs(
    centers: Tensor, reach: Tensor, origins: Tensor, directions: Tensor
) -> tuple[Tensor, Tensor]:
    """``(ray, solid)`` index pairs (float64 inputs) where ray ``origins + t directions``,
    ``t >= 0``, passes within ``reach`` of a solid's centre (sphere screening). Blocks of
    :data:`_RAY_BLOCK` consecutive rays are screened first: their rays lie in a cone (the
    block's spread of directions) from a ball around the block's mean origin, and a sphere
    that misses that region misses each of the block's rays; then every ray of a block's
    remaining pairs is screened on its own."""
    n = origins.shape[0]
    norm = torch.linalg.vector_norm(directions, dim=-1)
    unit = directions / norm.clamp_min(1e-300)[:, None]
    block = min(_RAY_BLOCK, n)
    blocks = -(-n // block)
    pad = blocks * block - n  # repeat the last ray: it does not widen the block
    o = torch.cat([origins, origins[-1:].expand(pad, 3)]).view(blocks, block, 3)
    u = torch.cat([unit, unit[-1:].expand(pad, 3)]).view(blocks, block, 3)
    apex = o.mean(1)
    spread = torch.linalg.vector_norm(o - apex[:, None], dim=-1).amax(1)
    axis = u.sum(1)
    axis_norm = torch.linalg.vector_norm(axis, dim=-1)
    axis = axis / axis_norm.clamp_min(1e-300)[:, None]
    cos_half = (u * axis[:, None]).sum(-1).amin(1).clamp(-1, 1)
    half = torch.where(axis_norm > 1e-6, torch.acos(cos_half), math.pi)  # (B,)
    v = centers[None] - apex[:, None]  # (B, P, 3)
    dist = torch.linalg.vector_norm(v, dim=-1).clamp_min(1e-300)
    radius = reach[None] + spread[:, None]
    angle = torch.acos(((v * axis[:, None]).sum(-1) / dist).clamp(-1, 1))
    seen = torch.asin((radius / dist).clamp_max(1))  # the sphere's angular radius
    near_block = (dist <= radius) | (angle <= half[:, None] + seen + 1e-6)
    # every ray of a block that starts inside the sphere passes (the big ground solids)
    inside = (dist + spread[:, None]) * (1 + 1e-9) <= reach[None]
    b, owner = inside.nonzero(as_tuple=True)
    ray = (b[:, None] * block + torch.arange(block)).flatten()
    owner = owner[:, None].expand(-1, block).flatten()
    # the other rays one by one: the line passes within reach, the sphere is not behind
    b_check, owner_check = (near_block & ~inside).nonzero(as_tuple=True)
    rel = centers[owner_check][:, None] - o[b_check]  # (K, block, 3)
    along = (rel * u[b_check]).sum(-1)
    r = reach[owner_check][:, None]
    near = (rel.square().sum(-1) - along.square() <= r.square()) & (along >= -r)
    k, j = near.nonzero(as_tuple=True)
    ray = torch.cat([ray, b_check[k] * block + j])
    owner = torch.cat([owner, owner_check[k]])
    keep = (ray < n) & (norm[ray.clamp_max(n - 1)] > 0)
    return ray[keep], owner[keep]


def _box_entry(o: Tensor, d: Tensor, size: Tensor) -> Tensor:
    """Entry parameters of local rays ``o + t d`` ``(M, 3)`` into boxes: slabs."""
    inv = 1.0 / torch.where(d == 0, torch.full_like(d, 1e-30), d)
    t0, t1 = (-size - o) * inv, (size - o) * inv
    near = torch.minimum(t0, t1).max(-1).values
    far = torch.maximum(t0, t1).min(-1).values
    return torch.where((near <= far) & (far >= 0), near.clamp_min(0), math.inf)


def _ellipsoid_entry(o: Tensor, d: Tensor, size: Tensor) -> Tensor:
    """Entry parameters into ellipsoids: the unit sphere after scaling."""
    os, ds = o / size, d / size
    return _quadratic_entry(ds.square().sum(-1), (os * ds).sum(-1), os.square().sum(-1) - 1)


def _cylinder_entry(o: Tensor, d: Tensor, size: Tensor) -> Tensor:
    """Entry parameters into cylinders about local z: the infinite cylinder in xy, cut by
    the z slab."""
    inf = torch.full_like(o[:, 0], math.inf)
    r, h = size[:, 0], size[:, 2]
    a = d[:, :2].square().sum(-1)
    b = (o[:, :2] * d[:, :2]).sum(-1)
    c = o[:, :2].square().sum(-1) - r.square()
    disc = b.square() - a * c
    root = disc.clamp_min(0).sqrt()
    safe_a = torch.where(a > 1e-20, a, torch.ones_like(a))
    side_in, side_out = (-b - root) / safe_a, (-b + root) / safe_a
    parallel = a <= 1e-20  # ray along the axis: inside the circle or never
    side_in = torch.where(parallel, torch.where(c <= 0, -inf, inf), side_in)
    side_out = torch.where(parallel, torch.where(c <= 0, inf, -inf), side_out)
    side_in = torch.where(disc < 0, inf, side_in)
    side_out = torch.where(disc < 0, -inf, side_out)
    dz = torch.where(d[:, 2] == 0, torch.full_like(d[:, 2], 1e-30), d[:, 2])
    z0, z1 = (-h - o[:, 2]) / dz, (h - o[:, 2]) / dz
    cap_in, cap_out = torch.minimum(z0, z1), torch.maximum(z0, z1)
    enter, leave = torch.maximum(side_in, cap_in), torch.minimum(side_out, cap_out)
    return torch.where((enter <= leave) & (leave >= 0), enter.clamp_min(0), inf)


def _quadratic_entry(a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """Entry parameter of ``a t^2 + 2 b t + c <= 0`` for t >= 0 (0 if inside, inf if
    never)."""
    disc = b.square() - a * c
    root = disc.clamp_min(0).sqrt()
    t_in, t_out = (-b - root) / a, (-b + root) / a
    return torch.where((disc >= 0) & (t_out >= 0), t_in.clamp_min(0), math.inf)


__all__ = ["BOX", "CYLINDER", "ELLIPSOID", "Primitives", "axis_to_matrix", "yaw_matrix"]
