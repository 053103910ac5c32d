"""What ``import dego`` and ``dego --version`` cost, over ``import torch``, in fresh processes.

Each round starts one Python process per source tree (this checkout, and ``--before SRC``
when given: the ``src`` folder of another checkout, e.g. a ``git worktree`` of an older
commit) and times, inside it: ``import torch``, then ``import dego``, then the first use
of two public names (``dego.splat``, ``dego.GaussianSet``: their modules import then),
then one small eager ``dego.splat`` call (its checks are built on first use); and, as a
separate process, ``python -m dego --version`` end to end. Rounds alternate the trees;
medians (min-max) over ``--repeats`` rounds, with the process's peak RSS.

    python benchmarks/bench_import.py [--repeats 7] [--before ../old/src]
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from harness import benchmark_parser

SRC = Path(__file__).resolve().parents[1] / "src"

_PROBE = """
import json, resource, sys, time
start = time.perf_counter()
import torch
torch_done = time.perf_counter()
import dego
dego_done = time.perf_counter()
modules = sum(name.startswith("dego") for name in sys.modules)
dego.splat, dego.GaussianSet
names_done = time.perf_counter()
gaussians = dego.GaussianSet(
    means=(torch.zeros(4, 3) + torch.tensor([0.0, 0.0, 5.0]))[None],
    quats=torch.tensor([[[1.0, 0.0, 0.0, 0.0]]]).expand(1, 4, 4),
    scales=torch.full((1, 4, 3), 0.2),
    opacities=torch.full((1, 4), 0.5),
    features=torch.rand(1, 4, 3),
)
k = torch.tensor([[20.0, 0, 16], [0, 20.0, 16], [0, 0, 1]])
dego.splat(gaussians, torch.eye(4)[None, None], k[None, None], (32, 32))
splat_done = time.perf_counter()
print(json.dumps({
    "torch": torch_done - start,
    "dego": dego_done - torch_done,
    "names": names_done - dego_done,
    "first splat": splat_done - names_done,
    "dego modules loaded by import dego": modules,
    "dynamo after first splat": "torch._dynamo" in sys.modules,
    "peak MiB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
}))
"""


def _env(src: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(src), "PYTHONDONTWRITEBYTECODE": "0"}


def probe(src: Path) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, "-c", _PROBE], env=_env(src), capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def version_seconds(src: Path) -> float:
    start = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "dego", "--version"], env=_env(src), capture_output=True, check=True
    )
    return time.perf_counter() - start


def _cell(values: list[float]) -> str:
    return f"{statistics.median(values):.3f} ({min(values):.3f}-{max(values):.3f})"


def main() -> None:
    parser = benchmark_parser(__doc__, repeats=7)
    parser.add_argument("--before", type=Path, help="the src folder of another checkout")
    args = parser.parse_args()
    trees = {"now": SRC, **({"before": args.before.resolve()} if args.before else {})}
    for src in trees.values():  # warm the bytecode caches; not timed
        probe(src)
        version_seconds(src)
    rows: dict[str, dict[str, list[float]]] = {name: {} for name in trees}
    dynamo: dict[str, bool] = {}
    for _ in range(args.repeats):
        for name, src in trees.items():
            result = probe(src)
            dynamo[name] = bool(result.pop("dynamo after first splat"))
            result["dego --version"] = version_seconds(src)
            for key, value in result.items():
                rows[name].setdefault(key, []).append(float(value))
    print(
        f"fresh processes, {os.cpu_count()} CPUs, Python {sys.version.split()[0]}; "
        f"median (min-max) seconds over {args.repeats} rounds"
    )
    keys = list(next(iter(rows.values())))
    print("| step | " + " | ".join(trees) + " |")
    print("|---|" + "---:|" * len(trees))
    for key in keys:
        unit = "" if key in ("peak MiB", "dego modules loaded by import dego") else " s"
        cells = [_cell(rows[name][key]) for name in trees]
        print(f"| {key}{unit} | " + " | ".join(cells) + " |")
    print(
        "| torch._dynamo loaded after the first splat | "
        + " | ".join(str(dynamo[n]) for n in trees)
        + " |"
    )
    if "before" in rows:
        for key in ("dego", "dego --version"):
            before, now = (statistics.median(rows[n][key]) for n in ("before", "now"))
            print(f"{key}: {before / now:.1f}x faster now")


if __name__ == "__main__":
    main()
