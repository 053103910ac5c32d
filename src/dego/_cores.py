"""The CPUs this process may run on: what ``--threads auto`` and ``dego eval``'s workers
divide."""

from __future__ import annotations

import os


def usable_cores() -> int:
    """The CPUs this process may run on (its affinity where the system has one)."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


__all__ = ["usable_cores"]
