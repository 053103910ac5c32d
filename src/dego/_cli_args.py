"""What the ``dego`` subcommands share: flag types (ints, devices, lists, ``--threads``),
output folders, the usage error, Ctrl-C handling and the progress bar.

Every command module (:mod:`dego.cli` lists them) imports these from here; nothing here
imports a command, so the commands sit above this module and never beside each other.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NoReturn, TextIO

import torch

from dego._atomic import check_output_file, check_output_files, make_output_dir, same_file
from dego._checks import repeated_values
from dego._cores import usable_cores

INTERRUPTED_STATUS = 130
"""Exit status after Ctrl-C (128 + SIGINT, as shells report it)."""


class UsageError(Exception):
    """A flag's value found wrong once the work has looked at the data: ``flag`` and a
    one-line ``message``; :func:`dego.cli.main` reports it as a usage error (exit status 2)."""

    def __init__(self, flag: str, message: str) -> None:
        super().__init__(f"{flag}: {message}")
        self.flag, self.message = flag, message


MAX_ITERATIONS = 100_000
"""The most optimiser steps ``--iterations`` takes (the full demo takes 150; 100,000 steps
of one fit are hours on a CPU): more is a typing slip, refused before any work."""

MAX_LIST_VALUES = 1000
"""The most values ``dego study --seeds`` / ``--budgets`` take (each seed renders a clip
and each value multiplies the fits)."""


class ProgressBar:
    """A one-line progress bar on ``stream`` (redrawn on a terminal, quartiles otherwise)."""

    def __init__(self, label: str, total: int, stream: TextIO | None = None) -> None:
        self.label, self.total = label, total
        self.stream = stream or sys.stderr
        self.interactive = self.stream.isatty()
        self.start = time.perf_counter()
        self.last_draw = 0.0
        self.first: tuple[int, float] | None = None
        """(steps done, time) at the first call: the rate counts the steps after it."""

    def __call__(self, iteration: int, losses: dict[str, float]) -> None:
        done = iteration + 1
        now = time.perf_counter()
        if self.first is None:
            self.first = (done, now)
        if self.interactive:
            if done < self.total and now - self.last_draw < 0.1:
                return
            self.last_draw = now
            end = "\n" if done == self.total else ""
            self.stream.write("\r" + self._line(done, losses, now) + end)
        elif done == self.total or done % max(1, self.total // 4) == 0:
            self.stream.write(self._line(done, losses, now) + "\n")
        self.stream.flush()

    def _line(self, done: int, losses: dict[str, float], now: float) -> str:
        width = 24
        filled = width * done // max(self.total, 1)
        first_done, first_time = self.first if self.first is not None else (done, now)
        loss = f" loss {losses['total']:.3f}" if "total" in losses else ""
        speed = pace(done - first_done, now - first_time, self.total - done)
        return (
            f"{self.label:>10} [{'#' * filled}{'.' * (width - filled)}] {done}/{self.total}"
            f"{loss}{' ' if speed else ''}{speed}"
        )


def clock(seconds: float) -> str:
    """``"1:05"`` / ``"1:02:05"``: a duration for a progress line."""
    minutes, secs = divmod(round(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


MIN_TIMED_STEPS = 2
"""The fewest steps a progress line's rate is measured over (issue 51: from the first step
alone it read ``117329.6 it/s``, the bar made just before that step's end)."""


def pace(steps: int, seconds: float, left: int) -> str:
    """``"ETA 0:12 3.4 it/s"`` (``s/it`` below one step a second, not ``0.0 it/s``):
    ``steps`` timed over ``seconds``, ``left`` to go; ``""`` until :data:`MIN_TIMED_STEPS`
    steps are timed."""
    if steps < MIN_TIMED_STEPS or seconds <= 0:
        return ""
    rate = steps / seconds
    speed = f"{rate:.1f} it/s" if rate >= 1 else f"{1 / rate:.1f} s/it"
    return f"ETA {clock(left / rate)} {speed}"


