"""``dego study``: the argparse definition and the main of the subcommand
(:func:`~dego.demo.study.run_study` does the work)."""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import torch

from dego._cli_args import (
    MAX_ITERATIONS,
    UsageError,
    add_device,
    bounded_int,
    check_outputs,
    config_error,
    format_ints,
    int_list,
    name_list,
    output_dir,
)
from dego._version import __version__
from dego.demo.clip import MAX_DEMO_FRAMES
from dego.demo.study.report import study_outputs, write_study
from dego.demo.study.runner import QUICK_STUDY, STUDY_VARIANTS, StudyConfig, run_study

DESCRIPTION = (
    "When does decoupling pay off? Fits the static, rigid and decoupled variants and the "
    "reference rows (single-frame, free offsets, free velocities, true motion) over seeds "
    "and Gaussian budgets, scores them at every frame and reports means with 95% confidence "
    "intervals and paired differences."
)

STUDY_DURATION = (
    "with the defaults, about 5-16 minutes per seed (2 budgets x 6 fits) on 2 CPU cores: "
    "55 min 14 s for seeds 0-9 on one thread beside another job, 16 min for seed 0 beside "
    "a test run; the time grows with the seeds, budgets, variants, frames and iterations, "
    "and --quick takes about a minute on idle cores"
)
"""How long ``dego study`` takes, as its ``--help`` and docs/study.md say it (the tests check
that they agree). The 55 minutes are docs/performance.md's "The study"; the 16 minutes were
timed for this text (``dego study --seeds 0``, 961 s, 1.26 GB peak, beside a test run)."""

EPILOG = f"How long: {STUDY_DURATION}."


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dego study`` (on an existing (sub)parser)."""
    default, quick_study = StudyConfig(), QUICK_STUDY
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"tiny settings (seeds {format_ints(quick_study.seeds)}, budgets "
        f"{format_ints(quick_study.budgets)}, {quick_study.iterations} iterations)",
    )
    parser.add_argument(
        "--seeds",
        type=int_list,
        help=f"seeds, e.g. 0-7 or 0,3,5 ({format_ints(default.seeds)})",
    )
    parser.add_argument(
        "--budgets",
        type=int_list,
        help=f"total Gaussians per fit, e.g. 1000,3000 ({format_ints(default.budgets)})",
    )
    parser.add_argument(
        "--frames",
        type=bounded_int(2, MAX_DEMO_FRAMES),
        help=f"frames per clip, 2-{MAX_DEMO_FRAMES} ({default.frames})",
    )
    parser.add_argument(
        "--iterations",
        type=bounded_int(0, MAX_ITERATIONS),
        help=f"optimiser steps per fit, 0-{MAX_ITERATIONS:,} ({default.iterations})",
    )
    parser.add_argument(
        "--variants",
        type=name_list,
        help=f"comma-separated, some of {', '.join(STUDY_VARIANTS)} ({','.join(default.variants)})",
    )
    parser.add_argument(
        "--mask-prior",
        type=float,
        help=f"weight of the mask sparsity prior of decoupled+prior ({default.mask_prior})",
    )
    add_device(parser)
    parser.add_argument(
        "--out", type=Path, default=Path("dego-study"), help="output folder (./dego-study)"
    )
    parser.add_argument("--no-pictures", action="store_true", help="skip the plot")
    return parser


def run_command(
    args: argparse.Namespace, parser: argparse.ArgumentParser, created: list[Path]
) -> int:
    """``dego study``: check the flags, create ``--out``, run the study, write its report.
    ``created``: where the folders made for ``--out`` are recorded."""
    base = QUICK_STUDY if args.quick else StudyConfig()
    changes = {
        name: getattr(args, name)
        for name in ("seeds", "budgets", "frames", "iterations", "variants", "mask_prior")
        if getattr(args, name) is not None
    }
    try:
        config = dataclasses.replace(base, **changes)
    except ValueError as error:
        config_error(parser, error)
    created += output_dir(parser, "--out", args.out)
    outputs = study_outputs(args.out, pictures=not args.no_pictures)
    check_outputs(parser, [("--out", path) for path in outputs], created)
    runs = len(config.seeds) * len(config.budgets) * len(config.variants)
    fits = len(config.seeds) * len(config.budgets) * len(set(config.variants) - {"lifted-labels"})
    print(
        f"dego {__version__} study: {runs} runs, {fits} of them fits (seeds "
        f"{format_ints(config.seeds)}, budgets {format_ints(config.budgets)}, "
        f"variants {', '.join(config.variants)}), "
        f"{config.frames} frames, {config.iterations} iterations each, {args.device}"
    )
    start = time.perf_counter()
    done = []

    def progress(line: str) -> None:
        done.append(line)
        print(f"[{len(done)}/{runs} {time.perf_counter() - start:.0f} s] {line}", flush=True)

    try:
        results = run_study(config, progress=progress, device=torch.device(args.device))
    except ValueError as error:
        if not str(error).startswith("num_gaussians: "):
            raise
        raise UsageError("--budgets", str(error).removeprefix("num_gaussians: ")) from None
    report, paths = write_study(results, config, args.out, pictures=not args.no_pictures)
    print(report)
    print(f"wrote {', '.join(str(p) for p in paths)}")
    print(f"total {time.perf_counter() - start:.1f} s")
    return 0
