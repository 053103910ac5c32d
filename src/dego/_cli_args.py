"""Flag parsing and progress output shared by the ``dego`` subcommands (``dego demo``,
``dego study``, ``dego train``)."""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path
from typing import TextIO

from dego._atomic import make_output_dir
from dego.evaluation import command as eval_command

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


def add_device(parser: argparse.ArgumentParser) -> None:
    """The ``--device`` and ``--threads`` flags of ``dego demo``, ``dego study`` and
    ``dego train``: checked while parsing, so a device that is not usable here is the
    subcommand's usage error."""
    parser.add_argument(
        "--device",
        type=eval_command.parse_device,
        default="cpu",
        help="torch device: cpu, cuda or cuda:N (cpu)",
    )
    eval_command.add_threads_argument(parser)


def repeated_values(values: tuple) -> list:
    """The values that occur more than once, in order of first appearance."""
    return sorted({v for v in values if values.count(v) > 1}, key=values.index)


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
