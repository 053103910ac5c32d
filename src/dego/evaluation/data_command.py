"""``dego data``: data tools. ``dego data write-tree --benchmark NAME OUT`` writes a small
tree of any benchmark (ground truth in its layout, predictions, an infos file for the
nuScenes benchmarks) from procedural street scenes, to try ``dego eval`` before any
download. Exit status 0, or 2 with one ``error:`` line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dego._cli_args import bounded_int
from dego.evaluation.benchmarks import BENCHMARKS, DEFAULT_BENCHMARK

DESCRIPTION = (
    "Data tools. 'write-tree' writes a small synthetic tree of a benchmark (ground truth in "
    "its official layout, predictions, and an infos file for nuScenes benchmarks) to try "
    "'dego eval --benchmark NAME' end to end before any download."
)
EPILOG = "Then: dego eval --benchmark NAME --gt OUT/gt --pred OUT/pred [--infos OUT/...pkl]"


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    parser.add_argument("action", choices=["write-tree"], help="what to do (write-tree)")
    parser.add_argument("out", type=Path, help="the folder to write (gt/, pred/, infos)")
    parser.add_argument(
        "--benchmark",
        choices=list(BENCHMARKS),
        default=DEFAULT_BENCHMARK,
        help=f"the benchmark whose layout is written ({DEFAULT_BENCHMARK})",
    )
    parser.add_argument("--scenes", type=bounded_int(1, 50), default=1, help="scenes (1)")
    parser.add_argument(
        "--frames", type=bounded_int(1, 40), default=2, help="keyframes per scene (2)"
    )
    parser.add_argument("--seed", type=bounded_int(0, 2**31 - 1), default=0, help="seed (0)")
    return parser


def run_command(
    args: argparse.Namespace, parser: argparse.ArgumentParser, created: list[Path]
) -> int:
    from dego.evaluation.trees import write_benchmark_tree

    out = Path(args.out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        print(f"error: {out}: exists and is not an empty folder", file=sys.stderr)
        return 2
    tree = write_benchmark_tree(
        args.benchmark, out, scenes=args.scenes, frames=args.frames, seed=args.seed
    )
    infos = f" --infos {tree.infos}" if tree.infos is not None else ""
    print(f"wrote {tree.samples} {tree.benchmark} samples under {out}")
    print(
        f"score them: dego eval --benchmark {tree.benchmark} --gt {tree.gt} "
        f"--pred {tree.pred}{infos}"
    )
    return 0


__all__ = ["DESCRIPTION", "EPILOG", "add_arguments", "run_command"]
