"""Fit a deformable Gaussian scene to a synthetic clip from 2D pseudo labels only.

The core of ``dego demo``, written out step by step for one variant:

1. render a synthetic clip: six cameras per frame, pseudo depth and pseudo semantics;
2. put learnable canonical Gaussians on the pseudo-depth surfaces (reference time);
3. each step, deform them to one frame's time with DecoupledDeformation (only the
   Gaussians whose most likely class is movable; each of them passes the same share of
   gradient to the network), splat class probabilities and depth into that frame's
   cameras, and minimise cross-entropy + L1 depth + the (weak) deformation losses with Adam;
4. voxelise the Gaussians at every frame (deformed to its time, in its ego coordinates)
   and score them against that frame's ground-truth grid, used for nothing else.

    python examples/fit_scene.py --iterations 100 --gaussians 2000 --out fit-scene
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

import dego
from dego.demo import (
    DEMO_FRAME_DT,
    MOVABLE_CLASSES,
    DemoClip,
    FitConfig,
    GaussianSceneModel,
    balance_deformation_gradients,
    build_deformation,
    format_table,
    predict_clip,
    score_clip,
)
from dego.losses import rendering_loss


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", choices=["rigid", "decoupled"], default="decoupled")
    parser.add_argument("--iterations", type=int, default=100)
    parser.add_argument("--gaussians", type=int, default=2000)
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="write a BEV picture here (needs matplotlib)")
    args = parser.parse_args()

    # 1. The clip. World coordinates = the reference frame's ego frame (offset 0).
    scene = dego.SyntheticScene(args.seed, num_frames=args.frames, frame_dt=DEMO_FRAME_DT)
    clip = DemoClip.from_scene(scene)
    print(f"clip: offsets {scene.offsets}, {clip.depth.shape[1]} cameras, {clip.image_size}")

    # 2. Canonical Gaussians (means, quats, scales, opacities, semantic logits, latent
    # features) on the pseudo-depth surfaces, and the deformation network. The latent
    # features start from one random code per segment (Gaussians of one pseudo class
    # closer than 1 m), so that the network can tell one agent from another.
    config = FitConfig(iterations=args.iterations, num_gaussians=args.gaussians, seed=args.seed)
    model = GaussianSceneModel.from_clip(
        clip,
        config.num_gaussians,
        latent_init=config.latent_init,
        generator=torch.Generator().manual_seed(args.seed),
    )
    model.deform_classes = MOVABLE_CLASSES  # what predict_clip gates by, as the fit does
    deformation = build_deformation(args.variant, config, clip)
    initial_labels = predict_clip(model, None, clip)  # no deformation: a static scene
    optimizer = torch.optim.Adam(
        [
            {"params": [model.means], "lr": config.lr["means"]},
            {"params": [model.quats], "lr": config.lr["quats"]},
            {"params": [model.log_scales], "lr": config.lr["log_scales"]},
            {"params": [model.opacity_logits], "lr": config.lr["opacity_logits"]},
            {"params": [model.semantic_logits], "lr": config.lr["semantic_logits"]},
            {"params": [model.latent], "lr": config.lr["latent"]},
            {"params": deformation.parameters(), "lr": config.lr["deformation"]},
        ]
    )

    # 3. The fit: one frame per step. At the other frames only the Gaussians whose most
    # likely class is movable are deformed (class gating), and the position gradient
    # that reaches the network is equalised over them: otherwise the few Gaussians of a
    # small agent, each covering a few pixels, are outvoted by large ones.
    frames = torch.Generator().manual_seed(args.seed)
    movable = torch.tensor(MOVABLE_CLASSES)
    for step in range(args.iterations):
        index = int(torch.randint(clip.num_frames, (), generator=frames))
        gaussians = model.gaussians()  # (1, N), features = class probabilities (1, N, 17)
        deformation_term = torch.zeros(())
        if index != clip.reference:  # other frames: deform the canonical set to their time
            canonical = gaussians
            keep = torch.isin(model.semantic_logits.detach().argmax(-1), movable)[None]
            deformed = deformation(canonical, model.latent[None], clip.times[index : index + 1])
            deformed = deformed.gated(keep, canonical)
            gaussians = balance_deformation_gradients(deformed.at(0), canonical, keep)
            deformation_term = dego.deformation_loss(deformed).total
        rendered = dego.splat(
            gaussians,
            clip.world_to_cam[index : index + 1],
            clip.intrinsics[index : index + 1],
            clip.image_size,
        )
        # L_seg (cross-entropy, free space = 1 - alpha) and L_dep (L1 where there is
        # pseudo depth) on the supervised pixels; inputs are (B, V, ...) with B = 1.
        losses = rendering_loss(
            rendered.features,
            rendered.alpha,
            rendered.depth,
            clip.semantics[index][None],
            clip.depth[index][None],
            clip.supervised[index][None],
        )
        total = (
            losses.semantic
            + config.depth_weight * losses.depth
            + config.deformation_weight * deformation_term
        )
        optimizer.zero_grad()
        total.backward()
        optimizer.step()
        if step % max(1, args.iterations // 5) == 0 or step == args.iterations - 1:
            print(
                f"step {step:4d}  frame {index}  semantics {losses.semantic.item():.3f}  "
                f"depth {losses.depth.item():.2f} m  deformation {deformation_term.item():.4f}"
            )

    # 4. Voxelise at every frame (deformed to t, in t's ego coordinates) and score: the
    # reference frame (weak protocol + RayIoU), the other frames, and moving agents.
    labels = predict_clip(model, deformation, clip)
    scores = {
        "initial": score_clip(initial_labels, clip),
        args.variant: score_clip(labels, clip),
    }
    print(format_table(scores))
    if args.out is not None:
        from dego.viz import compare_bev, save_figure

        reference = clip.reference
        figure = compare_bev(labels[reference], clip.occupancy[reference], grid=clip.grid)
        path = save_figure(figure, args.out / "bev.png")
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
