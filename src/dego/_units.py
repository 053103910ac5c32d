"""The one unit of every score dego prints or writes: percent.

Scores live in Python as fractions in [0, 1] (report attributes, ``as_dict()``, the
torchmetrics wrappers, as torchmetrics does); every table, Markdown and JSON report
(``dego eval``, ``dego demo``, ``dego study``) shows them in percent and says so.
"""

from __future__ import annotations

import math

UNIT = "percent"
"""The unit named in report headings and in the ``"units"`` field of JSON reports."""


def percent(value: float) -> float:
    """A fraction as a percentage (NaN stays NaN)."""
    return 100.0 * value


def percent_or_none(value: float) -> float | None:
    """:func:`percent` for JSON: ``None`` (``null``) for NaN."""
    return None if math.isnan(value) else percent(value)


def percent_text(value: float) -> str:
    """A fraction as a percentage with 2 decimals, ``"-"`` for NaN (a class absent from
    ground truth and predictions)."""
    return "-" if math.isnan(value) else f"{percent(value):.2f}"
