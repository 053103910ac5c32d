"""The classes that ``torch.load(weights_only=True)`` may rebuild, and their registration.

Kept apart from :mod:`dego._serialization` (which every result class imports) so that
listing the classes creates no import circle: only ``dego/__init__`` imports this module.
"""

from __future__ import annotations

import contextlib

import torch

from dego.deformation import DeformationDeltas, DeformationLossWeights, DeformationOutput
from dego.gaussians import GaussianSet
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
        TeacherOutput,
        OccupancyReport,
        RayIoUReport,
    )


def register_safe_globals() -> bool:
    """Allowlist :func:`safe_types` for ``torch.load(weights_only=True)``; ``False`` (and
    nothing registered) on torch < 2.4, which has no ``add_safe_globals``: load the
    ``to_dict`` form there."""
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is None:
        return False
    add(list(safe_types()))
    with contextlib.suppress(TypeError, AttributeError):  # (class, name) pairs: torch >= 2.5
        add([(cls, name) for name, cls in _FORMER_NAMES.items()])
    return True


__all__ = ["register_safe_globals", "safe_types"]
