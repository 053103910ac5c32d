"""The classes that ``torch.load(weights_only=True)`` may rebuild, and their registration.

Kept apart from :mod:`dego._serialization` (which every result class imports) so that
listing the classes creates no import circle: only ``dego/__init__`` imports this module.
"""

from __future__ import annotations

import functools
from typing import Any

import torch

from dego.deformation import (
    DeformationDeltas,
    DeformationLoss,
    DeformationLossWeights,
    DeformationOutput,
)
from dego.gaussians import GaussianSet
from dego.grid import VoxelGrid
from dego.metrics.rayiou import RayIoUReport
from dego.metrics.report import OccupancyReport
from dego.splatting.projection import Projection
from dego.splatting.splatter import SplatOutput
from dego.teacher.factorized import TeacherOutput
from dego.voxelizer import VoxelOutput

_FORMER_NAMES = {
    f"dego.deformation.{cls.__name__}": cls
    for cls in (DeformationDeltas, DeformationLossWeights, DeformationOutput)
}
"""Where checkpoints saved before a module split name a class (they still load)."""


def safe_types() -> tuple[type, ...]:
    """The classes :func:`register_safe_globals` allowlists for ``weights_only`` loading:
    those with checked pickle state, and the dataclasses nested in them."""
    return (
        GaussianSet,
        SplatOutput,
        Projection,
        VoxelOutput,
        DeformationOutput,
        DeformationDeltas,
        DeformationLossWeights,
        DeformationLoss,
        VoxelGrid,
        TeacherOutput,
        OccupancyReport,
        RayIoUReport,
    )


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

    target: type = object

    def __new__(cls, *args: Any, **kwargs: Any) -> Any:
        if args or kwargs:
            return cls.target(*args, **kwargs)
        return object.__new__(cls)

    def __setstate__(self, state: Any) -> None:
        target = self.target
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
            f"{self.target.__name__}: the pickle made this object but never gave it its "
            f"fields (no state): a damaged or hostile file; nothing was built (reading {name!r})"
        )

    def __repr__(self) -> str:
        return f"<{self.target.__name__} that its pickle never built>"


@functools.cache
def _stand_in(cls: type) -> type:
    """The :class:`_Unbuilt` stand-in of ``cls`` (one per class)."""
    return type(f"Unbuilt{cls.__name__}", (_Unbuilt,), {"target": cls})


def register_safe_globals() -> bool:
    """Allowlist :func:`safe_types` for ``torch.load(weights_only=True)``; ``False`` (and
    nothing registered) on torch < 2.4, which has no ``add_safe_globals``: load the
    ``to_dict`` form there.

    From torch 2.5 each class's pickled name (and the names it had before a module split)
    resolves to its :class:`_Unbuilt` stand-in, so that a pickle cannot leave a dego object
    whose fields were never checked; torch 2.4 allowlists the classes themselves."""
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is None:
        return False
    names = {f"{cls.__module__}.{cls.__qualname__}": cls for cls in safe_types()}
    try:  # (object, name) pairs: torch >= 2.5
        add([(_stand_in(cls), name) for name, cls in {**names, **_FORMER_NAMES}.items()])
    except (TypeError, AttributeError):
        add(list(safe_types()))
    return True


__all__ = ["register_safe_globals", "safe_types"]
