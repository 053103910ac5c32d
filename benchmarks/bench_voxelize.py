"""GaussianVoxelizer benchmarks, side by side on the same inputs in one run.

Workload: 10,000 Gaussians (``--n``) in the Occ3D volume (scales 0.05-1 m), C = 16, the
Occ3D 200 x 200 x 16 grid, additive mode.

1. Ours, ``neighborhood="cube", nbh=5`` vs the official algorithm as described for
   DeGO / GaussianFlowOcc: the fixed 11^3 cube around each mean's voxel, a repeated 3x3
   precision matrix per (Gaussian, voxel) pair, ``unique`` over voxel indices, then
   ``scatter_add``. Outputs must be identical (up to float summation order).
2. Ours, ``neighborhood="ellipsoid"`` (k = 3) vs a dense evaluation of every Gaussian at
   every voxel centre, chunked over Gaussians (float64 quadratic form by one GEMM).
3. Ours, ``neighborhood="scale_cube", scale_multiplier=3`` (GaussianFormer's cube of
   ``max(1, ceil(3 max(s) / voxel))`` voxels around the mean's voxel) vs the same dense
   evaluation, timed and memory-measured side by side (the dense one once: it takes
   minutes at the default N), with the cube's truncation error.

``--precision`` instead measures float32 accuracy (no timings): the same float32 inputs are
voxelised in float32 by ours and by the official algorithm, and compared with a float64
evaluation of those inputs (the official algorithm run in float64; ours in float64 is
compared with it too). Workloads: the one above (independent log-uniform scales per
axis, anisotropy up to 20:1), needles (long axis 0.2-1 m, the other two 50x thinner), and
the first on a 0.5 m grid (a voxel size float32 represents exactly, unlike 0.4 m).

    python benchmarks/bench_voxelize.py [--device cuda] [--repeats 3] [--skip-dense]
        [--n 10000] [--only all|cube|ellipsoid|scale_cube]
    python benchmarks/bench_voxelize.py --precision [--n 10000]
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import torch

from dego import GaussianSet, VoxelGrid, voxelize

from harness import benchmark_parser, median_seconds, peak_memory_mib
from scenes import occ3d_gaussians


def official_cube(gs: GaussianSet, grid: VoxelGrid, nbh: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The official algorithm, written plainly (one batch element)."""
    means, precision = gs.means[0], gs.precisions()[0]
    opacity, logits = gs.opacities[0], gs.features[0]
    lower = torch.tensor(grid.lower, dtype=means.dtype)
    size = grid.voxel_size[0]
    shape = torch.tensor(grid.shape)
    centre = torch.floor((means - lower) / size).long()
    r = torch.arange(-nbh, nbh + 1)
    offsets = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    index = (centre[:, None, :] + offsets[None]).reshape(-1, 3)
    owner = torch.arange(means.shape[0]).repeat_interleave(offsets.shape[0])
    keep = ((index >= 0) & (index < shape)).all(-1)
    index, owner = index[keep], owner[keep]
    d = (lower + (index.to(means.dtype) + 0.5) * size) - means[owner]
    pair_precision = precision[owner]  # a repeated 3x3 matrix per pair
    w = torch.exp(-0.5 * (d.unsqueeze(-2) @ pair_precision @ d.unsqueeze(-1)).reshape(-1))
    flat = (index[:, 0] * shape[1] + index[:, 1]) * shape[2] + index[:, 2]
    voxels, inverse = torch.unique(flat, return_inverse=True)
    density = torch.zeros(voxels.shape[0], dtype=means.dtype).scatter_add(
        0, inverse, opacity[owner] * w
    )
    semantics = torch.zeros(voxels.shape[0], logits.shape[1], dtype=means.dtype).scatter_add(
        0, inverse[:, None].expand(-1, logits.shape[1]), w[:, None] * logits[owner]
    )
    full_density = torch.zeros(grid.num_voxels, dtype=means.dtype)
    full_density[voxels] = density.clamp(0, 1)
    full_semantics = torch.zeros(grid.num_voxels, logits.shape[1], dtype=means.dtype)
    full_semantics[voxels] = semantics
    return full_density.view(*grid.shape), full_semantics.view(*grid.shape, -1)


