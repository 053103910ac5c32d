"""RayIoU per sample: the vectorised caster vs a scalar per-ray traversal.

Workload (the issue's): one Occ3D-sized sample (200 x 200 x 16) with a street-like label
layout (road and sidewalks, terrain, building walls, trees, parked cars, pedestrians,
barriers), a prediction that differs from it (shifted objects, missing and spurious
voxels), 8 origins x 14,040 rays, cast through pred and gt and scored. The scalar
reference (``tests/reference/ray.py``, one Python loop per ray, the rules written out
plainly) is timed on a subset of rays and extrapolated to the full sample.

On a CPU it times RayIoU with both traversals, the compiled kernel (numba, when
installed) and the torch loop. It also times ``cast_rays`` of the gt grid in its two
precision modes, SparseOcc mode
(float32 directions: float32 voxel coordinates, float64 traversal, float32 distances;
what RayIoU uses) and float64 mode (float64 origins and directions: no float32 rounding,
float64 distances), and prints how far their hits differ.

    python benchmarks/bench_rayiou.py [--device cuda] [--repeats 3] [--subset 1500]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import torch

from dego import RayIoU, VoxelGrid, cast_rays, generate_lidar_rays, raycast

from harness import benchmark_parser, median_seconds, peak_memory_mib

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.reference.ray import cast_one


def street_scene(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``(gt, pred)`` label grids of a street along x with buildings, trees and objects."""
    g = torch.Generator().manual_seed(seed)
    gt = torch.full((200, 200, 16), 17, dtype=torch.long)
    gt[:, :, 0] = 14  # terrain everywhere at the bottom
    gt[:, 80:120, 0:2] = 11  # road, y in [-8, 8) m
    gt[:, 70:80, 0:2] = 13  # sidewalks
    gt[:, 120:130, 0:2] = 13
    gt[:, 60:65, 0:14] = 15  # building walls along the street
    gt[:, 135:140, 0:12] = 15
    for x in range(10, 190, 25):  # trees: trunk and crown
        gt[x : x + 2, 67:69, 2:6] = 16
        gt[x - 3 : x + 5, 64:72, 6:11] = 16
    for _ in range(25):  # cars, pedestrians, barriers
        label, size = [(4, (11, 5, 4)), (7, (2, 2, 5)), (1, (1, 6, 3))][
            int(torch.randint(0, 3, (1,), generator=g))
        ]
        x0 = int(torch.randint(5, 190, (1,), generator=g))
        y0 = int(torch.randint(82, 115, (1,), generator=g))
        gt[x0 : x0 + size[0], y0 : y0 + size[1], 2 : 2 + size[2]] = label
    pred = gt.clone()
    cars = (gt == 4).nonzero()
    pred[cars[:, 0], cars[:, 1], cars[:, 2]] = 17
    moved = cars + torch.tensor([2, 0, 0])  # cars predicted 0.8 m further along x
    moved = moved[moved[:, 0] < 200]
    pred[moved[:, 0], moved[:, 1], moved[:, 2]] = 4
    noise = torch.rand(gt.shape, generator=g) < 0.01  # spurious and missing voxels
    pred[noise & (gt == 17)] = 15
    pred[noise & (gt == 16)] = 17
    return gt, pred


def main() -> None:
    parser = benchmark_parser(__doc__, repeats=3)
    parser.add_argument("--subset", type=int, default=1500, help="rays timed in the scalar loop")
    args = parser.parse_args()
    device = torch.device(args.device)
    grid = VoxelGrid.occ3d()
    gt, pred = street_scene()
    origins = torch.tensor([[0.9858, 0.0, 1.8402]]) + torch.tensor(
        [[-6.0 + 1.8 * i, 0.3 * (i % 2), 0.0] for i in range(8)]
    )
    rays = generate_lidar_rays()
    gt, pred, origins = gt.to(device), pred.to(device), origins.to(device)

    def sample() -> object:
        metric = RayIoU(device=device)
        metric.update(pred, gt, origins)
        return metric.compute()

    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, device {device}")
    total_rays = 2 * origins.shape[0] * rays.shape[0]
    # on CPU: the compiled kernel (when numba is installed) and the torch traversal
    kernels = [raycast.cpu_kernel()] if device.type == "cpu" else ["torch (CUDA)"]
    if device.type == "cpu" and kernels[0] == "numba":
        kernels.append("torch")
    for kernel in kernels:
        if device.type == "cpu":
            raycast.CPU_KERNEL = kernel
        seconds = median_seconds(sample, device, repeats=args.repeats)
        peak = peak_memory_mib(sample, device)
        report = sample()
        print(
            f"RayIoU of one sample (8 origins x {rays.shape[0]} rays, pred + gt = {total_rays} "
            f"casts), traversal {kernel}: {seconds:.3f} s, peak {peak:.1f} MiB; RayIoU "
            f"{report.rayiou:.4f} (@1 {report.at[0]:.4f}, @2 {report.at[1]:.4f}, "
            f"@4 {report.at[2]:.4f})"
        )
        if kernel == kernels[0]:
            fastest = seconds
    if device.type == "cpu":
        raycast.CPU_KERNEL = kernels[0]
    seconds = fastest
    origins64 = origins.double()
    rays = rays.to(device)
    modes = {
        "SparseOcc": lambda: cast_rays(gt, origins64, rays, grid),
        "float64": lambda: cast_rays(gt, origins64, rays.double(), grid),
    }
    timing = {name: median_seconds(fn, device, repeats=args.repeats) for name, fn in modes.items()}
    (d32, l32), (d64, l64) = (fn() for fn in modes.values())
    agree = l32 == l64
    error = (d32.double() - d64).abs()[agree]
    relative = error / d64[agree].abs().clamp_min(1e-9)
    print(
        f"cast_rays of gt ({l32.numel()} rays): SparseOcc mode {timing['SparseOcc']:.3f} s, "
        f"float64 mode {timing['float64']:.3f} s "
        f"({timing['float64'] / timing['SparseOcc']:.2f}x); labels differ on "
        f"{int((~agree).sum())} rays, distances by at most {float(error.max()):.2g} m "
        f"({float(relative.max()):.2g} relative; 99.9% within "
        f"{float(error.quantile(0.999)):.2g} m)"
    )
    rays = rays.cpu()
    subset = torch.randperm(rays.shape[0], generator=torch.Generator().manual_seed(0))
    subset = rays[subset[: args.subset]]
    gt_cpu, origin = gt.cpu(), origins[:1].cpu()
    labels, o = gt_cpu.numpy(), origin[0].tolist()
    start = time.perf_counter()
    expected = [
        cast_one(labels, o, direction.tolist(), grid.lower, grid.voxel_size[0])
        for direction in subset
    ]
    scalar = (time.perf_counter() - start) / subset.shape[0] * total_rays
    distance, label = cast_rays(gt_cpu, origin, subset, grid)
    same = all(
        (float(d), int(c)) == (float(e[0]), int(e[1]))
        for d, c, e in zip(distance, label, expected, strict=True)
    )
    print(
        f"scalar per-ray traversal, extrapolated from {subset.shape[0]} rays: {scalar:.1f} s "
        f"-> RayIoU.update ({kernels[0]}) is {scalar / seconds:.0f}x faster; identical hits on "
        f"the subset: {same}"
    )


if __name__ == "__main__":
    main()
