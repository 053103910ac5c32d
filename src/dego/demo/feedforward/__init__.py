"""The paper's regime in miniature: one network predicts Gaussians from images for every
scene, trained from pseudo labels with or without deformation (``dego train``).

:mod:`~dego.demo.feedforward.data` renders and caches synthetic scenes;
:class:`GaussianPredictor` turns one frame's six images into a :class:`~dego.GaussianSet`;
:func:`train` fits it (and a :class:`~dego.DecoupledDeformation`) on many scenes' pseudo
labels; :func:`evaluate` scores held-out scenes at t = 0.
"""

from dego.demo.feedforward.data import (
    DataConfig,
    SceneRecord,
    default_cache,
    load_scenes,
    scene_seeds,
)
from dego.demo.feedforward.evaluate import SCORES, evaluate, predict_scene_labels, score_scenes
from dego.demo.feedforward.network import CLASSES, GaussianPredictor, Prediction
from dego.demo.feedforward.training import (
    FEEDFORWARD_VARIANTS,
    TrainConfig,
    TrainResult,
    build_deformation,
    build_network,
    gaussians_at_frame,
    predict,
    step_loss,
    train,
)

__all__ = [
    "CLASSES",
    "FEEDFORWARD_VARIANTS",
    "SCORES",
    "DataConfig",
    "GaussianPredictor",
    "Prediction",
    "SceneRecord",
    "TrainConfig",
    "TrainResult",
    "build_deformation",
    "build_network",
    "default_cache",
    "evaluate",
    "gaussians_at_frame",
    "load_scenes",
    "predict",
    "predict_scene_labels",
    "scene_seeds",
    "score_scenes",
    "step_loss",
    "train",
]
