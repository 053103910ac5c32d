"""The ``dego`` command: ``demo``, ``study``, ``train``, ``eval`` and ``view``.

``dego demo`` runs DeGO end to end on a synthetic clip: it renders the clip, fits
canonical Gaussians from the pseudo labels only without deformation, with a rigid-only
and with a decoupled deformation, voxelises them at every frame, scores them against
each frame's ground truth (weak protocol, RayIoU, moving agents), prints one table and
writes pictures. ``dego study`` repeats the fits over seeds and Gaussian budgets and
reports means with confidence intervals. ``dego train`` trains a feed-forward network on
many scenes with and without deformation (:mod:`dego.demo.feedforward`). ``dego eval``
scores a folder of Occ3D-nuScenes predictions (:mod:`dego.evaluation.command`).
``--rerun FILE.rrd`` on ``dego demo`` and ``dego eval`` records what they computed for
rerun's viewer, which ``dego view`` opens (:mod:`dego.viz.rerun`).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TextIO

import torch

from dego._atomic import check_output_file, remove_empty_dirs, write_files
from dego._cli_args import MAX_ITERATIONS, ProgressBar
from dego._cli_args import MAX_LIST_VALUES as MAX_LIST_VALUES  # re-exported: the docs' bound
from dego._cli_args import add_device as _add_device
from dego._cli_args import format_ints as _format_ints
from dego._cli_args import int_list as _int_list
from dego._cli_args import name_list as _name_list
from dego._cli_args import output_dir as _output_dir
from dego._version import __version__
from dego.data.synthetic import SyntheticScene
from dego.demo import (
    DEMO_FRAME_DT,
    VARIANTS,
    ClipScore,
    DemoClip,
    FitConfig,
    FitResult,
    fit_iterations,
    fit_scene,
    format_table,
    initial_model,
    lifted_clip_labels,
    mask_by_group,
    predict_clip,
    rigidity_mask,
    row_name,
    score_clip,
)
from dego.demo.clip import MAX_DEMO_FRAMES, max_gaussians
from dego.demo.feedforward.command import add_train_parser, train_main
from dego.demo.fit import MAX_SEED
from dego.evaluation import command as eval_command
from dego.study import QUICK_STUDY, STUDY_VARIANTS, StudyConfig, run_study, write_study
from dego.viz.eval_recording import DEFAULT_LIMIT, MAX_RECORDED_SAMPLES

PROGRAM_DESCRIPTION = (
    "Run Deformable Gaussian Occupancy (DeGO) end to end on synthetic driving clips. "
    "'dego demo' fits static, rigid and decoupled Gaussians (and reference rows) to one clip "
    "and scores them; 'dego study' repeats the fits over seeds and Gaussian budgets; "
    "'dego train' trains a feed-forward network on many clips with and without deformation; "
    "'dego eval' scores a folder of Occ3D-nuScenes predictions; 'dego view' opens a "
    "recording of demo or eval (--rerun) in rerun's viewer."
)
DEMO_DESCRIPTION = (
    "Fit static, rigid and decoupled Gaussians to a synthetic clip from its pseudo labels, "
    "beside four reference rows (single-frame, free offsets, free velocities and the "
    "ground-truth true motion), score them at every frame against the ground truth, print "
    "one table and each variant's gain over static, and write results.md, results.json and "
    "pictures."
)
STUDY_DESCRIPTION = (
    "When does decoupling pay off? Fits the static, rigid and decoupled variants and the "
    "reference rows (single-frame, free offsets, free velocities, true motion) over seeds "
    "and Gaussian budgets, scores them at every frame and reports means with 95% confidence "
    "intervals and paired differences."
)

BUDGETS = {
    "quick": {"frames": 3, "iterations": 30, "gaussians": 1000},
    "full": {"frames": 5, "iterations": 150, "gaussians": 2500},
}
"""Default clip length, iterations per variant and Gaussians of ``--quick`` and the full run."""

DURATIONS = {
    "quick": "56 s wall on 2 idle CPU cores; more when other jobs share the cores",
    "full": "3 minutes wall on 2 idle CPU cores; 5-6 minutes on one thread beside another job",
}
"""How long each :data:`BUDGETS` entry takes, as ``--help`` and docs/demo.md say it (the
tests check that they agree); measured on docs/performance.md's "The demo"."""

