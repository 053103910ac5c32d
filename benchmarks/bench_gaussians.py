"""Closed-form precisions vs inverting covariances (the naive baseline).

``GaussianSet.precisions()`` builds ``R diag(1/s^2) R^T`` directly; the baseline is
``torch.linalg.inv_ex(covariances())``. Both run side by side on the same Gaussians;
we report the time ratio, peak memory and the worst relative error of each against
a float64 closed-form reference, for well-conditioned and very flat Gaussians.

    python benchmarks/bench_gaussians.py [--device cuda] [--n 1000000]
"""

from __future__ import annotations

import math

import torch

from dego import GaussianSet

from harness import benchmark_parser, run_comparison


def random_set(n: int, scale_range: tuple[float, float], device: torch.device) -> GaussianSet:
    g = torch.Generator().manual_seed(0)
    lo, hi = math.log(scale_range[0]), math.log(scale_range[1])
    return GaussianSet(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        scales=torch.exp(torch.rand(n, 3, generator=g) * (hi - lo) + lo),
        opacities=torch.rand(n, generator=g),
    ).to(device)


def relative_error(estimate: torch.Tensor, exact: torch.Tensor) -> float:
    norm = torch.linalg.matrix_norm(exact).clamp_min(1e-300)
    return float((torch.linalg.matrix_norm(estimate.double() - exact) / norm).max())


def main() -> None:
    parser = benchmark_parser(__doc__, repeats=20)
    parser.add_argument("--n", type=int, default=200_000, help="number of Gaussians")
    args = parser.parse_args()
    device = torch.device(args.device)

    cases, notes = {}, {}
    for label, scale_range in {
        "s in [0.1, 1] (cond <= 1e2)": (0.1, 1.0),
        "s in [1e-2, 10] (cond <= 1e6)": (1e-2, 10.0),
        "s in [1e-3, 10] (cond <= 1e8)": (1e-3, 10.0),
    }.items():
        gs = random_set(args.n, scale_range, device)

        def naive(gs: GaussianSet = gs) -> torch.Tensor:
            return torch.linalg.inv_ex(gs.covariances()).inverse

        exact = gs.to(torch.float64).precisions()
        failed = int((torch.linalg.inv_ex(gs.covariances()).info != 0).sum())
        notes[label] = (
            f"max rel. err: ours {relative_error(gs.precisions(), exact):.1e}, "
            f"inv {relative_error(naive(), exact):.1e}; inv singular: {failed}"
        )
        cases[label] = (gs.precisions, naive)
    run_comparison(
        f"precisions(): closed form (ours) vs linalg.inv_ex(covariances()), N={args.n}, float32",
        cases,
        device,
        repeats=args.repeats,
        notes=notes,
    )


if __name__ == "__main__":
    main()
