"""OccupancyMetrics.update vs the numpy recipe of the Occ3D devkit, per sample.

One 200 x 200 x 16 uint8 sample with a camera mask (as Occ3D-nuScenes ships it). The
reference boolean-masks the grids and runs ``np.bincount(18 * gt + pred)``, after
dropping gt outside [0, 18) and, for the weak protocol, gt in {others, other_flat}.
Ours is a whole ``OccupancyMetrics.update`` call, input validation included. Both run
side by side on the same inputs; the confusion matrices are checked to be identical.

    python benchmarks/bench_metrics.py [--device cuda] [--repeats 200]
"""

from __future__ import annotations

import numpy as np
import torch

from dego import OccupancyMetrics

from harness import benchmark_parser, run_comparison


def occ3d_like_sample(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """uint8 gt/pred with ~70% free voxels and a ~60% camera mask."""
    rng = np.random.default_rng(seed)
    shape = (200, 200, 16)
    gt = rng.integers(0, 17, shape, dtype=np.uint8)
    gt[rng.random(shape) < 0.7] = 17
    pred = np.where(rng.random(shape) < 0.7, gt, rng.integers(0, 18, shape)).astype(np.uint8)
    mask = rng.random(shape) < 0.6
    return pred, gt, mask


def numpy_reference(
    pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, protocol: str
) -> np.ndarray:
    if protocol == "weak":
        mask = mask & ~((gt == 0) | (gt == 12))
    g, p = gt[mask], pred[mask]
    keep = (g >= 0) & (g < 18)
    return np.bincount(18 * g[keep].astype(int) + p[keep], minlength=324).reshape(18, 18)


def main() -> None:
    args = benchmark_parser(__doc__, repeats=200).parse_args()
    device = torch.device(args.device)

    pred, gt, mask = occ3d_like_sample()
    tensors = [torch.from_numpy(a).to(device) for a in (pred, gt, mask)]
    cases, notes = {}, {}
    for protocol in ("occ3d", "weak"):
        metrics = OccupancyMetrics(protocol, device=device)
        metrics.update(*tensors)
        same = np.array_equal(
            metrics.confusion.cpu().numpy(), numpy_reference(pred, gt, mask, protocol)
        )
        notes[f"update, protocol={protocol}"] = f"identical confusion matrix: {same}"

        def ours(metrics: OccupancyMetrics = metrics) -> None:
            metrics.update(*tensors)

        def reference(protocol: str = protocol) -> np.ndarray:
            return numpy_reference(pred, gt, mask, protocol)

        cases[f"update, protocol={protocol}"] = (ours, reference)
    run_comparison(
        f"OccupancyMetrics.update (ours) vs numpy {np.__version__} Occ3D recipe (CPU), "
        "one 200x200x16 uint8 sample",
        cases,
        device,
        repeats=args.repeats,
        notes=notes,
    )


if __name__ == "__main__":
    main()
