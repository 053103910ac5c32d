"""Synthetic scene generation: time and peak memory of one frame of the default clip.

One frame = the Occ3D-sized ground-truth grid (200 x 200 x 16) rasterised from the
scene's solids, six 64 x 176 camera images with depth and semantics ray-cast from them,
and the camera and LiDAR visibility masks (the issue's goal: under 2 s on 2 CPU cores).

    python benchmarks/bench_synthetic.py [--repeats 5] [--seed 0]
"""

from __future__ import annotations

import torch

from dego.data.synthetic import SyntheticScene

from harness import benchmark_parser, median_seconds, peak_memory_mib


def main() -> None:
    parser = benchmark_parser(__doc__, repeats=5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    device = torch.device("cpu")  # the generator runs on the CPU
    scene = SyntheticScene(args.seed)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}")
    for offset in (0, scene.offsets[-1]):
        seconds = median_seconds(lambda o=offset: scene.frame(o), device, repeats=args.repeats)
        peak = peak_memory_mib(lambda o=offset: scene.frame(o), device)
        print(
            f"frame({offset:+d}): {seconds:.3f} s (median of {args.repeats}), peak {peak:.1f} MiB"
        )
    frame = scene.frame(0)
    occupied = int((frame.occupancy != 17).sum())
    print(
        f"{occupied} occupied voxels, camera mask {int(frame.mask_camera.sum())}, "
        f"LiDAR mask {int(frame.mask_lidar.sum())}, {len(scene.primitives(0.0))} solids"
    )


if __name__ == "__main__":
    main()
