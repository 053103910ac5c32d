"""tools/mutate.py, the mutation-testing script: which mutants it makes (not the runs)."""

from __future__ import annotations

import ast
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

from tests.helpers.repo import ROOT, SOURCE_TREE_REASON

pytestmark = pytest.mark.skipif(ROOT is None, reason=SOURCE_TREE_REASON)


def _load() -> ModuleType | None:
    if ROOT is None:
        return None
    spec = importlib.util.spec_from_file_location("dego_tools_mutate", ROOT / "tools" / "mutate.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


mutate: ModuleType = _load()  # type: ignore[assignment]

SOURCE = '''"""Module docstring."""


def check(n: int | None, limit: float = 2.5) -> bool:
    """Docstring."""
    if n is not None and not n < 3:
        raise ValueError(f"n: {n + 1} is too big")
    validate(n)
    return n * 2 == limit
'''


@pytest.fixture
def module(tmp_path: Path) -> Path:
    path = tmp_path / "m.py"
    path.write_text(SOURCE)
    return path


def test_every_kind_of_mutant_on_the_selected_lines(module: Path) -> None:
    made = {(m.line, m.description) for m in mutate.mutants(module, set(range(1, 10)))}
    assert made == {
        (4, "2.5 -> 5.0"),
        (6, "And -> Or"),
        (6, "IsNot -> Is"),
        (6, "drop Not"),
        (6, "Lt -> LtE"),
        (6, "3 -> 4"),
        (7, "raise -> pass"),
        (8, "call statement -> pass"),
        (9, "Mult -> Div"),
        (9, "Eq -> NotEq"),
        (9, "2 -> 3"),
        (9, "return value -> None"),
    }  # nothing in docstrings, annotations (int | None) or f-strings


def test_each_mutant_changes_exactly_its_point(module: Path) -> None:
    original = ast.dump(ast.parse(SOURCE))
    for mutant in mutate.mutants(module, {6, 9}):
        assert ast.dump(ast.parse(mutant.source)) != original
        assert mutant.line in (6, 9)
    assert mutate.mutants(module, {1, 2, 3}) == []


def test_line_ranges() -> None:
    assert mutate.parse_ranges("3-5,9") == {3, 4, 5, 9}
