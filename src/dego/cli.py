"""The ``dego`` command. ``dego demo`` runs DeGO end to end on a synthetic clip:

generate a clip, fit canonical Gaussians with a rigid-only and a decoupled deformation
from the pseudo labels only, voxelise, score against the ground truth (weak protocol and
RayIoU), print one table and write pictures.
"""

from __future__ import annotations

import argparse
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
    VARIANTS,
    DemoClip,
    FitConfig,
    FitResult,
    GaussianSceneModel,
    VariantScore,
    fit_scene,
    format_table,
    mask_by_group,
    predict_labels,
    rigidity_mask,
    score_labels,
)

BUDGETS = {
    "quick": {"frames": 3, "iterations": 150, "gaussians": 3000},
    "full": {"frames": 5, "iterations": 600, "gaussians": 8000},
}
"""Default clip length, iterations per variant and Gaussians of ``--quick`` and the full run."""


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
    parser = argparse.ArgumentParser(prog="dego", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"dego {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser(
        "demo",
        help="fit rigid-only and decoupled Gaussians to a synthetic clip and score them",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    quick, full = BUDGETS["quick"], BUDGETS["full"]
    demo.add_argument(
        "--quick",
        action="store_true",
        help=f"a smaller budget ({quick['frames']} frames, {quick['gaussians']} Gaussians, "
        f"{quick['iterations']} iterations per variant; about a minute on 2 CPU cores)",
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
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``dego`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
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
    scene = SyntheticScene(seed, num_frames=budget["frames"])
    clip = DemoClip.from_scene(scene).to(device)
    print(
        f"clip: {clip.num_frames} frames of {clip.image_size[0]}x{clip.image_size[1]} pseudo "
        f"depth + semantics, offsets {scene.offsets} ({time.perf_counter() - start:.1f} s)"
    )
    config = FitConfig(
        iterations=budget["iterations"], num_gaussians=budget["gaussians"], seed=seed
    )
    initial = GaussianSceneModel.from_clip(
        clip,
        config.num_gaussians,
        latent_dim=config.latent_dim,
        generator=torch.Generator().manual_seed(seed),  # the same draw as fit_scene's
    )
    labels = {"initial": predict_labels(initial.gaussians(), clip)}
    results: list[FitResult] = []
    for variant in VARIANTS:
        result = fit_scene(clip, variant, config, progress=ProgressBar(variant, config.iterations))
        results.append(result)
        labels[variant] = predict_labels(result.model.gaussians(), clip)
    scores = {name: score_labels(grid, clip) for name, grid in labels.items()}
    seconds = {result.variant: result.seconds for result in results}
    table = format_table(scores, seconds)
    print(table)
    masks = {r.variant: mask_by_group(rigidity_mask(r), r.model) for r in results}
    for variant, summary in masks.items():
        print(
            f"{variant}: mean rigidity mask m (1 = nonrigid) "
            + ", ".join(f"{group} {value:.3f}" for group, value in summary.items())
        )

    out.mkdir(parents=True, exist_ok=True)
    written = [
        _write_results(out, table, scores, seconds, masks, seed, budget, device),
    ]
    if pictures:
        written += _write_pictures(out, clip, labels, results)
    print(f"wrote {', '.join(str(path) for path in written)}")
    print(f"total {time.perf_counter() - start:.1f} s")
    return 0


def _write_results(
    out: Path,
    table: str,
    scores: dict[str, VariantScore],
    seconds: dict[str, float],
    masks: dict[str, dict[str, float]],
    seed: int,
    budget: dict[str, int],
    device: torch.device,
) -> Path:
    settings = {"seed": seed, **budget, "device": str(device), "dego": __version__}
    rows = {name: _json_floats(score.row()) for name, score in scores.items()}
    payload = {
        "settings": settings,
        "percent": rows,
        "fit_seconds": seconds,
        "rigidity_mask": {variant: _json_floats(summary) for variant, summary in masks.items()},
    }
    (out / "results.json").write_text(json.dumps(payload, indent=2) + "\n")
    path = out / "results.md"
    path.write_text(
        "# dego demo\n\n"
        + ", ".join(f"{key} {value}" for key, value in settings.items())
        + "\n\nWeak protocol (camera mask) and RayIoU, percent:\n\n"
        + table
        + "\n\nMean rigidity mask m (1 = nonrigid) over all Gaussians and by the group of "
        + "their most likely class:\n\n"
        + "\n".join(
            f"- {variant}: " + ", ".join(f"{g} {v:.3f}" for g, v in summary.items())
            for variant, summary in masks.items()
        )
        + "\n"
    )
    return path


def _json_floats(values: dict[str, float]) -> dict[str, float | None]:
    return {key: (None if math.isnan(value) else value) for key, value in values.items()}


def _write_pictures(
    out: Path, clip: DemoClip, labels: dict[str, torch.Tensor], results: list[FitResult]
) -> list[Path]:
    try:
        import matplotlib  # noqa: F401

        from dego.demo.pictures import bev_picture, camera_picture, loss_picture
    except ImportError:
        print('pictures skipped: they need matplotlib (pip install "dego[viz]")')
        return []
    paths = [
        bev_picture(labels[r.variant], clip, r.variant, out / f"bev_{r.variant}.png")
        for r in results
    ]
    paths += [camera_picture(r, clip, out / f"camera_{r.variant}.png") for r in results]
    paths.append(loss_picture(results, out / "losses.png"))
    return paths


if __name__ == "__main__":
    sys.exit(main())
