"""Splatting at scale: dego's torch path, dego's Triton kernels and gsplat, side by side.

Every case renders N Gaussians in the Occ3D volume into the 6-camera surround rig with C
feature channels and expected depth, forward + backward, for N in 10k / 50k / 200k, images
of 256 x 704, 448 x 800 and 900 x 1600 and C = 18 and 48. Each row is one case: the median
time and the peak extra memory of each backend (``-`` where it is not available, ``failed``
with the error where it raised, for example out of memory), then triton / gsplat ratios.
Rows are printed as they finish; ``--budget`` seconds bound the whole sweep (later cases
are listed as skipped), so a run cut short keeps what it measured.

    python benchmarks/bench_splat_sweep.py --device cuda [--repeats 3] [--budget 240]
        [--backends torch,triton,gsplat] [--torch-max-n 50000] [--quick]

``--torch-max-n``: the torch path, the slowest, is timed up to that N only (the goals
compare Triton with gsplat; the GPU check keeps it to 10k to fit its minutes).

``--quick`` sweeps tiny cases (for the dry run of benchmarks/gpu_check.sh on CPU, where
``triton`` and ``gsplat`` are skipped).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable

import torch

from dego import GaussianSet, splat
from dego.splatting import triton_backend

from harness import benchmark_parser, median_seconds, peak_memory_mib, splat_versions
from scenes import occ3d_gaussians, surround_rig

COUNTS = (10_000, 50_000, 200_000)
SIZES = ((256, 704), (448, 800), (900, 1600))
CHANNELS = (18, 48)
QUICK = ((200, 1_000), ((32, 88), (64, 176)), (18,))


def renderer(backend: str, w2c: torch.Tensor, k: torch.Tensor, size: tuple[int, int]) -> Callable:
    """``GaussianSet -> (colours, depth, alpha)`` through one backend."""
    if backend == "gsplat":
        from gsplat import rasterization

        def through_gsplat(gs: GaussianSet) -> tuple[torch.Tensor, ...]:
            colors, alphas, _ = rasterization(
                gs.means[0],
                gs.quats[0],
                gs.scales[0],
                gs.opacities[0],
                gs.features[0],
                w2c[0],
                k[0],
                size[1],
                size[0],
                render_mode="RGB+ED",
            )
            return colors, alphas

        return through_gsplat

    def through_dego(gs: GaussianSet) -> tuple[torch.Tensor, ...]:
        out = splat(gs, w2c, k, size, backend=backend)  # type: ignore[arg-type]
        return out.features, out.depth, out.alpha

    return through_dego


def forward_backward(render: Callable, gs: GaussianSet) -> Callable[[], None]:
    def run() -> None:
        leaves = [
            t.detach().clone().requires_grad_()
            for t in (gs.means, gs.quats, gs.scales, gs.opacities, gs.features)
        ]
        outputs = render(GaussianSet(*leaves))
        sum(o.float().square().mean() for o in outputs).backward()

    return run


def available(backend: str, device: torch.device) -> str | None:
    """Why ``backend`` cannot run here, or None."""
    if backend == "torch":
        return None
    if device.type != "cuda":
        return "CUDA only"
    if backend == "triton":
        return None if triton_backend.installed() else "triton not installed"
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return "gsplat not installed"
    return None


def main() -> None:
    parser = benchmark_parser(__doc__, repeats=3)
    parser.add_argument("--budget", type=float, default=240.0, help="seconds for the sweep")
    parser.add_argument("--backends", default="torch,triton,gsplat")
    parser.add_argument("--quick", action="store_true", help="tiny cases (a dry run)")
    parser.add_argument(
        "--torch-max-n", type=int, default=50_000, help="time the torch path up to this N"
    )
    args = parser.parse_args()
    device = torch.device(args.device)
    backends = [b for b in args.backends.split(",") if b]
    counts, sizes, channels = QUICK if args.quick else (COUNTS, SIZES, CHANNELS)
    print(splat_versions(device))
    reasons = {b: available(b, device) for b in backends}
    for backend, reason in reasons.items():
        if reason:
            print(f"{backend}: not measured ({reason})")
    if "torch" in backends and not reasons["torch"]:
        print(f"torch: timed up to N = {args.torch_max_n:,} (--torch-max-n)")
    header = f"{'N':>8} {'H x W':>10} {'C':>3}" + "".join(
        f" {b + ' ms':>12} {b + ' MiB':>12}" for b in backends
    )
    header += "  triton/gsplat time, memory"
    print(header)
    print("-" * len(header))
    start = time.perf_counter()
    for n, (height, width), c in itertools.product(counts, sizes, channels):
        label = f"{n:>8} {f'{height}x{width}':>10} {c:>3}"
        if time.perf_counter() - start > args.budget:
            print(f"{label}  skipped (--budget {args.budget:.0f} s spent)")
            continue
        w2c, k = (t.to(device) for t in surround_rig(height, width))
        gs = occ3d_gaussians(n, c).to(device)
        cells, measured = [], {}
        for backend in backends:
            if reasons[backend] or (backend == "torch" and n > args.torch_max_n):
                cells.append(f" {'-':>12} {'-':>12}")
                continue
            run = forward_backward(renderer(backend, w2c, k, (height, width)), gs)
            try:
                seconds = median_seconds(run, device, repeats=args.repeats, warmup=1)
                peak = peak_memory_mib(run, device)
            except (RuntimeError, ValueError, MemoryError) as error:
                cells.append(f" {'failed':>12} {type(error).__name__[:12]:>12}")
                print(f"# {backend} failed at {label.split()}: {str(error).splitlines()[0]}")
                if device.type == "cuda":
                    torch.cuda.empty_cache()
                continue
            measured[backend] = (seconds, peak)
            cells.append(f" {seconds * 1e3:>12.2f} {peak:>12.1f}")
        ratio = ""
        if "triton" in measured and "gsplat" in measured:
            (t_s, t_m), (g_s, g_m) = measured["triton"], measured["gsplat"]
            ratio = f"  {t_s / g_s:.2f}x, {t_m / max(g_m, 1e-9):.2f}x"
        print(label + "".join(cells) + ratio, flush=True)
        del gs
        if device.type == "cuda":
            torch.cuda.empty_cache()
    print(f"sweep: {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
