"""The demo page's multi-seed tables, from a ``dego study`` run at the demo's budget.

``dego study --seeds 0-4 --budgets 2500 --frames 5 --iterations 150`` fits exactly what
``dego demo --seed S`` fits for S = 0-4 (same clips, same FitConfig, same seeds), so its
``study.json`` holds the demo's numbers over seeds::

    python docs/demo_tables.py dego-study/study.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from dego.demo import row_name
from dego.demo.study import METRICS, STUDY_VARIANTS, Interval, mean_interval

GAINS = ("rigid", "decoupled", "free-offsets", "free-velocities", "true-motion", "single-frame")
PAIRED = (
    "articulated t=±1",
    "articulated t=±2+",
    "vehicles t=±1",
    "vehicles t=±2+",
    "HCM t=0",
    "mIoU t=0",
)
PER_SEED = ("articulated t=±1", "vehicles t=±1", "HCM t=0")


def tables(payload: dict) -> str:
    runs = payload["runs"]
    seeds = sorted({r["seed"] for r in runs})
    variants = [v for v in STUDY_VARIANTS if any(r["variant"] == v for r in runs)]

    def values(variant: str, metric: str) -> dict[int, float]:
        return {r["seed"]: r["scores"][metric] for r in runs if r["variant"] == variant}

    def interval(xs: list[float | None]) -> Interval:
        return mean_interval([float("nan") if x is None else x for x in xs])

    lines = [f"Mean over seeds {seeds[0]}-{seeds[-1]}, percent:", ""]
    lines += ["| variant | " + " | ".join(METRICS) + " |", "|---|" + "---:|" * len(METRICS)]
    for v in variants:
        cells = [f"{interval(list(values(v, m).values())).mean:.1f}" for m in METRICS]
        lines.append(f"| {row_name(v)} | " + " | ".join(cells) + " |")
    lines += ["", "Gain over static, paired by seed, points, mean [95% t-interval]:", ""]
    lines += ["| variant - static | " + " | ".join(PAIRED) + " |", "|---|" + "---|" * len(PAIRED)]
    for v in (g for g in GAINS if g in variants):
        cells = []
        for m in PAIRED:
            a, b = values(v, m), values("static", m)
            diff = interval(
                [a[s] - b[s] for s in seeds if a.get(s) is not None and b.get(s) is not None]
            )
            cells.append(f"{diff}{' *' if diff.excludes_zero() else ''}")
        lines.append(f"| {row_name(v)} | " + " | ".join(cells) + " |")
    lines += ["", f"Per seed, {' / '.join(PER_SEED)}:", ""]
    lines += ["| seed | " + " | ".join(row_name(v) for v in variants) + " |"]
    lines += ["|---:|" + "---|" * len(variants)]
    for s in seeds:
        cells = [" / ".join(f"{values(v, m)[s]:.1f}" for m in PER_SEED) for v in variants]
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(tables(json.loads(Path(sys.argv[1]).read_text())))
