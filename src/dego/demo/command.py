"""``dego demo``: the argparse definition, the main of the subcommand and the runner.

:func:`run_demo` renders a synthetic clip, fits canonical Gaussians to its pseudo labels
without deformation, with a rigid-only and with a decoupled deformation (beside reference
rows), voxelises them at every frame, scores them against each frame's ground truth (weak
protocol, RayIoU, moving agents), prints one table and writes ``results.md``,
``results.json`` and pictures, all or nothing.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Mapping
from pathlib import Path

import torch

from dego._atomic import write_files
from dego._cli_args import (
    MAX_ITERATIONS,
    ProgressBar,
    UsageError,
    add_device,
    bounded_int,
    check_outputs,
    output_dir,
    parse_int,
    rerun_target,
)
from dego._version import __version__
from dego.data.synthetic import SyntheticScene
from dego.demo.clip import DEMO_FRAME_DT, MAX_DEMO_FRAMES, DemoClip, max_gaussians
from dego.demo.evaluate import ClipScore, lifted_clip_labels, predict_clip, score_clip
from dego.demo.fit import (
    MAX_SEED,
    VARIANTS,
    FitConfig,
    FitResult,
    fit_iterations,
    fit_scene,
    initial_model,
    mask_by_group,
    rigidity_mask,
    row_name,
)
from dego.demo.score import format_table

DESCRIPTION = (
    "Fit static, rigid and decoupled Gaussians to a synthetic clip from its pseudo labels, "
    "beside four reference rows (single-frame, free offsets, free velocities and the "
    "ground-truth true motion), score them at every frame against the ground truth, print "
    "one table and each variant's gain over static, and write results.md, results.json and "
    "pictures."
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


def describe_budget(name: str) -> str:
    """``"3 frames, 2,500 Gaussians, 80 iterations per variant"``: how the docs and
    ``--help`` name a :data:`BUDGETS` entry (the tests check that the docs agree)."""
    budget = BUDGETS[name]
    return (
        f"{budget['frames']} frames, {budget['gaussians']:,} Gaussians, "
        f"{budget['iterations']} iterations per variant"
    )


EPILOG = f"Without --quick: {describe_budget('full')} ({DURATIONS['full']})."


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dego demo`` (on an existing (sub)parser)."""
    quick, full = BUDGETS["quick"], BUDGETS["full"]
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"a smaller budget: {describe_budget('quick')} ({DURATIONS['quick']})",
    )
    parser.add_argument(
        "--seed", type=_seed, default=0, help=f"scene and fitting seed, 0-{MAX_SEED} (0)"
    )
    parser.add_argument(
        "--frames",
        type=_demo_frames,
        help=f"frames of the clip, 2-{MAX_DEMO_FRAMES} ({full['frames']}; quick {quick['frames']})",
    )
    parser.add_argument(
        "--iterations",
        type=bounded_int(0, MAX_ITERATIONS),
        help=f"optimiser steps per variant, 0-{MAX_ITERATIONS:,} ({full['iterations']}; "
        f"quick {quick['iterations']})",
    )
    parser.add_argument(
        "--gaussians",
        type=bounded_int(1, max_gaussians(MAX_DEMO_FRAMES)),
        help=f"canonical Gaussians, at most one per camera pixel of the clip "
        f"({full['gaussians']}; quick {quick['gaussians']})",
    )
    add_device(parser)
    parser.add_argument(
        "--out", type=Path, default=Path("dego-demo"), help="output folder (./dego-demo)"
    )
    parser.add_argument("--no-pictures", action="store_true", help="skip the pictures")
    parser.add_argument(
        "--rerun",
        type=Path,
        metavar="FILE.rrd",
        help="also record the clip, the ground truth and every variant's predictions and "
        "Gaussians over the frames for rerun's viewer (open it with: dego view FILE.rrd)",
    )
    return parser


def _demo_frames(text: str) -> int:
    """``dego demo --frames``: an int in ``[2, MAX_DEMO_FRAMES]``. One frame is refused
    with its reason: the demo scores the deformation at the frames other than the
    reference frame, and a one-frame clip has none (its ``t=±1`` columns and the gains
    on them would be undefined)."""
    if parse_int(text) == 1:
        raise argparse.ArgumentTypeError(
            "expected at least 2: the demo scores the deformation at the frames other than "
            "the reference frame (the t=±1 columns), and a 1-frame clip has none"
        )
    return bounded_int(2, MAX_DEMO_FRAMES)(text)


def _seed(text: str) -> int:
    """A seed: an int in ``[0, MAX_SEED]``."""
    value = parse_int(text)
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"expected a seed in [0, {MAX_SEED}], got {text!r}")
    return value


def run_command(
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
    created += output_dir(parser, "--out", args.out)
    created += rerun_target(parser, args.rerun)
    outputs = demo_outputs(args.out, pictures=not args.no_pictures)
    check_outputs(parser, [("--rerun", args.rerun), *(("--out", p) for p in outputs)], created)
    device = torch.device(args.device)
    return run_demo(
        args.seed, budget, device, args.out, pictures=not args.no_pictures, rerun=args.rerun
    )


def demo_outputs(out: Path, *, pictures: bool = True) -> list[Path]:
    """Every file :func:`run_demo` writes to ``out`` (the pictures' names whether or not
    matplotlib is here), checked before the work starts."""
    names = ["results.md", "results.json"]
    if pictures:
        names += [f"bev_{variant}.png" for variant in PICTURED_VARIANTS]
        names += [f"camera_{variant}.png" for variant in VARIANTS]
        names.append("losses.png")
    return [out / name for name in names]


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

    recording_error: OSError | None = None
    if rerun is not None:
        from dego.demo.recording import record_demo

        began = time.perf_counter()
        try:
            record_demo(
                rerun,
                clip,
                labels,
                results,
                row_names={r.variant: row_name(r.variant) for r in results},
                pictured=PICTURED_VARIANTS,
                learns_mask=[r.variant for r in results if _learns_mask(r)],
            )
        except OSError as error:  # a full disk: the run's results are still written
            recording_error = error
        else:
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
    if recording_error is not None:
        print(f"error: {recording_error}", file=sys.stderr)
        return 1
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

        from dego.demo.pictures import bev_figure, camera_figure, loss_figure
        from dego.viz import png_bytes
    except ImportError:
        print('pictures skipped: they need matplotlib (pip install -e ".[viz]" in your dego clone)')
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
