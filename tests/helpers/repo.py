"""Where the repository (the source tree) is, when the tests run from it.

The tests also run from a copy of `tests/` against an installed wheel (`.ci/run`, second
stage). There, README.md, docs/, examples/ and benchmarks/ do not exist, and the tests that
read them skip with `SOURCE_TREE_REASON` instead of failing or finding nothing.

The tree is `$DEGO_SOURCE_TREE` when that is set (it must then be the repository), otherwise the
first directory above this file that holds both `pyproject.toml` and `src/dego/`.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import pytest

SOURCE_TREE_REASON = "needs the source tree (README.md, docs/, examples/, benchmarks/)"
ENV_VAR = "DEGO_SOURCE_TREE"


def is_source_tree(path: Path) -> bool:
    return (path / "pyproject.toml").is_file() and (path / "src" / "dego").is_dir()


def find_source_tree() -> Path | None:
    """The repository root, or None when these tests are a copy outside it."""
    explicit = os.environ.get(ENV_VAR)
    if explicit:
        path = Path(explicit).expanduser().resolve()
        if not is_source_tree(path):
            raise RuntimeError(f"{ENV_VAR}={explicit!r} is not the dego repository")
        return path
    for directory in Path(__file__).resolve().parents:
        if is_source_tree(directory):
            return directory
    return None


ROOT: Path | None = find_source_tree()

needs_source_tree = pytest.mark.skipif(ROOT is None, reason=SOURCE_TREE_REASON)


def source_params(
    values: Callable[[Path], Iterable[Any]], ids: Callable[[Any], str] | None = None
) -> list[Any]:
    """Parameters for a test over repository files: `values(ROOT)` in the tree; outside it one
    skipped parameter with `SOURCE_TREE_REASON` (never pytest's "got empty parameter set")."""
    if ROOT is None:
        return [
            pytest.param(
                None, marks=pytest.mark.skip(reason=SOURCE_TREE_REASON), id="no-source-tree"
            )
        ]
    return [pytest.param(v, id=ids(v) if ids else None) for v in values(ROOT)]


SLOW_MARKER = (
    "slow: a case over ~0.3 s (subprocess, example, notebook, fit, compile, big gradcheck); "
    "left out of the default run `pytest` (the fast set), run with `pytest -m slow`; CI runs "
    "both"
)
"""The ``slow`` marker's description, as pyproject.toml registers it (a test checks)."""
