"""A lean ``import dego``: public names import their modules on first use, nothing imports
``torch._dynamo`` or beartype before it is needed, checkpoints load after a bare import, and
``dego --version`` answers before the commands are imported."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
import types
from pathlib import Path

import pytest
import torch
from jaxtyping import TypeCheckError

import dego
from dego import _compile, _typing

SRC = Path(dego.__file__).resolve().parent

# What ``import dego`` may load: the version and the safe-globals registration (not torch).
LOADED_BY_IMPORT = {"dego", "dego._version", "dego._safe_globals"}


def _run(code: str) -> str:
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert result.returncode == 0, result.stderr
    return result.stdout


@pytest.mark.slow
def test_a_fresh_import_is_lean_and_every_name_then_resolves(tmp_path: Path) -> None:
    """One process: what ``import dego`` loaded, then every public name and a submodule;
    then a checkpoint saved here loads with ``weights_only=True`` after only ``import dego``
    (the class's module imported when the pickle names it)."""
    checkpoint = tmp_path / "gaussians.pt"
    gaussians = dego.GaussianSet(
        means=torch.zeros(3, 3),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(3, 4),
        scales=torch.ones(3, 3),
        opacities=torch.full((3,), 0.5),
        features=torch.rand(3, 2),
    )
    torch.save(gaussians, checkpoint)
    code = f"""
import json, sys
import dego
loaded = sorted(m for m in sys.modules if m.startswith("dego"))
heavy = sorted(m for m in ("torch", "torch._dynamo", "beartype") if m in sys.modules)
import torch
before_load = "dego.gaussians" in sys.modules
restored = torch.load({str(checkpoint)!r}, weights_only=True)
modules = [n for n in dego.__all__ if type(getattr(dego, n)).__name__ == "module"]
try:
    dego.no_such_name
except AttributeError as error:
    missing = str(error)
print(json.dumps({{
    "loaded": loaded, "heavy": heavy, "before_load": before_load,
    "restored": type(restored).__name__, "features": restored.features.tolist(),
    "modules": modules, "metrics": dego.metrics.OccupancyMetrics.__name__,
    "dir": sorted(set(dego.__all__) - set(dir(dego))), "missing": missing,
}}))
"""
    seen = json.loads(_run(code).strip().splitlines()[-1])
    assert set(seen["loaded"]) <= LOADED_BY_IMPORT, set(seen["loaded"]) - LOADED_BY_IMPORT
    assert seen["heavy"] == []
    assert not seen["before_load"]
    assert seen["restored"] == "GaussianSet"
    assert seen["features"] == gaussians.features.tolist()
    assert seen["modules"] == []  # every public name is the object, not a module
    assert seen["metrics"] == "OccupancyMetrics"
    assert seen["dir"] == []
    assert seen["missing"] == "module 'dego' has no attribute 'no_such_name'"


@pytest.mark.slow
def test_dego_version_does_not_import_the_commands() -> None:
    code = """
import sys
sys.argv = ["dego", "--version"]
from dego._entry import main
status = main()
print("cli" if "dego.cli" in sys.modules else "no cli", status)
"""
    assert _run(code).splitlines() == [f"dego {dego.__version__}", "no cli 0"]


def test_dego_version_imports_no_torch() -> None:
    """Issue 51: ``dego --version`` took 2.4 s, ``import dego`` (run first by the console
    script ``dego._entry:main`` and by ``python -m dego``) importing torch. Both ways, no
    torch, nothing of dego's beyond the version and the registration, numpy nor jaxtyping."""
    heavy = ("torch", "numpy", "jaxtyping", "beartype")
    code = f"""
import sys
sys.argv = ["dego", "--version"]
from dego._entry import main
status = main()
print(status, sorted(m for m in sys.modules if m.startswith("dego") or m in {heavy!r}))
"""
    lines = _run(code).splitlines()
    assert lines == [f"dego {dego.__version__}", f"0 {sorted(LOADED_BY_IMPORT | {'dego._entry'})}"]
    result = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "dego", "--version"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert (result.returncode, result.stdout) == (0, f"dego {dego.__version__}\n"), result.stderr
    imported = {line.rpartition("|")[2].strip() for line in result.stderr.splitlines()}
    assert not imported & set(heavy), sorted(imported & set(heavy))


def test_the_function_named_like_its_module_stays_the_packages_name(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``import dego`` no longer imports ``dego.spherical_harmonics``: importing that module
    later (it binds its name in the package) still leaves ``dego.spherical_harmonics`` the
    function, as when the package imported the function first."""
    import dego.spherical_harmonics as by_statement

    module = sys.modules["dego.spherical_harmonics"]
    assert isinstance(module, types.ModuleType)
    function = module.spherical_harmonics
    assert dego.spherical_harmonics is function and by_statement is function
    monkeypatch.setattr(dego, "spherical_harmonics", module)  # what the import system does
    assert dego.spherical_harmonics is function
    monkeypatch.setattr(dego, "other_name", module, raising=False)  # other names: as given
    assert dego.other_name is module  # type: ignore[attr-defined]


def _init_tree() -> ast.Module:
    return ast.parse((SRC / "__init__.py").read_text())


def test_the_lazy_names_are_the_type_checkers_names_and_all() -> None:
    """``_EXPORTS`` (run time), the ``if TYPE_CHECKING:`` imports (type checkers, editors)
    and ``__all__`` name the same things from the same modules."""
    typing_block = next(
        node
        for node in _init_tree().body
        if isinstance(node, ast.If) and ast.unparse(node.test) == "TYPE_CHECKING"
    )
    static = {
        alias.name: node.module
        for node in typing_block.body
        if isinstance(node, ast.ImportFrom)
        for alias in node.names
    }
    assert static == dego._EXPORTS
    assert set(dego.__all__) == {*dego._EXPORTS, "__version__", "spherical_harmonics"}
    assert len(dego.__all__) == len(set(dego.__all__))


def _module(source: str, monkeypatch: pytest.MonkeyPatch) -> types.ModuleType:
    """``source`` run as a module (registered: dynamo looks its globals up by name)."""
    module = types.ModuleType("dego_lazy_import_case")
    monkeypatch.setitem(sys.modules, module.__name__, module)
    exec(compile(source, "<case>", "exec"), module.__dict__)
    return module


BOX = """
from __future__ import annotations
import torch
from jaxtyping import Float
from torch import Tensor
from dego._typing import typechecked

class Box:
    def __init__(self, x):
        self.x = x

    @typechecked
    def scaled(self, factor: Float[Tensor, " n"] | float) -> Box:
        return Box(self.x * factor)
"""


def test_a_method_returning_its_class_is_checked_under_compile_from_the_first_call(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Annotations naming the enclosing class (not defined while its body runs) resolve at
    decoration, so a first call under ``torch.compile(fullgraph=True)`` needs no eager step;
    the check holds there and eagerly."""
    box = _module(BOX, monkeypatch).Box

    def step(x: torch.Tensor, factor: torch.Tensor) -> torch.Tensor:
        return box(x).scaled(factor).x

    compiled = torch.compile(step, fullgraph=True, backend="eager")
    x = torch.arange(3.0)
    assert torch.equal(compiled(x, torch.full((3,), 2.0)), 2 * x)
    # the traced check's message (fullgraph: dynamo reports it as unsupported, not eager)
    with pytest.raises(Exception, match=r"parameter 'factor'.{1,4}Actual value: int64\[3\]"):
        compiled(x, torch.ones(3, dtype=torch.int64))
    with pytest.raises(TypeCheckError, match="factor"):
        box(x).scaled(torch.ones(3, 2))
    assert box(x).scaled(3.0).x.tolist() == [0.0, 3.0, 6.0]


def test_an_annotation_naming_nothing_defined_fails_at_decoration(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    with pytest.raises(NameError, match="Undefined"):
        _module(BOX.replace("-> Box:", "-> Undefined:"), monkeypatch)


def test_eager_checks_disable_dynamo_exactly_when_it_is_loaded(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Before ``torch._dynamo`` is imported nothing can be compiling: the eager check runs
    as is (importing dynamo to disable it would cost a second); once it is loaded the
    check runs dynamo-disabled. Either way a wrong argument raises."""
    disabled_runs: list[str] = []

    def recording_disabled(check):  # type: ignore[no-untyped-def]
        def run(*args, **kwargs):  # type: ignore[no-untyped-def]
            disabled_runs.append("disabled")
            return check(*args, **kwargs)

        return run

    monkeypatch.setattr(_compile, "disabled", recording_disabled)

    @_typing.typechecked
    def double(x: torch.Tensor) -> torch.Tensor:
        return 2 * x

    import torch._dynamo  # loaded: the disabled checks

    assert double(torch.ones(2)).tolist() == [2.0, 2.0]
    assert disabled_runs == ["disabled"] * 2  # the arguments', then the result's
    monkeypatch.delitem(sys.modules, "torch._dynamo")  # as before anything compiled
    assert double(torch.ones(2)).tolist() == [2.0, 2.0]
    with pytest.raises(TypeCheckError, match="x"):
        double([1.0])  # type: ignore[arg-type]
    assert disabled_runs == ["disabled"] * 2
