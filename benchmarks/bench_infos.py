"""Reading an mmdet3d infos pickle: ``dego.data.load_pickle`` vs ``pickle.load``, one run.

Workload: the nuScenes val infos file of ``infos_file.py`` (6,019 samples, 10 lidar
sweeps and 6 cameras each, gt boxes, Occ3D's ``occ_path``; its docstring has the layout)
written at each of ``--protocols`` (mmcv's ``dump`` writes 2, ``pickle.dump`` 4 since
Python 3.8). Per protocol:

- both loaders read the file once (warm-up: the file is in the page cache afterwards) and
  their results must be equal: same types (``ndarray`` exactly), dict keys in the same
  order, list lengths, array dtypes, shapes, memory order and values (NaN equal to NaN);
  a difference stops the run;
- ``--repeats`` rounds each call both, the order alternating between rounds; the time
  covers opening the file and unpickling it, not freeing the result; median [min-max];
- peak memory, untimed (tracemalloc slows the loaders down): the tracemalloc peak of one
  call in this process (Python and numpy allocations, the result included), and, in a
  fresh process per loader (in this one the heap that earlier loads freed and kept
  would hide most of it), the resident high-water mark (``VmHWM``, reset first where
  Linux allows; else ``ru_maxrss``) of one call over the resident size before it;
- that fresh process first calls the loader on a 2-sample file of the same protocol
  and reports that first call's seconds and resident growth: what the first load of a
  process pays once (imports, compilation) on top of the table's warm times.

ratio = load_pickle / pickle.load (times the C unpickler's time); a third column times
``pickle.load`` with the cyclic garbage collector paused, as ``load_pickle`` pauses it for
its own load: the ratio to that one is what the checks cost. ``--cache DIR`` keeps
the generated files between runs (a temporary folder by default), ``--json OUT`` writes
the results.

    python benchmarks/bench_infos.py [--samples 6019] [--sweeps 10] [--protocols 4,2]
                                     [--repeats 5] [--cache DIR] [--json OUT]
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import hashlib
import inspect
import json
import os
import pickle
import platform
import resource
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from infos_file import VALIDATION_SAMPLES, write_infos

import dego.data
from dego.data import load_pickle

LOADERS = ("pickle.load", "load_pickle")
PAUSED = "pickle.load, gc paused"
"""Also timed: ``pickle.load`` with the cyclic garbage collector paused, as ``load_pickle``
pauses it for its load (``pickle.load`` does not): the ratio to it is the cost of the
checks alone."""
_STATUS = Path("/proc/self/status")
_CLEAR_REFS = Path("/proc/self/clear_refs")


def _pickle_load(path: Path) -> Any:
    with path.open("rb") as stream:
        return pickle.load(stream)


def _pickle_load_gc_paused(path: Path) -> Any:
    collecting = gc.isenabled()
    gc.disable()
    try:
        return _pickle_load(path)
    finally:
        if collecting:
            gc.enable()


def _loaders(path: Path) -> dict[str, Callable[[], Any]]:
    return {"pickle.load": lambda: _pickle_load(path), "load_pickle": lambda: load_pickle(path)}


def assert_same(a: Any, b: Any, where: str = "") -> None:
    """Raise ``AssertionError`` naming the first place where ``a`` and ``b`` differ."""
    if type(a) is not type(b):
        raise AssertionError(f"{where or 'root'}: {type(a).__name__} vs {type(b).__name__}")
    if isinstance(a, dict):
        if list(a) != list(b):
            raise AssertionError(f"{where}: keys {list(a)} vs {list(b)}")
        for key in a:
            assert_same(a[key], b[key], f"{where}[{key!r}]")
    elif isinstance(a, list | tuple):
        if len(a) != len(b):
            raise AssertionError(f"{where}: length {len(a)} vs {len(b)}")
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        if a.dtype != b.dtype or a.shape != b.shape:
            raise AssertionError(f"{where}: {a.dtype}{a.shape} vs {b.dtype}{b.shape}")
        if (a.flags.c_contiguous, a.flags.f_contiguous) != (
            b.flags.c_contiguous,
            b.flags.f_contiguous,
        ):
            raise AssertionError(f"{where}: memory order differs")
        if not np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"):
            raise AssertionError(f"{where}: values differ")
    elif a != b and not (isinstance(a, float) and np.isnan(a) and np.isnan(b)):
        raise AssertionError(f"{where}: {a!r} vs {b!r}")


def _timed(fn: Callable[[], Any]) -> float:
    gc.collect()
    start = time.perf_counter()
    result = fn()
    seconds = time.perf_counter() - start
    del result
    return seconds


def _tracemalloc_peak_mib(fn: Callable[[], Any]) -> float:
    gc.collect()
    tracemalloc.start()
    try:
        result = fn()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    del result
    return peak / 2**20


def _rss_kib() -> tuple[int, int]:
    """(resident KiB now, resident high-water KiB) of this process."""
    fields = {}
    if _STATUS.exists():
        for line in _STATUS.read_text().splitlines():
            name, _, value = line.partition(":")
            fields[name] = value
    if "VmRSS" in fields and "VmHWM" in fields:
        return int(fields["VmRSS"].split()[0]), int(fields["VmHWM"].split()[0])
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak, peak


def _fresh_process(loader: str, path: Path, tiny: Path) -> None:
    """In a fresh process: one call of ``loader`` on ``tiny`` (its first call: lazy imports,
    compilation), then one on ``path``; prints the first call's seconds and resident
    growth, and the second call's resident high-water mark over the resident size before
    it (the mark reset where Linux allows), in MiB."""
    gc.collect()
    before, _ = _rss_kib()
    first = _timed(_loaders(tiny)[loader])
    gc.collect()
    after_first, _ = _rss_kib()
    with contextlib.suppress(OSError):
        _CLEAR_REFS.write_text("5")  # resets VmHWM to the current RSS
    result = _loaders(path)[loader]()
    peak = _rss_kib()[1]
    del result
    record = {
        "first_call_s": first,
        "first_call_rss_mib": (after_first - before) / 1024,
        "rss_peak_mib": (peak - after_first) / 1024,
        "source": SOURCE,
    }
    print(json.dumps(record))


def _in_fresh_process(loader: str, path: Path, tiny: Path) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, __file__, "--fresh-process", loader, str(path), str(tiny)],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def measure(path: Path, tiny: Path, repeats: int) -> dict[str, Any]:
    """Check, time and measure both loaders on ``path`` (see the module docstring); ``tiny``:
    a small file of the same protocol for the fresh processes' first calls."""
    loaders = _loaders(path)
    assert_same(loaders["pickle.load"](), loaders["load_pickle"]())
    timed = {**loaders, PAUSED: lambda: _pickle_load_gc_paused(path)}
    times: dict[str, list[float]] = {name: [] for name in timed}
    for round_ in range(repeats):
        for name in list(timed) if round_ % 2 == 0 else list(timed)[::-1]:
            times[name].append(_timed(timed[name]))
    fresh = {n: _in_fresh_process(n, path, tiny) for n in LOADERS}
    if fresh["load_pickle"]["source"] != SOURCE:
        raise RuntimeError("load_pickle's source changed during the run: run it again")
    return {
        "file_bytes": path.stat().st_size,
        "seconds": times,
        "tracemalloc_peak_mib": {n: _tracemalloc_peak_mib(f) for n, f in loaders.items()},
        "rss_peak_mib": {n: fresh[n]["rss_peak_mib"] for n in LOADERS},
        "first_call_s": {n: fresh[n]["first_call_s"] for n in LOADERS},
        "first_call_rss_mib": {n: fresh[n]["first_call_rss_mib"] for n in LOADERS},
    }


