"""Factorized spatio-temporal teacher: forward cost, and factorized vs joint attention.

Workload (the issue's): B = 1, T = 8, V = 6 images of 252 x 700 with patch 14 (18 x 50
patches, P = 905 tokens per image with the 5 special tokens), a small width. Rows:

1. The teacher's forward (all blocks), time and peak memory.
2. One factorized block pair (cross-camera attention over V P tokens per time step, then
   cross-frame attention over T P tokens per camera) vs the same two attention blocks run
   jointly over all T V P = 43,440 tokens (the VGGT "global" layout), same width and
   weights: the ratio is what factorizing saves.

    python benchmarks/bench_teacher.py [--device cuda] [--repeats 3] [--width 64]
"""

from __future__ import annotations

import torch

from dego.teacher import FactorizedSpatioTemporalTeacher

from harness import benchmark_parser, compare, median_seconds, peak_memory_mib, print_comparison


def main() -> None:
    parser = benchmark_parser(__doc__, repeats=3)
    parser.add_argument("--width", type=int, default=64, help="embed_dim")
    parser.add_argument("--heads", type=int, default=4)
    parser.add_argument("--depth", type=int, default=2)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--cameras", type=int, default=6)
    parser.add_argument("--size", type=int, nargs=2, default=(252, 700), metavar=("H", "W"))
    args = parser.parse_args()
    device = torch.device(args.device)
    b, t, v = 1, args.frames, args.cameras
    teacher = FactorizedSpatioTemporalTeacher(args.width, args.depth, args.heads, patch_size=14).to(
        device
    )
    images = torch.rand(b, t, v, 3, *args.size, generator=torch.Generator().manual_seed(0))
    images = images.to(device)
    with torch.no_grad():
        z = teacher.tokens(images)
    p, c = z.shape[-2:]
    grid = (args.size[0] // 14, args.size[1] // 14)
    positions = teacher._positions(*grid, device=device)
    spatial, temporal = teacher.spatial_blocks[0], teacher.temporal_blocks[0]

    def factorized() -> torch.Tensor:
        x = spatial(z.reshape(b * t, v * p, c), positions.repeat(v, 1)).view(b, t, v, p, c)
        x = x.transpose(1, 2).reshape(b * v, t * p, c)
        return temporal(x, positions.repeat(t, 1))

    def joint() -> torch.Tensor:
        x = spatial(z.reshape(b, t * v * p, c), positions.repeat(t * v, 1))
        return temporal(x, positions.repeat(t * v, 1))

    def forward() -> object:
        return teacher(images)

    tokens = t * v * p
    print(
        f"teacher width {c}, {args.heads} heads, depth {args.depth}; {b} x {t} frames x {v} "
        f"cameras of {args.size[0]} x {args.size[1]}, patch grid {grid[0]} x {grid[1]}, "
        f"P = {p}, {tokens} tokens"
    )
    with torch.no_grad():
        results = compare(
            {"one block: factorized vs joint": (factorized, joint)},
            device,
            repeats=args.repeats,
        )
        print_comparison(
            f"[torch {torch.__version__}, threads {torch.get_num_threads()}, device {device}]",
            results,
            {"one block: factorized vs joint": f"joint attends over all {tokens} tokens"},
        )
        seconds = median_seconds(forward, device, repeats=args.repeats)
        peak = peak_memory_mib(forward, device)
    print(f"teacher forward ({args.depth} block pairs): {seconds:.3f} s, peak {peak:.1f} MiB")


if __name__ == "__main__":
    main()
