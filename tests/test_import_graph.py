"""The module graph of ``src/dego``: no import cycle, and the core never imports the outer layers.

The graph is read from the source with :mod:`ast` (nothing is imported): every ``import``
and ``from ... import`` anywhere in a module counts, lazy ones inside functions and those
under ``if TYPE_CHECKING:`` included; relative imports are resolved; ``from dego.x import y``
is an edge to ``dego.x.y`` when ``y`` is a submodule, else to ``dego.x``; a literal
``importlib.import_module("dego.x")`` counts too, and so does ``Command("dego.x", ...)`` (an
entry of ``dego.cli.COMMANDS``). Edges to the parent packages that Python
runs implicitly (``dego`` for ``import dego.x``) are not added: they are not import
statements of the module, and every module would otherwise sit in a cycle with ``dego``.

Layers (docs/architecture.md, whose table this file parses): every package sits on one
layer and imports only its own layer and those below; the packages' graph has no cycle; no
module is over :data:`MAX_MODULE_LINES` lines and ``dego.cli`` is under
:data:`MAX_CLI_LINES`. The two-layer rule that came first stays: the *outer* modules
(:data:`OUTER`) may import the core and each other; the *core* (everything else) never
imports an outer module.
"""

from __future__ import annotations

import ast
import re
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
ARCHITECTURE = SRC.parent / "docs" / "architecture.md"
MAX_MODULE_LINES = 850
MAX_CLI_LINES = 200
OUTER = (
    "dego.__main__",
    "dego._entry",
    "dego.cli",
    "dego.compat",
    "dego.demo",
    "dego.study",
    "dego.viz",
)

Graph = dict[str, set[str]]


