"""Threads under contention: one splat of 2,000 Gaussians into 6 cameras at torch's
default thread count vs one thread, on an idle machine and beside ``--load`` busy
processes (what a shared machine or data-loader workers do to it).

Each row times the same call alternately at both settings (medians over ``--repeats``
rounds) in this process; the load is ``--load`` Python processes spinning on the CPU,
started before the loaded rows and stopped after them.

    python benchmarks/bench_threads.py [--load 4] [--repeats 15]
"""

from __future__ import annotations

import multiprocessing
import os
import statistics
import time

import torch

from dego import splat

from harness import benchmark_parser
from scenes import occ3d_gaussians, surround_rig


def _spin() -> None:
    while True:
        pass


def timed_rounds(call, threads: dict[str, int], repeats: int) -> dict[str, list[float]]:  # type: ignore[no-untyped-def]
    times: dict[str, list[float]] = {name: [] for name in threads}
    for _ in range(repeats):
        for name, count in threads.items():
            torch.set_num_threads(count)
            start = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - start)
    return times


def main() -> None:
    parser = benchmark_parser(__doc__, repeats=15)
    parser.add_argument("--load", type=int, default=4, help="busy processes for the loaded rows")
    args = parser.parse_args()
    default = torch.get_num_threads()
    gaussians = occ3d_gaussians(2000, 8)
    w2c, k = surround_rig(90, 160)

    def call() -> None:
        splat(gaussians, w2c, k, (90, 160))

    settings = {f"default ({default} threads)": default, "--threads 1": 1}
    call()  # warm-up
    print(
        f"splat, 2,000 Gaussians, 6 cameras of 90 x 160 [torch {torch.__version__}, "
        f"{os.cpu_count()} CPUs, median (min-max) seconds over {args.repeats} rounds]"
    )
    idle = timed_rounds(call, settings, args.repeats)
    spinners = [multiprocessing.Process(target=_spin, daemon=True) for _ in range(args.load)]
    for process in spinners:
        process.start()
    try:
        time.sleep(0.5)
        loaded = timed_rounds(call, settings, args.repeats)
    finally:
        for process in spinners:
            process.terminate()
    for label, rows in (("idle", idle), (f"beside {args.load} busy processes", loaded)):
        cells = [
            f"{name}: {statistics.median(v):.3f} ({min(v):.3f}-{max(v):.3f})"
            for name, v in rows.items()
        ]
        print(f"{label:<28}" + "; ".join(cells))
    torch.set_num_threads(default)


if __name__ == "__main__":
    main()
