"""``dego view`` (open a recording in rerun's viewer, :mod:`dego.viz.viewer`) and the
recording flags that ``dego eval`` gains here (``--rerun``, ``--limit``:
:mod:`dego.viz.eval_recording`).

``dego eval`` itself lives in :mod:`dego.evaluation.command`, which is core and may not
import :mod:`dego.viz`; :mod:`dego.cli` wraps it with :func:`add_eval_recording_arguments`
and :func:`run_eval_recording`.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

from dego._cli_args import bounded_int, rerun_target
from dego.viz.eval_recording import DEFAULT_LIMIT, MAX_RECORDED_SAMPLES
from dego.viz.viewer import GRPC_PORT, LOCAL_BIND, WEB_VIEWER_PORT

DESCRIPTION = (
    "Open a rerun recording in rerun's viewer: the native viewer where there is a screen, "
    "or with --web rerun's web viewer, served from this machine."
)
EPILOG = None


def ip_address(text: str) -> str:
    """An argparse type: an IPv4 or IPv6 address (what rerun's ``--bind`` takes), as given."""
    try:
        ipaddress.ip_address(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected an IP address such as 127.0.0.1 or 0.0.0.0, got {text!r}"
        ) from None
    return text


ip_address.__name__ = "address"

PORT = bounded_int(1, 65535)
"""An argparse type: a TCP port."""


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dego view`` (on an existing (sub)parser)."""
    parser.add_argument("file", type=Path, metavar="FILE.rrd", help="the recording")
    parser.add_argument(
        "--web", action="store_true", help="serve rerun's web viewer instead (headless, SSH)"
    )
    parser.add_argument(
        "--bind",
        type=ip_address,
        default=LOCAL_BIND,
        metavar="ADDR",
        help="the address rerun's servers listen on (127.0.0.1: this machine only, reached "
        "over SSH by forwarding the ports; 0.0.0.0: every interface, anyone on the network)",
    )
    parser.add_argument(
        "--port",
        type=PORT,
        metavar="N",
        help=f"with --web: the web viewer page's port ({WEB_VIEWER_PORT})",
    )
    parser.add_argument(
        "--grpc-port",
        type=PORT,
        metavar="N",
        help=f"the port the viewer streams the recording from ({GRPC_PORT}); with --web the "
        "browser connects to it too",
    )
    return parser


def run_command(
    args: argparse.Namespace, parser: argparse.ArgumentParser, created: list[Path]
) -> int:
    """``dego view FILE.rrd [--web] [--bind ADDR] [--port N] [--grpc-port N]``: open the
    recording; 1 with one line where no viewer can start here."""
    from dego.viz.viewer import ViewerUnavailableError, check_recording, open_viewer

    if args.port is not None and not args.web:
        parser.error("--port: the web viewer's port, only with --web")
    try:
        check_recording(args.file)
    except ValueError as error:
        parser.error(str(error))
    try:
        return open_viewer(
            args.file, web=args.web, bind=args.bind, port=args.port, grpc_port=args.grpc_port
        )
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
