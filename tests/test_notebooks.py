"""The example notebooks (examples/*.ipynb) execute from top to bottom without errors."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "examples").glob("*.ipynb"))


def test_there_are_at_least_four_notebooks() -> None:
    assert len(NOTEBOOKS) >= 4, [p.name for p in NOTEBOOKS]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
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
