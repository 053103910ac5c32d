"""What a rerun recording costs: logging one grid / Gaussian set / camera rig, and what
`--rerun` adds to `dego eval` and `dego demo`, measured side by side in one run.

1. Logging (in this process, into a recording streamed to a file): one Occ3D
   200 x 200 x 16 street frame (``dego.evaluation.trees``) in each grid style, whole and inside its
   camera mask; Gaussian sets of 10,000 and 100,000; the six cameras of a synthetic frame
   with their images and pseudo labels. Median milliseconds, bytes written per call, peak
   memory.
2. ``dego eval --no-rayiou`` on a synthetic release of ``--samples`` samples, without and
   with ``--rerun FILE --limit N`` (N = all samples), alternating, each run a new process:
   the wall time added and the file's size.
3. With ``--demo``: ``dego demo --quick`` without and with ``--rerun`` (one of each,
   alternating over ``--demo-repeats``): the ratio of wall times and the file's size.

    python benchmarks/bench_rerun.py [--samples 20] [--eval-repeats 3] [--demo]
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from dego import GaussianSet, VoxelGrid
from dego.data import SyntheticScene
from dego.evaluation.trees import street, write_benchmark_tree
from dego.viz import rerun as rerun_log

from harness import benchmark_parser, median_seconds, peak_memory_mib


def logging_rows(folder: Path, repeats: int) -> None:
    generator = torch.Generator().manual_seed(0)
    labels = street(200, generator)
    mask = torch.rand(labels.shape, generator=generator) < 0.7
    mask[:, :, 8:] = False  # the upper half unseen, as cameras see less of it
    grid = VoxelGrid.occ3d()
    frame = SyntheticScene(0, num_frames=1).frames()[0]
    path = folder / "logging.rrd"
    device = torch.device("cpu")
    print(
        f"1. logging into one recording [torch {torch.__version__}, threads "
        f"{torch.get_num_threads()}, rerun-sdk {rerun_log.require_rerun().__version__}]"
    )
    print(f"{'case':<44}{'ms':>9}{'MiB peak':>10}{'items':>10}")
    with rerun_log.recording_file(path) as rec:
        cases = {}
        for style in ("voxels", "boxes", "points"):
            for masked in (False, True):
                name = f"grid 200x200x16, {style}{', camera mask' if masked else ''}"
                cases[name] = lambda style=style, masked=masked: rerun_log.log_occupancy(
                    "world/occ",
                    labels,
                    grid,
                    mask=mask if masked else None,
                    style=style,
                    recording=rec,
                )
        for n in (10_000, 100_000):
            g = torch.Generator().manual_seed(n)
            gaussians = GaussianSet(
                torch.randn(n, 3, generator=g) * 20,
                torch.randn(n, 4, generator=g),
                torch.rand(n, 3, generator=g) * 0.3 + 0.05,
                torch.rand(n, generator=g),
                torch.randn(n, 17, generator=g),
            )
            cases[f"{n:,} Gaussians, ellipsoids"] = lambda gaussians=gaussians: (
                rerun_log.log_gaussians("world/gaussians", gaussians, recording=rec)
            )
        cases["6 cameras with images and pseudo labels"] = lambda: len(
            rerun_log.log_cameras(
                "world/cameras",
                frame.world_to_cam,
                frame.intrinsics,
                tuple(frame.images.shape[-2:]),
                images=frame.images,
                semantics=frame.semantics,
                recording=rec,
            )
        )
        for name, fn in cases.items():
            items = fn()
            seconds = median_seconds(fn, device, repeats=repeats, warmup=1)
            peak = peak_memory_mib(fn, device)
            print(f"{name:<44}{seconds * 1e3:>9.1f}{peak:>10.1f}{items:>10,}")
    size = path.stat().st_size
    print(f"file: {size / 1e6:.1f} MB for all the calls above\n")


def timed(argv: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "dego", *argv], check=True, capture_output=True)
    return time.perf_counter() - start


def command_rows(
    title: str, plain: list[str], recorded: list[str], rrd: Path, repeats: int
) -> None:
    times: dict[str, list[float]] = {"without --rerun": [], "with --rerun": []}
    for _ in range(repeats):
        times["without --rerun"].append(timed(plain))
        times["with --rerun"].append(timed(recorded))
    base, with_rerun = (statistics.median(v) for v in times.values())
    print(title)
    for name, values in times.items():
        print(
            f"  {name:<18} median {statistics.median(values):6.1f} s  "
            f"(runs {', '.join(f'{v:.1f}' for v in values)})"
        )
    print(
        f"  added {with_rerun - base:+.1f} s ({with_rerun / base - 1:+.1%}); "
        f"file {rrd.stat().st_size / 1e6:.1f} MB\n"
    )


def main() -> None:
    parser = benchmark_parser(__doc__, repeats=5)
    parser.add_argument("--samples", type=int, default=20, help="samples of dego eval")
    parser.add_argument("--eval-repeats", type=int, default=3, help="runs of each eval row")
    parser.add_argument("--demo", action="store_true", help="also time dego demo --quick")
    parser.add_argument("--demo-repeats", type=int, default=1, help="runs of each demo row")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        logging_rows(folder, args.repeats)
        tree = write_benchmark_tree("occ3d-nuscenes", folder / "release", frames=args.samples)
        gt, pred = tree.gt, tree.pred
        rrd = folder / "eval.rrd"
        plain = ["eval", "--gt", str(gt), "--pred", str(pred), "--no-rayiou", "--quiet"]
        command_rows(
            f"2. dego eval --no-rayiou, {args.samples} samples",
            plain,
            [*plain, "--rerun", str(rrd), "--limit", str(args.samples)],
            rrd,
            args.eval_repeats,
        )
        if args.demo:
            demo_rrd = folder / "demo.rrd"
            plain = ["demo", "--quick", "--no-pictures", "--out", str(folder / "demo")]
            command_rows(
                "3. dego demo --quick --no-pictures",
                plain,
                [*plain, "--rerun", str(demo_rrd)],
                demo_rrd,
                args.demo_repeats,
            )


if __name__ == "__main__":
    main()
