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


@pytest.mark.slow
@pytest.mark.parametrize(
    "script, args, expect",
    [
        ("bench_gaussians.py", ["--n", "500", "--repeats", "2"], "speed-up"),
        (
            "bench_deformation.py",
            ["--n", "300", "--t", "3", "--channels", "16", "--repeats", "1"],
            "speed-up",
        ),
        ("bench_feedforward.py", ["--repeats", "1"], "splatting and losses"),
        ("bench_threads.py", ["--load", "1", "--repeats", "1", "--settle", "1"], "--threads 1"),
        ("bench_infos.py", ["--samples", "40", "--sweeps", "2", "--repeats", "1"], "ratio"),
    ],
)
def test_benchmark_script_runs_on_a_small_case(
    source_tree: Path, script: str, args: list[str], expect: str
) -> None:
    result = subprocess.run(
        [sys.executable, str(source_tree / "benchmarks" / script), *args],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert expect in result.stdout


def test_the_tuning_script_refuses_reported_seeds_and_unknown_fields(
    source_tree: Path, tmp_path: Path
) -> None:
    script = str(source_tree / "benchmarks" / "feedforward_dev.py")
    for args, message in (
        (["--seeds", "4"], "development seeds are >= 100"),
        (["--set", "no_such_field=1"], "no DataConfig or TrainConfig field 'no_such_field'"),
    ):
        result = subprocess.run(
            [sys.executable, script, *args, "--out", str(tmp_path / "out")],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert result.returncode != 0 and message in result.stderr, result.stderr
    assert not (tmp_path / "out").exists()


# -- the README and the repository's small promises -----------------------------------------

CPU_INDEX = "--index-url https://download.pytorch.org/whl/cpu"


def test_readme_installs_the_cpu_torch_build_on_every_path(source_tree: Path) -> None:
    import re

    text = (source_tree / "README.md").read_text()
    blocks = re.findall(r"```(?:bash|text)\n(.*?)```", text, flags=re.DOTALL)
    installs = [
        command.strip()
        for block in blocks
        for line in block.splitlines()
        if not line.startswith("#")
        for command in line.split("&&")
        if re.match(r"python -m pip install torch\b", command.strip())
    ]
    assert len(installs) == 2  # both clone commands (nothing is on a package index yet)
    assert all(command.endswith(CPU_INDEX) for command in installs), installs


FAST_SET_TIME = "52-56 s"
"""The README's test command (the fast set) on the 2-core development machine, idle: three
runs of ``python -m pytest -q`` on 2026-12-06 (README and getting started quote it)."""


def test_readme_states_how_long_the_tests_take(source_tree: Path) -> None:
    text = " ".join((source_tree / "README.md").read_text().split())
    assert "The tests (`python -m pytest -q`" in text
    assert f"run the fast set, in {FAST_SET_TIME} wall on the 2-core" in text
    assert "The slow set, `python -m pytest -q -m slow`" in text
    # getting started quotes the same measurement
    page = " ".join((source_tree / "docs" / "getting-started.md").read_text().split())
    assert f"the fast set of tests ({FAST_SET_TIME} on 2 idle CPU cores" in page
    assert "`python -m pytest -q -m slow`" in page


def test_readme_test_command_installs_what_ci_installs(source_tree: Path) -> None:
    """Issue 41: the README's second set-up command is CI's install and test command, but
    for the index CI does not need (its torch 2.13.0 comes from a local copy)."""
    import re

    text = (source_tree / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.DOTALL)
    (line,) = next(b for b in blocks if "pytest" in b).strip().splitlines()[1:]
    readme = [c.strip().replace(f" {CPU_INDEX}", "") for c in line.split("&&")]
    ci = [
        c.strip()
        for c in (source_tree / ".ci" / "run").read_text().split("\n# Second stage")[0].splitlines()
        if re.match(r"python -m (pip install|pytest)", c.strip())
    ]
    # CI runs the README's commands (the fast set), then the slow set
    assert ci == [*readme, "python -m pytest -q -m slow"]
    assert "not on a package index yet" in " ".join(text.split())


def test_the_slow_marker_is_registered_with_one_description(source_tree: Path) -> None:
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

    from tests.helpers.repo import SLOW_MARKER

    pyproject = tomllib.loads((source_tree / "pyproject.toml").read_text())
    assert pyproject["tool"]["pytest"]["ini_options"]["markers"] == [SLOW_MARKER]
    ci = (source_tree / ".ci" / "run").read_text()
    lines = [line.strip() for line in ci.splitlines()]
    assert "python -m pytest -q" in lines  # the README's command: the fast set
    assert "python -m pytest -q -m slow" in lines  # then the slow set
    assert "-m 'not slow'" in pyproject["tool"]["pytest"]["ini_options"]["addopts"]


def test_built_wheels_are_ignored(source_tree: Path) -> None:
    patterns = (source_tree / ".gitignore").read_text().splitlines()
    assert "*.whl" in patterns  # `pip wheel .` writes one into the repository root


def test_docstrings_cite_only_documents_the_package_has(source_tree: Path) -> None:
    import re

    for path in sorted((source_tree / "src" / "dego").rglob("*.py")):
        for cited in re.findall(r"\b((?:docs|reference)/[\w/.-]+\.md)\b", path.read_text()):
            assert (source_tree / cited).is_file(), (path.name, cited)


def test_docs_index_does_not_deny_the_gpu_numbers(source_tree: Path) -> None:
    index = " ".join((source_tree / "docs" / "index.md").read_text().split())
    performance = (source_tree / "docs" / "performance.md").read_text()
    assert "H200" in performance
    assert "no GPU measurement" not in index and "H200" in index
