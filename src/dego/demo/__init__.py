"""The ``dego demo`` pipeline: weakly supervised Gaussian fitting of a synthetic clip.

:class:`DemoClip` stacks a :class:`~dego.data.SyntheticScene`'s frames;
:class:`GaussianSceneModel` holds learnable canonical Gaussians; :func:`fit_scene` fits them
and a :class:`~dego.DecoupledDeformation` to the pseudo labels; :func:`predict_clip` and
:func:`score_clip` voxelise and score the result at every frame (:func:`predict_labels`
and :func:`score_labels` at the reference frame).
"""

from dego.demo.balance import balance_deformation_gradients
from dego.demo.clip import DEMO_FRAME_DT, DemoClip, backproject
from dego.demo.evaluate import (
    DYNAMIC_GROUPS,
    LIFT_SCALE,
    OFFSET_GROUPS,
    ClipScore,
    DynamicCounts,
    dynamic_counts,
    dynamic_regions,
    lift_labels,
    lifted_clip_labels,
    offset_group,
    predict_clip,
    score_clip,
    to_ego,
)
from dego.demo.fit import (
    EXTENSION_VARIANTS,
    LOSS_TERMS,
    REFERENCE_VARIANTS,
    ROW_NAMES,
    VARIANTS,
    FitConfig,
    FitResult,
    build_deformation,
    deformable,
    fit_iterations,
    fit_scene,
    gaussians_at,
    initial_model,
    mask_by_group,
    most_likely_in,
    render,
    rigidity_mask,
    row_name,
)
from dego.demo.model import (
    ALLOCATIONS,
    MOVABLE_CLASSES,
    GaussianSceneModel,
    nearest_neighbour_distance,
)
from dego.demo.offsets import (
    FrameOffsets,
    FrameVelocities,
    agent_under,
    free_offsets,
    free_velocities,
    true_motion,
)
from dego.demo.score import (
    OCCUPANCY_THRESHOLD,
    VariantScore,
    format_table,
    predict_labels,
    score_labels,
)

__all__ = [
    "ALLOCATIONS",
    "DEMO_FRAME_DT",
    "DYNAMIC_GROUPS",
    "EXTENSION_VARIANTS",
    "LIFT_SCALE",
    "LOSS_TERMS",
    "MOVABLE_CLASSES",
    "OCCUPANCY_THRESHOLD",
    "OFFSET_GROUPS",
    "REFERENCE_VARIANTS",
    "ROW_NAMES",
    "VARIANTS",
    "ClipScore",
    "DemoClip",
    "DynamicCounts",
    "FitConfig",
    "FitResult",
    "FrameOffsets",
    "FrameVelocities",
    "GaussianSceneModel",
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
]
