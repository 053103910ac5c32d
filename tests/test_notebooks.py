"""The example notebooks (examples/*.ipynb) execute from top to bottom without errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers.repo import source_params

NOTEBOOKS = source_params(
    lambda root: sorted((root / "examples").glob("*.ipynb")), ids=lambda p: p.stem
)


def test_there_are_at_least_four_notebooks(source_tree: Path) -> None:
    notebooks = sorted((source_tree / "examples").glob("*.ipynb"))
    assert len(notebooks) >= 4, [p.name for p in notebooks]


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS)
def test_notebook_executes(path: Path, tmp_path: Path) -> None:
    nbclient = pytest.importorskip("nbclient")
    import nbformat  # a dependency of nbclient

    notebook = nbformat.read(path, as_version=4)
    assert notebook.nbformat == 4
    assert not any(cell.get("outputs") for cell in notebook.cells), "stored with outputs"
    client = nbclient.NotebookClient(
        notebook,
        timeout=300,
        kernel_name="python3",
        resources={"metadata": {"path": str(tmp_path)}},  # the working directory
    )
    client.execute()  # raises CellExecutionError, naming the cell, on any error
