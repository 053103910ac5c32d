"""``dego eval``: the argparse definition and the main of the subcommand.

Exit status: 0 when every sample was scored, 1 when some samples failed to read or
validate (the scores over the others are printed, labelled incomplete), 2 for setup
errors (no samples, missing predictions or origins, bad options: one ``error: ...`` line,
no traceback). Under torchrun only rank 0 prints and writes the reports.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from dego.evaluation.errors import EvaluationSetupError
from dego.evaluation.run import MISSING_POLICIES, PROTOCOL_CHOICES, evaluate

DESCRIPTION = (
    "Score Occ3D-nuScenes occupancy predictions on CPU: voxel IoU / mIoU (with InsM, ScnM, "
    "HCM) under the occ3d and weak protocols, and SparseOcc's RayIoU at 1/2/4 m. Tables are "
    "printed in percent with 2 decimals; --json holds fractions."
)
EPILOG = (
    "Ray origins (RayIoU), in order of preference: --infos, --nuscenes, --origins. "
    "Exit status: 0 all samples scored, 1 some samples failed (scores over the rest), "
    "2 setup error. Multi-process: --workers N, or torchrun --nproc_per_node N -m dego eval."
)


def parse_classes(text: str) -> tuple[int, ...]:
    """``"1-11,13-16"`` -> ``(1, ..., 11, 13, ..., 16)``."""
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
                out.extend(range(low, high + 1))
            else:
                out.append(int(part))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected class ids like 1-11,13-16, got {text!r}"
        ) from None
    if not out:
        raise argparse.ArgumentTypeError(f"expected class ids like 1-11,13-16, got {text!r}")
    return tuple(out)


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an int >= 1, got {text!r}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dego eval`` (on an existing (sub)parser)."""
    parser.add_argument(
        "--gt", type=Path, required=True, help="Occ3D root holding gts/<scene>/<token>/labels.npz"
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
        "--version",
        "--nuscenes-version",
        dest="nuscenes_version",
        default="v1.0-trainval",
        help="nuScenes version of --nuscenes (v1.0-trainval)",
    )
    origins.add_argument("--origins", type=Path, help="folder of <token>.npy (K, 3) origins")
    parser.add_argument("--no-rayiou", action="store_true", help="skip RayIoU")
    parser.add_argument(
        "--protocol", choices=PROTOCOL_CHOICES, default="both", help="voxel protocol(s) (both)"
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
        "--workers", type=_positive, default=1, help="local processes (torch.distributed, gloo)"
    )
    parser.add_argument("--device", default="cpu", help="where the metrics run (cpu)")
    parser.add_argument("--json", type=Path, help="write a JSON report (fractions) here")
    parser.add_argument("--markdown", type=Path, help="write a Markdown report (percent) here")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    return parser


def build_parser() -> argparse.ArgumentParser:
    """A stand-alone parser of the subcommand (``dego eval``)."""
    return add_arguments(
        argparse.ArgumentParser(prog="dego eval", description=DESCRIPTION, epilog=EPILOG)
    )


def run(args: argparse.Namespace) -> int:
    """Run ``dego eval`` with parsed arguments; returns the exit status."""
    is_rank0 = os.environ.get("RANK", "0") == "0"
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
        )
    except EvaluationSetupError as error:
        if is_rank0:
            print(f"error: {error}", file=sys.stderr)
        return 2
    if not is_rank0:
        return 0 if report.complete else 1
    print(report.tables())
    for path, text in ((args.json, report.to_json), (args.markdown, report.to_markdown)):
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text())
            print(f"wrote {path}")
    if not report.complete:
        print(f"error: {len(report.failed)} sample(s) failed:", file=sys.stderr)
        for failure in report.failed:
            print(f"  {failure.token}: {failure.message}", file=sys.stderr)
        return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    """``dego eval`` on its own (``dego.cli`` registers the same options)."""
    return run(build_parser().parse_args(argv))


__all__ = ["add_arguments", "build_parser", "main", "parse_classes", "run"]
