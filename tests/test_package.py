"""Package surface: version, public names, typing marker, bench script."""

from __future__ import annotations

import subprocess
import sys
from importlib import resources
from pathlib import Path

import pytest

import dego


def test_version_and_public_names() -> None:
    assert isinstance(dego.__version__, str) and dego.__version__
    for name in dego.__all__:
        assert hasattr(dego, name), name
    dego.VoxelGrid.occ3d()
    dego.PositionalEncoding(6)


def test_typed_marker_is_shipped() -> None:
    assert resources.files("dego").joinpath("py.typed").is_file()


@pytest.mark.parametrize(
    "script, args",
    [
        ("bench_gaussians.py", ["--n", "500", "--repeats", "2"]),
        ("bench_deformation.py", ["--n", "300", "--t", "3", "--channels", "16", "--repeats", "1"]),
    ],
)
def test_benchmark_script_runs_on_a_small_case(
    source_tree: Path, script: str, args: list[str]
) -> None:
    result = subprocess.run(
        [sys.executable, str(source_tree / "benchmarks" / script), *args],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert "speed-up" in result.stdout
