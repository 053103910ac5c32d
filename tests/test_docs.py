"""The README's and the docs' Python examples run as written (the example scripts: test_examples)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.helpers.repo import source_params

DOCUMENTS = source_params(
    lambda root: [root / "README.md", *sorted((root / "docs").glob("*.md"))], ids=lambda p: p.name
)


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
