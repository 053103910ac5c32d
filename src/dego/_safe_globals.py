"""The classes that ``torch.load(weights_only=True)`` may rebuild, and their registration.

The classes are named, not imported: ``import dego`` registers them without loading their
modules (and without an import circle with :mod:`dego._serialization`, which every result
class imports); a class is imported when a pickle first names it.

``import dego`` does not import torch either (``dego --version`` answers without it):
:func:`register_when_torch_loads` registers the classes at once where torch is loaded
already, else as soon as torch's import finishes, so that ``import dego`` then ``import
torch`` loads dego's objects with ``weights_only=True`` as ``import torch`` then ``import
dego`` does.
"""

from __future__ import annotations

import functools
import importlib
import importlib.abc
import importlib.util
import sys
import threading
from collections.abc import Sequence
from importlib.machinery import ModuleSpec
from types import ModuleType
from typing import Any

_SAFE_NAMES = (
    "dego.gaussians.GaussianSet",
    "dego.splatting.splatter.SplatOutput",
    "dego.splatting.projection.Projection",
    "dego.voxelizer.VoxelOutput",
    "dego.deformation.results.DeformationOutput",
    "dego.deformation.results.DeformationDeltas",
    "dego.deformation.loss.DeformationLossWeights",
    "dego.deformation.loss.DeformationLoss",
    "dego.grid.VoxelGrid",
    "dego.teacher.factorized.TeacherOutput",
    "dego.metrics.report.OccupancyReport",
    "dego.metrics.rayiou.RayIoUReport",
)
"""Where each class of :func:`safe_types` is defined (``module.qualname``, its pickled name):
by name, so that registering them imports none of their modules."""

_FORMER_NAMES = {
    # in dego.deformation, one module, until it was split (the names the face re-exports now)
    **{
        f"dego.deformation.{name}": f"dego.deformation.{module}.{name}"
        for module, name in [
            ("results", "DeformationDeltas"),
            ("loss", "DeformationLossWeights"),
            ("results", "DeformationOutput"),
        ]
    },
    # in dego.deformation_results, until dego.deformation became a package
    **{
        f"dego.deformation_results.{name}": f"dego.deformation.{module}.{name}"
        for module, name in [
            ("results", "DeformationDeltas"),
            ("loss", "DeformationLoss"),
            ("loss", "DeformationLossWeights"),
            ("results", "DeformationOutput"),
        ]
    },
}
"""Where checkpoints saved before a module split name a class (they still load): former
name -> the class's name in :data:`_SAFE_NAMES`."""


@functools.cache
def _class(name: str) -> type:
    """The class named ``module.qualname``, its module imported now."""
    module, _, qualname = name.rpartition(".")
    cls: type = getattr(importlib.import_module(module), qualname)
    return cls


def safe_types() -> tuple[type, ...]:
    """The classes :func:`register_safe_globals` allowlists for ``weights_only`` loading:
    those with checked pickle state, and the dataclasses nested in them (imports them)."""
    return tuple(_class(name) for name in _SAFE_NAMES)


