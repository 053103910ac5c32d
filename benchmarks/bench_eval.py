"""`dego eval` throughput: samples per second and peak memory, before vs now, in one run.

Workload: a synthetic Occ3D-nuScenes release (``dego.evaluation.write_benchmark_tree``:
street scenes of 40 keyframes, 200 x 200 x 16 ground truth in the release layout,
SparseOcc-style ``pred``
predictions, an mmdet3d infos file), scored the way ``dego eval --infos`` scores the
real one: read and validate both files, mIoU under the ``occ3d`` and ``weak`` protocols,
RayIoU from up to 8 origins per sample (SparseOcc's EgoPoseDataset) x 14,040 rays
through prediction and ground truth.

Rows (each in its own process, so peak memory is that run's high-water mark; every row
is warmed up on one sample first, which also fills numba's cache):

- ``before``: the scoring loop as it was (torch traversal, prediction and ground truth
  cast separately), on the first ``--before-samples`` samples;
- ``torch``: the torch traversal with one traversal for both grids (what CUDA and CPUs
  without numba run), same samples;
- ``kernel``: the compiled CPU kernel (numba), 1 process;
- ``kernel --workers N``: the same over N processes (torch.distributed, gloo).

The kernel rows run over the first ``--before-samples`` samples and over all of them:
the difference gives the time per sample once the processes are up, the rest is their
start-up (spawning, imports, loading the kernel and the infos), and the projection to
the 6,019 validation samples adds both. Every row's counts over the same samples must be
identical (checked).

    python benchmarks/bench_eval.py [--scenes 6] [--frames 40] [--before-samples 16]
                                    [--workers 2] [--data DIR]

``--benchmarks``: every benchmark of ``dego eval --benchmark`` side by side instead, each
in its own process on a fixture tree of ``--frames`` keyframes in its own layout (one
scene): seconds per sample (after a warm-up run over the same tree), peak RSS, and the
ratio to Occ3D-nuScenes scored the same way (voxel metrics alone, and with RayIoU where
the benchmark has rays).

    python benchmarks/bench_eval.py --benchmarks [--frames 8]
"""

from __future__ import annotations

import argparse
import json
import pickle
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

VALIDATION_SAMPLES = 6019  # Occ3D-nuScenes val


def _row(args: argparse.Namespace) -> None:
    """One measured row (runs in a child process); prints a JSON line."""
    import torch

    import dego
    from dego import raycast
    from dego.metrics import rayiou

    raycast.CPU_KERNEL = "torch" if args.row in ("before", "torch") else "numba"
    if args.row == "before":  # one cast per grid, as before the shared traversal
        shared = rayiou.cast_product

        def separately(labels, *rest, **kwargs):
            parts = [shared([grid], *rest, **kwargs) for grid in labels]
            return tuple(torch.cat([p[i] for p in parts]) for i in range(2))

        rayiou.cast_product = separately
    root = Path(args.data)
    infos = root / f"infos_{args.limit}.pkl" if args.limit else root / "nuscenes_infos_val.pkl"
    kwargs = {"gt": root / "gt", "pred": root / "pred", "workers": args.workers}
    dego.evaluate(**kwargs, infos=root / "infos_1.pkl")  # warm-up (and numba's cache)
    start = time.perf_counter()
    report = dego.evaluate(**kwargs, infos=infos)
    seconds = time.perf_counter() - start
    peak_kib = max(
        resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
        resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss,
    )
    counts = {
        f"{metric}.{name}": np.asarray(value).tolist()
        for metric, parts in report.counts.items()
        for name, value in parts.items()
    }
    print(
        json.dumps(
            {
                "samples": report.samples_scored,
                "seconds": seconds,
                "peak_mib": peak_kib / 1024,
                "rayiou": report.rayiou.rayiou if report.rayiou else None,
                "rays_cast": report.rays_cast,
                "counts": counts,
            }
        )
    )


def _benchmark_row(args: argparse.Namespace) -> None:
    """One benchmark row (a child process): warm-up, then the timed run; a JSON line."""
    import dego
    from dego.evaluation.trees import write_benchmark_tree

    name, rays = args.row.split(":")[1:]
    tree = write_benchmark_tree(name, Path(args.data) / name, frames=args.frames)
    kwargs = {"benchmark": name, "rayiou": rays == "rays", "infos": tree.infos}
    dego.evaluate(tree.gt, tree.pred, **kwargs)  # warm-up: imports, numba's cache
    start = time.perf_counter()
    report = dego.evaluate(tree.gt, tree.pred, **kwargs)
    seconds = time.perf_counter() - start
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(
        json.dumps(
            {"samples": report.samples_scored, "seconds": seconds, "peak_mib": peak_kib / 1024}
        )
    )


