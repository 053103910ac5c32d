"""The ``dego`` command: ``dego demo``, ``dego study`` and ``dego eval``.

``dego demo`` runs DeGO end to end on a synthetic clip: it renders the clip, fits
canonical Gaussians from the pseudo labels only without deformation, with a rigid-only
and with a decoupled deformation, voxelises them at every frame, scores them against
each frame's ground truth (weak protocol, RayIoU, moving agents), prints one table and
writes pictures. ``dego study`` repeats the fits over seeds and Gaussian budgets and
reports means with confidence intervals. ``dego eval`` scores a folder of Occ3D-nuScenes
predictions (:mod:`dego.evaluation.command`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import TextIO

import torch

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
from dego.evaluation import command as eval_command
from dego.study import QUICK_STUDY, STUDY_VARIANTS, StudyConfig, run_study, write_study

PROGRAM_DESCRIPTION = (
    "Run Deformable Gaussian Occupancy (DeGO) end to end on synthetic driving clips. "
    "'dego demo' fits static, rigid and decoupled Gaussians (and reference rows) to one clip "
    "and scores them; 'dego study' repeats the fits over seeds and Gaussian budgets; "
    "'dego eval' scores a folder of Occ3D-nuScenes predictions."
)
DEMO_DESCRIPTION = (
    "Fit static, rigid and decoupled Gaussians to a synthetic clip from its pseudo labels, "
    "beside three reference rows (single-frame, free offsets and the ground-truth true "
    "motion), score them at every frame against the ground truth, print one table and "
    "each variant's gain over static, and write results.md, results.json and pictures."
)
STUDY_DESCRIPTION = (
    "When does decoupling pay off? Fits the static, rigid and decoupled variants and the "
    "reference rows (single-frame, free offsets, true motion) over seeds and Gaussian "
    "budgets, scores them at every frame and reports means with 95% confidence intervals "
    "and paired differences."
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


class ProgressBar:
    """A one-line progress bar on ``stream`` (redrawn on a terminal, quartiles otherwise)."""

    def __init__(self, label: str, total: int, stream: TextIO | None = None) -> None:
        self.label, self.total = label, total
        self.stream = stream or sys.stderr
        self.interactive = self.stream.isatty()
        self.start = time.perf_counter()
        self.last_draw = 0.0

    def __call__(self, iteration: int, losses: dict[str, float]) -> None:
        done = iteration + 1
        now = time.perf_counter()
        if self.interactive:
            if done < self.total and now - self.last_draw < 0.1:
                return
            self.last_draw = now
            end = "\n" if done == self.total else ""
            self.stream.write("\r" + self._line(done, losses, now) + end)
        elif done == self.total or done % max(1, self.total // 4) == 0:
            self.stream.write(self._line(done, losses, now) + "\n")
        self.stream.flush()

    def _line(self, done: int, losses: dict[str, float], now: float) -> str:
        width = 24
        filled = width * done // max(self.total, 1)
        rate = done / max(now - self.start, 1e-9)
        return (
            f"{self.label:>10} [{'#' * filled}{'.' * (width - filled)}] {done}/{self.total} "
            f"loss {losses['total']:.3f} {rate:.1f} it/s"
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
    demo.add_argument("--seed", type=int, default=0, help="scene and fitting seed (0)")
    demo.add_argument(
        "--frames", type=int, help=f"frames of the clip ({full['frames']}; quick {quick['frames']})"
    )
    demo.add_argument(
        "--iterations",
        type=int,
        help=f"optimiser steps per variant ({full['iterations']}; quick {quick['iterations']})",
    )
    demo.add_argument(
        "--gaussians",
        type=int,
        help=f"canonical Gaussians ({full['gaussians']}; quick {quick['gaussians']})",
    )
    demo.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (cpu)")
    demo.add_argument(
        "--out", type=Path, default=Path("dego-demo"), help="output folder (./dego-demo)"
    )
    demo.add_argument("--no-pictures", action="store_true", help="skip the pictures")

    default, quick_study = StudyConfig(), QUICK_STUDY
    study = commands.add_parser(
        "study",
        help="when does decoupling pay off? variants x seeds x Gaussian budgets, with CIs",
        description=STUDY_DESCRIPTION,
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
    study.add_argument("--frames", type=int, help=f"frames per clip ({default.frames})")
    study.add_argument(
        "--iterations", type=int, help=f"optimiser steps per fit ({default.iterations})"
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
    study.add_argument(
        "--out", type=Path, default=Path("dego-study"), help="output folder (./dego-study)"
    )
    study.add_argument("--no-pictures", action="store_true", help="skip the plot")
    eval_command.add_arguments(
        commands.add_parser(
            "eval",
            help="score Occ3D-nuScenes predictions: mIoU, IoU, InsM/ScnM/HCM, RayIoU",
            description=eval_command.DESCRIPTION,
            epilog=eval_command.EPILOG,
        )
    )
    return parser


def _name_list(text: str) -> tuple[str, ...]:
    """``"static,rigid"`` -> ``("static", "rigid")``."""
    return tuple(part.strip() for part in text.split(",") if part.strip())


def _int_list(text: str) -> tuple[int, ...]:
    """``"0-7"`` or ``"0,3,5"`` -> a tuple of ints."""
    try:
        if "-" in text.strip("-"):
            low, high = text.split("-")
            return tuple(range(int(low), int(high) + 1))
        return tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected integers like 0-7 or 0,3,5, got {text!r}"
        ) from None


def _format_ints(values: tuple[int, ...]) -> str:
    if len(values) > 2 and values == tuple(range(values[0], values[-1] + 1)):
        return f"{values[0]}-{values[-1]}"
    return ",".join(map(str, values))


def study_main(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """``dego study``: run the study and write its report."""
    base = QUICK_STUDY if args.quick else StudyConfig()
    changes = {
        name: getattr(args, name)
        for name in ("seeds", "budgets", "frames", "iterations", "variants", "mask_prior")
        if getattr(args, name) is not None
    }
    try:
        config = dataclasses.replace(base, **changes)
    except ValueError as error:
        parser.error(f"--{str(error).split(':')[0].replace('_', '-')}: {error}")
    runs = len(config.seeds) * len(config.budgets) * len(config.variants)
    print(
        f"dego {__version__} study: {runs} fits (seeds {_format_ints(config.seeds)}, budgets "
        f"{_format_ints(config.budgets)}, variants {', '.join(config.variants)}), "
        f"{config.frames} frames, {config.iterations} iterations each"
    )
    start = time.perf_counter()
    done = []

    def progress(line: str) -> None:
        done.append(line)
        print(f"[{len(done)}/{runs} {time.perf_counter() - start:.0f} s] {line}", flush=True)

    results = run_study(config, progress=progress)
    report, paths = write_study(results, config, args.out, pictures=not args.no_pictures)
    print(report)
    print(f"wrote {', '.join(str(p) for p in paths)}")
    print(f"total {time.perf_counter() - start:.1f} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``dego`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "study":
        return study_main(args, parser)
    if args.command == "eval":
        return eval_command.run(args)
    budget = dict(BUDGETS["quick" if args.quick else "full"])
    for name in budget:
        if getattr(args, name) is not None:
            budget[name] = getattr(args, name)
    for name, low in [("frames", 1), ("iterations", 0), ("gaussians", 1)]:
        if budget[name] < low:
            parser.error(f"--{name}: expected an int >= {low}, got {budget[name]}")
    try:
        device = torch.device(args.device)
        torch.empty(0, device=device)
    except (RuntimeError, AssertionError) as error:
        parser.error(f"--device: {args.device!r} is not usable here ({error})")
    return run_demo(args.seed, budget, device, args.out, pictures=not args.no_pictures)


LIFTED_ROW = row_name("lifted-labels")
"""The table's ceiling row: each frame's own pseudo labels lifted to 3D."""

PICTURED_VARIANTS = ("static", "rigid", "decoupled", "true-motion")
"""Variants whose BEV at the last frame ``dego demo`` draws."""

DEMO_VARIANTS = ("single-frame", *VARIANTS, "free-offsets", "true-motion")
"""What ``dego demo`` fits, in table order: the fitted variants between their references."""

GAIN_COLUMNS = ("articulated t!=0", "vehicles t!=0", "HCM", "mIoU")
"""The columns of the demo's "gain over static" lines (HCM, mIoU: at t = 0)."""


