"""The README's and the docs' Python examples run as written (the example scripts: test_examples)."""

from __future__ import annotations

import contextlib
import io
import json
import re
import shlex
from pathlib import Path

import pytest
from packaging.requirements import Requirement  # pytest's own dependency

from dego.cli import main
from tests.helpers.repo import ROOT, source_params

DOCUMENTS = source_params(
    lambda root: [root / "README.md", *sorted((root / "docs").glob("*.md"))], ids=lambda p: p.name
)
# Every page and example a user reads for what to install: README, docs/ (API pages too),
# the example scripts and notebooks.
INSTALL_DOCUMENTS = source_params(
    lambda root: [
        root / "README.md",
        *sorted((root / "docs").rglob("*.md")),
        *sorted((root / "examples").glob("*.py")),
        *sorted((root / "examples").glob("*.ipynb")),
    ],
    ids=lambda p: p.relative_to(ROOT).as_posix(),
)
# `pip install` of the distribution by name, with any options and quoting:
# `pip install "dego-occupancy[eval]"`, `pip install -U dego-occupancy`, `pip install dego`
# (that name on PyPI is another project). A clone's `pip install -e ".[eval]"` does not match.
INDEX_INSTALL = re.compile(r"""pip\s+install\s+(?:-\S+\s+)*["']?dego(?:-occupancy)?(?![\w.-])""")


def python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.DOTALL)


@pytest.mark.slow
@pytest.mark.parametrize("path", DOCUMENTS)
def test_python_examples_run(path: Path) -> None:
    namespace: dict[str, object] = {}
    for block in python_blocks(path):  # blocks of one page share a namespace, as in a session
        exec(compile(block, str(path), "exec"), namespace)


def test_readme_has_exactly_two_setup_commands(source_tree: Path) -> None:
    bash_blocks = re.findall(
        r"```bash\n(.*?)```", (source_tree / "README.md").read_text(), flags=re.DOTALL
    )
    commands = [
        line
        for block in bash_blocks
        for line in block.splitlines()
        if line and not line.startswith("#")
    ]
    assert len(commands) == 2
    assert commands[0].endswith("dego demo --quick")
    assert commands[1].endswith("python -m pytest -q")


def test_getting_started_repeats_the_readme_install_commands(source_tree: Path) -> None:
    def blocks(page: Path, kind: str) -> list[str]:
        return re.findall(rf"```{kind}\n(.*?)```", page.read_text(), flags=re.DOTALL)

    readme, page = source_tree / "README.md", source_tree / "docs" / "getting-started.md"
    assert blocks(page, "bash") == blocks(readme, "bash")  # the clone path's two commands
    for document in (readme, page):  # no install command for an index that has no dego yet
        assert 'pip install "dego-occupancy' not in "".join(blocks(document, "text"))


@pytest.mark.parametrize("path", INSTALL_DOCUMENTS)
def test_installs_come_from_the_clone(path: Path) -> None:
    """dego is on no package index yet: every install a page or an example shows is the
    clone's (`pip install -e ".[eval]"`), never one by the distribution's name, which fails."""
    text = path.read_text()
    found = [
        f"{path.name}:{text.count(chr(10), 0, m.start()) + 1}: {m.group(0)!r}"
        for m in INDEX_INSTALL.finditer(text)
    ]
    assert not found, (
        "install from a package index (use the clone's pip install -e):\n" + "\n".join(found)
    )


def test_index_install_pattern() -> None:
    for line in (
        'pip install "dego-occupancy[eval]"',
        "python -m pip install 'dego-occupancy[triton]'",
        "pip install -U dego-occupancy",
        "pip install dego",
    ):
        assert INDEX_INSTALL.search(line), line
    for line in (
        'pip install -e ".[eval]"',
        'python -m pip install -e ".[dev,notebooks]"',
        "pip install torch --index-url https://download.pytorch.org/whl/cpu",
        "pip install degoo",
        "pip uninstall --yes dego",
    ):
        assert not INDEX_INSTALL.search(line), line


@pytest.mark.slow
def test_evaluation_page_synthetic_tree_commands_run(
    source_tree: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """docs/evaluation.md's "try it before any download" block: `dego data write-tree` then
    the `dego eval` command that write-tree itself suggests for that folder; both succeed."""
    text = (source_tree / "docs" / "evaluation.md").read_text()
    head = text[: text.index("\n## ")]  # near the top, before the first section
    block = next(
        b for b in re.findall(r"```bash\n(.*?)```", head, flags=re.DOTALL) if "write-tree" in b
    )
    write, score = (shlex.split(line) for line in block.strip().splitlines())
    assert write[:3] == ["dego", "data", "write-tree"] and score[:2] == ["dego", "eval"]
    folder = write[-1]
    monkeypatch.chdir(tmp_path)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(write[1:]) == 0
    suggested = out.getvalue().split("score them: ", 1)[1].strip()
    for where in (tmp_path.resolve() / folder, tmp_path / folder):
        suggested = suggested.replace(str(where), folder)
    assert score == shlex.split(suggested)
    assert main([*score[1:], "--quiet", "--json", "report.json"]) == 0
    assert json.loads((tmp_path / "report.json").read_text())["samples"] == 2


def test_test_extra_is_light_and_the_readme_says_so(source_tree: Path) -> None:
    """`[test]` runs the suite without dev's heavy downloads (its tests skip what is missing);
    dev includes it; the README says so beside its test command (in prose: still two commands)."""
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    extras = tomllib.loads((source_tree / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]

    def names(extra: str) -> set[str]:  # the distributions an extra pulls in, self-extras expanded
        found: set[str] = set()
        for requirement in map(Requirement, extras[extra]):
            if requirement.name == "dego-occupancy":
                found = found.union(*map(names, requirement.extras))
            else:
                found.add(requirement.name.lower())
        return found

    light = names("test")
    assert {"pytest", "pytest-xdist", "hypothesis", "matplotlib"} <= light
    assert not light & {"triton", "rerun-sdk", "lightning", "torchmetrics", "numba", "mkdocs"}
    assert light <= names("dev")
    setup = (source_tree / "README.md").read_text().split("\n## ")[1]
    assert setup.startswith("Set up") and '`".[test]"` in place of `".[dev]"`' in setup
