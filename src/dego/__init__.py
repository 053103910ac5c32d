"""dego: composable, typed PyTorch modules for Gaussian-based 3D semantic occupancy.

Implements the building blocks of "Deformable Gaussian Occupancy" (DeGO, CVPR 2026)
so that they run on CPU and GPU, in float32 and float64, with checked shapes.

``import dego`` is lean: each public name is imported from its module on first use
(PEP 562), so that ``import dego`` or ``dego --version`` loads no other module of dego's,
nor torch.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import types
from typing import TYPE_CHECKING, Any

from dego import _safe_globals
from dego._version import __version__

if TYPE_CHECKING:  # the same names, for type checkers and editors
    from dego._policy import get_memory_limit, memory_limit, set_memory_limit
    from dego.cameras import apply_image_aug, resize_crop_intrinsics, split_projection
    from dego.classes import (
        CLASS_GROUPS,
        CLASS_NAMES,
        FREE_LABEL,
        HUMAN_CENTRIC_CLASSES,
        INSTANCE_CLASSES,
        NUM_CLASSES,
        PALETTE,
        PROTOCOL_CLASSES,
        SCENE_CLASSES,
        Occ3DLabel,
        protocol_classes,
    )
    from dego.data import (
        Keyframe,
        Occ3DDataset,
        Occ3DLabels,
        SceneOrigins,
        SyntheticFrame,
        SyntheticScene,
        load_infos,
        load_nuscenes_keyframes,
        load_occ3d_labels,
        save_occ3d_labels,
    )
    from dego.deformation import (
        DecoupledDeformation,
        DeformationDeltas,
        DeformationLoss,
        DeformationLossWeights,
        DeformationOutput,
        deformation_loss,
    )
    from dego.encoding import PositionalEncoding, positional_encoding
    from dego.evaluation import EvaluationReport, evaluate
    from dego.gaussians import (
        GaussianSet,
        build_covariances,
        build_precisions,
        normalize_quaternions,
        quaternions_to_rotation_matrices,
        rotation_matrices_to_quaternions,
    )
    from dego.grid import VoxelGrid
    from dego.metrics import (
        OccupancyMetrics,
        OccupancyReport,
        RayIoU,
        RayIoUReport,
        confusion_matrix,
        lidar_origins,
        per_class_iou,
    )
    from dego.raycast import cast_rays, generate_lidar_rays, observed_voxels
    from dego.spherical_harmonics import spherical_harmonics
    from dego.splatting import DifferentiableSplatter, SplatOutput, splat
    from dego.teacher import (
        FactorizedSpatioTemporalTeacher,
        FactorizedTeacherFeatures,
        StudentProjector,
        TeacherFeatureCache,
        TeacherOutput,
        distillation_loss,
    )
    from dego.voxelizer import GaussianVoxelizer, VoxelOutput, voxelize

# GaussianSet and the result dataclasses load with torch.load(weights_only=True) once dego
# is imported (torch >= 2.4), without importing their modules yet; see docs/foundation.md,
# "Saving and loading". Registered now where torch is loaded, else when torch's import ends.
_safe_globals.register_when_torch_loads()

_NAMED_LIKE_ITS_MODULE = ("spherical_harmonics",)
"""Public functions named like the submodule that defines them."""


class _Package(types.ModuleType):
    """The type of the ``dego`` module: importing a submodule binds its name in the package
    (``setattr``); for a function named like its module (:data:`_NAMED_LIKE_ITS_MODULE`) the
    package keeps the function instead, whichever of the two is imported first (as when
    ``import dego`` imported the function, and torch with it)."""

    def __setattr__(self, name: str, value: Any) -> None:
        if name in _NAMED_LIKE_ITS_MODULE and isinstance(value, types.ModuleType):
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package

_EXPORTS: dict[str, str] = {
    name: module
    for module, names in {
        "dego._policy": (
            "get_memory_limit",
            "memory_limit",
            "set_memory_limit",
        ),
        "dego.cameras": (
            "apply_image_aug",
            "resize_crop_intrinsics",
            "split_projection",
        ),
        "dego.classes": (
            "CLASS_GROUPS",
            "CLASS_NAMES",
            "FREE_LABEL",
            "HUMAN_CENTRIC_CLASSES",
            "INSTANCE_CLASSES",
            "NUM_CLASSES",
            "PALETTE",
            "PROTOCOL_CLASSES",
            "SCENE_CLASSES",
            "Occ3DLabel",
            "protocol_classes",
        ),
        "dego.data": (
            "Keyframe",
            "Occ3DDataset",
            "Occ3DLabels",
            "SceneOrigins",
            "SyntheticFrame",
            "SyntheticScene",
            "load_infos",
            "load_nuscenes_keyframes",
            "load_occ3d_labels",
            "save_occ3d_labels",
        ),
        "dego.deformation": (
            "DecoupledDeformation",
            "DeformationDeltas",
            "DeformationLoss",
            "DeformationLossWeights",
            "DeformationOutput",
            "deformation_loss",
        ),
        "dego.encoding": (
            "PositionalEncoding",
            "positional_encoding",
        ),
        "dego.evaluation": (
            "EvaluationReport",
            "evaluate",
        ),
        "dego.gaussians": (
            "GaussianSet",
            "build_covariances",
            "build_precisions",
            "normalize_quaternions",
            "quaternions_to_rotation_matrices",
            "rotation_matrices_to_quaternions",
        ),
        "dego.grid": ("VoxelGrid",),
        "dego.metrics": (
            "OccupancyMetrics",
            "OccupancyReport",
            "RayIoU",
            "RayIoUReport",
            "confusion_matrix",
            "lidar_origins",
            "per_class_iou",
        ),
        "dego.raycast": (
            "cast_rays",
            "generate_lidar_rays",
            "observed_voxels",
        ),
        "dego.spherical_harmonics": ("spherical_harmonics",),
        "dego.splatting": (
            "DifferentiableSplatter",
            "SplatOutput",
            "splat",
        ),
        "dego.teacher": (
            "FactorizedSpatioTemporalTeacher",
            "FactorizedTeacherFeatures",
            "StudentProjector",
            "TeacherFeatureCache",
            "TeacherOutput",
            "distillation_loss",
        ),
        "dego.voxelizer": (
            "GaussianVoxelizer",
            "VoxelOutput",
            "voxelize",
        ),
    }.items()
    for name in names
}
"""Each public name -> the module it is imported from on first use."""


def __getattr__(name: str) -> Any:
    """A public name, or a submodule (``dego.metrics``), imported on first use."""
    module = _EXPORTS.get(name)
    if module is not None:
        value = getattr(importlib.import_module(module), name)
    elif not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_EXPORTS})


__all__ = [
    "CLASS_GROUPS",
    "CLASS_NAMES",
    "FREE_LABEL",
    "HUMAN_CENTRIC_CLASSES",
    "INSTANCE_CLASSES",
    "NUM_CLASSES",
    "PALETTE",
    "PROTOCOL_CLASSES",
    "SCENE_CLASSES",
    "DecoupledDeformation",
    "DeformationDeltas",
    "DeformationLoss",
    "DeformationLossWeights",
    "DeformationOutput",
    "DifferentiableSplatter",
    "EvaluationReport",
    "FactorizedSpatioTemporalTeacher",
    "FactorizedTeacherFeatures",
    "GaussianSet",
    "GaussianVoxelizer",
    "Keyframe",
    "Occ3DDataset",
    "Occ3DLabel",
    "Occ3DLabels",
    "OccupancyMetrics",
    "OccupancyReport",
    "PositionalEncoding",
    "RayIoU",
    "RayIoUReport",
    "SceneOrigins",
    "SplatOutput",
    "StudentProjector",
    "SyntheticFrame",
    "SyntheticScene",
    "TeacherFeatureCache",
    "TeacherOutput",
    "VoxelGrid",
    "VoxelOutput",
    "__version__",
    "apply_image_aug",
    "build_covariances",
    "build_precisions",
    "cast_rays",
    "confusion_matrix",
    "deformation_loss",
    "distillation_loss",
    "evaluate",
    "generate_lidar_rays",
    "get_memory_limit",
    "lidar_origins",
    "load_infos",
    "load_nuscenes_keyframes",
    "load_occ3d_labels",
    "memory_limit",
    "normalize_quaternions",
    "observed_voxels",
    "per_class_iou",
    "positional_encoding",
    "protocol_classes",
    "quaternions_to_rotation_matrices",
    "resize_crop_intrinsics",
    "rotation_matrices_to_quaternions",
    "save_occ3d_labels",
    "set_memory_limit",
    "spherical_harmonics",
    "splat",
    "split_projection",
    "voxelize",
]
