"""The ``dego demo`` pipeline: weakly supervised Gaussian fitting of a synthetic clip.

:class:`DemoClip` stacks a :class:`~dego.data.SyntheticScene`'s frames;
:class:`GaussianSceneModel` holds learnable canonical Gaussians; :func:`fit_scene` fits them
and a :class:`~dego.DecoupledDeformation` to the pseudo labels; :func:`predict_labels` and
:func:`score_labels` voxelise and score the result.
"""

from dego.demo.clip import DemoClip, backproject
from dego.demo.fit import (
    LOSS_TERMS,
    VARIANTS,
    FitConfig,
    FitResult,
    build_deformation,
    fit_scene,
    gaussians_at,
    mask_by_group,
    render,
    rigidity_mask,
    weak_losses,
)
from dego.demo.model import GaussianSceneModel, nearest_neighbour_distance
from dego.demo.score import (
    OCCUPANCY_THRESHOLD,
    VariantScore,
    format_table,
    predict_labels,
    score_labels,
)

__all__ = [
    "LOSS_TERMS",
    "OCCUPANCY_THRESHOLD",
    "VARIANTS",
    "DemoClip",
    "FitConfig",
    "FitResult",
    "GaussianSceneModel",
    "VariantScore",
    "backproject",
    "build_deformation",
    "fit_scene",
    "format_table",
    "gaussians_at",
    "mask_by_group",
    "nearest_neighbour_distance",
    "predict_labels",
    "render",
    "rigidity_mask",
    "score_labels",
    "weak_losses",
]
