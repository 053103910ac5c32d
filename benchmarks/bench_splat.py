"""DifferentiableSplatter benchmarks (forward + backward, side by side in one run).

W1 (paper scale): 6 surround cameras at 256 x 704, 10,000 Gaussians in the Occ3D
    volume (scales 0.05-1 m), C = 48 features (16 semantic + 32 distillation), expected
    depth; ours on the chosen device (on CUDA: the torch path and ``backend="triton"``
    when triton is installed), and gsplat's ``rasterization`` on the same inputs when
    CUDA and gsplat are available, forward + backward and forward alone. Also the
    overhead of ``dego.compat.gsplat``'s ``rasterization`` over ``dego.splat`` with the
    same rules.
W2 (mid): 2 cameras at 128 x 352, 2,000 Gaussians: ours (tile-based) vs a dense
    evaluation of every Gaussian at every pixel with the same rules (chunked over pixel
    rows so that it fits in memory).

    python benchmarks/bench_splat.py [--device cuda] [--repeats 3] [--png docs/images/w1.png]
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch

from dego import GaussianSet, splat
from dego.compat import gsplat as compat
from dego.splatting import pipeline, project_gaussians
from dego.splatting.types import SplatConfig

from harness import (
    alternating_median_seconds,
    benchmark_parser,
    median_seconds,
    peak_memory_mib,
    splat_versions,
)
from pictures import save_depth_and_semantics
from scenes import occ3d_gaussians, surround_rig


def forward_backward(
    render: Callable[[GaussianSet], tuple[torch.Tensor, ...]], gs: GaussianSet
) -> Callable[[], None]:
    """A call that renders, reduces every output to a scalar and back-propagates."""

    def run() -> None:
        leaves = [
            t.detach().clone().requires_grad_()
            for t in (gs.means, gs.quats, gs.scales, gs.opacities, gs.features)
        ]
        scene = GaussianSet(*leaves)
        outputs = render(scene)
        sum(o.float().square().mean() for o in outputs).backward()

    return run


def dense_render(
    gs: GaussianSet,
    w2c: torch.Tensor,
    k: torch.Tensor,
    size: tuple[int, int],
    rows_per_chunk: int = 8,
) -> tuple[torch.Tensor, ...]:
    """Every Gaussian at every pixel (same rules as ``splat``), chunked over pixel rows."""
    h, w = size
    proj = project_gaussians(
        gs.means,
        gs.quats,
        gs.scales,
        w2c,
        k,
        size,
        near=0.01,
        far=1e10,
        eps2d=0.3,
        radius_sigma=3.0,
    )
    b, v, n = proj.depths.shape
    order = torch.argsort(proj.depths, dim=-1)
    take = lambda t: torch.take_along_dim(t, order.unsqueeze(-1), dim=2)  # noqa: E731
    mean, conic = take(proj.means2d), take(proj.conics)
    depth = torch.take_along_dim(proj.depths, order, dim=2)
    radius = torch.take_along_dim(proj.radii, order, dim=2).to(mean.dtype)
    opacity = torch.take_along_dim(gs.opacities.unsqueeze(1).expand(b, v, n), order, dim=2)
    colors = torch.cat(
        [take(gs.features.unsqueeze(1).expand(b, v, n, -1)), depth.unsqueeze(-1)], -1
    )
    # a Gaussian reaches a pixel only inside its radius box, rounded out to whole tiles
    tile = 16
    lo = torch.floor((mean - radius.unsqueeze(-1)) / tile) * tile
    hi = torch.ceil((mean + radius.unsqueeze(-1)) / tile) * tile
    images, alphas = [], []
    xs = torch.arange(w, dtype=mean.dtype) + 0.5
    for y0 in range(0, h, rows_per_chunk):
        ys = torch.arange(y0, min(y0 + rows_per_chunk, h), dtype=mean.dtype) + 0.5
        px = xs.expand(len(ys), w).reshape(-1)
        py = ys.unsqueeze(-1).expand(len(ys), w).reshape(-1)
        dx = mean[..., 0:1] - px
        dy = mean[..., 1:2] - py
        a, bb, c = (t.unsqueeze(-1) for t in conic.unbind(-1))
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + bb * dx * dy
        alpha = (opacity.unsqueeze(-1) * torch.exp(-sigma)).clamp(max=0.999)
        inside = (
            (px >= lo[..., 0:1]) & (px < hi[..., 0:1]) & (py >= lo[..., 1:2]) & (py < hi[..., 1:2])
        )
        inside &= (radius > 0).unsqueeze(-1)
        alpha = torch.where((sigma < 0) | (alpha < 1 / 255) | ~inside, 0.0, alpha)
        after = torch.cumprod(1 - alpha, dim=2)
        before = torch.cat([torch.ones_like(after[:, :, :1]), after[:, :, :-1]], dim=2)
        weights = torch.where(after <= 1e-4, 0.0, before - after)
        images.append(torch.einsum("bvnp,bvnc->bvcp", weights, colors))
        alphas.append(weights.sum(2))
    image = torch.cat(images, -1).unflatten(-1, (h, w))
    alpha = torch.cat(alphas, -1).unflatten(-1, (h, w))
    return image[:, :, :-1], image[:, :, -1] / alpha.clamp_min(1e-10), alpha


def report(
    label: str, fn: Callable[[], None], repeats: int, device: torch.device
) -> tuple[float, float]:
    seconds = median_seconds(fn, device, repeats=repeats, warmup=1)
    peak = peak_memory_mib(fn, device)
    print(f"  {label:<44} {seconds:8.3f} s   peak {peak:8.1f} MiB")
    return seconds, peak


def triton_rows(
    ours: Callable[..., tuple[torch.Tensor, ...]],
    gs: GaussianSet,
    repeats: int,
    device: torch.device,
) -> tuple[float, float] | None:
    """W1 through ``backend="triton"`` (CUDA and triton only): forward + backward, forward
    alone, the ratio to the torch path and the largest difference from it."""
    from dego.splatting import triton_backend

    if device.type != "cuda" or not triton_backend.installed():
        print("  backend='triton': needs CUDA and triton, not measured")
        return None

    def triton(scene: GaussianSet) -> tuple[torch.Tensor, ...]:
        return ours(scene, "triton")

    both, _ = report("dego splat, backend='triton'", forward_backward(triton, gs), repeats, device)
    with torch.no_grad():
        forward, _ = report("backend='triton', forward only", lambda: triton(gs), repeats, device)
        difference = max(
            float((a - b).abs().max()) for a, b in zip(triton(gs), ours(gs), strict=True)
        )
    print(f"  max |triton - torch path| (features, depth, alpha): {difference:.2e}")
    return both, forward


def gsplat_call(
    rasterization: Callable[..., tuple[torch.Tensor, torch.Tensor, dict]],
    scene: GaussianSet,
    w2c: torch.Tensor,
    k: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """W1 through a gsplat-style ``rasterization`` (gsplat's own or dego's adapter):
    unbatched tensors, ``RGB+ED``; returns ``(colours with depth, alphas)``."""
    colors, alphas, _ = rasterization(
        scene.means[0],
        scene.quats[0],
        scene.scales[0],
        scene.opacities[0],
        scene.features[0],
        w2c[0],
        k[0],
        704,
        256,
        render_mode="RGB+ED",
    )
    return colors, alphas


def compat_overhead(
    gs: GaussianSet, w2c: torch.Tensor, k: torch.Tensor, repeats: int, device: torch.device
) -> None:
    """``dego.compat.gsplat.rasterization`` (gsplat's call and layout, packed meta) vs
    ``dego.splat`` with the same rules, and ``dego.splat``'s channels-first output vs the
    pipeline's channels-last layout, forward + backward, timed alternately."""

    def direct(scene: GaussianSet) -> tuple[torch.Tensor, ...]:
        out = splat(scene, w2c, k, (256, 704), radius_rule="gsplat>=1.5")
        return out.features, out.depth, out.alpha

    def wrapped(scene: GaussianSet) -> tuple[torch.Tensor, ...]:
        return gsplat_call(compat.rasterization, scene, w2c, k)

    config = SplatConfig(radius_rule="gsplat>=1.5")

    def last(scene: GaussianSet) -> tuple[torch.Tensor, ...]:
        out = pipeline.render(scene, w2c, k, (256, 704), None, None, config, layout="channels_last")
        return out.image, out.alpha

    runs = {
        "direct": forward_backward(direct, gs),
        "last": forward_backward(last, gs),
        "wrapped": forward_backward(wrapped, gs),
    }
    medians = alternating_median_seconds(runs, device, repeats=max(repeats, 5))
    direct_s, last_s, wrapped_s = medians["direct"], medians["last"], medians["wrapped"]
    peaks = {name: peak_memory_mib(fn, device) for name, fn in runs.items()}
    print(
        f"  {'dego splat, radius_rule gsplat>=1.5':<44} {direct_s:8.3f} s   "
        f"peak {peaks['direct']:8.1f} MiB"
    )
    print(f"  {'same, layout channels_last':<44} {last_s:8.3f} s   peak {peaks['last']:8.1f} MiB")
    print(f"  channels-first / channels-last time: {direct_s / last_s:.3f}")
    print(
        f"  {'compat.gsplat.rasterization (packed)':<44} {wrapped_s:8.3f} s   "
        f"peak {peaks['wrapped']:8.1f} MiB"
    )
    print(f"  wrapper overhead: {100 * (wrapped_s / direct_s - 1):+.1f}% of the splat time")


GOAL_GSPLAT = "1.5.3"
"""The gsplat release the Triton path's goals are stated against (its unreleased main
made the forward one thread per pixel, up to 8.8x faster at 128 channels)."""


def main() -> None:
    parser = benchmark_parser(__doc__, repeats=3)
    parser.add_argument("--png", type=Path, default=None, help="save W1 depth and semantics here")
    parser.add_argument("--skip-w1", action="store_true")
    parser.add_argument("--skip-w2", action="store_true")
    args = parser.parse_args()
    device = torch.device(args.device)
    print(splat_versions(device))

    w2c, k = (t.to(device) for t in surround_rig(256, 704))
    gs = occ3d_gaussians(10_000, 48).to(device)

    def ours(scene: GaussianSet, backend: str = "torch") -> tuple[torch.Tensor, ...]:
        out = splat(scene, w2c, k, (256, 704), backend=backend)  # type: ignore[arg-type]
        return out.features, out.depth, out.alpha

    if not args.skip_w1:
        print("W1: 6 x 256x704, 10k Gaussians, C=48, expected depth, forward+backward")
        ours_time, _ = report(
            "dego splat (torch path)", forward_backward(ours, gs), args.repeats, device
        )
        with torch.no_grad():
            forward_time, _ = report(
                "dego splat, forward only", lambda: ours(gs), args.repeats, device
            )
        triton_times = triton_rows(ours, gs, args.repeats, device)
        compat_overhead(gs, w2c, k, args.repeats, device)
        if device.type == "cuda":
            try:
                from gsplat import rasterization
            except ImportError:
                print("  gsplat not installed: no comparison")
            else:

                def theirs(scene: GaussianSet) -> tuple[torch.Tensor, ...]:
                    return gsplat_call(rasterization, scene, w2c, k)

                gsplat_time, _ = report(
                    "gsplat rasterization", forward_backward(theirs, gs), args.repeats, device
                )
                with torch.no_grad():
                    gsplat_forward, _ = report(
                        "gsplat rasterization, forward only",
                        lambda: theirs(gs),
                        args.repeats,
                        device,
                    )
                import gsplat

                if gsplat.__version__ != GOAL_GSPLAT:
                    print(f"  the goals name gsplat {GOAL_GSPLAT}; this is {gsplat.__version__}")
                print(f"  torch path / gsplat time: {ours_time / gsplat_time:.2f}x")
                print(f"  torch path / gsplat forward: {forward_time / gsplat_forward:.2f}x")
                if triton_times is not None:
                    print(
                        f"  triton / gsplat time: {triton_times[0] / gsplat_time:.2f}x (goal <= 2)"
                    )
                    print(
                        f"  triton / gsplat forward: {triton_times[1] / gsplat_forward:.2f}x "
                        "(goal <= 1.5)"
                    )
                from dego.splatting import gsplat_backend

                rule = gsplat_backend.rule_of(gsplat_backend.installed_version() or (1, 5))
                with torch.no_grad():
                    same = splat(gs, w2c, k, (256, 704), radius_rule=rule)  # gsplat's rule
                    mine, (img, alpha) = (same.features, same.depth, same.alpha), theirs(gs)
                    feature_error = (mine[0][0] - img.permute(0, 3, 1, 2)[:, :48]).abs().max()
                    alpha_error = (mine[2][0] - alpha[..., 0]).abs().max()
                    print(
                        f"  max |ours - gsplat|: features {feature_error:.2e}, "
                        f"alpha {alpha_error:.2e}"
                    )
        if args.png is not None:
            with torch.no_grad():
                out = splat(gs, w2c, k, (256, 704))
            save_depth_and_semantics(
                args.png, out.depth[0].cpu(), out.features[0, :, :16].cpu(), out.alpha[0].cpu()
            )
            print(f"  wrote {args.png}")

    if not args.skip_w2:
        w2c2, k2 = (t.to(device) for t in surround_rig(128, 352, cameras=2))
        gs2 = occ3d_gaussians(2_000, 48, seed=1).to(device)

        def tiled(scene: GaussianSet) -> tuple[torch.Tensor, ...]:
            out = splat(scene, w2c2, k2, (128, 352))
            return out.features, out.depth, out.alpha

        print("W2: 2 x 128x352, 2k Gaussians, C=48, forward+backward")
        t_ours, _ = report(
            "dego splat (tile-based)", forward_backward(tiled, gs2), args.repeats, device
        )
        t_dense, _ = report(
            "dense reference (every Gaussian x pixel)",
            forward_backward(lambda s: dense_render(s, w2c2, k2, (128, 352)), gs2),
            1,
            device,
        )
        with torch.no_grad():
            a, b = tiled(gs2), dense_render(gs2, w2c2, k2, (128, 352))
        diff = max(float((x - y).abs().max()) for x, y in zip(a, b, strict=True))
        print(
            f"  speed-up of the tile path: {t_dense / t_ours:.1f}x; max |tile - dense| = {diff:.2e}"
        )


if __name__ == "__main__":
    main()
