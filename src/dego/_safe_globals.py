"""The classes that ``torch.load(weights_only=True)`` may rebuild, and their registration.

The classes are named, not imported: ``import dego`` registers them without loading their
modules (and without an import circle with :mod:`dego._serialization`, which every result
class imports); a class is imported when a pickle first names it.
"""

from __future__ import annotations

import functools
import importlib
from typing import Any

import torch

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
    2.4 allowlists the classes themselves (imported now)."""
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is None:
        return False
    names = {**{name: name for name in _SAFE_NAMES}, **_FORMER_NAMES}
    try:  # (object, name) pairs: torch >= 2.5
        add([(_stand_in(target), name) for name, target in names.items()])
    except (TypeError, AttributeError):
        add(list(safe_types()))
    return True


__all__ = ["register_safe_globals", "safe_types"]
