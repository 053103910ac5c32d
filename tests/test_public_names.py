"""No public name lost in a restructure: what each public module listed before the house
moved (0.1.0, before the command, deformation, statistics and picture moves) still
resolves, from the same module or from where it moved, and ``dego.__all__`` only grows."""

from __future__ import annotations

import importlib
import warnings

import pytest

import dego

BEFORE: dict[str, tuple[str, ...]] = {
    "dego": (
        "CLASS_GROUPS",
        "CLASS_NAMES",
        "DecoupledDeformation",
        "DeformationDeltas",
        "DeformationLoss",
        "DeformationLossWeights",
        "DeformationOutput",
        "DifferentiableSplatter",
        "EvaluationReport",
        "FREE_LABEL",
        "FactorizedSpatioTemporalTeacher",
        "FactorizedTeacherFeatures",
        "GaussianSet",
        "GaussianVoxelizer",
        "HUMAN_CENTRIC_CLASSES",
        "INSTANCE_CLASSES",
        "Keyframe",
        "NUM_CLASSES",
        "Occ3DDataset",
        "Occ3DLabel",
        "Occ3DLabels",
        "OccupancyMetrics",
        "OccupancyReport",
        "PALETTE",
        "PROTOCOL_CLASSES",
        "PositionalEncoding",
        "RayIoU",
        "RayIoUReport",
        "SCENE_CLASSES",
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
    ),
    "dego.deformation": (
        "DecoupledDeformation",
        "DeformationDeltas",
        "DeformationLoss",
        "DeformationLossWeights",
        "DeformationOutput",
        "MAX_LOG_SCALE_CHANGE",
        "OFFICIAL_CHECKPOINT_PREFIX",
        "PARAMETERS",
        "REDUCTIONS",
        "StateDictMismatchError",
        "deformation_loss",
        "quaternion_multiply",
        "shift_opacity_logit",
    ),
    "dego.viz": (
        "add_class_legend",
        "bev_labels",
        "camera_panels",
        "colorize_labels",
        "compare_bev",
        "plot_bev",
        "plot_occupancy_3d",
        "save_figure",
    ),
    "dego.demo": (
        "ALLOCATIONS",
        "ClipScore",
        "DEMO_FRAME_DT",
        "DYNAMIC_GROUPS",
        "DemoClip",
        "DynamicCounts",
        "FitConfig",
        "FitResult",
        "FrameOffsets",
        "FrameVelocities",
        "GaussianSceneModel",
        "LIFT_SCALE",
        "LOSS_TERMS",
        "MOVABLE_CLASSES",
        "OCCUPANCY_THRESHOLD",
        "OFFSET_GROUPS",
        "REFERENCE_VARIANTS",
        "ROW_NAMES",
        "VARIANTS",
        "VariantScore",
        "agent_under",
        "backproject",
        "balance_deformation_gradients",
        "build_deformation",
        "deformable",
        "dynamic_counts",
        "dynamic_regions",
        "fit_iterations",
        "fit_scene",
        "format_table",
        "free_offsets",
        "free_velocities",
        "gaussians_at",
        "initial_model",
        "lift_labels",
        "lifted_clip_labels",
        "mask_by_group",
        "most_likely_in",
        "nearest_neighbour_distance",
        "offset_group",
        "predict_clip",
        "predict_labels",
        "render",
        "rigidity_mask",
        "row_name",
        "score_clip",
        "score_labels",
        "to_ego",
        "true_motion",
        "weak_losses",
    ),
    "dego.evaluation.command": (
        "MAX_THREADS",
        "MAX_WORKERS",
        "add_arguments",
        "add_threads_argument",
        "apply_threads",
        "build_parser",
        "main",
        "parse_classes",
        "parse_device",
        "run",
    ),
    "dego.study": (
        "COMPARISONS",
        "DEFAULT_STUDY_VARIANTS",
        "HEADLINE",
        "Interval",
        "MASK_METRICS",
        "METRICS",
        "MIN_INTERVAL_SEEDS",
        "PAIRED_METRICS",
        "PICTURED_GAINS",
        "QUICK_STUDY",
        "STUDY_VARIANTS",
        "StudyConfig",
        "StudyRun",
        "check_distinct",
        "check_seeds",
        "mask_statistics",
        "mean_interval",
        "paired_differences",
        "roc_auc",
        "run_study",
        "study_figure",
        "study_picture",
        "study_report",
        "summarise",
        "write_study",
    ),
    "dego.metrics": (
        "OccupancyMetrics",
        "OccupancyReport",
        "RayIoU",
        "RayIoUReport",
        "SURROUNDOCC_REMOVED_CLASSES",
        "WEAK_REMOVED_CLASSES",
        "binary_occupancy_confusion",
        "confusion_matrix",
        "lidar_origins",
        "per_class_iou",
    ),
    "dego.splatting": (
        "DifferentiableSplatter",
        "Projection",
        "SplatConfig",
        "SplatOutput",
        "TileLists",
        "build_tile_lists",
        "project_gaussians",
        "splat",
    ),
    "dego.teacher": (
        "AttentionBlock",
        "DistillationLoss",
        "FactorizedSpatioTemporalTeacher",
        "FactorizedTeacherFeatures",
        "StudentProjector",
        "TeacherFeatureCache",
        "TeacherOutput",
        "cosine_distance_map",
        "distillation_loss",
        "rotary_2d",
    ),
    "dego.data": (
        "CAMERAS",
        "Keyframe",
        "LABELS_FILENAME",
        "LIDAR_ORIGIN",
        "OCC3D_SHAPE",
        "Occ3DDataset",
        "Occ3DLabels",
        "Occ3DSample",
        "Primitives",
        "SceneOrigins",
        "SyntheticAgent",
        "SyntheticFrame",
        "SyntheticScene",
        "UnsafePickleError",
        "load_infos",
        "load_nuscenes_keyframes",
        "load_occ3d_labels",
        "load_pickle",
        "save_occ3d_labels",
    ),
}
"""Each module's ``__all__`` as it was (``dego.study``: its public definitions; it had no
``__all__``)."""

MOVED_MODULES = {"dego.study": "dego.demo.study"}  # the study runner, beside its command
"""Modules that moved whole (``dego.study`` still imports, with a warning)."""

RENAMED = {"dego.demo.weak_losses": "dego.losses.rendering_loss"}  # on plain tensors
"""Names that became another name elsewhere."""


def new_home(module: str, name: str) -> tuple[str, str]:
    """Where ``module.name`` is now: ``(module, name)``."""
    renamed = RENAMED.get(f"{module}.{name}")
    if renamed is not None:
        where, _, new_name = renamed.rpartition(".")
        return where, new_name
    return MOVED_MODULES.get(module, module), name


def test_dego_all_only_grows() -> None:
    assert set(BEFORE["dego"]) <= set(dego.__all__)


@pytest.mark.parametrize("module", sorted(BEFORE))
def test_every_former_public_name_resolves(module: str) -> None:
    missing = []
    for former in BEFORE[module]:
        where, name = new_home(module, former)
        if not hasattr(importlib.import_module(where), name):
            missing.append(f"{where}.{name}")
    assert not missing


def test_the_former_study_module_still_imports_with_a_warning() -> None:
    import sys

    sys.modules.pop("dego.study", None)
    with pytest.warns(DeprecationWarning, match="dego.demo.study"):
        study = importlib.import_module("dego.study")
    new = importlib.import_module("dego.demo.study")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name in BEFORE["dego.study"]:
            assert getattr(study, name) is getattr(new, name)
