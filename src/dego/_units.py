"""Units and keys of scores.

Scores live in Python as fractions in [0, 1] under lower-case keys (``iou``, ``miou``,
``insm``, ``rayiou``, ``rayiou@1``, ``iou/<class>``): report attributes, ``as_dict()``,
``headline()``, the torchmetrics wrappers and what a logger records from them (as
torchmetrics does). dego's own reports for people, every table, Markdown and JSON report
of ``dego eval``, ``dego demo`` and ``dego study``, show percent and say so
(``"units": "percent"``), to compare with the papers' tables.
"""

from __future__ import annotations

import math
import warnings

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


def warn_percent_keys(call: str) -> None:
    """The deprecation of ``as_dict(percent=True)``: percent under keys that hold fractions
    everywhere else."""
    warnings.warn(
        f"{call} puts percentages under the keys that hold fractions everywhere else "
        "(headline(), the torchmetrics wrappers, loggers); print table() for the papers' "
        "numbers, or scale as_dict() yourself. percent=True is removed in dego 0.3.",
        FutureWarning,
        stacklevel=3,
    )
