"""dego under torch.compile: graph breaks per public op, and compiled vs eager timings.

Graph breaks: ``torch._dynamo.explain`` of each public op alone on the small inputs of
``tests/helpers/compile_step.py`` (splat, the gsplat adapter, voxelize, the deformation network,
the teacher, the distillation loss, ray casting, both metric updates).
W1: 6 surround cameras at 256 x 704, 10,000 Gaussians, C = 48, expected depth, forward +
    backward, eager vs ``torch.compile`` (inductor), timed alternately after the compile;
    with ``--device cuda`` through ``backend="triton"`` when triton is installed (one
    custom operator, no graph break), and the CPU passes (graph breaks, fit step) are
    skipped so that the CUDA timings come first.
Fit step: one step of the demo's fit (``dego demo --quick`` budget, the decoupled variant:
    the deformation network, splatting of the deformed Gaussians, the 2D losses, backward),
    eager vs compiled.

    python benchmarks/bench_compile.py [--device cuda] [--repeats 5] [--skip-w1] [--skip-fit]
        [--breaks-only]
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch._dynamo

from dego import splat

from harness import alternating_median_seconds, benchmark_parser, peak_memory_mib
from scenes import occ3d_gaussians, surround_rig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.helpers.compile_step import OPS, make_inputs, make_modules, op_functions


def graph_breaks() -> None:
    print("graph breaks per op (torch._dynamo.explain)")
    for op in OPS:
        torch._dynamo.reset()
        functions = op_functions(make_inputs(), make_modules())
        if op not in functions:
            continue
        explanation = torch._dynamo.explain(functions[op])()
        where = sorted(
            {
                f"{r.user_stack[-1].filename.rsplit('/', 1)[-1]}:{r.user_stack[-1].lineno}"
                for r in explanation.break_reasons
                if r.user_stack
            }
        )
        print(
            f"  {op:<20} graphs {explanation.graph_count:>3}  breaks "
            f"{explanation.graph_break_count:>3}  at {', '.join(where) or '-'}"
        )


def timed(
    label: str,
    fns: dict[str, Callable[[], None]],
    repeats: int,
    device: torch.device | None = None,
) -> None:
    device = device or torch.device("cpu")
    medians = alternating_median_seconds(fns, device, repeats=repeats, warmup=1)
    peaks = {name: peak_memory_mib(fn, device) for name, fn in fns.items()}
    for name in fns:
        print(f"  {label + ' ' + name:<34} {medians[name]:8.3f} s   peak {peaks[name]:8.1f} MiB")
    print(f"  compiled speed-up: {medians['eager'] / medians['compiled']:.2f}x")


def w1(repeats: int, device: torch.device, backend: str = "torch") -> None:
    w2c, k = (t.to(device) for t in surround_rig(256, 704))
    gs = occ3d_gaussians(10_000, 48).to(device)
    means = gs.means.clone().requires_grad_(True)
    features = gs.features.clone().requires_grad_(True)

    def step() -> torch.Tensor:
        scene = gs.replace(means=means, features=features)
        out = splat(scene, w2c, k, (256, 704), backend=backend)  # type: ignore[arg-type]
        return out.features.square().mean() + out.depth.mean() + out.alpha.mean()

    step().backward()  # eager first: probes the backend
    means.grad = features.grad = None

    compiled = torch.compile(step)

    def run(fn: Callable[[], torch.Tensor]) -> Callable[[], None]:
        def call() -> None:
            fn().backward()
            means.grad = features.grad = None

        return call

    start = time.perf_counter()
    run(compiled)()
    print(
        f"W1 forward + backward, backend {backend!r} on {device} "
        f"(first compiled call {time.perf_counter() - start:.1f} s)"
    )
    timed("W1", {"eager": run(step), "compiled": run(compiled)}, repeats, device)


def fit_step(repeats: int) -> None:
    from dego import SyntheticScene
    from dego.demo import DEMO_FRAME_DT, DemoClip, FitConfig, build_deformation, initial_model
    from dego.demo.command import BUDGETS
    from dego.demo.fit import _frame_losses

    budget = BUDGETS["quick"]
    scene = SyntheticScene(0, num_frames=budget["frames"], frame_dt=DEMO_FRAME_DT)
    clip = DemoClip.from_scene(scene)
    config = FitConfig(num_gaussians=budget["gaussians"])
    model = initial_model(clip, config, torch.Generator().manual_seed(0))
    deformation = build_deformation("decoupled", config, clip, means=model.means.detach())
    generator = torch.Generator().manual_seed(0)

    def losses(index: int) -> torch.Tensor:
        terms = _frame_losses(model, deformation, clip, index, config, generator)
        return terms["semantics"] + terms["depth"] + 1e-3 * terms["deformation"]

    compiled = torch.compile(losses)
    frames = iter(range(10**9))

    def run(fn: Callable[[int], torch.Tensor]) -> Callable[[], None]:
        def call() -> None:
            fn(next(frames) % clip.num_frames).backward()
            model.zero_grad(set_to_none=True)
            deformation.zero_grad(set_to_none=True)

        return call

    start = time.perf_counter()
    for _ in range(clip.num_frames):
        run(compiled)()
    print(
        f"demo fit step, quick budget ({budget['gaussians']} Gaussians, {clip.num_frames} "
        f"frames; compiling every frame took {time.perf_counter() - start:.1f} s)"
    )
    timed("fit step", {"eager": run(losses), "compiled": run(compiled)}, repeats)


def main() -> None:
    parser = benchmark_parser(__doc__, repeats=5)
    parser.add_argument("--skip-w1", action="store_true")
    parser.add_argument("--skip-fit", action="store_true")
    parser.add_argument("--breaks-only", action="store_true")
    args = parser.parse_args()
    device = torch.device(args.device)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, device {device}")
    if device.type == "cuda" and not args.breaks_only:
        # the CUDA timings only: the CPU passes would spend a GPU check's minutes
        from dego.splatting import triton_backend

        backend = "triton" if triton_backend.installed() else "torch"
        if not args.skip_w1:
            w1(args.repeats, device, backend)
        return
    graph_breaks()
    if args.breaks_only:
        return
    if not args.skip_w1:
        w1(args.repeats, device)
    if not args.skip_fit:
        fit_step(args.repeats)


if __name__ == "__main__":
    main()
