"""Train a feed-forward Gaussian occupancy network with DeGO's deformation, step by step.

One network predicts Gaussians from one frame of six camera images, for every scene; a
DecoupledDeformation on the network's latent features carries them to the neighbouring
frames, so those frames' pseudo labels supervise the prediction too. Copy the loop into
your own pipeline: swap the image network for yours, the synthetic scenes for your data.

    python examples/train_feedforward.py --steps 300 --device cuda
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from dego import DecoupledDeformation, deformation_loss, splat
from dego.demo import MOVABLE_CLASSES, most_likely_in
from dego.demo.feedforward import (
    DataConfig,
    GaussianPredictor,
    default_cache,
    evaluate,
    load_scenes,
    scene_seeds,
)
from dego.losses import rendering_loss


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--train-scenes", type=int, default=16)
    parser.add_argument("--heldout-scenes", type=int, default=4)
    parser.add_argument("--image-size", type=int, nargs=2, default=(64, 176))
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--cache", type=Path, default=default_cache())
    args = parser.parse_args()
    torch.manual_seed(0)

    # Data: synthetic scenes of 3 frames 0.5 s apart (t = -1, 0, +1), rendered once and cached.
    data = DataConfig(args.train_scenes, args.heldout_scenes, image_size=tuple(args.image_size))
    scenes = [
        r.to(args.device)
        for r in load_scenes(scene_seeds(0, 0, data.train_scenes), data, args.cache)
    ]
    heldout = [
        r.to(args.device)
        for r in load_scenes(scene_seeds(0, 1, data.heldout_scenes), data, args.cache)
    ]

    # The image network and DeGO's deformation on its latents (times in frames). For the
    # constant-velocity rigid branch (ours, beyond the paper): rigid_motion="velocity".
    network = GaussianPredictor(latent_dim=16).to(args.device)
    deformation = DecoupledDeformation(16, hidden_dim=64, depth=3, head_hidden=64).to(args.device)
    optimizer = torch.optim.Adam(
        [
            {"params": network.parameters(), "lr": 2e-3},
            {"params": deformation.parameters(), "lr": 1e-3},
        ]
    )

    for step in range(args.steps):
        scene = scenes[step % len(scenes)]
        ref = scene.reference
        # 1. Gaussians from the reference frame's images (inference sees this only), their
        #    depth along each ray anchored on that frame's pseudo depth (inference has it too).
        prediction = network(
            scene.images[None],
            scene.world_to_cam[ref][None],
            scene.intrinsics[ref][None],
            anchor_depth=scene.depth[ref][None],
        )
        loss = torch.zeros((), device=args.device)
        for index in range(scene.num_frames):
            gaussians = prediction.gaussians
            if index != ref:
                # 2. Carry them to frame t: movable classes deform, the rest stay.
                output = deformation(gaussians, prediction.latent, scene.times[index : index + 1])
                movable = most_likely_in(prediction.logits[0], MOVABLE_CLASSES)[None]
                output = output.gated(movable, gaussians)
                gaussians = output.at(0)
                loss = loss + 0.001 * deformation_loss(output).total
            # 3. Render into frame t's cameras and compare with its 2D pseudo labels.
            rendered = splat(
                gaussians,
                scene.world_to_cam[index][None],
                scene.intrinsics[index][None],
                scene.image_size,
            )
            terms = rendering_loss(
                rendered.features,
                rendered.alpha,
                rendered.depth,
                scene.semantics[index][None],
                scene.depth[index][None],
                scene.supervised[index][None],
            )
            loss = loss + terms.semantic + 0.1 * terms.depth
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        if step % 50 == 0 or step == args.steps - 1:
            print(f"step {step:4d}  loss {loss.item():.3f}")

    # 4. Score held-out scenes at t = 0: voxelise the predicted Gaussians, Occ3D metrics.
    scores = evaluate(network, heldout)
    print(", ".join(f"{name} {value:.1f}" for name, value in scores.items()), "(percent)")


if __name__ == "__main__":
    main()
