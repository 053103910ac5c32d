"""``benchmarks/gpu_check.sh``: its CPU dry run writes the report and installs nothing."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.helpers.repo import ROOT, SOURCE_TREE_REASON

SCRIPT = None if ROOT is None else ROOT / "benchmarks" / "gpu_check.sh"
STEPS = [
    "tests",
    "bench_splat",
    "bench_splat_sweep",
    "bench_compile",
    "gsplat_parity",
    "bench_voxelize",
    "bench_deformation",
    "bench_rayiou",
    "bench_metrics",
]

pytestmark = [
    pytest.mark.skipif(SCRIPT is None, reason=SOURCE_TREE_REASON),
    pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash"),
]


@pytest.mark.slow
def test_cpu_dry_run_writes_the_report(tmp_path: Path) -> None:
    out = tmp_path / "check"
    done = subprocess.run(
        ["bash", str(SCRIPT), str(out), "--device", "cpu"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    report = (out / "report.md").read_text()
    rows = [line for line in report.splitlines() if line.startswith("| ") and "---" not in line]
    assert [row.split("|")[1].strip() for row in rows[1:]] == STEPS
    assert all("skipped" in row for row in rows[1:])
    assert "- device: cpu" in report
    assert not (out / "install.log").exists()  # a dry run installs nothing


@pytest.mark.parametrize("args", [[], ["out", "--device", "tpu"], ["out", "--bogus"]])
def test_bad_usage_exits_2(tmp_path: Path, args: list[str]) -> None:
    done = subprocess.run(
        ["bash", str(SCRIPT), *args], cwd=tmp_path, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2
    assert "usage" in done.stderr


def test_the_step_limits_fit_in_eight_minutes() -> None:
    """Issue 37: the whole check runs in at most 8 minutes on one GPU. Each step's limit is
    its second argument; gsplat's background build is bounded by the tests' limit."""
    assert SCRIPT is not None
    text = SCRIPT.read_text()
    limits = {m[1]: int(m[2]) for m in re.finditer(r"^\s*step (\w+) (\d+) ", text, re.M)}
    assert set(limits) == set(STEPS)
    assert sum(limits.values()) <= 480, limits
    build = int(re.search(r"timeout (\d+) \"\$PY\" -c \"import gsplat", text)[1])
    assert build <= limits["tests"]