def benchmark_rows(args: argparse.Namespace) -> None:
    """``--benchmarks``: every benchmark side by side (see the module docstring)."""
    import torch

    from dego.evaluation.benchmarks import BENCHMARKS

    script = Path(__file__).resolve()
    rows = [(name, "voxels") for name, b in BENCHMARKS.items() if b.voxel]
    rows += [(name, "rays") for name, b in BENCHMARKS.items() if b.ray is not None]
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, CPU, {args.frames} samples"
    )
    results = {}
    with tempfile.TemporaryDirectory(prefix="dego-bench-benchmarks-") as scratch:
        for name, what in rows:
            command = [sys.executable, str(script), "--row", f"benchmark:{name}:{what}"]
            command += ["--data", scratch, "--frames", str(args.frames)]
            done = subprocess.run(command, capture_output=True, text=True, check=False)
            if done.returncode != 0:
                raise SystemExit(f"{name} failed:\n{done.stderr}")
            results[name, what] = json.loads(done.stdout.strip().splitlines()[-1])
    print("\n| benchmark | scored | grid | s / sample | peak RSS | vs occ3d-nuscenes |")
    print("|---|---|---|---|---|---|")
    for (name, what), r in results.items():
        per = r["seconds"] / r["samples"]
        base = results[("occ3d-nuscenes", what)]
        ratio = per / (base["seconds"] / base["samples"])
        shape = " x ".join(map(str, BENCHMARKS[name].shape))
        scored = "voxel metrics" if what == "voxels" else "RayIoU (+ mAVE) and voxel metrics"
        print(
            f"| {name} | {scored} | {shape} | {per:.3f} | {r['peak_mib']:.0f} MiB | {ratio:.2f}x |"
        )


def _subset_infos(root: Path, count: int) -> None:
    with (root / "nuscenes_infos_val.pkl").open("rb") as file:
        infos = pickle.load(file)  # our own file
    subset = {"infos": infos["infos"][:count], "metadata": infos["metadata"]}
    with (root / f"infos_{count}.pkl").open("wb") as file:
        pickle.dump(subset, file, protocol=4)


def _run_row(script: Path, data: Path, row: str, limit: int, workers: int) -> dict:
    command = [sys.executable, str(script), "--row", row, "--data", str(data)]
    command += ["--limit", str(limit), "--workers", str(workers)]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"row {row} failed:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=6)
    parser.add_argument("--frames", type=int, default=40, help="keyframes per scene")
    parser.add_argument("--before-samples", type=int, default=16)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--data", type=Path, help="build (or reuse) the data set here")
    parser.add_argument("--row", help=argparse.SUPPRESS)
    parser.add_argument("--limit", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--benchmarks", action="store_true", help="every benchmark side by side")
    args = parser.parse_args()
    if args.row and args.row.startswith("benchmark:"):
        _benchmark_row(args)
        return
    if args.row:
        _row(args)
        return
    if args.benchmarks:
        benchmark_rows(args)
        return

    import torch

    from dego.evaluation.trees import write_benchmark_tree

    with tempfile.TemporaryDirectory(prefix="dego-bench-eval-") as scratch:
        data = args.data or Path(scratch)
        total = args.scenes * args.frames
        if not (data / "nuscenes_infos_val.pkl").is_file():
            start = time.perf_counter()
            write_benchmark_tree("occ3d-nuscenes", data, scenes=args.scenes, frames=args.frames)
            print(f"wrote {total} samples in {time.perf_counter() - start:.0f} s to {data}")
        for count in (1, args.before_samples):
            _subset_infos(data, count)
        script = Path(__file__).resolve()
        print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, CPU")
        rows = {
            "before (torch, pred and gt cast separately)": ("before", args.before_samples, 1),
            "torch, one traversal for pred and gt": ("torch", args.before_samples, 1),
            "kernel": ("kernel", args.before_samples, 1),
            f"kernel, --workers {args.workers}": ("kernel", args.before_samples, args.workers),
        }
        subset = {name: _run_row(script, data, *spec) for name, spec in rows.items()}
        # the kernel rows also over every sample: the difference is the time per sample
        # once the processes are up, the rest their start-up
        full = {
            name: _run_row(script, data, spec[0], 0, spec[2])
            for name, spec in rows.items()
            if spec[0] == "kernel"
        }
        same = all(r["counts"] == next(iter(subset.values()))["counts"] for r in subset.values())
        same &= all(r["counts"] == next(iter(full.values()))["counts"] for r in full.values())
        n = args.before_samples
        print(
            f"\n| run | s / sample | samples / s | start-up | {VALIDATION_SAMPLES} samples "
            "| peak RSS | vs before |\n|---|---|---|---|---|---|---|"
        )
        base = None
        for name, r in subset.items():
            if name in full:
                extra = full[name]["samples"] - n
                per = (full[name]["seconds"] - r["seconds"]) / extra
                startup = max(r["seconds"] - n * per, 0.0)
                peak = max(r["peak_mib"], full[name]["peak_mib"])
            else:
                per, startup, peak = r["seconds"] / n, 0.0, r["peak_mib"]
            base = base or per
            total = (startup + per * VALIDATION_SAMPLES) / 60
            print(
                f"| {name} | {per:.3f} | {1 / per:.1f} | {startup:.1f} s | {total:.1f} min | "
                f"{peak:.0f} MiB | {base / per:.1f}x |"
            )
        last = next(iter(full.values()))
        print(
            f"\nbefore / torch rows: the first {n} samples; kernel rows: s / sample from the "
            f"runs over {n} and {last['samples']} samples (start-up: the rest). Identical "
            f"counts in every row: {same}; RayIoU over all {last['samples']} samples "
            f"{last['rayiou']:.4f}, {last['rays_cast']:,} rays cast per grid"
        )


if __name__ == "__main__":
    main()
