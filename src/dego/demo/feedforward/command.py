"""``dego train``: the argparse definition and the main of the subcommand (the work is the
feed-forward study, :mod:`dego.demo.feedforward.study`)."""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path
from typing import Any

import torch

from dego._cli_args import (
    MAX_ITERATIONS,
    ProgressBar,
    add_device,
    bounded_float,
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
from dego.demo.feedforward.data import MAX_CLIP_SECONDS, default_cache
from dego.demo.feedforward.study import (
    PRESETS,
    FeedForwardStudyConfig,
    feedforward_outputs,
    run_feedforward_study,
    write_feedforward_study,
)
from dego.demo.feedforward.training import DEPTH_SOURCES, FEEDFORWARD_VARIANTS, RECIPES

DESCRIPTION = (
    "The paper's regime in miniature: one small CNN predicts a Gaussian per image block of "
    "six cameras for every synthetic scene (frames 0.5 s apart, as nuScenes' keyframes), "
    "trained from pseudo labels only with dego's splatting and losses: a shared "
    "single-frame warm-up, then single-frame, static, rigid, decoupled (DeGO), velocity "
    "(a constant-velocity rigid branch, beyond the paper) and the true-motion oracle "
    "fine-tuned from it; scored on held-out scenes at t = 0 (IoU, mIoU, InsM, ScnM, HCM, "
    "RayIoU, moving agents, people voxels and blocks). Writes train.md, train.json and "
    "pictures."
)

TRAIN_DURATION = (
    "one seed (render its 80 scenes, a 400-step warm-up, six variants of 100 steps) took "
    "8.5-8.8 minutes on one thread of the 2-core CPU machine with a second run on the "
    "other core, 2.5-3 of them rendering the scenes the first time; --full (seeds 0-4) "
    "took 42 minutes that way; --quick took 10 s on 2 idle cores"
)
"""How long ``dego train`` takes, as its ``--help`` and docs/feedforward.md say it."""

MAX_SCENES = 10_000
"""The most scenes per split ``--train-scenes`` / ``--heldout-scenes`` take."""


EPILOG = f"How long: {TRAIN_DURATION}."


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dego train`` (on an existing (sub)parser)."""
    default, quick, full = PRESETS["cpu"], PRESETS["quick"], PRESETS["full"]
    size = parser.add_mutually_exclusive_group()
    size.add_argument(
        "--quick",
        action="store_true",
        help=f"the wiring only: {quick.data.train_scenes} tiny scenes, {quick.train.steps} steps",
    )
    size.add_argument(
        "--full",
        action="store_true",
        help=f"the study: seeds {format_ints(full.seeds)} (about 42 minutes on one CPU thread)",
    )
    parser.add_argument(
        "--seeds", type=int_list, help=f"seeds, e.g. 0-2 ({format_ints(default.seeds)})"
    )
    parser.add_argument(
        "--variants",
        type=name_list,
        help=f"comma-separated, some of {', '.join(FEEDFORWARD_VARIANTS)} (all)",
    )
    parser.add_argument(
        "--steps",
        type=bounded_int(0, MAX_ITERATIONS),
        help=f"each variant's own optimiser steps ({default.train.steps})",
    )
    parser.add_argument(
        "--warmup-steps",
        type=bounded_int(0, MAX_ITERATIONS),
        help=f"steps of the shared single-frame warm-up ({default.train.warmup_steps})",
    )
    parser.add_argument(
        "--recipe",
        choices=RECIPES,
        help="paired: every variant fine-tuned from the shared warm-up; scratch: each "
        f"trained from the initial weights for warm-up + steps ({default.train.recipe})",
    )
    parser.add_argument(
        "--depth",
        choices=DEPTH_SOURCES,
        help="anchored: each Gaussian's depth along its ray is the t = 0 pseudo depth at its "
        f"pixel; learned: the network's ({default.train.depth_source})",
    )
    parser.add_argument(
        "--frames",
        type=bounded_int(3, MAX_DEMO_FRAMES),
        help=f"frames per scene, odd, the reference in the middle ({default.data.frames})",
    )
    parser.add_argument(
        "--frame-dt",
        type=bounded_float(0.0, MAX_CLIP_SECONDS, open_low=True),
        help=f"seconds between frames ({default.data.frame_dt}; 0.2: the demo's spacing)",
    )
    parser.add_argument(
        "--depth-noise",
        type=bounded_float(0.0, 0.99),
        help="pseudo-depth noise, the relative error at 10 m growing with distance "
        f"({default.data.depth_noise:g}: exact)",
    )
    parser.add_argument(
        "--train-scenes",
        type=bounded_int(1, MAX_SCENES),
        help=f"training scenes per seed ({default.data.train_scenes})",
    )
    parser.add_argument(
        "--heldout-scenes",
        type=bounded_int(1, MAX_SCENES),
        help=f"held-out scenes per seed ({default.data.heldout_scenes})",
    )
    add_device(parser)
    parser.add_argument(
        "--cache",
        type=Path,
        default=None,
        help=f"folder of the rendered scenes ({default_cache()})",
    )
    parser.add_argument("--no-cache", action="store_true", help="render the scenes, keep none")
    parser.add_argument(
        "--out", type=Path, default=Path("dego-train"), help="output folder (./dego-train)"
    )
    parser.add_argument("--no-pictures", action="store_true", help="skip the pictures")
    return parser


def study_config(args: argparse.Namespace) -> FeedForwardStudyConfig:
    """The study the flags ask for (``ValueError`` naming a field on a bad value)."""
    base = PRESETS["quick" if args.quick else "full" if args.full else "cpu"]
    changes: dict[str, Any] = {}
    if args.seeds is not None:
        changes["seeds"] = args.seeds
    if args.variants is not None:
        changes["variants"] = args.variants
    data = {
        name: getattr(args, name)
        for name in ("train_scenes", "heldout_scenes", "frames", "frame_dt", "depth_noise")
        if getattr(args, name) is not None
    }
    if data:
        changes["data"] = dataclasses.replace(base.data, **data)
    train = {
        field: getattr(args, flag)
        for field, flag in (
            ("steps", "steps"),
            ("warmup_steps", "warmup_steps"),
            ("recipe", "recipe"),
            ("depth_source", "depth"),
        )
        if getattr(args, flag) is not None
    }
    if train:
        changes["train"] = dataclasses.replace(base.train, **train)
    return dataclasses.replace(base, **changes)


def run_command(
    args: argparse.Namespace, parser: argparse.ArgumentParser, created: list[Path]
) -> int:
    """``dego train``: check the flags, create ``--out`` and the cache, check every output
    file, run, write (all or nothing). A file that cannot be written at the end (a full
    disk, ``--out`` made read-only meanwhile) is one ``error:`` line and exit status 1."""
    try:
        config = study_config(args)
    except ValueError as error:
        config_error(parser, error)
    cache = None
    if not args.no_cache:
        cache = args.cache if args.cache is not None else default_cache()
        try:
            cache.mkdir(parents=True, exist_ok=True)
            probe = cache / f".dego-write-test-{time.time_ns()}"
            probe.touch()
            probe.unlink()
        except OSError as error:
            parser.error(f"--cache: {cache}: {error.strerror or error}")
    created += output_dir(parser, "--out", args.out)
    outputs = feedforward_outputs(args.out, config.variants, pictures=not args.no_pictures)
    check_outputs(parser, [("--out", path) for path in outputs], created)
    data, training = config.data, config.train
    print(
        f"dego {__version__} train: seeds {format_ints(config.seeds)}, variants "
        f"{', '.join(config.variants)}; {data.train_scenes} training + {data.heldout_scenes} "
        f"held-out scenes per seed of {data.frames} frames {data.frame_dt:g} s apart; "
        f"{training.recipe} recipe ({training.warmup_steps} warm-up + {training.steps} steps), "
        f"depth {training.depth_source}; {args.device}; scenes cached in "
        f"{cache if cache is not None else '(nowhere: --no-cache)'}",
        flush=True,
    )
    start = time.perf_counter()
    bars: dict[str, ProgressBar] = {}

    def progress(label: str, step: int, total: int, loss: float) -> None:
        if label not in bars:
            bars[label] = ProgressBar(label, total)
        bars[label](step, {} if math.isnan(loss) else {"total": loss})

    def note(line: str) -> None:
        print(f"[{time.perf_counter() - start:.0f} s] {line}", flush=True)

    device = str(args.device)
    result = run_feedforward_study(
        config, cache=cache, device=torch.device(device), progress=progress, note=note
    )
    wall = time.perf_counter() - start
    try:
        report, paths = write_feedforward_study(
            result,
            config,
            args.out,
            wall_seconds=wall,
            device=device,
            pictures=not args.no_pictures,
        )
    except OSError as error:  # a full disk, --out made read-only during the run
        where = error.filename if error.filename is not None else args.out
        print(
            f"error: cannot write {where}: {error.strerror or error}; "
            f"the previous files in {args.out} are as they were",
            file=sys.stderr,
        )
        return 1
    print(report)
    print(f"wrote {', '.join(str(p) for p in paths)}")
    # the whole command, the report and pictures included, as dego demo and dego study
    # print it (the report's own wall time cannot count its writing)
    print(f"total {time.perf_counter() - start:.1f} s")
    return 0