def parse_device(text: str) -> str:
    """A device flag: ``cpu``, ``cuda`` or ``cuda:N`` of a CUDA device that exists here
    (``torch.device`` spelling); anything else (``meta``, ``mps``, ``cuda`` without CUDA, a
    missing ``cuda:N``) is an ``ArgumentTypeError``. Returns the device's name."""
    try:
        device = torch.device(text)
    except (RuntimeError, ValueError, TypeError):
        raise argparse.ArgumentTypeError(f"expected cpu, cuda or cuda:N, got {text!r}") from None
    if device.type == "cpu":
        if device.index not in (None, 0):
            raise argparse.ArgumentTypeError(f"expected cpu, cuda or cuda:N, got {text!r}")
        return "cpu"
    if device.type != "cuda":
        raise argparse.ArgumentTypeError(
            f"expected cpu, cuda or cuda:N, got {text!r} ({device.type} is not supported)"
        )
    if not torch.cuda.is_available():
        raise argparse.ArgumentTypeError(f"{text!r}: CUDA is not available here")
    count = torch.cuda.device_count()
    if device.index is not None and device.index >= count:
        raise argparse.ArgumentTypeError(
            f"{text!r}: this machine has {count} CUDA device(s), cuda:0 .. cuda:{count - 1}"
        )
    try:
        torch.empty(0, device=device)
    except (RuntimeError, AssertionError) as error:
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise argparse.ArgumentTypeError(f"{text!r} is not usable here ({reason})") from None
    return str(device)


def parse_int(text: str) -> int:
    """An int argument (digits with an optional sign; anything else is an argparse error,
    which names the flag)."""
    if not re.fullmatch(r"\s*[+-]?\d+\s*", text):
        raise argparse.ArgumentTypeError(f"expected an int, got {text!r}")
    return int(text)