def dense(gs: GaussianSet, grid: VoxelGrid, chunk: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    """Every Gaussian at every voxel centre (additive), chunked over Gaussians."""
    centres = grid.centers(dtype=torch.float64, device=gs.device).reshape(-1, 3)
    x, y, z = centres.unbind(-1)
    basis = torch.stack([x * x, y * y, z * z, x * y, x * z, y * z, x, y, z, torch.ones_like(x)], -1)
    means, precision = gs.means[0].double(), gs.precisions()[0].double()
    values = torch.cat([gs.opacities[0, :, None], gs.features[0]], -1).double()
    total = torch.zeros(centres.shape[0], values.shape[1], dtype=torch.float64, device=gs.device)
    for start in range(0, means.shape[0], chunk):
        m, p = means[start : start + chunk], precision[start : start + chunk]
        pm = (p @ m.unsqueeze(-1)).squeeze(-1)
        # (c - m)^T P (c - m) expanded in the monomials of c
        coefficients = torch.stack(
            [
                p[:, 0, 0],
                p[:, 1, 1],
                p[:, 2, 2],
                2 * p[:, 0, 1],
                2 * p[:, 0, 2],
                2 * p[:, 1, 2],
                -2 * pm[:, 0],
                -2 * pm[:, 1],
                -2 * pm[:, 2],
                (m * pm).sum(-1),
            ],
            0,
        )
        g = torch.exp(-0.5 * (basis @ coefficients))
        total += g @ values[start : start + chunk]
    density = total[:, 0].clamp(0, 1).view(*grid.shape)
    return density, total[:, 1:].view(*grid.shape, -1)


def needle_gaussians(n: int, channels: int, *, seed: int = 0) -> GaussianSet:
    """The benchmark workload with needle scales: long axis 0.2-1 m, the other two 50x
    thinner, random rotations."""
    gs = occ3d_gaussians(n, channels, seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    long = 0.2 + 0.8 * torch.rand(1, n, 1, generator=g)
    return gs.replace(scales=long * torch.tensor([1.0, 0.02, 0.02]))


def precision_report(n: int) -> None:
    """Max abs. differences from a float64 evaluation of the same float32 inputs."""
    occ3d = VoxelGrid.occ3d()
    exact = VoxelGrid((-40.0, -40.0, -1.0), (40.0, 40.0, 5.5), 0.5)  # 0.5 m: exact in float32
    print(f"torch {torch.__version__}; {n} Gaussians, C = 16, nbh = 5; max |diff|")
    print(f"  {'workload / result':<62} {'density':>9} {'features':>9}  (max |feature|)")
    for name, gs32, grid in (
        ("scales 0.05-1 m", occ3d_gaussians(n, 16), occ3d),
        ("needles 50:1", needle_gaussians(n, 16), occ3d),
        ("scales 0.05-1 m, 0.5 m voxels", occ3d_gaussians(n, 16), exact),
    ):
        gs64 = gs32.to(torch.float64)
        with torch.no_grad():
            ref_density, ref_features = official_cube(gs64, grid, 5)
            ell64 = voxelize(gs64, grid)
            results = {
                "official algorithm, float32": official_cube(gs32, grid, 5),
                "ours cube, float32": voxelize(gs32, grid, neighborhood="cube", nbh=5),
                "ours cube, float64": voxelize(gs64, grid, neighborhood="cube", nbh=5),
                "ours ellipsoid k=3, float32 (vs ours float64)": voxelize(gs32, grid),
            }
        official32 = results["official algorithm, float32"]
        for label, out in [*results.items(), ("ours cube, float32 (vs official float32)", None)]:
            if out is None:
                out, expected = results["ours cube, float32"], official32
            elif label.startswith("ours ellipsoid"):
                expected = (ell64.density[0], ell64.features[0])
            else:
                expected = (ref_density, ref_features)
            density, features = out if isinstance(out, tuple) else (out.density, out.features)
            expected = tuple(t.double() for t in expected)
            d = float((density.reshape(expected[0].shape).double() - expected[0]).abs().max())
            f = float((features.reshape(expected[1].shape).double() - expected[1]).abs().max())
            print(
                f"  {name + ': ' + label:<62} {d:9.1e} {f:9.1e}  "
                f"({float(expected[1].abs().max()):.2g})"
            )


def row(label: str, seconds: float, peak: float, note: str = "") -> None:
    print(f"  {label:<46} {seconds:9.3f} s  peak {peak:8.1f} MiB  {note}")


def timed_once(fn: Callable[[], Any], device: torch.device) -> tuple[float, float, Any]:
    """``(seconds, peak MiB, result)`` of one call of ``fn``: the peak-memory measurement's
    own call is timed, so a slow reference runs once."""
    record: dict[str, Any] = {}

    def run() -> None:
        start = time.perf_counter()
        record["result"] = fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        record["seconds"] = time.perf_counter() - start

    peak = peak_memory_mib(run, device)
    return record["seconds"], peak, record["result"]


def scale_cube_case(
    gs: GaussianSet, grid: VoxelGrid, device: torch.device, repeats: int, skip_dense: bool
) -> None:
    """Section 3: the scale cube (k = 3) vs the dense evaluation, forward and backward."""

    def ours() -> object:
        return voxelize(gs, grid, neighborhood="scale_cube", scale_multiplier=3)

    print("3. scale_cube, k=3 (GaussianFormer's per-Gaussian cube)")
    with torch.no_grad():
        t_ours = median_seconds(ours, device, repeats=repeats, warmup=1)
        row("dego voxelize(scale_cube, k=3), forward", t_ours, peak_memory_mib(ours, device))
        if not skip_dense:
            t_dense, peak, (density, _) = timed_once(lambda: dense(gs, grid), device)
            diff = float((ours().density[0].double() - density).abs().max())
            note = f"speed-up {t_dense / t_ours:.1f}x, max |density diff| {diff:.1e} (cube cut)"
            row("dense (every Gaussian x voxel, chunked GEMM)", t_dense, peak, note)
    run = backward_of(gs, grid, neighborhood="scale_cube", scale_multiplier=3)
    t = median_seconds(run, device, repeats=repeats, warmup=1)
    row("dego voxelize(scale_cube, k=3), forward+backward", t, peak_memory_mib(run, device))


def backward_of(gs: GaussianSet, grid: VoxelGrid, **kw: object) -> Callable[[], None]:
    """One forward + backward of voxelize on fresh leaves (a scalar loss of both outputs)."""

    def run() -> None:
        leaves = [
            t.detach().clone().requires_grad_()
            for t in (gs.means, gs.quats, gs.scales, gs.opacities, gs.features)
        ]
        out = voxelize(GaussianSet(*leaves), grid, **kw)
        (out.density.sum() + out.features.square().mean()).backward()

    return run


def main() -> None:
    parser = benchmark_parser(__doc__, repeats=3)
    parser.add_argument("--skip-dense", action="store_true")
    parser.add_argument("--precision", action="store_true", help="float32 accuracy, no timing")
    parser.add_argument("--n", type=int, default=10_000, help="Gaussians (default 10,000)")
    parser.add_argument("--only", choices=("all", "cube", "ellipsoid", "scale_cube"), default="all")
    args = parser.parse_args()
    if args.precision:
        precision_report(args.n)
        return
    device = torch.device(args.device)
    print(
        f"torch {torch.__version__}, threads {torch.get_num_threads()}, device {device}, "
        f"N = {args.n}"
    )
    grid = VoxelGrid.occ3d()
    gs = occ3d_gaussians(args.n, 16).to(device)
    if args.only in ("all", "cube"):
        cube_case(gs, grid, device, args.repeats)
    if args.only in ("all", "ellipsoid"):
        ellipsoid_case(gs, grid, device, args.repeats, args.skip_dense)
    if args.only in ("all", "scale_cube"):
        scale_cube_case(gs, grid, device, args.repeats, args.skip_dense)


def cube_case(gs: GaussianSet, grid: VoxelGrid, device: torch.device, repeats: int) -> None:
    """Section 1: the official cube vs the official algorithm."""

    def ours_cube() -> object:
        return voxelize(gs, grid, neighborhood="cube", nbh=5)

    print("1. cube, nbh=5 (11^3 voxels per Gaussian), forward")
    with torch.no_grad():
        t_ours = median_seconds(ours_cube, device, repeats=repeats, warmup=1)
        row("dego voxelize(cube, nbh=5)", t_ours, peak_memory_mib(ours_cube, device))
        if device.type == "cpu":
            t_official = median_seconds(
                lambda: official_cube(gs, grid, 5), device, repeats=1, warmup=0
            )
            mine, theirs = ours_cube(), official_cube(gs, grid, 5)
            diff = max(
                float((mine.density[0] - theirs[0]).abs().max()),
                float((mine.features[0] - theirs[1]).abs().max()),
            )
            row(
                "official algorithm (repeated 3x3, unique, scatter_add)",
                t_official,
                peak_memory_mib(lambda: official_cube(gs, grid, 5), device),
                f"speed-up {t_official / t_ours:.1f}x, max |diff| {diff:.1e}",
            )
    run = backward_of(gs, grid, neighborhood="cube", nbh=5)
    t = median_seconds(run, device, repeats=repeats, warmup=1)
    row("dego voxelize(cube, nbh=5), forward+backward", t, peak_memory_mib(run, device))


def ellipsoid_case(
    gs: GaussianSet, grid: VoxelGrid, device: torch.device, repeats: int, skip_dense: bool
) -> None:
    """Section 2: the exact 3-sigma ellipsoid boxes vs the dense evaluation."""

    def ours_ellipsoid() -> object:
        return voxelize(gs, grid)

    print("2. ellipsoid, k=3")
    with torch.no_grad():
        t_ell = median_seconds(ours_ellipsoid, device, repeats=repeats, warmup=1)
        row("dego voxelize(ellipsoid), forward", t_ell, peak_memory_mib(ours_ellipsoid, device))
    run = backward_of(gs, grid)
    t = median_seconds(run, device, repeats=repeats, warmup=1)
    row("dego voxelize(ellipsoid), forward+backward", t, peak_memory_mib(run, device))
    if not skip_dense and device.type == "cpu":
        with torch.no_grad():
            start = time.perf_counter()
            dense_density, _ = dense(gs, grid)  # one run: it takes minutes
            t_dense = time.perf_counter() - start
            diff = float((ours_ellipsoid().density[0].double() - dense_density).abs().max())
            note = f"speed-up {t_dense / t_ell:.1f}x, max |density diff| {diff:.1e} (3-sigma cut)"
            row("dense (every Gaussian x voxel, chunked GEMM)", t_dense, float("nan"), note)


if __name__ == "__main__":
    main()
