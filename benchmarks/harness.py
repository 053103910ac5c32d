"""Side-by-side timing and peak-memory measurement shared by the benchmarks.

Each benchmark runs ours and the reference on the same inputs in one process and
reports ratios. Peak memory is measured per call: on CUDA with the caching
allocator's counters, on Linux CPUs from the process high-water mark (VmHWM),
which is reset before each measured call through ``/proc/self/clear_refs`` after
glibc has returned its cached free pages to the OS.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import ctypes.util
import gc
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

_STATUS = Path("/proc/self/status")
_CLEAR_REFS = Path("/proc/self/clear_refs")


@dataclass(frozen=True)
class Measurement:
    """Median wall time (seconds) over repeats and peak extra memory (MiB) of one call."""

    seconds: float
    peak_mib: float


def _release_free_heap_pages() -> None:
    """Return glibc's cached free pages to the OS so the next call's peak shows in RSS.

    glibc keeps freed tensors' pages resident for reuse; ``malloc_trim(0)`` unmaps
    them, so pages the measured call touches are counted again.
    """
    libc_name = ctypes.util.find_library("c")
    if libc_name is not None:
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(libc_name).malloc_trim(0)


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _rss_kib(field: str) -> int | None:
    try:
        for line in _STATUS.read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def peak_memory_mib(fn: Callable[[], Any], device: torch.device) -> float:
    """Extra memory at the peak of one call of ``fn``, in MiB (NaN where unmeasurable)."""
    gc.collect()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
        fn()
        torch.cuda.synchronize(device)
        return (torch.cuda.max_memory_allocated(device) - base) / 2**20
    _release_free_heap_pages()
    try:
        _CLEAR_REFS.write_text("5")  # resets VmHWM to the current RSS
    except OSError:
        return float("nan")
    base = _rss_kib("VmRSS")
    fn()
    peak = _rss_kib("VmHWM")
    if base is None or peak is None:
        return float("nan")
    return max(peak - base, 0) / 1024


def median_seconds(
    fn: Callable[[], Any], device: torch.device, *, repeats: int = 20, warmup: int = 3
) -> float:
    """Median wall time of ``repeats`` calls of ``fn`` after ``warmup`` calls."""
    return alternating_median_seconds({"fn": fn}, device, repeats=repeats, warmup=warmup)["fn"]


def alternating_median_seconds(
    fns: dict[str, Callable[[], Any]], device: torch.device, *, repeats: int, warmup: int = 1
) -> dict[str, float]:
    """Median wall time of each of ``fns`` over ``repeats`` rounds that call them in turn,
    after ``warmup`` rounds, so that drifts of a shared machine hit them all alike."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    _synchronize(device)
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            _synchronize(device)
            times[name].append(time.perf_counter() - start)
    return {name: statistics.median(values) for name, values in times.items()}


Case = tuple[Callable[[], Any], Callable[[], Any]]
"""``(ours, reference)``: two zero-argument callables over the same inputs."""


def compare(
    cases: dict[str, Case], device: torch.device, *, repeats: int = 20
) -> dict[str, tuple[Measurement, Measurement]]:
    """Time every case (ours, then the reference, on the same inputs) and measure peak memory."""
    seconds = {
        name: (
            median_seconds(ours, device, repeats=repeats),
            median_seconds(ref, device, repeats=repeats),
        )
        for name, (ours, ref) in cases.items()
    }
    return {
        name: (
            Measurement(seconds[name][0], peak_memory_mib(ours, device)),
            Measurement(seconds[name][1], peak_memory_mib(ref, device)),
        )
        for name, (ours, ref) in cases.items()
    }


def print_comparison(
    title: str,
    results: dict[str, tuple[Measurement, Measurement]],
    notes: dict[str, str] | None = None,
) -> None:
    """Print one row per case with the reference/ours time ratio ("speed-up")."""
    notes = notes or {}
    print(title)
    header = (
        f"{'case':<34}{'ours ms':>10}{'ref ms':>10}{'speed-up':>10}"
        f"{'ours MiB':>10}{'ref MiB':>10}  note"
    )
    print(header)
    print("-" * len(header))
    for case, (ours, ref) in results.items():
        print(
            f"{case:<34}{ours.seconds * 1e3:>10.3f}{ref.seconds * 1e3:>10.3f}"
            f"{ref.seconds / ours.seconds:>9.2f}x{ours.peak_mib:>10.1f}{ref.peak_mib:>10.1f}"
            f"  {notes.get(case, '')}"
        )


def splat_versions(device: torch.device) -> str:
    """One line naming what a splatting benchmark compares: torch, the device, triton and
    the launch settings dego's kernels use there, and gsplat's version (``gsplat.__version__``
    as installed: a release such as ``1.5.3``, or a build from its main branch, whose
    forward differs; see docs/performance.md)."""
    import importlib.metadata

    name = torch.cuda.get_device_name(device) if device.type == "cuda" else str(device)
    parts = [f"torch {torch.__version__}", f"threads {torch.get_num_threads()}", f"device {name}"]
    try:
        import triton
    except ImportError:
        parts.append("triton not installed")
    else:
        from dego.splatting import triton_configs

        if triton_configs.autotuning():
            settings = "autotuned"
        elif device.type == "cuda":  # what the launches will use, by the same lookup
            settings = f"{triton_configs.family(device)}: {triton_configs.config_for(device)}"
        else:
            settings = "table"
        parts.append(f"triton {triton.__version__} ({settings})")
    try:
        import gsplat
    except ImportError:
        parts.append("gsplat not installed")
    else:
        try:
            distribution = importlib.metadata.version("gsplat")
        except importlib.metadata.PackageNotFoundError:
            distribution = "no distribution metadata"
        where = Path(gsplat.__file__).parent
        parts.append(f"gsplat {gsplat.__version__} ({distribution}, {where})")
    return ", ".join(parts)


def benchmark_parser(doc: str, *, repeats: int) -> argparse.ArgumentParser:
    """Argument parser with the options every benchmark shares: ``--device``, ``--repeats``."""
    parser = argparse.ArgumentParser(description=doc.strip().splitlines()[0])
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--repeats", type=int, default=repeats, help="timed calls per case")
    return parser


def run_comparison(
    title: str,
    cases: dict[str, Case],
    device: torch.device,
    *,
    repeats: int,
    notes: dict[str, str] | None = None,
) -> None:
    """Measure every case with :func:`compare` and print the table, headed by ``title``
    and the software versions."""
    versions = f"torch {torch.__version__}, threads {torch.get_num_threads()}, device {device}"
    print_comparison(f"{title} [{versions}]", compare(cases, device, repeats=repeats), notes)
