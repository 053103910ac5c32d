"""Threads under contention: ``--threads 1`` vs torch's default vs ``--threads auto``, on
an idle machine and beside ``--load`` busy processes (what a shared machine or data-loader
workers do to it).

Workloads (``--workload``):

- ``eval``: a whole ``dego eval`` run with RayIoU, in a fresh process, on a
  small synthetic occ3d-nuscenes tree (``dego data write-tree --frames 4``): the wall
  time a user waits, start-up included.
- ``splat`` (default): one splat of 2,000 Gaussians into 6 cameras of 90 x 160, in this
  process.

The machines: as found (nothing started: idle, or whatever other jobs run), then for each
count in ``--load`` that many Python processes spinning on the CPU, started ``--settle``
seconds before the rows and stopped after them (the 1-minute load average, which
``--threads auto`` reads, follows them over about a minute: ``--settle 60`` for auto to see
them fully; docs/performance.md used 40). Each round runs every setting once, in a
rotating order; the table gives the 1-minute load average read before each run (min-max),
the threads the run had (``auto``: what it chose) and the median (min-max) seconds over
``--repeats`` rounds.
OMP_NUM_THREADS is removed first, so torch's default is its own (one thread per core).

    python benchmarks/bench_threads.py [--workload splat|eval] [--load 1,3] [--repeats 5]
        [--settle 15]
"""

from __future__ import annotations

import os

os.environ.pop("OMP_NUM_THREADS", None)  # before torch: its default, not the caller's

import multiprocessing
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch

from dego import splat
from dego._cli_args import auto_threads, machine_load, usable_cores

from harness import benchmark_parser
from scenes import occ3d_gaussians, surround_rig

AUTO = "auto"


def _spin() -> None:
    while True:
        pass


def load_list(text: str) -> list[int]:
    """``"1,3"`` -> ``[1, 3]``: busy-process counts of the loaded machines."""
    return [int(part) for part in text.split(",") if part.strip()]


def eval_runner(tree: Path) -> Callable[[str], str]:
    """One ``dego eval`` process at ``--threads setting``; returns the threads it had."""
    command = [sys.executable, "-m", "dego", "eval", "--gt", str(tree / "gt")]
    command += ["--pred", str(tree / "pred"), "--infos", str(tree / "nuscenes_infos_val.pkl")]

    def run(setting: str) -> str:
        result = subprocess.run(
            [*command, "--threads", setting], capture_output=True, text=True, check=False
        )
        if result.returncode != 0:
            raise SystemExit(f"dego eval --threads {setting} failed:\n{result.stderr}")
        if setting != AUTO:
            return setting
        return "1" if "dego: threads: 1 (auto" in result.stderr else str(torch.get_num_threads())

    return run


def splat_runner() -> Callable[[str], str]:
    """One splat in this process at ``setting`` threads (``auto``: what it would choose)."""
    default = torch.get_num_threads()
    gaussians = occ3d_gaussians(2000, 8)
    w2c, k = surround_rig(90, 160)
    splat(gaussians, w2c, k, (90, 160))  # warm-up

    def run(setting: str) -> str:
        if setting == AUTO:
            count = auto_threads(machine_load(), usable_cores()) or default
        else:
            count = int(setting)
        torch.set_num_threads(count)
        splat(gaussians, w2c, k, (90, 160))
        torch.set_num_threads(default)
        return str(count)

    return run


def rounds(run: Callable[[str], str], settings: list[str], repeats: int) -> list[list[str]]:
    """Every setting once a round, rotating the order; one table row per setting."""
    seen: dict[str, list[tuple[float | None, str, float]]] = {s: [] for s in settings}
    for index in range(repeats):
        for setting in settings[index % len(settings) :] + settings[: index % len(settings)]:
            load = machine_load()
            start = time.perf_counter()
            threads = run(setting)
            seen[setting].append((load, threads, time.perf_counter() - start))
    rows = []
    for setting, runs in seen.items():
        loads = [load for load, _, _ in runs if load is not None]
        times = [seconds for _, _, seconds in runs]
        digits = 3 if max(times) < 1 else 2
        chosen = "/".join(sorted({threads for _, threads, _ in runs}))
        label = f"--threads {setting}" + (f" (chose {chosen})" if setting == AUTO else "")
        rows.append(
            [
                label,
                f"{min(loads):.2f}-{max(loads):.2f}" if loads else "unknown",
                f"{statistics.median(times):.{digits}f} ({min(times):.{digits}f}-"
                f"{max(times):.{digits}f})",
            ]
        )
    return rows


def main() -> None:
    parser = benchmark_parser(__doc__, repeats=5)
    parser.add_argument("--workload", choices=("splat", "eval"), default="splat")
    parser.add_argument(
        "--load", type=load_list, default=[1, 3], help="busy processes, e.g. 1,3 (1,3)"
    )
    parser.add_argument(
        "--settle", type=float, default=15.0, help="seconds between starting them and timing (15)"
    )
    args = parser.parse_args()
    default = torch.get_num_threads()
    settings = ["1", str(default), AUTO] if default > 1 else ["1", AUTO]
    with tempfile.TemporaryDirectory() as folder:
        if args.workload == "eval":
            tree = Path(folder) / "tree"
            subprocess.run(
                [sys.executable, "-m", "dego", "data", "write-tree", "--frames", "4", str(tree)],
                check=True,
                capture_output=True,
            )
            run = eval_runner(tree)
            title = "dego eval (RayIoU), 4 occ3d-nuscenes samples, a fresh process each"
        else:
            run = splat_runner()
            title = "splat, 2,000 Gaussians, 6 cameras of 90 x 160, in this process"
        print(
            f"{title} [torch {torch.__version__}, {usable_cores()} CPUs, torch's default "
            f"{default} threads, median (min-max) seconds over {args.repeats} rounds]"
        )
        table = [["busy processes started", "threads", "load before", "seconds"], ["---"] * 4]
        for busy in [0, *args.load]:
            spinners = [multiprocessing.Process(target=_spin, daemon=True) for _ in range(busy)]
            for process in spinners:
                process.start()
            try:
                if busy:
                    time.sleep(args.settle)
                table += [[str(busy), *row] for row in rounds(run, settings, args.repeats)]
            finally:
                for process in spinners:
                    process.terminate()
                for process in spinners:
                    process.join()
    for row in table:
        print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
