"""Statistics of the seeded studies (``dego study``, ``dego train``): 95% Student-t
intervals over seeds, paired differences, the run record and the checks of seed lists.

Below both studies (:mod:`dego.demo.study`, :mod:`dego.demo.feedforward.study`), which
import it; it imports neither.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

from dego._checks import check_int, repeated_values
from dego.demo.fit import MAX_SEED


@dataclasses.dataclass(frozen=True)
class StudyRun:
    """One fit: its settings, scores (percent) and mask statistics."""

    seed: int
    budget: int
    variant: str
    scores: dict[str, float]
    mask: dict[str, float]
    per_articulated_agent: float
    seconds: float


def check_distinct(name: str, values: tuple) -> None:
    """``values`` of the config field ``name`` is not empty and names each value once."""
    if not values:
        raise ValueError(f"{name}: expected at least one value, got {values!r}")
    repeated = repeated_values(values)
    if repeated:
        raise ValueError(f"{name}: {', '.join(map(str, repeated))} repeated; each value runs once")


def check_seeds(seeds: tuple[int, ...]) -> None:
    """Every one of ``seeds`` is an int in ``[0, MAX_SEED]``."""
    for seed in seeds:
        if check_int("seeds", seed, 0) > MAX_SEED:
            raise ValueError(f"seeds: expected ints in [0, {MAX_SEED}], got {seed!r}")


# Two-sided 95% quantiles of Student's t for 1..30 degrees of freedom.
_T975 = (
    12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228,
    2.201, 2.179, 2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086,
    2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042,
)  # fmt: skip


MIN_INTERVAL_SEEDS = 3
"""The fewest values whose interval the report prints. With 2 the t quantile is 12.7 and
the interval is wider than the range of a bounded quantity (``mask AUC 0.70 [-0.86,
2.27]``): the report prints ``n/a (2 seeds)`` instead and marks no sign as resolved; the
JSON keeps the plain t-interval with its ``n``."""


@dataclasses.dataclass(frozen=True)
class Interval:
    """A mean with its 95% Student-t confidence interval over ``n`` values."""

    mean: float
    low: float
    high: float
    n: int

    def excludes_zero(self) -> bool:
        """Whether the interval resolves the sign: it excludes 0 and rests on at least
        :data:`MIN_INTERVAL_SEEDS` values."""
        return self.n >= MIN_INTERVAL_SEEDS and (self.low > 0 or self.high < 0)

    def __str__(self) -> str:
        if math.isnan(self.mean):
            return "nan"
        if self.n < 2:
            return f"{self.mean:.2f}"
        if self.n < MIN_INTERVAL_SEEDS:
            return f"{self.mean:.2f} [n/a ({self.n} seeds)]"
        return f"{self.mean:.2f} [{self.low:.2f}, {self.high:.2f}]"


def mean_interval(values: Sequence[float]) -> Interval:
    """Mean and 95% t-interval of the finite ``values`` (NaNs are dropped)."""
    finite = [v for v in values if not math.isnan(v)]
    n = len(finite)
    if n == 0:
        return Interval(math.nan, math.nan, math.nan, 0)
    mean = sum(finite) / n
    if n == 1:
        return Interval(mean, math.nan, math.nan, 1)
    sd = math.sqrt(sum((v - mean) ** 2 for v in finite) / (n - 1))
    t = _T975[n - 2] if n - 1 <= len(_T975) else 1.96
    half = t * sd / math.sqrt(n)
    return Interval(mean, mean - half, mean + half, n)


def paired_differences(
    runs: Sequence[StudyRun], metric: str, first: str, second: str
) -> dict[int, Interval]:
    """Per budget: ``first - second`` on ``metric``, paired by seed, with its interval."""
    table = {(r.seed, r.budget, r.variant): r for r in runs}
    out = {}
    for budget in sorted({r.budget for r in runs}):
        differences = [
            table[seed, budget, first].scores[metric] - table[seed, budget, second].scores[metric]
            for seed in sorted({r.seed for r in runs})
            if (seed, budget, first) in table and (seed, budget, second) in table
        ]
        out[budget] = mean_interval(differences)
    return out


def json_safe(value: object) -> object:
    """NaN -> None, recursively (JSON has no NaN)."""
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value