def _source_digest() -> str:
    """The first 12 hex digits of a sha256 over the sources of ``dego.data`` (where
    ``load_pickle`` lives) as they are on disk now."""
    digest = hashlib.sha256()
    for file in sorted(Path(inspect.getfile(dego.data)).parent.glob("*.py")):
        digest.update(file.name.encode() + b"\0" + file.read_bytes())
    return digest.hexdigest()[:12]


SOURCE = _source_digest()
"""The digest when this process imported ``load_pickle``."""


def _cell(values: list[float]) -> str:
    return f"{statistics.median(values):.2f} [{min(values):.2f}-{max(values):.2f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds")
    parser.add_argument("--samples", type=int, default=VALIDATION_SAMPLES)
    parser.add_argument("--sweeps", type=int, default=10, help="lidar sweeps per keyframe")
    parser.add_argument("--protocols", default="4,2", help="comma-separated pickle protocols")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", type=Path, help="keep the generated files in this folder")
    parser.add_argument("--json", type=Path, help="write the results to this file")
    parser.add_argument("--fresh-process", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.fresh_process:
        _fresh_process(args.fresh_process[0], *map(Path, args.fresh_process[1:]))
        return
    protocols = [int(p) for p in args.protocols.split(",")]
    with tempfile.TemporaryDirectory() as scratch:
        folder = args.cache or Path(scratch)
        folder.mkdir(parents=True, exist_ok=True)
        results: dict[str, Any] = {}
        for protocol in protocols:
            path = folder / f"infos_{args.samples}_{args.sweeps}_seed{args.seed}_p{protocol}.pkl"
            if not path.exists():
                write_infos(
                    path.with_suffix(".tmp"), args.samples, args.sweeps, protocol, args.seed
                )
                path.with_suffix(".tmp").replace(path)
            tiny = folder / f"infos_2_1_seed{args.seed}_p{protocol}.pkl"
            write_infos(tiny, 2, 1, protocol, args.seed)
            results[str(protocol)] = measure(path, tiny, args.repeats)
    environment = {
        "command": shlex.join([sys.executable, *sys.argv]),
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "cpus": os.cpu_count(),
        "machine": platform.machine(),
        "dego.data source sha256": SOURCE,
    }
    print(
        f"{environment['command']}\nPython {environment['python']}, numpy {np.__version__}, "
        f"{os.cpu_count()} CPUs, dego.data source {SOURCE}; "
        f"{args.samples} samples, {args.sweeps} sweeps; seconds: "
        f"median [min-max] over {args.repeats} alternating rounds; peak MiB: tracemalloc, RSS"
    )
    print(
        "| protocol | file MB | pickle.load s | load_pickle s | ratio "
        "| pickle.load, gc paused s | ratio to it | pickle.load MiB | load_pickle MiB |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for protocol, r in results.items():
        base, ours = (statistics.median(r["seconds"][n]) for n in LOADERS)
        peaks = [f"{r['tracemalloc_peak_mib'][n]:.0f}, {r['rss_peak_mib'][n]:.0f}" for n in LOADERS]
        print(
            f"| {protocol} | {r['file_bytes'] / 1e6:.1f} | {_cell(r['seconds']['pickle.load'])} "
            f"| {_cell(r['seconds']['load_pickle'])} | {ours / base:.2f}x "
            f"| {_cell(r['seconds'][PAUSED])} "
            f"| {ours / statistics.median(r['seconds'][PAUSED]):.2f}x "
            f"| {peaks[0]} | {peaks[1]} |"
        )
    print("first call in a fresh process (2-sample file of the same protocol): seconds, RSS MiB")
    for protocol, r in results.items():
        cells = [
            f"{n} {r['first_call_s'][n]:.3f}, {r['first_call_rss_mib'][n]:.0f}" for n in LOADERS
        ]
        print(f"  protocol {protocol}: " + "; ".join(cells))
    if args.json:
        payload = {"environment": environment, "arguments": vars(args), "results": results}
        args.json.write_text(json.dumps(payload, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()
