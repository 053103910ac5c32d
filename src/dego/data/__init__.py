"""Data: procedural driving scenes (:mod:`dego.data.synthetic`), Occ3D-nuScenes
ground-truth I/O (:mod:`dego.data.occ3d`), nuScenes keyframe poses from infos pickles
(:mod:`dego.data.infos`, through :mod:`dego.data.safe_pickle`) or the JSON tables
(:mod:`dego.data.nuscenes`), and RayIoU ray origins (:mod:`dego.data.origins`)."""

from dego.data.infos import load_infos
from dego.data.keyframes import Keyframe
from dego.data.nuscenes import load_nuscenes_keyframes
from dego.data.occ3d import (
    LABELS_FILENAME,
    OCC3D_SHAPE,
    Occ3DDataset,
    Occ3DLabels,
    Occ3DSample,
    load_occ3d_labels,
    save_occ3d_labels,
)
from dego.data.origins import SceneOrigins
from dego.data.primitives import Primitives
from dego.data.safe_pickle import UnsafePickleError, load_pickle
from dego.data.synthetic import (
    CAMERAS,
    LIDAR_ORIGIN,
    SyntheticAgent,
    SyntheticFrame,
    SyntheticScene,
)

__all__ = [
    "CAMERAS",
    "LABELS_FILENAME",
    "LIDAR_ORIGIN",
    "OCC3D_SHAPE",
    "Keyframe",
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
]
