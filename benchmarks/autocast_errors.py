"""Errors of every public op under torch.autocast against float32, for docs/validation.md.

Each op of ``tests/helpers/compile_step.py`` runs on the same inputs in float32 and under
``torch.autocast(device, dtype)``; the table gives the output dtype, the largest absolute
error relative to the largest float32 value, and the same for the gradients of
``sum(output^2)`` with respect to the Gaussians' means and features (where the op has
them), as a markdown table.

    python benchmarks/autocast_errors.py [--device cuda] [--seeds 3]
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from dego import distillation_loss, voxelize
from tests.helpers.compile_step import (
    GRID,
    StepInputs,
    StepModules,
    adapter,
    deform,
    gaussian_set,
    make_inputs,
    make_modules,
    render,
    targets,
)

Op = Callable[[StepInputs, StepModules], Tensor]
OPS: dict[str, Op] = {
    "splat (features)": lambda i, m: render(gaussian_set(i), i),
    "gsplat adapter (sum)": lambda i, m: adapter(gaussian_set(i), i),
    "voxelize (density)": lambda i, m: voxelize(gaussian_set(i), GRID).density,
    "deformation (offsets)": lambda i, m: (
        deform(gaussian_set(i), m).gaussians.means - i.means.unsqueeze(1)
    ),
    "deformation (rigid mask)": lambda i, m: deform(gaussian_set(i), m).rigid_mask,
    "teacher targets": lambda i, m: targets(i, m),
    "distillation loss": lambda i, m: distillation_loss(
        render(gaussian_set(i), i), targets(i, m).float()
    ),
}


def relative(a: Tensor, b: Tensor) -> float:
    a, b = a.detach().double(), b.detach().double()
    return float((a - b).abs().max() / a.abs().max().clamp_min(1e-30))


def errors(
    op: Op, device: str, dtype: torch.dtype, seed: int
) -> tuple[str, float, list[float | None]]:
    outputs, grads = [], []
    for autocast in (False, True):
        inputs, modules = make_inputs(seed), make_modules(seed)
        for name, value in vars(inputs).items():
            setattr(inputs, name, value.detach().to(device).requires_grad_(value.requires_grad))
        for module in vars(modules).values():
            module.to(device)
        with torch.autocast(device, dtype=dtype, enabled=autocast):
            out = op(inputs, modules)
        leaves = [inputs.means, inputs.features]
        if out.requires_grad:
            grads.append(torch.autograd.grad(out.float().square().sum(), leaves, allow_unused=True))
        outputs.append(out)
    grad_errors = (
        [None if a is None else relative(a, b) for a, b in zip(*grads, strict=True)]
        if grads
        else [None, None]
    )
    return str(outputs[1].dtype).removeprefix("torch."), relative(*outputs), grad_errors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seeds", type=int, default=3)
    args = parser.parse_args()
    dtypes = [torch.bfloat16] if args.device == "cpu" else [torch.float16, torch.bfloat16]
    for dtype in dtypes:
        name = str(dtype).removeprefix("torch.")
        print(f"\n{args.device} autocast {name}, max over seeds 0-{args.seeds - 1}\n")
        print("| op | output dtype | output error | d/d means error | d/d features error |")
        print("|---|---|---|---|---|")
        for label, op in OPS.items():
            runs = [errors(op, args.device, dtype, seed) for seed in range(args.seeds)]
            cells = [f"{max(r[1] for r in runs):.1e}"]
            for k in range(2):
                values = [r[2][k] for r in runs if r[2][k] is not None]
                cells.append(f"{max(values):.1e}" if values else "-")
            print(f"| {label} | {runs[0][0]} | {' | '.join(cells)} |")


if __name__ == "__main__":
    main()
