"""The Triton kernels compile for real GPUs, ahead of time, without one: an NVIDIA H200 /
H100 (sm_90), an A100 (sm_80) and an AMD MI300 (gfx942), each at its shipped launch
configuration; and the compiler's own report for sm_90 and sm_80 (no register spill, the
backward at <= 168 registers a thread). Triton's interpreter (the other tests' CPU path)
accepts programs its compiler rejects, so this is the CI check that the kernels are valid
GPU code. Runs ``benchmarks/triton_registers.py`` in a subprocess: the interpreter must be
off there."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [
    pytest.mark.skipif(importlib.util.find_spec("triton") is None, reason="needs triton"),
    pytest.mark.slow,
]

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"
BACKWARD_REGISTERS = 168
"""The goal for the backward's kernels on sm_90 and sm_80 (the old one: 255, and spilled)."""
KERNELS = ("_forward_kernel", "_backward_kernel (sums)", "_scan_kernel", "_backward_kernel")

COMPILE = r"""
import json, sys
sys.path.insert(0, sys.argv[4])
import triton_registers
from dego.splatting import triton_configs

backend, arch, warp = sys.argv[1], sys.argv[2], int(sys.argv[3])
family = f"sm_{arch}" if backend == "cuda" else arch
config = triton_configs.TABLE[family]
built = triton_registers.compile_kernels(int(arch) if arch.isdigit() else arch, config, backend, warp)
print(json.dumps({name: sorted(kernel.asm) for name, kernel in built.items()}))
"""


def _run(*command: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    return subprocess.run(
        [sys.executable, *command], capture_output=True, text=True, env=env, timeout=600
    )


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
    done = _run("-c", COMPILE, backend, arch, warp, str(BENCHMARKS))
    assert done.returncode == 0, done.stderr[-3000:]
    assert "FP_FUSION" not in done.stderr  # the option is passed, not left to warn
    built = json.loads(done.stdout.strip().splitlines()[-1])
    assert set(built) == set(KERNELS)
    for stages in built.values():
        assert binary in stages


def test_the_compiler_reports_no_spill_at_the_shipped_configurations() -> None:
    done = _run(str(BENCHMARKS / "triton_registers.py"), "--arch", "90", "80", "--json")
    assert done.returncode == 0, done.stderr[-3000:]
    rows = json.loads(done.stdout.strip().splitlines()[-1])
    assert {(r["arch"], r["kernel"]) for r in rows} == {
        (arch, kernel) for arch in ("sm_90", "sm_80") for kernel in KERNELS
    }
    for row in rows:
        print(
            f"{row['arch']} {row['kernel']}: {row['registers']} registers, {row['stack']} B stack"
        )
        assert row["spill_stores"] == 0 and row["stack"] == 0 and row["local"] == 0, row
        assert 0 < row["registers"] <= 255, row
        if row["kernel"] != "_forward_kernel":
            assert row["registers"] <= BACKWARD_REGISTERS, row
