"""Profile of one `dego train` step: what the image network, the deformation and the splatter
cost, and what rendering 3 of the 6 cameras per frame saves against all 6.

Each row is one training step (forward + backward) of the `decoupled` variant on one scene
(the reference frame and one other frame), or one part of it, timed side by side in one
run (alternating rounds, medians): the whole step with `cameras_per_step` 3 (what `dego
train` does) and 6 (every camera, the baseline), the same step of the `velocity` variant
(the constant-velocity rigid branch), the image network alone (forward + backward of a loss
on its outputs, depth anchored on the pseudo depth), and each deformation alone on the
predicted Gaussians.

    python benchmarks/bench_feedforward.py [--device cuda] [--repeats 10]
"""

from __future__ import annotations

import dataclasses

import torch

from dego.demo.feedforward import (
    DataConfig,
    TrainConfig,
    build_deformation,
    build_network,
    load_scenes,
    predict,
    scene_seeds,
    step_loss,
)

from harness import alternating_median_seconds, benchmark_parser, peak_memory_mib


def main() -> None:
    args = benchmark_parser(__doc__, repeats=10).parse_args()
    device = torch.device(args.device)
    record = load_scenes(scene_seeds(0, 0, 1), DataConfig(), cache=None)[0].to(device)
    config = TrainConfig()
    torch.manual_seed(0)
    network = build_network(config).to(device)
    deformation = build_deformation("decoupled", config, record.times)
    assert deformation is not None
    deformation = deformation.to(device)
    velocity = build_deformation("velocity", config, record.times)
    assert velocity is not None
    velocity = velocity.to(device)
    generator = torch.Generator().manual_seed(0)

    def step(cameras: int, variant: str = "decoupled") -> None:
        settings = dataclasses.replace(config, cameras_per_step=cameras)
        module = velocity if variant == "velocity" else deformation
        step_loss(network, module, record, variant, settings, generator).backward()  # type: ignore[arg-type]

    def network_only() -> None:
        prediction = predict(network, record)
        g = prediction.gaussians
        (g.means.mean() + g.scales.mean() + prediction.logits.mean()).backward()

    def deformation_only(module: torch.nn.Module) -> None:
        with torch.no_grad():
            prediction = predict(network, record)
        latent = prediction.latent.requires_grad_()
        out = module(prediction.gaussians, latent, record.times[:1])
        out.gaussians.means.square().mean().backward()

    cases = {
        "step, 3 of 6 cameras per frame": lambda: step(3),
        "step, all 6 cameras (baseline)": lambda: step(6),
        "velocity step, 3 cameras": lambda: step(3, "velocity"),
        "image network alone": network_only,
        "deformation alone": lambda: deformation_only(deformation),
        "velocity deformation alone": lambda: deformation_only(velocity),
    }
    seconds = alternating_median_seconds(cases, device, repeats=args.repeats, warmup=2)
    versions = f"torch {torch.__version__}, threads {torch.get_num_threads()}, device {device}"
    print(
        f"One dego train step ({config.block} x {config.block} blocks, "
        f"{predict(network, record).gaussians.num_gaussians} Gaussians) [{versions}]"
    )
    print(f"{'case':<34}{'ms':>10}{'of 3-camera step':>18}{'peak MiB':>10}")
    whole = seconds["step, 3 of 6 cameras per frame"]
    for name, fn in cases.items():
        peak = peak_memory_mib(fn, device)
        print(f"{name:<34}{seconds[name] * 1e3:>10.1f}{seconds[name] / whole:>17.2f}x{peak:>10.1f}")
    rest = whole - seconds["image network alone"] - seconds["deformation alone"]
    print(
        f"splatting and losses (the rest of the 3-camera step): {rest * 1e3:.1f} ms, "
        f"{rest / whole:.0%}"
    )


if __name__ == "__main__":
    main()