def module_files(src_root: Path, package: str = "dego") -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` file under ``src_root / package``."""
    modules = {}
    for path in sorted((src_root / package).rglob("*.py")):
        parts = list(path.relative_to(src_root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = path
    return modules


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def _resolve_relative(module: str, is_package: bool, level: int, target: str | None) -> str:
    """The absolute name of ``from <level dots><target> import ...`` written in ``module``."""
    base = module.split(".")
    if not is_package:
        base = base[:-1]  # a module's relative imports start at its package
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join([*base, *([target] if target else [])])


def _nearest_module(name: str, modules: Mapping[str, Path]) -> str | None:
    """``name`` or its longest prefix that is a module of the tree (``None``: external)."""
    parts = name.split(".")
    while parts:
        candidate = ".".join(parts)
        if candidate in modules:
            return candidate
        parts.pop()
    return None


def _imported_names(tree: ast.AST, module: str, is_package: bool) -> Iterable[str]:
    """Every dotted name the module imports, candidates ``x.y`` for ``from x import y``."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                source = _resolve_relative(module, is_package, node.level, node.module)
            else:
                source = node.module or ""
            for alias in node.names:
                if alias.name == "*":
                    yield source
                else:
                    # the submodule if there is one (resolved by _nearest_module), else source
                    yield f"{source}.{alias.name}"
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute | ast.Name)
            and (node.func.attr if isinstance(node.func, ast.Attribute) else node.func.id)
            in ("import_module", "Command")
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
            and not node.args[0].value.startswith(".")
        ):
            yield node.args[0].value


def build_import_graph(src_root: Path, package: str = "dego") -> Graph:
    """The import graph of the package under ``src_root``: module -> modules it imports.

    Only edges between modules of the package are kept; self-edges are dropped (``from .
    import x`` inside ``x``'s own package ``__init__`` is not a cycle of two modules).
    """
    modules = module_files(src_root, package)
    graph: Graph = {name: set() for name in modules}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for imported in _imported_names(tree, name, _is_package(path)):
            target = _nearest_module(imported, modules)
            if target is not None and target != name:
                graph[name].add(target)
    return graph


def strongly_connected_components(graph: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """Tarjan's algorithm (iterative); components in reverse topological order."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    components: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work: list[tuple[str, list[str]]] = [(root, sorted(graph[root]))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, successors = work[-1]
            if successors:
                nxt = successors.pop(0)
                if nxt not in graph:
                    continue
                if nxt not in index:
                    index[nxt] = low[nxt] = counter
                    counter += 1
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, sorted(graph[nxt])))
                elif nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                components.append(sorted(component))
    return components


def import_cycles(graph: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (or a self-import)."""
    return sorted(
        (c for c in strongly_connected_components(graph) if len(c) > 1 or c[0] in graph[c[0]]),
        key=lambda c: (-len(c), c),
    )


def cycle_edges(graph: Mapping[str, Iterable[str]], cycle: Iterable[str]) -> list[tuple[str, str]]:
    members = set(cycle)
    return sorted((a, b) for a in members for b in graph[a] if b in members)


def is_outer(module: str, outer: Iterable[str] = OUTER) -> bool:
    return any(module == o or module.startswith(o + ".") for o in outer)


def layering_violations(
    graph: Mapping[str, Iterable[str]], outer: Iterable[str] = OUTER
) -> list[tuple[str, str]]:
    """Edges from a core module into an outer-layer module."""
    outer = tuple(outer)
    return sorted(
        (a, b)
        for a, targets in graph.items()
        for b in targets
        if not is_outer(a, outer) and is_outer(b, outer)
    )


def describe(graph: Graph) -> str:
    """A summary of the graph: size, every cycle with its edges, every layering violation."""
    cycles = import_cycles(graph)
    lines = [
        f"{len(graph)} modules, {sum(map(len, graph.values()))} edges, "
        f"{len(cycles)} import cycle(s)"
    ]
    for number, cycle in enumerate(cycles, 1):
        edges = cycle_edges(graph, cycle)
        lines.append(
            f"cycle {number}: {len(cycle)} modules, {len(edges)} edges: {', '.join(cycle)}"
        )
        lines += [f"    {a} -> {b}" for a, b in edges]
    violations = layering_violations(graph)
    lines.append(f"{len(violations)} core -> outer edge(s)")
    lines += [f"    {a} -> {b}" for a, b in violations]
    return "\n".join(lines)


@pytest.fixture(scope="module")
def dego_graph() -> Graph:
    if not (SRC / "dego" / "__init__.py").is_file():
        pytest.skip("src/dego is not next to the tests (run from the repository)")
    graph = build_import_graph(SRC)
    print(describe(graph), file=sys.stderr)
    return graph


def test_graph_is_read(dego_graph: Graph) -> None:
    # sanity: the builder sees the package and its well-known edges
    assert {"dego", "dego.gaussians", "dego.splatting", "dego.metrics"} <= set(dego_graph)
    assert "dego.gaussians" in dego_graph["dego"]
    assert sum(map(len, dego_graph.values())) > len(dego_graph)


def test_no_import_cycle(dego_graph: Graph) -> None:
    cycles = import_cycles(dego_graph)
    message = "\n".join(
        f"cycle of {len(c)} modules: {', '.join(c)}; edges: "
        + ", ".join(f"{a} -> {b}" for a, b in cycle_edges(dego_graph, c))
        for c in cycles
    )
    assert not cycles, f"import cycles in src/dego:\n{message}"


def test_core_does_not_import_outer_layers(dego_graph: Graph) -> None:
    violations = layering_violations(dego_graph)
    listing = "\n".join(f"  {a} -> {b}" for a, b in violations)
    assert not violations, (
        "core modules import outer layers (dego.__main__, cli, compat, demo, study, viz):\n"
        + listing
    )


# -- the builder on a synthetic tree ---------------------------------------------------------


def _write_tree(root: Path, files: Mapping[str, str]) -> Path:
    for relative, text in files.items():
        path = root / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    return root


def test_builder_catches_planted_cycle_and_layering_violation(tmp_path: Path) -> None:
    root = _write_tree(
        tmp_path,
        {
            "dego/__init__.py": "from dego.a import f\n",
            # a <-> b through a lazy import in a function and a relative import
            "dego/a.py": "def f():\n    from dego import b\n    return b\n",
            "dego/b.py": "from . import a\n",
            # c <- d only under TYPE_CHECKING, d -> c.sub by `from dego.c import sub`
            "dego/c/__init__.py": "",
            "dego/c/sub.py": (
                "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ..d import g\n"
            ),
            "dego/d.py": "from dego.c import sub\n\ndef g():\n    pass\n",
            # core -> compat (forbidden), compat -> core (fine)
            "dego/compat/__init__.py": "",
            "dego/compat/x.py": "import dego.grid\n",
            "dego/grid.py": "",
            "dego/gaussians.py": "import torch\nfrom .compat.x import thing\n",
            "dego/cli.py": "from dego.compat import x\nfrom dego import gaussians\n",
        },
    )
    graph = build_import_graph(root)
    assert graph["dego.a"] == {"dego.b"}
    assert graph["dego.b"] == {"dego.a"}
    assert graph["dego.d"] == {"dego.c.sub"}
    assert graph["dego.c.sub"] == {"dego.d"}
    assert graph["dego.cli"] == {"dego.compat.x", "dego.gaussians"}
    assert graph["dego"] == {"dego.a"}
    assert import_cycles(graph) == [["dego.a", "dego.b"], ["dego.c.sub", "dego.d"]]
    assert cycle_edges(graph, ["dego.a", "dego.b"]) == [("dego.a", "dego.b"), ("dego.b", "dego.a")]
    assert layering_violations(graph) == [("dego.gaussians", "dego.compat.x")]
    with pytest.raises(AssertionError, match=r"dego\.a, dego\.b;"):
        test_no_import_cycle(graph)
    with pytest.raises(AssertionError, match=r"dego\.gaussians -> dego\.compat\.x"):
        test_core_does_not_import_outer_layers(graph)


def test_builder_outer_modules_may_import_each_other(tmp_path: Path) -> None:
    root = _write_tree(
        tmp_path,
        {
            "dego/__init__.py": "from dego.core import f\n",
            "dego/core.py": "from dego._util import g\n",
            "dego/_util.py": "import os\n",
            "dego/viz.py": "from dego import core\nimport dego.demo.run\n",
            "dego/demo/__init__.py": "",
            "dego/demo/run.py": "from .. import core\nfrom ..viz import plot\n",
        },
    )
    graph = build_import_graph(root)
    assert import_cycles(graph) == [["dego.demo.run", "dego.viz"]]
    assert layering_violations(graph) == []
    assert strongly_connected_components({"a": {"a"}}) == [["a"]]
    assert import_cycles({"a": {"a"}, "b": set()}) == [["a"]]


# -- the layers of docs/architecture.md -------------------------------------------------------


def read_layers(page: Path) -> dict[str, int]:
    """``{unit: layer}`` from the table of docs/architecture.md: rows ``| N | `dego.x`, ... |``."""
    layers: dict[str, int] = {}
    for match in re.finditer(r"^\| (\d+) \| ([^|]+) \|", page.read_text(), flags=re.MULTILINE):
        for name in re.findall(r"`(dego[\w.]*)`", match[2]):
            assert name not in layers, f"{name} is on two layers of {page.name}"
            layers[name] = int(match[1])
    return layers


def unit_of(module: str, units: Iterable[str]) -> str | None:
    """The longest unit of the layer table that is ``module`` or a package holding it."""
    found = [u for u in units if module == u or module.startswith(u + ".")]
    return max(found, key=len) if found else None


def package_of(module: str, graph: Mapping[str, Iterable[str]]) -> str:
    """The package a module belongs to: itself for a package or a top-level module, else
    its parent package (``dego.demo.stats`` -> ``dego.demo``, ``dego.cli`` -> ``dego.cli``)."""
    if any(other.startswith(module + ".") for other in graph):
        return module  # a package
    parent = module.rpartition(".")[0]
    return parent if module.count(".") >= 2 and parent in graph else module


def package_graph(graph: Mapping[str, Iterable[str]]) -> Graph:
    """The graph between packages (:func:`package_of`), self-edges dropped."""
    out: Graph = {package_of(m, graph): set() for m in graph}
    for a, targets in graph.items():
        for b in targets:
            pa, pb = package_of(a, graph), package_of(b, graph)
            if pa != pb:
                out[pa].add(pb)
    return out


def upward_imports(
    graph: Mapping[str, Iterable[str]], layers: Mapping[str, int]
) -> list[tuple[str, str]]:
    """Edges from a module into a module of a higher layer (an arrow back up)."""
    out = []
    for a, targets in graph.items():
        for b in targets:
            ua, ub = unit_of(a, layers), unit_of(b, layers)
            if ua is not None and ub is not None and layers[ua] < layers[ub]:
                out.append((a, b))
    return sorted(out)


@pytest.fixture(scope="module")
def layers() -> dict[str, int]:
    if not ARCHITECTURE.is_file():
        pytest.skip("docs/architecture.md is not next to the tests (run from the repository)")
    return read_layers(ARCHITECTURE)


def test_every_module_sits_on_a_layer(dego_graph: Graph, layers: dict[str, int]) -> None:
    assert set(layers) - set(dego_graph) == set(), "the table names modules that do not exist"
    homeless = sorted(m for m in dego_graph if unit_of(m, layers) is None)
    assert not homeless, f"add these to docs/architecture.md's table: {homeless}"


def test_no_import_goes_up_a_layer(dego_graph: Graph, layers: dict[str, int]) -> None:
    upward = upward_imports(dego_graph, layers)
    listing = "\n".join(
        f"  {a} (layer {layers[unit_of(a, layers)]}) -> {b} (layer {layers[unit_of(b, layers)]})"  # type: ignore[index]
        for a, b in upward
    )
    assert not upward, f"imports back up (docs/architecture.md):\n{listing}"


def test_the_outer_layers_are_the_table_s(layers: dict[str, int]) -> None:
    """The two-layer rule and the table agree: layers 8 and above are :data:`OUTER`."""
    core = {u for u, layer in layers.items() if layer <= 7}
    outer = {u for u, layer in layers.items() if layer >= 8}
    assert all(is_outer(u) for u in outer), sorted(u for u in outer if not is_outer(u))
    assert not any(is_outer(u) for u in core), sorted(u for u in core if is_outer(u))


def test_packages_import_each_other_in_one_direction(dego_graph: Graph) -> None:
    packages = package_graph(dego_graph)
    cycles = import_cycles(packages)
    message = "\n".join(
        f"{', '.join(c)}: " + ", ".join(f"{a} -> {b}" for a, b in cycle_edges(packages, c))
        for c in cycles
    )
    assert not cycles, f"packages that import each other:\n{message}"


def test_modules_are_short_and_the_cli_is_a_table(dego_graph: Graph) -> None:
    files = module_files(SRC)
    lines = {m: len(files[m].read_text(encoding="utf-8").splitlines()) for m in dego_graph}
    long = {m: n for m, n in lines.items() if n > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"
    assert lines["dego.cli"] < MAX_CLI_LINES


def test_layer_rules_catch_a_planted_arrow_back_up(tmp_path: Path) -> None:
    page = tmp_path / "architecture.md"
    page.write_text(
        "| layer | units | owns |\n| --- | --- | --- |\n"
        "| 1 | `dego.a`, `dego.b` | x |\n| 2 | `dego.c` | y |\n| 3 | `dego.c.d` | z |\n"
    )
    layers = read_layers(page)
    assert layers == {"dego.a": 1, "dego.b": 1, "dego.c": 2, "dego.c.d": 3}
    assert unit_of("dego.c.d.e", layers) == "dego.c.d" and unit_of("dego.z", layers) is None
    graph: Graph = {
        "dego.a": {"dego.c.x"},  # layer 1 -> layer 2: up
        "dego.c.x": {"dego.c.d.e", "dego.b"},  # layer 2 -> 3: up; 2 -> 1: down
        "dego.c.d.e": {"dego.c.x"},  # 3 -> 2: down, but a cycle of packages with the line above
        "dego.c": set(),
        "dego.c.d": set(),
        "dego.b": set(),
    }
    assert upward_imports(graph, layers) == [("dego.a", "dego.c.x"), ("dego.c.x", "dego.c.d.e")]
    assert package_of("dego.c.d.e", graph) == "dego.c.d" and package_of("dego.b", graph) == "dego.b"
    assert import_cycles(package_graph(graph)) == [["dego.c", "dego.c.d"]]
