"""``dego eval``: the argparse definition and the main of the subcommand.

Exit status: 0 when every sample was scored, 1 when some samples failed to read or
validate (the scores over the others are printed, labelled incomplete), 2 for setup
errors (no samples, missing predictions or origins, bad options, a report path that
cannot be written: one ``error: ...`` line, no traceback). The report paths are checked
before scoring and the reports written all or nothing at the end. Under torchrun only
rank 0 prints and writes the reports.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from dego._atomic import remove_empty_dirs, write_files
from dego._cli_args import (
    MAX_THREADS,
    add_threads_argument,
    apply_threads,
    bounded_int,
    output_problem,
    parse_device,
)
from dego.classes import FREE_LABEL
from dego.evaluation.benchmarks import DEFAULT_BENCHMARK, MAVE_VARIANTS, benchmark_list
from dego.evaluation.errors import EvaluationSetupError, EvaluationWorkerError
from dego.evaluation.run import MISSING_POLICIES, PROTOCOL_CHOICES, evaluate

MAX_WORKERS = 64
"""The most local processes ``--workers`` starts (each is a Python process with torch,
a few hundred MB; on a 2-core machine 2 is the fastest setting)."""

DESCRIPTION = (
    "Score occupancy predictions on CPU with the rules of a benchmark (--benchmark, default "
    "occ3d-nuscenes; --benchmarks lists them): voxel IoU / mIoU (with InsM, ScnM, HCM) under "
    "the occ3d and weak protocols, SparseOcc's RayIoU at 1/2/4 m, and each other benchmark's "
    "official metric. Every score is in percent: tables and --markdown with 2 decimals, --json "
    "unrounded."
)


class _ListBenchmarks(argparse.Action):
    """``dego eval --benchmarks``: one line per benchmark, then exit 0."""

    def __init__(self, **kwargs: object) -> None:
        super().__init__(nargs=0, default=argparse.SUPPRESS, **kwargs)  # type: ignore[arg-type]

    def __call__(self, parser: argparse.ArgumentParser, *args: object, **kwargs: object) -> None:
        print(benchmark_list())
        parser.exit(0)


EPILOG = (
    "Ray origins (RayIoU), in order of preference: --infos, --nuscenes, --origins. "
    "Exit status: 0 all samples scored, 1 some samples failed (scores over the rest), "
    "2 setup error. Multi-process: --workers N, or torchrun --nproc_per_node N -m dego eval."
)


def parse_classes(text: str) -> tuple[int, ...]:
    """``"1-11,13-16"`` -> ``(1, ..., 11, 13, ..., 16)``. Ids above 17 (free) are refused
    here, before any range is expanded; 17 itself is refused by the evaluation."""
    out: list[int] = []
    try:
        for part in text.split(","):
            part = part.strip()
            if not part:
                continue
            if "-" in part:
                low, high = (int(v) for v in part.split("-"))
                if high < low:
                    raise ValueError(part)
            else:
                low = high = int(part)
            if high > FREE_LABEL:
                raise argparse.ArgumentTypeError(
                    f"expected class ids in 0..{FREE_LABEL - 1}, got {part!r} in {text!r}"
                )
            out.extend(range(low, high + 1))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected class ids like 1-11,13-16, got {text!r}"
        ) from None
    if not out:
        raise argparse.ArgumentTypeError(f"expected class ids like 1-11,13-16, got {text!r}")
    return tuple(out)


class _NotTheNuScenesVersion(argparse.Action):
    """``dego eval --version``: a usage error that points at the two meanings it could have."""

    def __call__(self, parser: argparse.ArgumentParser, *args: object, **kwargs: object) -> None:
        parser.error(
            "--version: the nuScenes version of --nuscenes is --nuscenes-version; "
            "dego's own version is 'dego --version'"
        )


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dego eval`` (on an existing (sub)parser)."""
    parser.add_argument("--benchmarks", action=_ListBenchmarks, help="list the benchmarks and exit")
    parser.add_argument(
        "--benchmark",
        default=DEFAULT_BENCHMARK,
        help=f"whose rules score the predictions ({DEFAULT_BENCHMARK}; see --benchmarks)",
    )
    parser.add_argument(
        "--mave",
        choices=MAVE_VARIANTS,
        default="dataset",
        help="openocc-v2: which official RayIoU/mAVE script (dataset)",
    )
    parser.add_argument(
        "--gt",
        type=Path,
        required=True,
        help="ground-truth root in the benchmark's layout (occ3d-nuscenes: the Occ3D root "
        "holding gts/<scene>/<token>/labels.npz)",
    )
    parser.add_argument(
        "--pred",
        type=Path,
        required=True,
        help="predictions: <token>.npz (pred / arr_0 / semantics), <token>.npy or "
        "<scene>/<token>/labels.npz",
    )
    origins = parser.add_argument_group("RayIoU ray origins (first given wins)")
    origins.add_argument(
        "--infos", type=Path, help="mmdet3d nuscenes_infos_val.pkl (also sets the samples)"
    )
    origins.add_argument("--nuscenes", type=Path, help="nuScenes root with the JSON tables")
    origins.add_argument(
        "--nuscenes-version",
        dest="nuscenes_version",
        default="v1.0-trainval",
        help="nuScenes version of --nuscenes (v1.0-trainval)",
    )
    parser.add_argument(
        "--version", nargs="?", action=_NotTheNuScenesVersion, help=argparse.SUPPRESS
    )
    origins.add_argument("--origins", type=Path, help="folder of <token>.npy (K, 3) origins")
    parser.add_argument("--no-rayiou", action="store_true", help="skip RayIoU")
    parser.add_argument(
        "--protocol",
        default="both",
        help=f"voxel protocol(s): {', '.join(PROTOCOL_CHOICES)} for occ3d-nuscenes; a "
        "benchmark's own protocol name, or both/all (both)",
    )
    parser.add_argument(
        "--classes",
        type=parse_classes,
        help="classes averaged into mIoU and RayIoU instead of the protocol's, e.g. 1-11,13-16",
    )
    parser.add_argument(
        "--missing",
        choices=MISSING_POLICIES,
        default="error",
        help="a sample without prediction: error (checked up front), free (all free), skip",
    )
    parser.add_argument(
        "--workers",
        type=bounded_int(1, MAX_WORKERS),
        default=1,
        help=f"local processes, 1-{MAX_WORKERS} (torch.distributed, gloo)",
    )
    parser.add_argument(
        "--device",
        type=parse_device,
        default="cpu",
        help="where the metrics run: cpu, cuda or cuda:N (cpu)",
    )
    parser.add_argument("--json", type=Path, help="write a JSON report (percent, unrounded) here")
    parser.add_argument("--markdown", type=Path, help="write a Markdown report (percent) here")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    add_threads_argument(parser)
    return parser


