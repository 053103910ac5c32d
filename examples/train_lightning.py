"""Fit the demo's deformable Gaussian scene with Lightning: a compiled step under bf16 autocast.

    python examples/train_lightning.py                   # 20 steps, inductor, bf16-mixed
    python examples/train_lightning.py --steps 3 --compile-backend aot_eager --out runs/lit
    python examples/train_lightning.py --precision 32-true --compile-backend none

Needs the ``lightning`` extra (``pip install -e ".[lightning]"`` from the clone: Lightning
and torchmetrics). The ``decoupled`` variant of ``dego demo`` (``dego.demo.fit_scene``) as
a ``LightningModule``: canonical Gaussians (``GaussianSceneModel``) and a
``DecoupledDeformation`` fitted to one synthetic clip's 2D pseudo labels, one frame (three
of its six cameras) per step.

- ``training_step`` computes the demo's weak losses of the step's frame (deform the
  canonical Gaussians to the frame's time with ``gaussians_at``, splat them into its
  cameras with ``render``, cross-entropy + L1 depth with ``dego.losses.semantic_loss`` and
  ``depth_loss``, plus the deformation regulariser) in a function wrapped in ``torch.compile``
  (``--compile-backend``: ``inductor``, the default, ``aot_eager``, ``eager`` or ``none``).
  dego's data-dependent parts (tile binning and compositing, boolean masks) run eagerly
  between the compiled graphs. The function returns ``torch.compiler.is_compiling()``
  with the losses, so the module counts the steps that really ran compiled code.
- ``Trainer(precision="bf16-mixed", accelerator="cpu")`` runs the step under
  ``torch.autocast("cpu", dtype=torch.bfloat16)``: the deformation network's layers run in
  bfloat16, while ``splat`` and ``voxelize`` cast their inputs to float32 and run their
  geometry in float32 (dego's autocast policy), so the losses come back in float32.
- ``validation_step`` voxelises the Gaussians at the reference frame, the demo's
  evaluation path (``predict_labels``), and updates ``OccupancyMetric("weak")`` and
  ``RayIoUMetric`` from ``dego.compat.torchmetrics``; both metric objects are logged
  (``self.log("val/miou", self.occupancy)``), so Lightning computes and resets them at the
  end of the epoch. ``trainer.validate`` runs before and after the fit.

With ``--out DIR`` the script writes ``DIR/summary.json`` (settings, per-step losses,
initial and final metrics and what Lightning logged, all fractions under dego's score keys
like the CSV log, wall times) and Lightning's CSV log
(``DIR/lightning/version_0/metrics.csv``); stdout shows percent.

A few steps barely move the scores (the demo fits for hundreds of iterations): this shows
the plumbing, not a good fit. Most of a run is compilation. ``time python
examples/train_lightning.py`` (the defaults: 20 steps, 1000 Gaussians, 2 frames of
32 x 88 pixels, inductor, bf16-mixed) took 3.8 minutes on a first run (empty inductor
cache) and 1.2 minutes once inductor's on-disk cache held the compiled graphs (load
average 1-1.5); ``--compile-backend aot_eager`` (no code generation, nothing cached) 3
minutes and ``none`` (eager) 2-2.5 minutes (load average 2-4). All on a 2-core VM shared
with other jobs, so expect a wide range. Once compiled, a step takes well under a second.
The printed losses and scores agree to three decimals across the backends; bf16-mixed and
32-true differ slightly (the deformation network runs in bfloat16).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import time
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.loggers import CSVLogger
from torch import Tensor
from torch.utils.data import DataLoader

import dego
from dego.compat.torchmetrics import OccupancyMetric, RayIoUMetric
from dego.demo import (
    DEMO_FRAME_DT,
    LOSS_TERMS,
    MOVABLE_CLASSES,
    DemoClip,
    FitConfig,
    build_deformation,
    gaussians_at,
    initial_model,
    predict_labels,
    render,
    to_ego,
)
from dego.losses import depth_loss, semantic_loss
from dego.splatting import composite

BACKENDS = ("inductor", "aot_eager", "eager", "none")
PRECISIONS = ("bf16-mixed", "32-true")


class LitSceneFit(L.LightningModule):
    """The demo's ``decoupled`` fit as a LightningModule; batches are frame indices."""

    def __init__(self, clip: DemoClip, config: FitConfig, compile_backend: str = "inductor"):
        super().__init__()
        self.clip, self.config = clip, config
        # The same initialisation as fit_scene(clip, "decoupled", config)
        self.model = initial_model(clip, config, torch.Generator().manual_seed(config.seed))
        torch.manual_seed(config.seed)  # the deformation network's initial weights
        self.deformation = build_deformation("decoupled", config, clip)
        self.model.deform_classes = MOVABLE_CLASSES  # FitConfig(deform="movable")
        self.cameras = torch.Generator().manual_seed(config.seed)  # camera subset per step
        self.occupancy = OccupancyMetric("weak")
        self.rayiou = RayIoUMetric(grid=clip.grid)
        self.compile_backend = compile_backend
        self.losses = (
            self.frame_losses
            if compile_backend == "none"
            else torch.compile(self.frame_losses, backend=compile_backend)
        )
        self.history: dict[str, list[float]] = {term: [] for term in LOSS_TERMS}
        self.compiled_steps = 0  # steps whose losses came out of compiled code
        self.autocast_dtypes: set[str] = set()  # what the training steps ran under
        self.reports: list[dict[str, float]] = []  # one per validation run
        self.log_every = 1

    def frame_losses(self, index: int, cameras: Tensor) -> tuple[dict[str, Tensor], bool]:
        """Weak losses of frame ``index`` seen by ``cameras`` (what ``torch.compile`` wraps;
        the same terms as ``fit_scene``), and whether this ran as compiled code."""
        clip, config = self.clip, self.config
        gaussians, deformation_terms = gaussians_at(
            self.model,
            self.deformation,
            clip,
            index,
            config.mask_sparsity,
            config.offset_gradients,
        )
        rendered = render(gaussians, clip, index, cameras)
        supervised = clip.supervised[index][cameras][None]
        losses = {
            "semantics": semantic_loss(
                rendered.features, rendered.alpha, clip.semantics[index][cameras][None], supervised
            ),
            "depth": depth_loss(rendered.depth, clip.depth[index][cameras][None], supervised),
        }
        losses["deformation"] = (
            deformation_terms["total"] if deformation_terms else losses["depth"].new_zeros(())
        )
        losses["total"] = (
            losses["semantics"]
            + config.depth_weight * losses["depth"]
            + config.deformation_weight * losses["deformation"]
        )
        return losses, torch.compiler.is_compiling()  # a constant True in compiled code

    def training_step(self, index: int, batch_idx: int) -> Tensor:
        num_cameras = self.clip.world_to_cam.shape[1]
        cameras = torch.randperm(num_cameras, generator=self.cameras)
        cameras = cameras[: self.config.cameras_per_step or num_cameras]
        if torch.is_autocast_enabled("cpu"):
            self.autocast_dtypes.add(str(torch.get_autocast_dtype("cpu")))
        losses, compiled = self.losses(index, cameras)
        self.compiled_steps += int(compiled)
        values = {term: losses[term].item() for term in LOSS_TERMS}
        for term, value in values.items():
            self.history[term].append(value)
        self.log("train/loss", losses["total"].detach(), prog_bar=True)
        step = self.global_step + 1
        if step % self.log_every == 0 or step == self.trainer.max_steps:
            print(
                f"step {step:3d}/{self.trainer.max_steps}  frame {index}  "
                f"loss {values['total']:.3f}  semantics {values['semantics']:.3f}  "
                f"depth {values['depth']:.2f} m  deformation {values['deformation']:.4f}  "
                f"{'compiled' if compiled else 'eager'}, {losses['total'].dtype}",
                flush=True,
            )
        return losses["total"]

    @torch.no_grad()
    def validation_step(self, index: int, batch_idx: int) -> None:
        # The demo's evaluation: the Gaussians at the frame, in its ego frame, voxelised.
        # Scoring needs no mixed precision: evaluate in float32.
        clip = self.clip
        with torch.autocast(self.device.type, enabled=False):
            gaussians, _ = gaussians_at(self.model, self.deformation, clip, index)
            labels = predict_labels(to_ego(gaussians, clip, index), clip)
        self.occupancy.update(labels, clip.occupancy[index], clip.mask_camera[index])
        self.rayiou.update(labels, clip.occupancy[index], clip.ray_origins)
        self.log("val/miou", self.occupancy)
        self.log("val/rayiou", self.rayiou)

    def on_validation_epoch_end(self) -> None:
        # dego's reports of the states, before Lightning computes and resets the metrics
        occupancy, rayiou = self.occupancy.report(), self.rayiou.report()
        self.reports.append(
            {
                "iou": occupancy.iou,
                "miou": occupancy.miou,
                **{f"rayiou@{t:g}": v for t, v in zip(rayiou.thresholds, rayiou.at, strict=True)},
                "rayiou": rayiou.rayiou,
            }
        )

    def configure_optimizers(self) -> torch.optim.Optimizer:
        lr = self.config.lr
        names = ("means", "quats", "log_scales", "opacity_logits", "semantic_logits", "latent")
        groups: list[dict[str, Any]] = [
            {"params": [getattr(self.model, name)], "lr": lr[name]} for name in names
        ]
        groups.append({"params": list(self.deformation.parameters()), "lr": lr["deformation"]})
        return torch.optim.Adam(groups)


