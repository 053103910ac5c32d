"""How close ``backend="triton"`` is to the torch path, case by case, through Triton's
interpreter on CPU (or on CUDA with ``--device cuda``): the largest forward difference
and, per gradient the kernels produce, the relative difference from the float32 torch
path and each one's distance from float64.

    TRITON_INTERPRET=1 python benchmarks/triton_exactness.py [--device cpu|cuda]

The scenes are those of ``tests/splatting/test_triton.py`` (which asserts the bounds;
this prints the numbers behind them). Run from the repository root.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.splatting import test_triton as cases

CASES = {
    "defaults": ({}, {}),
    "expected depth, 5 px tiles": ({}, {"tile_size": 5}),
    "accumulated depth": ({}, {"depth_mode": "accumulated"}),
    "antialiased": ({}, {"rasterize_mode": "antialiased"}),
    "max_alpha 1, T_min 1e-2": ({}, {"max_alpha": 1.0, "transmittance_min": 1e-2}),
    "C = 40": ({"batch": 1, "n": 10, "channels": 40}, {}),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    if args.device == "cpu" and os.environ.get("TRITON_INTERPRET") != "1":
        parser.error("on CPU, set TRITON_INTERPRET=1 (Triton's interpreter)")
    scenes = {
        name: (cases._scene(args.device, culled=True, near_plane=True, **kw), options)
        for name, (kw, options) in CASES.items()
    }
    scenes["70 stacked Gaussians, buckets"] = (cases._deep_stack(args.device), {})
    print(f"torch {torch.__version__}, device {args.device}")
    for name, (scene, options) in scenes.items():
        ours = cases.render(scene, backend="triton", **options)
        theirs = cases.render(scene, backend="torch", **options)
        forward = max(
            float((a - b).abs().max())
            for a, b in ((ours.features, theirs.features), (ours.alpha, theirs.alpha))
            if a.numel()
        )
        triton = cases._screen_gradients(scene, backend="triton", **options)
        torch32 = cases._screen_gradients(scene, backend="torch", **options)
        exact = cases._screen_gradients(scene.to(torch.float64), backend="torch", **options)
        cells = []
        for key, grad in torch32.items():
            if grad is None:
                continue
            reference = exact[key].to(grad)
            cells.append(
                f"{key} {cases._relative(triton[key], grad):.1e} "
                f"(f64: {cases._relative(triton[key], reference):.1e} vs torch "
                f"{cases._relative(grad, reference):.1e})"
            )
        print(f"{name}: forward {forward:.1e}; " + "; ".join(cells), flush=True)


if __name__ == "__main__":
    main()