STUDY_DURATION = (
    "with the defaults, about 5-16 minutes per seed (2 budgets x 6 fits) on 2 CPU cores: "
    "55 min 14 s for seeds 0-9 on one thread beside another job, 16 min for seed 0 beside "
    "a test run; the time grows with the seeds, budgets, variants, frames and iterations, "
    "and --quick takes about a minute on idle cores"
)
"""How long ``dego study`` takes, as its ``--help`` and docs/study.md say it (the tests check
that they agree). The 55 minutes are docs/performance.md's "The study"; the 16 minutes were
timed for this text (``dego study --seeds 0``, 961 s, 1.26 GB peak, beside a test run)."""


INTERRUPTED_STATUS = 130
"""Exit status after Ctrl-C (128 + SIGINT, as shells report it)."""


class UsageError(Exception):
    """A flag's value found wrong once the work has looked at the data: ``flag`` and a
    one-line ``message``; :func:`main` reports it as a usage error (exit status 2)."""

    def __init__(self, flag: str, message: str) -> None:
        super().__init__(f"{flag}: {message}")
        self.flag, self.message = flag, message


def describe_budget(name: str) -> str:
    """``"3 frames, 2,500 Gaussians, 80 iterations per variant"``: how the docs and
    ``--help`` name a :data:`BUDGETS` entry (the tests check that the docs agree)."""
    budget = BUDGETS[name]
    return (
        f"{budget['frames']} frames, {budget['gaussians']:,} Gaussians, "
        f"{budget['iterations']} iterations per variant"
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dego", description=PROGRAM_DESCRIPTION)
    parser.add_argument("--version", action="version", version=f"dego {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser(
        "demo",
        help="fit static, rigid and decoupled Gaussians to a synthetic clip and score them",
        description=DEMO_DESCRIPTION,
        epilog=f"Without --quick: {describe_budget('full')} ({DURATIONS['full']}).",
    )
    quick, full = BUDGETS["quick"], BUDGETS["full"]
    demo.add_argument(
        "--quick",
        action="store_true",
        help=f"a smaller budget: {describe_budget('quick')} ({DURATIONS['quick']})",
    )
    demo.add_argument(
        "--seed", type=_seed, default=0, help=f"scene and fitting seed, 0-{MAX_SEED} (0)"
    )
    demo.add_argument(
        "--frames",
        type=_demo_frames,
        help=f"frames of the clip, 2-{MAX_DEMO_FRAMES} ({full['frames']}; quick {quick['frames']})",
    )
    demo.add_argument(
        "--iterations",
        type=eval_command.bounded_int(0, MAX_ITERATIONS),
        help=f"optimiser steps per variant, 0-{MAX_ITERATIONS:,} ({full['iterations']}; "
        f"quick {quick['iterations']})",
    )
    demo.add_argument(
        "--gaussians",
        type=eval_command.bounded_int(1, max_gaussians(MAX_DEMO_FRAMES)),
        help=f"canonical Gaussians, at most one per camera pixel of the clip "
        f"({full['gaussians']}; quick {quick['gaussians']})",
    )
    _add_device(demo)
    demo.add_argument(
        "--out", type=Path, default=Path("dego-demo"), help="output folder (./dego-demo)"
    )
    demo.add_argument("--no-pictures", action="store_true", help="skip the pictures")
    demo.add_argument(
        "--rerun",
        type=Path,
        metavar="FILE.rrd",
        help="also record the clip, the ground truth and every variant's predictions and "
        "Gaussians over the frames for rerun's viewer (open it with: dego view FILE.rrd)",
    )
    demo.set_defaults(command_parser=demo)

    default, quick_study = StudyConfig(), QUICK_STUDY
    study = commands.add_parser(
        "study",
        help="when does decoupling pay off? variants x seeds x Gaussian budgets, with CIs",
        description=STUDY_DESCRIPTION,
        epilog=f"How long: {STUDY_DURATION}.",
    )
    study.add_argument(
        "--quick",
        action="store_true",
        help=f"tiny settings (seeds {_format_ints(quick_study.seeds)}, budgets "
        f"{_format_ints(quick_study.budgets)}, {quick_study.iterations} iterations)",
    )
    study.add_argument(
        "--seeds",
        type=_int_list,
        help=f"seeds, e.g. 0-7 or 0,3,5 ({_format_ints(default.seeds)})",
    )
    study.add_argument(
        "--budgets",
        type=_int_list,
        help=f"total Gaussians per fit, e.g. 1000,3000 ({_format_ints(default.budgets)})",
    )
    study.add_argument(
        "--frames",
        type=eval_command.bounded_int(2, MAX_DEMO_FRAMES),
        help=f"frames per clip, 2-{MAX_DEMO_FRAMES} ({default.frames})",
    )
    study.add_argument(
        "--iterations",
        type=eval_command.bounded_int(0, MAX_ITERATIONS),
        help=f"optimiser steps per fit, 0-{MAX_ITERATIONS:,} ({default.iterations})",
    )
    study.add_argument(
        "--variants",
        type=_name_list,
        help=f"comma-separated, some of {', '.join(STUDY_VARIANTS)} ({','.join(default.variants)})",
    )
    study.add_argument(
        "--mask-prior",
        type=float,
        help=f"weight of the mask sparsity prior of decoupled+prior ({default.mask_prior})",
    )
    _add_device(study)
    study.add_argument(
        "--out", type=Path, default=Path("dego-study"), help="output folder (./dego-study)"
    )
    study.add_argument("--no-pictures", action="store_true", help="skip the plot")
    study.set_defaults(command_parser=study)
    add_train_parser(commands)
    evaluation = commands.add_parser(
        "eval",
        help="score Occ3D-nuScenes predictions: mIoU, IoU, InsM/ScnM/HCM, RayIoU",
        description=eval_command.DESCRIPTION,
        epilog=eval_command.EPILOG,
    )
    eval_command.add_arguments(evaluation)
    recording = evaluation.add_argument_group("recording for rerun's viewer")
    recording.add_argument(
        "--rerun",
        type=Path,
        metavar="FILE.rrd",
        help="also record ground truth beside prediction for the first --limit samples",
    )
    recording.add_argument(
        "--limit",
        type=eval_command.bounded_int(1, MAX_RECORDED_SAMPLES),
        help=f"samples --rerun records, 1-{MAX_RECORDED_SAMPLES:,} ({DEFAULT_LIMIT}); "
        "every sample is still scored",
    )
    evaluation.set_defaults(command_parser=evaluation)
    view = commands.add_parser(
        "view",
        help="open a .rrd recording (dego demo --rerun, dego eval --rerun) in rerun's viewer",
        description="Open a rerun recording in rerun's viewer: the native viewer where there "
        "is a screen, or with --web rerun's web viewer, served from this machine.",
    )
    view.add_argument("file", type=Path, metavar="FILE.rrd", help="the recording")
    view.add_argument(
        "--web", action="store_true", help="serve rerun's web viewer instead (headless, SSH)"
    )
    view.set_defaults(command_parser=view)
    return parser


def _demo_frames(text: str) -> int:
    """``dego demo --frames``: an int in ``[2, MAX_DEMO_FRAMES]``. One frame is refused
    with its reason: the demo scores the deformation at the frames other than the
    reference frame, and a one-frame clip has none (its ``t=±1`` columns and the gains
    on them would be undefined)."""
    if eval_command.parse_int(text) == 1:
        raise argparse.ArgumentTypeError(
            "expected at least 2: the demo scores the deformation at the frames other than "
            "the reference frame (the t=±1 columns), and a 1-frame clip has none"
        )
    return eval_command.bounded_int(2, MAX_DEMO_FRAMES)(text)


def _seed(text: str) -> int:
    """A seed: an int in ``[0, MAX_SEED]``."""
    value = eval_command.parse_int(text)
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"expected a seed in [0, {MAX_SEED}], got {text!r}")
    return value


