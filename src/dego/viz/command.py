"""``dego view`` (open a recording in rerun's viewer, :mod:`dego.viz.viewer`) and the
recording flags that ``dego eval`` gains here (``--rerun``, ``--limit``:
:mod:`dego.viz.eval_recording`).

``dego eval`` itself lives in :mod:`dego.evaluation.command`, which is core and may not
import :mod:`dego.viz`; :mod:`dego.cli` wraps it with :func:`add_eval_recording_arguments`
and :func:`run_eval_recording`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

from dego._cli_args import bounded_int, rerun_target
from dego.viz.eval_recording import DEFAULT_LIMIT, MAX_RECORDED_SAMPLES

DESCRIPTION = (
    "Open a rerun recording in rerun's viewer: the native viewer where there is a screen, "
    "or with --web rerun's web viewer, served from this machine."
)
EPILOG = None


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dego view`` (on an existing (sub)parser)."""
    parser.add_argument("file", type=Path, metavar="FILE.rrd", help="the recording")
    parser.add_argument(
        "--web", action="store_true", help="serve rerun's web viewer instead (headless, SSH)"
    )
    return parser


def run_command(
    args: argparse.Namespace, parser: argparse.ArgumentParser, created: list[Path]
) -> int:
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


def add_eval_recording_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """``dego eval --rerun FILE.rrd [--limit N]``: a group of options on eval's parser."""
    recording = parser.add_argument_group("recording for rerun's viewer")
    recording.add_argument(
        "--rerun",
        type=Path,
        metavar="FILE.rrd",
        help="also record ground truth beside prediction for the first --limit samples",
    )
    recording.add_argument(
        "--limit",
        type=bounded_int(1, MAX_RECORDED_SAMPLES),
        help=f"samples --rerun records, 1-{MAX_RECORDED_SAMPLES:,} ({DEFAULT_LIMIT}); "
        "every sample is still scored",
    )
    return parser


def run_eval_recording(
    args: argparse.Namespace,
    parser: argparse.ArgumentParser,
    created: list[Path],
    score: Callable[[], int],
) -> int:
    """``dego eval`` with its recording flags: check them, ``score()`` (the exit status of
    :func:`dego.evaluation.command.run`), then, with ``--rerun``, record the first
    ``--limit`` samples (rank 0 only under torchrun). A recording that cannot be written
    (a full or stalled disk) is one ``error:`` line and exit status 1, after the scores."""
    if args.limit is not None and args.rerun is None:
        parser.error("--limit: only with --rerun (every sample is scored either way)")
    benchmark = getattr(args, "benchmark", "occ3d-nuscenes")
    if args.rerun is not None and benchmark != "occ3d-nuscenes":
        parser.error(
            f"--rerun: records occ3d-nuscenes samples only, not {benchmark}; score without --rerun"
        )
    created += rerun_target(parser, args.rerun)
    code = score()
    if args.rerun is None or code == 2 or os.environ.get("RANK", "0") != "0":
        return code
    from dego.viz.eval_recording import record_samples

    start = time.perf_counter()
    try:
        recorded = record_samples(
            args.rerun,
            args.gt,
            args.pred,
            limit=DEFAULT_LIMIT if args.limit is None else args.limit,
            infos=args.infos,
            missing=args.missing,
        )
    except OSError as error:  # the recording cannot be written (a full or stalled disk)
        print(f"error: {error}", file=sys.stderr)
        return 1
    print(
        f"wrote {recorded.path} ({recorded.recorded} samples, "
        f"{recorded.path.stat().st_size / 1e6:.1f} MB, {time.perf_counter() - start:.1f} s)"
    )
    for token, reason in recorded.failed.items():
        print(f"  not recorded: {token}: {reason}", file=sys.stderr)
    return code
