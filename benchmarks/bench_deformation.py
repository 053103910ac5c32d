"""DecoupledDeformation: one batched pass over all T time steps vs a loop over T.

Workload (the issue's): 10,000 Gaussians, C_g = 256, T = 8, the paper's network (depth
6, width 256, 2-layer heads of width 256), ``deformation_loss`` plus a term on the
deformed Gaussians, forward + backward (and forward alone). The baseline calls the same
module once per time step (``times[i:i+1]``), as the official code loops over T, and sums
the losses before one backward. A third row runs the batched pass without row chunking
(``chunk_rows`` = all rows) to show what the cache-sized chunks buy on a CPU.

    python benchmarks/bench_deformation.py [--device cuda] [--repeats 3] [--n 10000] [--t 8]
"""

from __future__ import annotations

import torch

from dego import GaussianSet
from dego.deformation import DecoupledDeformation, DeformationOutput, deformation_loss

from harness import benchmark_parser, run_comparison


def objective(out: DeformationOutput) -> torch.Tensor:
    gs = out.gaussians
    rendered = gs.means.square().mean() + gs.scales.mean() + gs.opacities.mean()
    return deformation_loss(out).total + rendered + gs.quats.square().mean()


def main() -> None:
    parser = benchmark_parser(__doc__, repeats=3)
    parser.add_argument("--n", type=int, default=10_000, help="number of Gaussians")
    parser.add_argument("--t", type=int, default=8, help="number of time steps")
    parser.add_argument("--channels", type=int, default=256, help="C_g")
    args = parser.parse_args()
    device = torch.device(args.device)
    g = torch.Generator().manual_seed(0)
    n, t, c = args.n, args.t, args.channels
    gaussians = GaussianSet(
        means=torch.rand(1, n, 3, generator=g) * 80 - 40,
        quats=torch.randn(1, n, 4, generator=g),
        scales=torch.rand(1, n, 3, generator=g) * 0.9 + 0.1,
        opacities=torch.rand(1, n, generator=g),
    ).to(device)
    features = torch.randn(1, n, c, generator=g).to(device).requires_grad_()
    times = torch.linspace(-4, 4, t).to(device)
    module = DecoupledDeformation(c)
    with torch.no_grad():  # non-zero last layers, so every layer gets gradients
        for head in [*module.heads.values(), module.mask_head]:
            # drawn on the CPU (a CPU generator cannot fill a CUDA tensor), then moved
            head[-1].weight.normal_(0, 0.01, generator=g)
    module = module.to(device)
    chunkless = DecoupledDeformation(c, chunk_rows=n * t).to(device)
    chunkless.load_state_dict(module.state_dict())

    def batched(net: DecoupledDeformation = module) -> None:
        objective(net(gaussians, features, times)).backward()

    def loop() -> None:
        total = sum(objective(module(gaussians, features, times[i : i + 1])) for i in range(t))
        total.backward()

    def batched_forward() -> None:
        with torch.no_grad():
            module(gaussians, features, times)

    def loop_forward() -> None:
        with torch.no_grad():
            for i in range(t):
                module(gaussians, features, times[i : i + 1])

    run_comparison(
        f"DecoupledDeformation, N={n}, C_g={c}, T={t}, paper preset: batched (ours) vs loop over T",
        {
            "forward + backward": (batched, loop),
            "forward": (batched_forward, loop_forward),
            "fwd + bwd, ours vs ours unchunked": (batched, lambda: batched(chunkless)),
        },
        device,
        repeats=args.repeats,
        notes={"fwd + bwd, ours vs ours unchunked": "ref = one pass over all N T rows"},
    )


if __name__ == "__main__":
    main()