def paired_gains(scores: dict[str, ClipScore]) -> list[str]:
    """One line per variant: its gain over ``static`` (points) on :data:`GAIN_COLUMNS`."""
    if "static" not in scores:
        return []
    base = scores["static"].row()
    lines = []
    for name, score in scores.items():
        if name in ("static", LIFTED_ROW, "initial"):
            continue
        row = score.row()
        cells = ", ".join(
            f"{c}{'' if 't!=0' in c else ' t=0'} {row[c] - base[c]:+.1f}" for c in GAIN_COLUMNS
        )
        lines.append(f"{name} - static: {cells}")
    return lines


def _learns_mask(result: FitResult) -> bool:
    return getattr(result.deformation, "fixed_mask", 0.0) is None


def run_demo(
    seed: int, budget: dict[str, int], device: torch.device, out: Path, *, pictures: bool = True
) -> int:
    """Run the demo and write ``results.md``, ``results.json`` and pictures to ``out``."""
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
    initial = initial_model(clip, config, torch.Generator().manual_seed(seed))
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
    print(TABLE_LEGEND)
    gains = paired_gains(scores)
    for line in gains:
        print(line)
    masks = {
        r.variant: mask_by_group(rigidity_mask(r), r.model) for r in results if _learns_mask(r)
    }
    for variant, summary in masks.items():
        print(
            f"{variant}: mean rigidity mask m (1 = nonrigid) "
            + ", ".join(f"{group} {value:.3f}" for group, value in summary.items())
        )

    out.mkdir(parents=True, exist_ok=True)
    written = list(_write_results(out, table, gains, scores, seconds, masks, seed, budget, device))
    if pictures:
        written += _write_pictures(out, clip, labels, results)
    print(f"wrote {', '.join(str(path) for path in written)}")
    print(f"total {time.perf_counter() - start:.1f} s")
    return 0


