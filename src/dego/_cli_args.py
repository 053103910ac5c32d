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

    def __call__(self, iteration: int, losses: dict[str, float]) -> None:
        done = iteration + 1
        now = time.perf_counter()
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
        rate = done / max(now - self.start, 1e-9)
        loss = f"loss {losses['total']:.3f} " if "total" in losses else ""
        return (
            f"{self.label:>10} [{'#' * filled}{'.' * (width - filled)}] {done}/{self.total} "
            f"{loss}ETA {clock((self.total - done) / rate)} {rate:.1f} it/s"
        )


def clock(seconds: float) -> str:
    """``"1:05"`` / ``"1:02:05"``: a duration for a progress line."""
    minutes, secs = divmod(round(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


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

THREADS_HELP = (
    "CPU threads per process (torch.set_num_threads; default: torch's, one per core). "
    "On a shared or busy machine 1 is often much faster: torch's threads otherwise wait "
    "for each other (docs/performance.md, Threads)"
)


def add_threads_argument(parser: argparse.ArgumentParser) -> None:
    """The ``--threads N`` flag of every ``dego`` command that computes."""
    parser.add_argument(
        "--threads", type=bounded_int(1, MAX_THREADS), metavar="N", help=THREADS_HELP
    )


def apply_threads(threads: int | None) -> None:
    """``--threads N``: N threads in this process, and ``OMP_NUM_THREADS=N`` for the
    processes it starts (``--workers``, subprocesses); ``None`` leaves torch's default."""
    if threads is None:
        return
    os.environ["OMP_NUM_THREADS"] = str(threads)
    torch.set_num_threads(threads)


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
        parser.error('--rerun: needs rerun-sdk: pip install "dego-occupancy[rerun]"')
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
