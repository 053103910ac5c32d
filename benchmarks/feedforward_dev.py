"""`dego train` with any `DataConfig` / `TrainConfig` field set: how the feed-forward
settings were tuned on development seeds (>= 100) before seeds 0-4 were run.

    python benchmarks/feedforward_dev.py --seeds 100 --out DIR \
        --variants single-frame,static,decoupled,velocity,true-motion \
        --set deformation_lr=0.01 --set steps=100 [--cache DIR] [--threads 1]

Writes `DIR/train.md` and `DIR/train.json` (the report of `dego train`, whose settings
record every field). Seeds below 100 are refused: they are the reported ones.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import torch

from dego._cli_args import int_list, name_list
from dego.demo.feedforward import DataConfig, TrainConfig, default_cache
from dego.demo.feedforward.study import (
    PRESETS,
    FeedForwardStudyConfig,
    run_feedforward_study,
    write_feedforward_study,
)

DEVELOPMENT_SEEDS = 100
"""The smallest development seed; seeds 0-99 are kept for reported runs."""


def _value(text: str, like: object) -> object:
    if isinstance(like, bool):
        if text not in ("true", "false"):
            raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")
        return text == "true"
    if isinstance(like, int):
        return int(text)
    if isinstance(like, float):
        return float(text)
    if isinstance(like, tuple):
        return tuple(int(v) for v in text.split("x"))
    return text


def configs(settings: list[str]) -> tuple[DataConfig, TrainConfig]:
    """The CPU default with ``field=value`` settings applied (DataConfig or TrainConfig)."""
    base = PRESETS["cpu"]
    data, train = dataclasses.asdict(base.data), dataclasses.asdict(base.train)
    for item in settings:
        name, _, text = item.partition("=")
        target = data if name in data else train if name in train else None
        if target is None:
            raise SystemExit(f"--set: no DataConfig or TrainConfig field {name!r}")
        target[name] = _value(text, target[name])
    return DataConfig(**data), TrainConfig(**train)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int_list, default=(DEVELOPMENT_SEEDS,))
    parser.add_argument("--variants", type=name_list)
    parser.add_argument("--set", action="append", default=[], help="field=value")
    parser.add_argument("--cache", type=Path, default=default_cache())
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    if min(args.seeds) < DEVELOPMENT_SEEDS:
        parser.error(f"--seeds: development seeds are >= {DEVELOPMENT_SEEDS}")
    torch.set_num_threads(args.threads)
    data, train = configs(args.set)
    config = FeedForwardStudyConfig(
        seeds=tuple(args.seeds),
        variants=tuple(args.variants or PRESETS["cpu"].variants),
        data=data,
        train=train,
    )
    start = time.perf_counter()

    def note(line: str) -> None:
        print(f"[{time.perf_counter() - start:.0f} s] {line}", flush=True)

    result = run_feedforward_study(config, cache=args.cache, note=note)
    text, _ = write_feedforward_study(
        result, config, args.out, wall_seconds=time.perf_counter() - start, device="cpu",
        pictures=False,
    )  # fmt: skip
    print(text)


if __name__ == "__main__":
    main()