TABLE_LEGEND = (
    "Percent, weak protocol (camera mask). IoU .. RayIoU: the reference frame (t = 0). "
    "t!=0: pooled over every other frame, where the deformation acts. vehicles / "
    "articulated: IoU on the voxels of moving vehicles / of pedestrians and cyclists "
    "(grown by one voxel), at t != 0."
)


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
) -> tuple[Path, Path]:
    settings = {"seed": seed, **budget, "device": str(device), "dego": __version__}
    rows = {name: _json_floats(score.row()) for name, score in scores.items()}
    payload = {
        "settings": settings,
        "percent": rows,
        "fit_seconds": seconds,
        "gains_over_static": gains,
        "rigidity_mask": {variant: _json_floats(summary) for variant, summary in masks.items()},
    }
    json_path = out / "results.json"
    json_path.write_text(json.dumps(payload, indent=2) + "\n")
    path = out / "results.md"
    path.write_text(
        "# dego demo\n\n"
        + ", ".join(f"{key} {value}" for key, value in settings.items())
        + "\n\n"
        + table
        + "\n\n"
        + TABLE_LEGEND
        + "\n\nGain over static, points (one seed; see `dego study` for intervals):\n\n"
        + "\n".join(f"- {line}" for line in gains)
        + "\n\nMean rigidity mask m (1 = nonrigid) over all Gaussians and by the group of "
        + "their most likely class:\n\n"
        + "\n".join(
            f"- {variant}: " + ", ".join(f"{g} {v:.3f}" for g, v in summary.items())
            for variant, summary in masks.items()
        )
        + "\n"
    )
    return path, json_path


def _json_floats(values: dict[str, float]) -> dict[str, float | None]:
    return {key: (None if math.isnan(value) else value) for key, value in values.items()}


def _write_pictures(
    out: Path, clip: DemoClip, labels: dict[str, torch.Tensor], results: list[FitResult]
) -> list[Path]:
    try:
        import matplotlib  # noqa: F401

        from dego.demo.pictures import bev_picture, camera_picture, loss_picture
    except ImportError:
        print('pictures skipped: they need matplotlib (pip install "dego-occupancy[viz]")')
        return []
    last = clip.num_frames - 1
    pictured = [r for r in results if r.variant in PICTURED_VARIANTS]
    paths = [
        bev_picture(
            labels[row_name(r.variant)][last],
            clip,
            row_name(r.variant),
            out / f"bev_{r.variant}.png",
            last,
        )
        for r in pictured
    ]
    fitted = [r for r in results if r.variant in VARIANTS]
    paths += [camera_picture(r, clip, out / f"camera_{r.variant}.png") for r in fitted]
    paths.append(loss_picture(fitted, out / "losses.png"))
    return paths


if __name__ == "__main__":
    sys.exit(main())