@contextlib.contextmanager
def splat_kernels(backend: str) -> Iterator[None]:
    """Inside a compiled ``splat`` the compositing loop runs eagerly and its chunk kernels
    are compiled with ``dego.splatting.composite.COMPILED_KERNELS`` (inductor by default):
    keep that for ``inductor``; with the other backends, which generate no code and so
    gain nothing from compiling the kernels, use the eager kernels. Restored on exit."""
    saved = composite.COMPILED_KERNELS
    composite.COMPILED_KERNELS = "inductor" if backend == "inductor" else None
    try:
        yield
    finally:
        composite.COMPILED_KERNELS = saved


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20, help="optimizer steps")
    parser.add_argument("--gaussians", type=int, default=1000, help="canonical Gaussians")
    parser.add_argument("--frames", type=int, default=2, help="frames of the clip")
    parser.add_argument("--image-size", type=int, nargs=2, default=(32, 88), metavar=("H", "W"))
    parser.add_argument("--seed", type=int, default=0, help="scene, initialisation, order")
    parser.add_argument("--compile-backend", choices=BACKENDS, default="inductor")
    parser.add_argument("--precision", choices=PRECISIONS, default="bf16-mixed")
    parser.add_argument("--progress-bar", action="store_true", help="Lightning's progress bar")
    parser.add_argument("--out", type=Path, help="write summary.json and a CSV log here")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.gaussians < 1 or args.frames < 1:
        parser.error("--steps, --gaussians and --frames must be positive")
    return args