class _Unbuilt:
    """What ``torch.load(weights_only=True)`` builds under the name of one of dego's classes
    until the pickle gives it its state.

    ``NEWOBJ`` makes one (``cls.__new__(cls)``, no constructor); ``BUILD`` hands it the
    state, which :meth:`__setstate__` checks as the constructor does
    (:func:`dego._serialization.set_state`) before the object becomes an instance of the
    class. A pickle that never sends the state (``NEWOBJ; STOP``) leaves this stand-in,
    which is not an instance of the class and says so on any use: no dego object exists
    whose constructor's checks did not run. ``NEWOBJ`` or ``REDUCE`` with arguments call
    the constructor.
    """

    target_name: str = ""
    """The class this stands in for, imported when a pickle first uses it."""

    @classmethod
    def target(cls) -> type:
        return _class(cls.target_name)

    def __new__(cls, *args: Any, **kwargs: Any) -> Any:
        if args or kwargs:
            return cls.target()(*args, **kwargs)
        return object.__new__(cls)

    def __setstate__(self, state: Any) -> None:
        target = self.target()
        built: Any
        if hasattr(target, "__setstate__"):  # dego's checked state and the constructor
            built = object.__new__(target)
            built.__setstate__(state)
        elif isinstance(state, dict):  # a plain dataclass: its constructor
            built = target(**state)
        else:
            raise TypeError(f"{target.__name__}: expected a dict of fields as pickled state")
        object.__setattr__(self, "__class__", target)
        self.__dict__.update(built.__dict__)

    def __getattr__(self, name: str) -> Any:
        raise AttributeError(
            f"{self.target().__name__}: the pickle made this object but never gave it its "
            f"fields (no state): a damaged or hostile file; nothing was built (reading {name!r})"
        )

    def __repr__(self) -> str:
        return f"<{self.target().__name__} that its pickle never built>"


@functools.cache
def _stand_in(name: str) -> type:
    """The :class:`_Unbuilt` stand-in of the class named ``name`` (one per class)."""
    return type(f"Unbuilt{name.rpartition('.')[2]}", (_Unbuilt,), {"target_name": name})


def register_safe_globals() -> bool:
    """Allowlist :func:`safe_types` for ``torch.load(weights_only=True)``; ``False`` (and
    nothing registered) on torch < 2.4, which has no ``add_safe_globals``: load the
    ``to_dict`` form there.

    From torch 2.5 each class's pickled name (and the names it had before a module split)
    resolves to its :class:`_Unbuilt` stand-in, so that a pickle cannot leave a dego object
    whose fields were never checked; no class is imported until a pickle names it. torch
    2.4 allowlists the classes themselves (imported now). Imports torch."""
    import torch

    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is None:
        return False
    names = {**{name: name for name in _SAFE_NAMES}, **_FORMER_NAMES}
    try:  # (object, name) pairs: torch >= 2.5
        add([(_stand_in(target), name) for name, target in names.items()])
    except (TypeError, AttributeError):
        add(list(safe_types()))
    return True


class _RegisterOnTorchImport(importlib.abc.MetaPathFinder):
    """A finder first on ``sys.meta_path`` that finds nothing itself: for ``torch`` it asks
    the other finders for the spec and has that spec's loader call
    :func:`register_safe_globals` once torch's ``__init__`` has run (then the loader is as
    it was). Once that is done it only answers ``None`` (it stays on ``sys.meta_path``:
    removing it while another thread walks the list could make that thread skip a finder)."""

    def __init__(self) -> None:
        self.done = False
        self._finding = threading.local()

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> ModuleSpec | None:
        if fullname != "torch" or self.done or getattr(self._finding, "active", False):
            return None
        self._finding.active = True  # the finders after this one, not this one again
        try:
            spec = importlib.util.find_spec(fullname)
        finally:
            self._finding.active = False
        loader = spec.loader if spec is not None else None
        if spec is None or loader is None or not hasattr(loader, "exec_module"):
            return None  # the import goes on (or fails) without this finder
        run = loader.exec_module

        def exec_module(module: ModuleType) -> None:
            vars(loader).pop("exec_module", None)  # the loader as it was, from now on
            run(module)
            self.done = True
            register_safe_globals()

        try:  # this spec's own loader (one per spec), not its class
            loader.exec_module = exec_module  # type: ignore[method-assign]
        except AttributeError:  # pragma: no cover - a loader without an instance dict
            return None
        return spec


_HOOK = _RegisterOnTorchImport()


def register_when_torch_loads() -> None:
    """:func:`register_safe_globals` now if torch is imported already, else as soon as
    torch's import finishes (without importing torch here)."""
    if "torch" in sys.modules:
        register_safe_globals()
    elif _HOOK not in sys.meta_path:
        sys.meta_path.insert(0, _HOOK)


__all__ = ["register_safe_globals", "register_when_torch_loads", "safe_types"]