def study_main(
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
        field, _, message = str(error).partition(": ")
        parser.error(f"--{field.replace('_', '-')}: {message or error}")
    created += _output_dir(parser, "--out", args.out)
    runs = len(config.seeds) * len(config.budgets) * len(config.variants)
    fits = len(config.seeds) * len(config.budgets) * len(set(config.variants) - {"lifted-labels"})
    print(
        f"dego {__version__} study: {runs} runs, {fits} of them fits (seeds "
        f"{_format_ints(config.seeds)}, budgets {_format_ints(config.budgets)}, "
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


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``dego`` console script.

    Every flag is checked, and the output folder created, before any work starts: a bad
    value is a usage error (exit status 2, one ``error:`` line naming the flag). Ctrl-C
    ends any command with exit status 130 and one line, ``dego: interrupted``, on
    stderr; the outputs are written all or nothing at the end, and output folders the
    command made itself are removed again when it ends without filling them."""
    created: list[Path] = []
    try:
        code = _dispatch(argv, created)
    except KeyboardInterrupt:
        with _SigintIgnored():  # a second Ctrl-C does not cut the cleanup short
            remove_empty_dirs(created)
            print(("\n" if _isatty(sys.stderr) else "") + "dego: interrupted", file=sys.stderr)
        return INTERRUPTED_STATUS
    except BaseException:
        remove_empty_dirs(created)
        raise
    if code != 0:
        remove_empty_dirs(created)
    return code


def _dispatch(argv: list[str] | None, created: list[Path]) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    command_parser: argparse.ArgumentParser = args.command_parser
    if args.command != "eval":  # dego eval applies its own (dego.evaluation.command.run)
        eval_command.apply_threads(getattr(args, "threads", None))
    try:
        if args.command == "study":
            return study_main(args, command_parser, created)
        if args.command == "eval":
            return eval_main(args, command_parser, created)
        if args.command == "view":
            return view_main(args, command_parser)
        if args.command == "train":
            return train_main(args, command_parser, created)
        return demo_main(args, command_parser, created)
    except UsageError as error:
        command_parser.error(str(error))


def demo_main(
    args: argparse.Namespace, parser: argparse.ArgumentParser, created: list[Path]
) -> int:
    """``dego demo``: check the flags, create ``--out``, run the demo."""
    budget = dict(BUDGETS["quick" if args.quick else "full"])
    for name in budget:
        if getattr(args, name) is not None:
            budget[name] = getattr(args, name)
    most = max_gaussians(budget["frames"])
    if budget["gaussians"] > most:
        parser.error(
            f"--gaussians: expected at most {most} for {budget['frames']} frame(s) (one per "
            f"camera pixel of the clip), got {budget['gaussians']}"
        )
    created += _output_dir(parser, "--out", args.out)
    created += _rerun_target(parser, args.rerun)
    device = torch.device(args.device)
    return run_demo(
        args.seed, budget, device, args.out, pictures=not args.no_pictures, rerun=args.rerun
    )


def _rerun_target(parser: argparse.ArgumentParser, path: Path | None) -> list[Path]:
    """Check ``--rerun`` before any work (rerun-sdk present, a ``.rrd`` file that can be
    written; its folder is created) or exit with a usage error; returns the folders made."""
    if path is None:
        return []
    if importlib.util.find_spec("rerun") is None:
        parser.error('--rerun: needs rerun-sdk: pip install "dego-occupancy[rerun]"')
    if path.suffix != ".rrd":
        parser.error(f"--rerun: expected a file name ending in .rrd, got {str(path)!r}")
    try:
        return check_output_file(path)
    except OSError as error:
        parser.error(f"--rerun: {error.strerror or error}")


def eval_main(
    args: argparse.Namespace, parser: argparse.ArgumentParser, created: list[Path]
) -> int:
    """``dego eval``: score (:func:`dego.evaluation.command.run`), then, with ``--rerun``,
    record the first ``--limit`` samples (rank 0 only under torchrun)."""
    if args.limit is not None and args.rerun is None:
        parser.error("--limit: only with --rerun (every sample is scored either way)")
    created += _rerun_target(parser, args.rerun)
    code = eval_command.run(args, created=created)
    if args.rerun is None or code == 2 or os.environ.get("RANK", "0") != "0":
        return code
    from dego.viz.eval_recording import record_samples

    start = time.perf_counter()
    recorded = record_samples(
        args.rerun,
        args.gt,
        args.pred,
        limit=DEFAULT_LIMIT if args.limit is None else args.limit,
        infos=args.infos,
        missing=args.missing,
    )
    print(
        f"wrote {recorded.path} ({recorded.recorded} samples, "
        f"{recorded.path.stat().st_size / 1e6:.1f} MB, {time.perf_counter() - start:.1f} s)"
    )
    for token, reason in recorded.failed.items():
        print(f"  not recorded: {token}: {reason}", file=sys.stderr)
    return code


def view_main(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """``dego view FILE.rrd [--web]``: open the recording; 1 with one line where no viewer
    can start here."""
    from dego.viz.viewer import ViewerUnavailableError, check_recording, open_viewer

    try:
        check_recording(args.file)
    except ValueError as error:
        parser.error(str(error))
    try:
        return open_viewer(args.file, web=args.web)
    except ViewerUnavailableError as error:
        print(f"dego view: {error}", file=sys.stderr)
        return 1


def _isatty(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


class _SigintIgnored:
    """Ignore SIGINT inside the block (main thread only), then restore the handler."""

    def __enter__(self) -> None:
        self.previous = None
        if threading.current_thread() is threading.main_thread():
            self.previous = signal.signal(signal.SIGINT, signal.SIG_IGN)

    def __exit__(self, *exc: object) -> None:
        if self.previous is not None:
            signal.signal(signal.SIGINT, self.previous)


LIFTED_ROW = row_name("lifted-labels")
"""The table's ceiling row: each frame's own pseudo labels lifted to 3D."""

PICTURED_VARIANTS = ("static", "rigid", "decoupled", "true-motion")
"""Variants whose BEV at the last frame ``dego demo`` draws."""

DEMO_VARIANTS = ("single-frame", *VARIANTS, "free-offsets", "free-velocities", "true-motion")
"""What ``dego demo`` fits, in table order: the fitted variants between their references."""

GAIN_COLUMNS = (
    "articulated t=±1",
    "articulated t=±2+",
    "vehicles t=±1",
    "vehicles t=±2+",
    "HCM",
    "mIoU",
)
"""The columns of the demo's "gain over static" lines (HCM, mIoU: at t = 0)."""


def paired_gains(scores: dict[str, ClipScore]) -> list[str]:
    """One line per variant: its gain over ``static`` (points) on :data:`GAIN_COLUMNS`
    (a column the clip does not have, such as ``t=±2+`` of a 3-frame clip, is left out)."""
    if "static" not in scores:
        return []
    base = scores["static"].row()
    lines = []
    for name, score in scores.items():
        if name in ("static", LIFTED_ROW, "initial"):
            continue
        row = score.row()
        cells = ", ".join(
            f"{c}{'' if ' t=' in c else ' t=0'} {row[c] - base[c]:+.1f}"
            for c in GAIN_COLUMNS
            if not (math.isnan(row[c]) and math.isnan(base[c]))
        )
        lines.append(f"{name} - static: {cells}")
    return lines


def _learns_mask(result: FitResult) -> bool:
    return getattr(result.deformation, "fixed_mask", 0.0) is None


def run_demo(
    seed: int,
    budget: dict[str, int],
    device: torch.device,
    out: Path,
    *,
    pictures: bool = True,
    rerun: Path | None = None,
) -> int:
    """Run the demo and write ``results.md``, ``results.json`` and pictures to ``out``,
    all or nothing (a failure leaves the previous run's files as they were); with
    ``rerun``, first a recording of the clip and every variant there
    (:mod:`dego.demo.recording`)."""
    print(
        f"dego {__version__} demo: seed {seed}, {budget['frames']} frames x 6 cameras, "
        f"{budget['gaussians']} Gaussians, {budget['iterations']} iterations per variant, "
        f"{device}"
    )
    start = time.perf_counter()
    scene = SyntheticScene(seed, num_frames=budget["frames"], frame_dt=DEMO_FRAME_DT)
    clip = DemoClip.from_scene(scene).to(device)
    print(
        f"clip: {clip.num_frames} frames of {clip.image_size[0]}x{clip.image_size[1]} pseudo "
        f"depth + semantics, offsets {scene.offsets} ({time.perf_counter() - start:.1f} s)"
    )
    config = FitConfig(
        iterations=budget["iterations"], num_gaussians=budget["gaussians"], seed=seed
    )
    try:
        initial = initial_model(clip, config, torch.Generator().manual_seed(seed))
    except ValueError as error:  # more Gaussians than the clip has surface pixels
        if not str(error).startswith("num_gaussians: "):
            raise
        raise UsageError("--gaussians", str(error).removeprefix("num_gaussians: ")) from None
    labels = {
        LIFTED_ROW: lifted_clip_labels(clip),
        "initial": predict_clip(initial, None, clip),
    }
    results: list[FitResult] = []
    for variant in DEMO_VARIANTS:
        bar = ProgressBar(variant, fit_iterations(variant, config, clip))
        result = fit_scene(clip, variant, config, scene=scene, progress=bar)
        results.append(result)
        labels[row_name(variant)] = predict_clip(result.model, result.deformation, clip)
    scores = {name: score_clip(grids, clip) for name, grids in labels.items()}
    seconds = {row_name(r.variant): r.seconds for r in results}
    table = format_table(scores, seconds)
    print(table)
    print("\n".join(TABLE_GUIDE))
    gains = paired_gains(scores)
    print(GAINS_HEADING)
    for line in gains:
        print(f"  {line}")
    masks: dict[str, dict[str, float]] = {
        r.variant: mask_by_group(rigidity_mask(r), r.model) for r in results if _learns_mask(r)
    }
    for learned, summary in masks.items():
        print(
            f"{learned}: mean rigidity mask m (1 = nonrigid) "
            + ", ".join(f"{group} {value:.3f}" for group, value in summary.items())
        )

    if rerun is not None:
        from dego.demo.recording import record_demo

        began = time.perf_counter()
        record_demo(
            rerun,
            clip,
            labels,
            results,
            row_names={r.variant: row_name(r.variant) for r in results},
            pictured=PICTURED_VARIANTS,
            learns_mask=[r.variant for r in results if _learns_mask(r)],
        )
        print(
            f"wrote {rerun} ({rerun.stat().st_size / 1e6:.1f} MB, "
            f"{time.perf_counter() - began:.1f} s; open it with: dego view {rerun})"
        )
    drawn = _pictures(out, clip, labels, results) if pictures else {}
    written = _write_results(
        out, table, gains, scores, seconds, masks, seed, budget, device, pictures=drawn
    )
    print(f"wrote {', '.join(str(path) for path in written)}")
    print(f"total {time.perf_counter() - start:.1f} s")
    return 0


TABLE_GUIDE = (
    "Columns, percent, weak protocol inside the camera mask: IoU (occupied vs free), mIoU "
    "(15 classes), InsM / ScnM / HCM (instance / scene / human-centric class means), RayIoU; "
    "at the reference frame t=0.",
    "t=±1 / t=±2+: pooled over the frames one / two or more frames from the reference, where "
    "the deformation acts; vehicles / articulated: "
    "IoU on moving vehicles / on pedestrians and cyclists (their voxels grown by one).",
    "Ceilings, not competitors: lifted labels (no learning) and true motion (oracle: the true "
    "motion); references: free offsets / free velocities (per frame / one per Gaussian, no "
    "network); initial: before fitting. Compare static, rigid and decoupled (DeGO).",
)
"""The three lines the demo prints under its table (and writes under it in results.md)."""

GAINS_HEADING = "Gain over static, percentage points (one seed; `dego study` gives intervals):"


def _write_results(
    out: Path,
    table: str,
    gains: list[str],
    scores: dict[str, ClipScore],
    seconds: dict[str, float],
    masks: dict[str, dict[str, float]],
    seed: int,
    budget: dict[str, int],
    device: torch.device,
    *,
    pictures: Mapping[Path, bytes] | None = None,
) -> list[Path]:
    """Write ``results.md``, ``results.json`` and the encoded ``pictures`` (path: PNG
    bytes) to ``out``, all or nothing (:func:`dego._atomic.write_files`); return the paths."""
    settings = {"seed": seed, **budget, "device": str(device), "dego": __version__}
    rows = {name: _json_floats(score.row()) for name, score in scores.items()}
    payload = {
        "settings": settings,
        "percent": rows,
        "fit_seconds": seconds,
        "gains_over_static": gains,
        "rigidity_mask": {variant: _json_floats(summary) for variant, summary in masks.items()},
    }
    markdown = (
        "# dego demo\n\n"
        + ", ".join(f"{key} {value}" for key, value in settings.items())
        + "\n\n"
        + table
        + "\n\n"
        + "  \n".join(TABLE_GUIDE)
        + f"\n\n{GAINS_HEADING}\n\n"
        + "\n".join(f"- {line}" for line in gains)
        + "\n\nMean rigidity mask m (1 = nonrigid) over all Gaussians and by the group of "
        + "their most likely class:\n\n"
        + "\n".join(
            f"- {variant}: " + ", ".join(f"{g} {v:.3f}" for g, v in summary.items())
            for variant, summary in masks.items()
        )
        + "\n"
    )
    files: dict[Path, str | bytes] = {
        out / "results.md": markdown,
        out / "results.json": json.dumps(payload, indent=2) + "\n",
        **(pictures or {}),
    }
    return write_files(files)


def _json_floats(values: dict[str, float]) -> dict[str, float | None]:
    return {key: (None if math.isnan(value) else value) for key, value in values.items()}


def _pictures(
    out: Path, clip: DemoClip, labels: dict[str, torch.Tensor], results: list[FitResult]
) -> dict[Path, bytes]:
    """The demo's pictures, ``path: PNG bytes`` (written with the results)."""
    try:
        import matplotlib  # noqa: F401

        from dego.demo.pictures import bev_figure, camera_figure, loss_figure, png_bytes
    except ImportError:
        print('pictures skipped: they need matplotlib (pip install "dego-occupancy[viz]")')
        return {}
    last = clip.num_frames - 1
    pictures = {
        out / f"bev_{r.variant}.png": png_bytes(
            bev_figure(labels[row_name(r.variant)][last], clip, row_name(r.variant), last)
        )
        for r in results
        if r.variant in PICTURED_VARIANTS
    }
    fitted = [r for r in results if r.variant in VARIANTS]
    for r in fitted:
        pictures[out / f"camera_{r.variant}.png"] = png_bytes(camera_figure(r, clip))
    pictures[out / "losses.png"] = png_bytes(loss_figure(fitted))
    return pictures


if __name__ == "__main__":
    sys.exit(main())
