"""``dego.compat.gsplat.rasterization`` against gsplat's own ``rasterization`` (CUDA + gsplat).

The same call goes to both, for every render mode, packed and dense, classic and
antialiased, with and without ``radius_clip``; the script prints the largest differences
of the images, the alphas, the radii and the gradients (means, scales, opacities,
colours and ``meta["means2d"]``, plus ``absgrad``), and the share of pixels that differ by
more than 1e-4. Scene: N Gaussians in front of C cameras at H x W, float32.

    python benchmarks/gsplat_parity.py [--n 20000] [--cameras 6]
"""

from __future__ import annotations

import argparse
import importlib.metadata
import itertools
from collections.abc import Callable
from typing import Any

import torch

from dego.compat import gsplat as compat


def scene(n: int, cameras: int, width: int, height: int, device: str) -> dict[str, torch.Tensor]:
    g = torch.Generator(device="cpu").manual_seed(0)
    focal = 0.8 * width
    z = 2 + 30 * torch.rand(n, generator=g)
    u = (1.4 * torch.rand(n, generator=g) - 0.2) * width
    v = (1.4 * torch.rand(n, generator=g) - 0.2) * height
    means = torch.stack([(u - width / 2) * z / focal, (v - height / 2) * z / focal, z], -1)
    tensors = {
        "means": means,
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.exp(torch.empty(n, 3).uniform_(-4, 0, generator=g)),
        "opacities": torch.rand(n, generator=g),
        "colors": torch.rand(n, 8, generator=g),
        "viewmats": torch.eye(4).repeat(cameras, 1, 1),
        "Ks": torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]]).repeat(
            cameras, 1, 1
        ),
    }
    tensors["viewmats"][:, 0, 3] = torch.linspace(-0.5, 0.5, cameras)
    return {k: t.to(device) for k, t in tensors.items()}


def run(
    fn: Callable[..., Any], t: dict[str, torch.Tensor], width: int, height: int, **kw: Any
) -> Any:
    """One forward + backward; returns colours, alphas, meta and the gradients."""
    trained = ("means", "scales", "opacities", "colors")
    leaves = {k: x.clone().requires_grad_(k in trained) for k, x in t.items()}
    colors, alphas, meta = fn(
        leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
        leaves["colors"], leaves["viewmats"], leaves["Ks"], width, height, **kw,
    )  # fmt: skip
    meta["means2d"].retain_grad()
    weights = torch.linspace(-1, 1, colors.shape[-1], device=colors.device)
    ((colors * weights).sum() + alphas.sum()).backward()
    grads = {k: leaves[k].grad for k in ("means", "scales", "opacities", "colors")}
    grads["means2d"] = meta["means2d"].grad
    if kw.get("absgrad"):
        grads["absgrad"] = meta["means2d"].absgrad
    return colors.detach(), alphas.detach(), meta, grads


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n", type=int, default=20_000)
    parser.add_argument("--cameras", type=int, default=6)
    parser.add_argument("--width", type=int, default=704)
    parser.add_argument("--height", type=int, default=256)
    args = parser.parse_args()
    from gsplat import rasterization

    version = importlib.metadata.version("gsplat")
    print(f"gsplat {version}, torch {torch.__version__}, {torch.cuda.get_device_name()}")
    t = scene(args.n, args.cameras, args.width, args.height, "cuda")
    w, h = args.width, args.height
    header = "mode     packed aa    clip | max|img|  >1e-4 px  max|alpha| radii=  | grads (max rel)"
    print(header)
    for mode, packed, aa, clip in itertools.product(
        ["RGB", "D", "ED", "RGB+D", "RGB+ED"], [True, False], [False, True], [0.0, 2.0]
    ):
        if (packed or aa or clip) and mode not in ("RGB+D",):
            continue  # every mode once; the options on RGB+D
        kw = {"render_mode": mode, "packed": packed, "radius_clip": clip, "absgrad": True}
        kw["rasterize_mode"] = "antialiased" if aa else "classic"
        ours = run(compat.rasterization, t, w, h, gsplat_version=version, **kw)
        theirs = run(rasterization, t, w, h, **kw)
        image_diff = (ours[0] - theirs[0]).abs()
        alpha_diff = (ours[1] - theirs[1]).abs().max().item()
        share = (image_diff.amax(-1) > 1e-4).float().mean().item()
        radii_ours, radii_theirs = ours[2]["radii"], theirs[2]["radii"]
        if packed:
            radii_same = radii_ours.shape == radii_theirs.shape and bool(
                (radii_ours == radii_theirs).all()
            )
            radii_text = "same" if radii_same else f"{radii_ours.shape[0]}/{radii_theirs.shape[0]}"
        else:
            radii_text = f"{(radii_ours == radii_theirs).float().mean().item():.4f}"
        grad_text = []
        for name in ours[3]:
            a, b = ours[3][name], theirs[3][name]
            if a is None or b is None or a.shape != b.shape:
                grad_text.append(f"{name} n/a")
                continue
            rel = ((a - b).abs().max() / b.abs().max().clamp_min(1e-12)).item()
            grad_text.append(f"{name} {rel:.1e}")
        print(
            f"{mode:<8} {packed!s:<6} {aa!s:<5} {clip:<4} | {image_diff.max().item():.2e}  "
            f"{share:.2e}  {alpha_diff:.2e}   {radii_text:<7} | {', '.join(grad_text)}"
        )


if __name__ == "__main__":
    main()
