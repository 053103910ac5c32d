"""The paper's regime in miniature: one network predicts Gaussians from images for every
scene, trained from pseudo labels with or without deformation (``dego train``).

:mod:`~dego.demo.feedforward.data` renders and caches synthetic scenes (frames 0.5 s apart
by default); :class:`GaussianPredictor` turns one frame's six images into a
:class:`~dego.GaussianSet` (its depth optionally anchored on a depth map); :func:`warm_up`
and :func:`fine_tune` (or :func:`train`) fit it, and a :class:`~dego.DecoupledDeformation`,
on many scenes' pseudo labels; :func:`evaluate` scores held-out scenes at t = 0.
"""

from dego.demo.feedforward.data import (
    FEEDFORWARD_FRAME_DT,
    MAX_CLIP_SECONDS,
    DataConfig,
    SceneRecord,
    default_cache,
    load_scenes,
    scene_seeds,
)
from dego.demo.feedforward.evaluate import (
    PEOPLE_SCORES,
    SCORES,
    PeopleCounts,
    evaluate,
    people_counts,
    predict_scene,
    predict_scene_labels,
    score_scenes,
)
from dego.demo.feedforward.network import CLASSES, SCALE_FLOOR, GaussianPredictor, Prediction
from dego.demo.feedforward.training import (
    DEFORMED_VARIANTS,
    DEPTH_SOURCES,
    FEEDFORWARD_VARIANTS,
    RECIPES,
    TrainConfig,
    TrainResult,
    build_deformation,
    build_network,
    fine_tune,
    gaussians_at_frame,
    median_frequency_weights,
    predict,
    step_loss,
    train,
    warm_up,
)

__all__ = [
    "CLASSES",
    "DEFORMED_VARIANTS",
    "DEPTH_SOURCES",
    "FEEDFORWARD_FRAME_DT",
    "FEEDFORWARD_VARIANTS",
    "MAX_CLIP_SECONDS",
    "PEOPLE_SCORES",
    "RECIPES",
    "SCALE_FLOOR",
    "SCORES",
    "DataConfig",
    "GaussianPredictor",
    "PeopleCounts",
    "Prediction",
    "SceneRecord",
    "TrainConfig",
    "TrainResult",
    "build_deformation",
    "build_network",
    "default_cache",
    "evaluate",
    "fine_tune",
    "gaussians_at_frame",
    "load_scenes",
    "median_frequency_weights",
    "people_counts",
    "predict",
    "predict_scene",
    "predict_scene_labels",
    "scene_seeds",
    "score_scenes",
    "step_loss",
    "train",
    "warm_up",
]
