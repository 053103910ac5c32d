"""Argument checks shared by constructors: each raises ValueError naming the argument."""

from __future__ import annotations

import math


def check_int(name: str, value: object, low: int | None = None) -> int:
    """``value`` as an int (bools rejected), at least ``low`` when given."""
    if isinstance(value, bool) or not isinstance(value, int) or (low is not None and value < low):
        expected = "an int" if low is None else f"an int >= {low}"
        raise ValueError(f"{name}: expected {expected}, got {value!r}")
    return value


def check_positive(name: str, value: object) -> float:
    """``value`` as a finite float > 0."""
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or value <= 0
    ):
        raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")
    return float(value)


def repeated_values(values: tuple) -> list:
    """The values that occur more than once, in order of first appearance."""
    return sorted({v for v in values if values.count(v) > 1}, key=values.index)
