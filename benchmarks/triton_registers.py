"""The compiler's own report on dego's Triton kernels, without a GPU: compile them ahead of
time for a GPU family and print each kernel's registers a thread, stack and spill bytes
(``cuobjdump -res-usage`` on the cubin Triton built, both shipped with triton).

    python benchmarks/triton_registers.py [--arch 90 80] [--config shipped|safe|all] [--json]

``--config shipped`` compiles each family's table entry (:mod:`dego.splatting.
triton_configs`); ``safe`` the fallback; ``all`` also a small grid of other settings, to
choose the table from. Prints one row per (arch, settings, kernel); ``--json`` one JSON list
instead (the slow test ``tests/splatting/test_triton_registers.py`` reads it). Run with
``TRITON_INTERPRET`` unset: the interpreter does not compile.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import os
import re
import subprocess
import tempfile
from pathlib import Path

INDEX = {"pairs_ptr", "starts_ptr", "counts_ptr", "first_bucket_ptr", "bucket_tile_ptr"}
COUNTS = {"tiles_x", "tiles_per_image", "dim"}
TILE = 16  # pixels a side: dego's default tile


def _argument_type(name: str) -> str:
    if name in INDEX:
        return "*i64"
    if name == "stop_ptr":
        return "*i32"
    if name.endswith("_ptr"):
        return "*fp32"
    return "i32" if name in COUNTS else "fp32"


def compile_kernels(
    arch: int | str, config: object, backend: str = "cuda", warp: int = 32
) -> dict[str, object]:
    """Compile the four kernels for ``arch`` (``90`` for sm_90; ``"gfx942"`` with ``backend="hip"``
    and ``warp=64``) at ``config`` (a ``LaunchConfig``): Triton's compiled kernels."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from dego.splatting import triton_kernels as kernels

    built = {}
    plan = (
        ("_forward_kernel", kernels._forward_kernel, "forward", {}),
        ("_backward_kernel (sums)", kernels._backward_kernel, "backward", {"SUMS": True}),
        ("_scan_kernel", kernels._scan_kernel, "scan", {}),
        ("_backward_kernel", kernels._backward_kernel, "backward", {"SUMS": False}),
    )
    for name, kernel, role, extra in plan:
        if role == "scan":
            options = {"num_warps": kernels.SCAN_WARPS, "BLOCK_P": kernels.SCAN_PIXELS}
        else:
            options = config.options(role == "backward")  # type: ignore[attr-defined]
        constants = {"S": TILE, **extra, **{k: v for k, v in options.items() if k.isupper()}}
        if role == "forward":
            constants.update(PIX=TILE * TILE, BLOCK_G=kernels.BLOCK_G)
        else:
            constants["BUCKET"] = config.bucket  # type: ignore[attr-defined]
        if role == "backward":
            constants["ABSGRAD"] = not extra["SUMS"]
        names = list(inspect.signature(kernel.fn).parameters)
        signature = {n: "constexpr" if n in constants else _argument_type(n) for n in names}
        source = ASTSource(
            fn=kernel,
            signature=signature,
            constexprs={(names.index(k),): v for k, v in constants.items()},
        )
        compiler = {k: v for k, v in options.items() if not k.isupper()}
        compiler["enable_fp_fusion"] = kernels.FP_FUSION
        if backend != "cuda":
            compiler.pop("maxnreg", None)
        target = GPUTarget(backend, arch, warp)
        built[name] = triton.compile(source, target=target, options=compiler)
    return built


def resources(cubin: bytes) -> dict[str, int]:
    """``REG``, ``STACK``, ``SHARED``, ``LOCAL`` of the one function in ``cubin``."""
    import triton

    tool = Path(triton.__file__).parent / "backends" / "nvidia" / "bin" / "cuobjdump"
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "kernel.cubin"
        path.write_bytes(cubin)
        text = subprocess.run(
            [str(tool), "-res-usage", str(path)], capture_output=True, text=True, check=True
        ).stdout
    found = dict(re.findall(r"\b(REG|STACK|SHARED|LOCAL):(\d+)", text))
    return {k: int(v) for k, v in found.items()}


def spills(compiled: object) -> int:
    """Bytes of spill stores ptxas reports, from the kernel's PTX compiled again with -v."""
    import triton

    tools = Path(triton.__file__).parent / "backends" / "nvidia" / "bin"
    ptx = compiled.asm["ptx"]  # type: ignore[attr-defined]
    arch = compiled.metadata.target.arch  # type: ignore[attr-defined]
    maxnreg = compiled.metadata.maxnreg  # type: ignore[attr-defined]
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "kernel.ptx"
        path.write_text(ptx)
        suffix = "a" if arch >= 90 else ""
        flags = ["-v", f"--gpu-name=sm_{arch}{suffix}", str(path), "-o", os.devnull]
        if maxnreg:
            flags.insert(0, f"--maxrregcount={maxnreg}")
        # triton ships two ptxas; the newer PTX versions need the newer one
        for tool in sorted(tools.glob("ptxas*"), reverse=True):
            done = subprocess.run([str(tool), *flags], capture_output=True, text=True)
            if done.returncode == 0:
                text = done.stderr
                break
        else:
            raise RuntimeError(f"no ptxas in {tools} assembles the kernel: {done.stderr[-300:]}")
    stores = re.findall(r"(\d+) bytes spill stores", text)
    return max((int(s) for s in stores), default=0)


def configurations(choice: str, arch: int) -> list[tuple[str, object]]:
    from dego.splatting import triton_configs as configs

    family = f"sm_{arch}"
    shipped = configs.TABLE.get(family, configs.SAFE)
    chosen = [(f"{family} entry", shipped)] if choice in ("shipped", "all") else []
    if choice in ("safe", "all"):
        chosen.append(("safe default", configs.SAFE))
    if choice == "all":
        for warps, pixels, channels in ((4, 32, 32), (8, 64, 32), (8, 128, 32), (4, 64, 16)):
            config = dataclasses.replace(
                shipped,
                forward_warps=warps,
                backward_warps=warps,
                pixels=pixels,
                channels=channels,
            )
            chosen.append((f"{warps} warps, {pixels} px, {channels} ch", config))
    return chosen


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arch", type=int, nargs="+", default=[90, 80])
    parser.add_argument("--config", choices=("shipped", "safe", "all"), default="shipped")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    if os.environ.get("TRITON_INTERPRET", "0") not in ("", "0"):
        parser.error("unset TRITON_INTERPRET: the interpreter does not compile")
    rows = []
    for arch in args.arch:
        for label, config in configurations(args.config, arch):
            for name, compiled in compile_kernels(arch, config).items():
                usage = resources(compiled.asm["cubin"])  # type: ignore[attr-defined]
                rows.append(
                    {
                        "arch": f"sm_{arch}",
                        "settings": label,
                        "config": dataclasses.asdict(config),  # type: ignore[call-overload]
                        "kernel": name,
                        "registers": usage.get("REG", 0),
                        "stack": usage.get("STACK", 0),
                        "local": usage.get("LOCAL", 0),
                        "spill_stores": spills(compiled),
                    }
                )
                if not args.json:
                    row = rows[-1]
                    print(
                        f"{row['arch']:6} {label:26} {name:23} registers {row['registers']:3}  "
                        f"stack {row['stack']:5} B  spill stores {row['spill_stores']:5} B"
                    )
    if args.json:
        print(json.dumps(rows))


if __name__ == "__main__":
    main()
