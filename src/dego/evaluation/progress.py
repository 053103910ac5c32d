"""Progress of an evaluation: a tqdm bar on a terminal, plain lines otherwise.

On a TTY (and with ``tqdm`` installed, the ``eval`` extra) a tqdm bar with rate and ETA is
drawn on ``stream`` (stderr by default). Elsewhere (a log file, CI, or no tqdm) one plain
line is written every ~10% of the samples or every 30 s, whichever comes first, and at the
end: ``eval: 12/120 samples (10%), 3.4 samples/s, ETA 0:00:31``.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from typing import Any, TextIO


def _clock_text(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    seconds = round(seconds)
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


class Progress:
    """Counts finished samples: ``progress.update(n)``, then ``progress.close()``.

    Args:
        total: the samples to be done.
        enabled: ``False`` draws nothing (``--quiet``).
        stream: where to write (stderr).
        label: the line's prefix.
        interval_s: the longest gap between two plain lines.
        use_tqdm: ``None`` chooses tqdm on a TTY when it is installed.
        clock: the time source (tests pass a fake one).
    """

    def __init__(
        self,
        total: int,
        *,
        enabled: bool = True,
        stream: TextIO | None = None,
        label: str = "eval",
        interval_s: float = 30.0,
        use_tqdm: bool | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.total, self.done, self.enabled = int(total), 0, enabled
        self.stream = stream if stream is not None else sys.stderr
        self.label, self.interval_s, self.clock = label, interval_s, clock
        self.start = self.last_line = clock()
        self.step = max(1, math.ceil(self.total / 10))
        self.next_done = self.step
        self.bar: Any = None
        if enabled and total > 0:
            if use_tqdm is None:
                use_tqdm = bool(getattr(self.stream, "isatty", lambda: False)())
            if use_tqdm:
                try:
                    from tqdm import tqdm
                except ImportError:
                    tqdm = None
                if tqdm is not None:
                    self.bar = tqdm(
                        total=self.total, desc=label, unit="sample", file=self.stream, leave=True
                    )

    def line(self) -> str:
        """The plain progress line of now."""
        elapsed = max(self.clock() - self.start, 1e-9)
        rate = self.done / elapsed
        eta = (self.total - self.done) / rate if rate > 0 else math.inf
        percent = 100 * self.done / max(self.total, 1)
        return (
            f"{self.label}: {self.done}/{self.total} samples ({percent:.0f}%), "
            f"{rate:.2f} samples/s, ETA {_clock_text(eta)}"
        )

    def update(self, n: int = 1) -> None:
        """Record ``n`` more finished samples."""
        self.done += n
        if not self.enabled or self.total <= 0:
            return
        if self.bar is not None:
            self.bar.update(n)
            return
        now = self.clock()
        due = self.done >= self.next_done or self.done >= self.total
        if due or now - self.last_line >= self.interval_s:
            self.stream.write(self.line() + "\n")
            self.stream.flush()
            self.last_line = now
            while self.next_done <= self.done:
                self.next_done += self.step

    def close(self) -> None:
        """Finish the bar (the final plain line has been written by the last update)."""
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["Progress"]
