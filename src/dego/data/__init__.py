"""Data: procedural driving scenes (:mod:`dego.data.synthetic`) and Occ3D-nuScenes
ground-truth I/O (:mod:`dego.data.occ3d`)."""

from dego.data.occ3d import (
    LABELS_FILENAME,
    OCC3D_SHAPE,
    Occ3DDataset,
    Occ3DLabels,
    Occ3DSample,
    load_occ3d_labels,
    save_occ3d_labels,
)
from dego.data.primitives import Primitives
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
    "Occ3DDataset",
    "Occ3DLabels",
    "Occ3DSample",
    "Primitives",
    "SyntheticAgent",
    "SyntheticFrame",
    "SyntheticScene",
    "load_occ3d_labels",
    "save_occ3d_labels",
]