def build_parser() -> argparse.ArgumentParser:
    """A stand-alone parser of the subcommand (``dego eval``)."""
    return add_arguments(
        argparse.ArgumentParser(prog="dego eval", description=DESCRIPTION, epilog=EPILOG)
    )


def run(args: argparse.Namespace, *, created: list[Path] | None = None) -> int:
    """Run ``dego eval`` with parsed arguments; returns the exit status.

    ``--json`` / ``--markdown`` are checked (and their folders created) before scoring;
    the reports are written together at the end, all or nothing. ``created``: where the
    folders made for them are recorded (by default they are removed again here when the
    run fails before writing)."""
    own = created is None
    made: list[Path] = [] if created is None else created
    try:
        code = _run(args, made)
    except BaseException:
        if own:
            remove_empty_dirs(made)
        raise
    if code != 0 and own:
        remove_empty_dirs(made)
    return code


def run_command(
    args: argparse.Namespace, parser: argparse.ArgumentParser, created: list[Path]
) -> int:
    """``dego eval`` as a subcommand of ``dego`` (:mod:`dego.cli`): :func:`run`."""
    return run(args, created=created)


def _check_reports(args: argparse.Namespace, created: list[Path]) -> str | None:
    """Why ``--json`` / ``--markdown`` cannot be written (one line), or ``None``: each
    must be a file that can be written, and no two of them and ``--rerun`` (the recording
    flag :mod:`dego.cli` adds) may name the same file."""
    return output_problem(
        [
            ("--json", args.json),
            ("--markdown", args.markdown),
            ("--rerun", getattr(args, "rerun", None)),
        ],
        created,
    )


def _run(args: argparse.Namespace, created: list[Path]) -> int:
    # under dego.cli --threads auto is resolved already (a count or None): one note
    args.threads = apply_threads(args.threads, quiet=args.quiet)
    is_rank0 = os.environ.get("RANK", "0") == "0"
    problem = _check_reports(args, created)
    if problem is not None:
        if is_rank0:
            print(f"error: {problem}", file=sys.stderr)
        return 2
    try:
        report = evaluate(
            args.gt,
            args.pred,
            protocol=args.protocol,
            rayiou=not args.no_rayiou,
            classes=args.classes,
            infos=args.infos,
            nuscenes=args.nuscenes,
            version=args.nuscenes_version,
            origins=args.origins,
            missing=args.missing,
            workers=args.workers,
            device=args.device,
            progress=not args.quiet,
            benchmark=args.benchmark,
            mave=args.mave,
        )
    except EvaluationSetupError as error:
        if is_rank0:
            print(f"error: {error}", file=sys.stderr)
        return 2
    except EvaluationWorkerError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    if not is_rank0:
        return 0 if report.complete else 1
    print(report.tables())
    reports = {
        Path(path): text()
        for path, text in ((args.json, report.to_json), (args.markdown, report.to_markdown))
        if path is not None
    }
    for path in write_files(reports):
        print(f"wrote {path}")
    if not report.complete:
        print(f"error: {len(report.failed)} sample(s) failed:", file=sys.stderr)
        for failure in report.failed:
            print(f"  {failure.token}: {failure.message}", file=sys.stderr)
        return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    """``dego eval`` on its own (``dego.cli`` registers the same options); Ctrl-C ends it
    with exit status 130 and one line on stderr."""
    try:
        return run(build_parser().parse_args(argv))
    except KeyboardInterrupt:
        print("dego eval: interrupted", file=sys.stderr)
        return 130


__all__ = [
    "MAX_THREADS",
    "MAX_WORKERS",
    "add_arguments",
    "add_threads_argument",
    "apply_threads",
    "build_parser",
    "main",
    "parse_classes",
    "parse_device",
    "run",
    "run_command",
]
