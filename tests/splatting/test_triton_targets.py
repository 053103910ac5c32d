"""The Triton kernels compile for real GPUs, ahead of time, without one: an NVIDIA H200 /
H100 (sm_90), an A100 (sm_80) and an AMD MI300 (gfx942). Triton's interpreter (the other
tests' CPU path) accepts programs its compiler rejects, so this is the CI check that the
kernels are valid GPU code. Runs in a subprocess: the interpreter must be off there."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import pytest

pytestmark = [
    pytest.mark.skipif(importlib.util.find_spec("triton") is None, reason="needs triton"),
    pytest.mark.slow,
]

COMPILE = r"""
import inspect, json, sys
import triton
from triton.backends.compiler import GPUTarget
from triton.compiler import ASTSource
from dego.splatting import triton_kernels as kernels

INDEX = {"pairs_ptr", "starts_ptr", "counts_ptr"}
COUNTS = {"tiles_x", "tiles_per_image", "dim"}

def argument_type(name):
    if name in INDEX:
        return "*i64"
    if name == "stop_ptr":
        return "*i32"
    if name.endswith("_ptr"):
        return "*fp32"
    return "i32" if name in COUNTS else "fp32"

backend, arch, warp = sys.argv[1], sys.argv[2], int(sys.argv[3])
target = GPUTarget(backend, int(arch) if arch.isdigit() else arch, warp)
built = {}
for kernel, extra in ((kernels._forward_kernel, {}), (kernels._backward_kernel, {"ABSGRAD": True})):
    constants = {"S": 16, "PIX": 256, "BLOCK_G": kernels.BLOCK_G, "BLOCK_D": kernels.BLOCK_D, **extra}
    names = list(inspect.signature(kernel.fn).parameters)
    signature = {n: "constexpr" if n in constants else argument_type(n) for n in names}
    source = ASTSource(
        fn=kernel,
        signature=signature,
        constexprs={(names.index(k),): v for k, v in constants.items()},
    )
    options = {"num_warps": kernels.NUM_WARPS, "enable_fp_fusion": kernels.FP_FUSION}
    compiled = triton.compile(source, target=target, options=options)
    built[kernel.fn.__name__] = sorted(compiled.asm)
print(json.dumps(built))
"""


@pytest.mark.parametrize(
    ("backend", "arch", "warp", "binary"),
    [
        ("cuda", "90", "32", "cubin"),
        ("cuda", "80", "32", "cubin"),
        ("hip", "gfx942", "64", "hsaco"),
    ],
    ids=["sm_90", "sm_80", "gfx942"],
)
def test_the_kernels_compile_for_gpus(backend: str, arch: str, warp: str, binary: str) -> None:
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    done = subprocess.run(
        [sys.executable, "-c", COMPILE, backend, arch, warp],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "FP_FUSION" not in done.stderr  # the option is passed, not left to warn
    built = json.loads(done.stdout.strip().splitlines()[-1])
    assert set(built) == {"_forward_kernel", "_backward_kernel"}
    for stages in built.values():
        assert binary in stages