def bounded_int(low: int, high: int) -> Callable[[str], int]:
    """An argparse type: an int in ``[low, high]`` (``dego eval`` and the other commands)."""

    def parse(text: str) -> int:
        value = parse_int(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected an int in [{low}, {high}], got {text!r}")
        return value

    parse.__name__ = "int"
    return parse


def bounded_float(low: float, high: float, *, open_low: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite float in ``[low, high]`` (``(low, high]`` with
    ``open_low``)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        above = value > low if open_low else value >= low
        if not (math.isfinite(value) and above and value <= high):
            interval = f"{'(' if open_low else '['}{low:g}, {high:g}]"
            raise argparse.ArgumentTypeError(f"expected a number in {interval}, got {text!r}")
        return value

    parse.__name__ = "float"
    return parse


MAX_THREADS = 256
"""The most threads ``--threads`` allows."""

AUTO_THREADS = "auto"
"""``--threads auto``, the default: :func:`auto_threads` decides from the machine's load."""

BUSY_MARGIN = 1.2
"""``--threads auto`` counts the machine busy when its 1-minute load average is at least
its cores minus this (0.8 on 2 cores): other jobs leave at most about one core free, and
torch's threads would wait for each other. The load is the other jobs': the command has
not started computing when it looks. One steady other job shows as a load approaching
1.0 from below, so the threshold sits under cores - 1. Measured on 2 cores
(docs/performance.md, Threads): beside one busy process (load 0.7-1.3) torch's 2 threads
were 1.2-3.8x slower than 1; at a load of 0.4-0.6 they were as fast or 1.7x faster."""

THREADS_HELP = (
    "CPU threads per process (torch.set_num_threads), or auto (the default): 1 when other "
    f"jobs keep the machine busy (1-minute load average >= cores - {BUSY_MARGIN}), torch's "
    "default (one "
    "per core) otherwise; auto prints a note when it picks 1, and leaves the threads alone "
    "where OMP_NUM_THREADS is set or the load is unknown (Windows). On a shared machine 1 "
    "is often several times faster: torch's threads otherwise wait for each other "
    "(docs/performance.md, Threads)"
)


def auto_threads(load: float | None, cores: int) -> int | None:
    """What ``--threads auto`` sets, from the 1-minute load average ``load`` (``None``:
    unknown) and the ``cores`` this process may run on: 1 when the machine is busy,
    ``load >= cores - BUSY_MARGIN``; ``None`` (torch's default) when it is not or the
    load is unknown. Pure: :func:`apply_threads` reads the machine."""
    if load is None or not math.isfinite(load):
        return None
    return 1 if load >= max(cores, 1) - BUSY_MARGIN else None


def machine_load() -> float | None:
    """The 1-minute load average (``os.getloadavg``), or ``None`` where there is none
    (Windows) or it cannot be read."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return None


def parse_threads(text: str) -> int | str:
    """A ``--threads`` value: ``auto`` or an int in ``[1, MAX_THREADS]``."""
    if text.strip().lower() == AUTO_THREADS:
        return AUTO_THREADS
    try:
        return bounded_int(1, MAX_THREADS)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"expected auto or an int in [1, {MAX_THREADS}], got {text!r}"
        ) from None


parse_threads.__name__ = "threads"


def add_threads_argument(parser: argparse.ArgumentParser) -> None:
    """The ``--threads N`` / ``--threads auto`` flag of every ``dego`` command that
    computes (default: auto)."""
    parser.add_argument(
        "--threads", type=parse_threads, default=AUTO_THREADS, metavar="N", help=THREADS_HELP
    )


def apply_threads(
    threads: int | str | None, *, quiet: bool = False, stream: TextIO | None = None
) -> int | None:
    """``--threads N``: N threads in this process, and ``OMP_NUM_THREADS=N`` for the
    processes it starts (``--workers``, subprocesses); ``None`` leaves torch's default.

    ``--threads auto``: where ``OMP_NUM_THREADS`` is set (torch read it at start) nothing
    changes; otherwise :func:`auto_threads` of :func:`machine_load` and
    :func:`usable_cores`, applied as above, with a one-line note on ``stream`` (stderr)
    unless ``quiet`` when it picks fewer threads than torch has. Returns the count set
    (``None``: torch's default kept), so applying the result again changes nothing."""
    if threads == AUTO_THREADS:
        if "OMP_NUM_THREADS" in os.environ:
            return None
        load, cores = machine_load(), usable_cores()
        chosen = auto_threads(load, cores)
        if chosen is None:
            return None
        if not quiet and chosen < torch.get_num_threads() and os.environ.get("RANK", "0") == "0":
            print(
                f"dego: threads: {chosen} (auto: load {load:.1f} on {cores} cores; "
                "--threads N to choose)",
                file=stream or sys.stderr,
                flush=True,
            )
        threads = chosen
    if threads is None:
        return None
    if isinstance(threads, str) or not 1 <= threads <= MAX_THREADS:
        raise ValueError(
            f"threads: expected auto, None or an int in [1, {MAX_THREADS}], got {threads!r}"
        )
    os.environ["OMP_NUM_THREADS"] = str(threads)
    torch.set_num_threads(threads)
    return threads


def add_device(parser: argparse.ArgumentParser) -> None:
    """The ``--device`` and ``--threads`` flags of ``dego demo``, ``dego study`` and
    ``dego train``: checked while parsing, so a device that is not usable here is the
    subcommand's usage error."""
    parser.add_argument(
        "--device",
        type=parse_device,
        default="cpu",
        help="torch device: cpu, cuda or cuda:N (cpu)",
    )
    add_threads_argument(parser)


def name_list(text: str) -> tuple[str, ...]:
    """``"static,rigid"`` -> ``("static", "rigid")``; empty or repeated names are refused."""
    names = tuple(part.strip() for part in text.split(",") if part.strip())
    if not names:
        raise argparse.ArgumentTypeError(f"expected at least one name, got {text!r}")
    repeated = repeated_values(names)
    if repeated:
        raise argparse.ArgumentTypeError(
            f"{', '.join(repeated)} repeated in {text!r}; each runs once"
        )
    return names


def int_list(text: str) -> tuple[int, ...]:
    """``"0-7"``, ``"0,3,5"`` or ``"0-3,8"`` -> a tuple of non-negative ints, each once
    and at most :data:`MAX_LIST_VALUES` of them (counted before any is made)."""
    ranges = []
    for part in text.split(","):
        match = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if match is None:
            raise argparse.ArgumentTypeError(
                f"expected non-negative integers like 0-7, 0,3,5 or 0-3,8, got {text!r}"
            )
        low = int(match[1])
        high = low if match[2] is None else int(match[2])
        if high < low:
            raise argparse.ArgumentTypeError(f"the range {part.strip()!r} is empty")
        ranges.append((low, high))
    if sum(high - low + 1 for low, high in ranges) > MAX_LIST_VALUES:
        raise argparse.ArgumentTypeError(f"at most {MAX_LIST_VALUES} values, got {text!r}")
    values = tuple(v for low, high in ranges for v in range(low, high + 1))
    repeated = repeated_values(values)
    if repeated:
        raise argparse.ArgumentTypeError(
            f"{', '.join(map(str, repeated))} repeated in {text!r}; each value runs once"
        )
    return values


def format_ints(values: tuple[int, ...]) -> str:
    if len(values) > 2 and values == tuple(range(values[0], values[-1] + 1)):
        return f"{values[0]}-{values[-1]}"
    return ",".join(map(str, values))


def output_dir(parser: argparse.ArgumentParser, flag: str, path: Path) -> list[Path]:
    """Create the output folder ``path`` of ``flag`` or exit with a usage error; returns
    the folders made."""
    try:
        return make_output_dir(path)
    except OSError as error:
        parser.error(f"{flag}: {error.strerror or error}")


def output_problem(outputs: Sequence[tuple[str, Path | None]], created: list[Path]) -> str | None:
    """Why the files a command writes cannot be written, as one line, or ``None``.

    ``outputs``: ``(flag, path)`` of every output file (``None``: not asked for), e.g.
    ``("--out", out / "results.md")``. Two paths naming one file (after resolving links and
    relative spellings, :func:`dego._atomic.same_file`) are refused, naming both flags; then
    every path is checked with :func:`dego._atomic.check_output_files` (a directory in its
    place, a folder that cannot be created or written), naming the flag. The folders made
    are added to ``created``. Called before any work."""
    given = [(flag, Path(path)) for flag, path in outputs if path is not None]
    for index, (flag, path) in enumerate(given):
        for other, other_path in given[index + 1 :]:
            if same_file(path, other_path):
                if flag == other:
                    return f"{flag}: {path} is named twice"
                return f"{flag} and {other} name the same file, {path}"
    for flag in dict.fromkeys(flag for flag, _ in given):
        try:
            created += check_output_files(path for name, path in given if name == flag)
        except OSError as error:
            return f"{flag}: {error.strerror or error}"
    return None


def check_outputs(
    parser: argparse.ArgumentParser,
    outputs: Sequence[tuple[str, Path | None]],
    created: list[Path],
) -> None:
    """:func:`output_problem`, as a usage error (exit status 2) of ``parser``."""
    problem = output_problem(outputs, created)
    if problem is not None:
        parser.error(problem)


def config_error(parser: argparse.ArgumentParser, error: ValueError) -> NoReturn:
    """A config's ``ValueError`` (``"field_name: message"``) as the usage error of its flag,
    ``--field-name: message``; exits with status 2."""
    field, _, message = str(error).partition(": ")
    parser.error(f"--{field.replace('_', '-')}: {message or error}")


def rerun_target(parser: argparse.ArgumentParser, path: Path | None) -> list[Path]:
    """Check ``--rerun`` before any work (rerun-sdk present, a ``.rrd`` file that can be
    written; its folder is created) or exit with a usage error; returns the folders made."""
    if path is None:
        return []
    if importlib.util.find_spec("rerun") is None:
        parser.error('--rerun: needs rerun-sdk: pip install -e ".[rerun]" in your dego clone')
    if path.suffix != ".rrd":
        parser.error(f"--rerun: expected a file name ending in .rrd, got {str(path)!r}")
    try:
        return check_output_file(path)
    except OSError as error:
        parser.error(f"--rerun: {error.strerror or error}")


def isatty(stream: TextIO) -> bool:
    """Whether ``stream`` is a terminal (``False`` for closed or fake streams)."""
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


class SigintIgnored:
    """Ignore SIGINT inside the block (main thread only), then restore the handler."""

    def __enter__(self) -> None:
        self.previous = None
        if threading.current_thread() is threading.main_thread():
            self.previous = signal.signal(signal.SIGINT, signal.SIG_IGN)

    def __exit__(self, *exc: object) -> None:
        if self.previous is not None:
            signal.signal(signal.SIGINT, self.previous)