def _finite_or_none(value: float) -> float | None:
    return None if math.isnan(value) else value


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the example; returns the summary (also written to ``--out``/summary.json)."""
    args = parse_args(argv)
    start = time.perf_counter()
    L.seed_everything(args.seed, verbose=False)
    # One in-memory clip needs no worker processes, and validation runs on its own
    warnings.filterwarnings("ignore", ".*does not have many workers.*")
    warnings.filterwarnings("ignore", ".*but have no `val_dataloader`.*")

    scene = dego.SyntheticScene(
        args.seed,
        num_frames=args.frames,
        frame_dt=DEMO_FRAME_DT,
        image_size=tuple(args.image_size),
    )
    clip = DemoClip.from_scene(scene)
    clip_seconds = time.perf_counter() - start
    print(
        f"clip: offsets {scene.offsets}, {clip.depth.shape[1]} cameras of "
        f"{clip.image_size[0]}x{clip.image_size[1]} ({clip_seconds:.1f} s); "
        f"{args.gaussians} Gaussians, {args.steps} steps, backend {args.compile_backend}, "
        f"precision {args.precision}",
        flush=True,
    )
    config = FitConfig(iterations=args.steps, num_gaussians=args.gaussians, seed=args.seed)
    module = LitSceneFit(clip, config, args.compile_backend)
    module.log_every = max(1, args.steps // 5)

    frames = DataLoader(
        range(clip.num_frames),  # a seeded shuffled cycle over the frames, as fit_scene
        batch_size=None,
        shuffle=True,
        generator=torch.Generator().manual_seed(args.seed),
    )
    reference = DataLoader([clip.reference], batch_size=None)
    logger = False if args.out is None else CSVLogger(args.out, name="lightning", version=0)
    trainer = L.Trainer(
        accelerator="cpu",
        devices=1,
        precision=args.precision,
        max_steps=args.steps,
        max_epochs=-1,
        logger=logger,
        enable_checkpointing=False,
        enable_model_summary=False,
        enable_progress_bar=args.progress_bar,
        num_sanity_val_steps=0,
        log_every_n_steps=1,
    )
    with splat_kernels(args.compile_backend):
        validate_start = time.perf_counter()
        trainer.validate(module, reference, verbose=False)  # the untrained Gaussians
        fit_start = time.perf_counter()
        trainer.fit(module, frames)
        fit_seconds = time.perf_counter() - fit_start
        logged = trainer.validate(module, reference, verbose=False)[0]
        validate_seconds = time.perf_counter() - validate_start - fit_seconds

    initial, final = module.reports
    summary = {
        "settings": {
            "steps": args.steps,
            "gaussians": args.gaussians,
            "frames": args.frames,
            "image_size": list(args.image_size),
            "seed": args.seed,
            "compile_backend": args.compile_backend,
            "precision": args.precision,
        },
        "losses": module.history,
        "compiled_steps": module.compiled_steps,
        "autocast": sorted(module.autocast_dtypes),
        "initial": {k: _finite_or_none(v) for k, v in initial.items()},
        "final": {k: _finite_or_none(v) for k, v in final.items()},
        # a key holds one unit everywhere: fractions, as torchmetrics and the CSV log have them
        "units": "fraction",
        "logged": {k: float(v) for k, v in logged.items()},
        "seconds": {
            "clip": clip_seconds,
            "fit": fit_seconds,
            "validate": validate_seconds,
            "total": time.perf_counter() - start,
        },
    }
    total = module.history["total"]
    print(
        f"\nloss {total[0]:.3f} -> {total[-1]:.3f} over {args.steps} steps "
        f"({module.compiled_steps} compiled, autocast {summary['autocast'] or 'off'}); "
        f"fit {fit_seconds:.1f} s, total {summary['seconds']['total']:.1f} s"
    )
    for name in ("initial", "final"):
        scores = summary[name]
        print(
            f"{name:>7}: IoU {100 * scores['iou']:.2f}  mIoU {100 * scores['miou']:.2f} (weak)  "
            f"RayIoU {100 * scores['rayiou']:.2f} (percent)"
        )
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        path = args.out / "summary.json"
        path.write_text(json.dumps(summary, indent=2) + "\n")
        print(f"wrote {path}")
    return summary


if __name__ == "__main__":
    main()
