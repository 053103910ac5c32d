"""Occ3D-nuScenes semantic labels, the paper's colour palette and the metric class groups."""

from __future__ import annotations

import enum
from types import MappingProxyType
from typing import Literal


class Occ3DLabel(enum.IntEnum):
    """The 18 Occ3D-nuScenes labels; ``FREE`` (17) marks empty space."""

    OTHERS = 0
    BARRIER = 1
    BICYCLE = 2
    BUS = 3
    CAR = 4
    CONSTRUCTION_VEHICLE = 5
    MOTORCYCLE = 6
    PEDESTRIAN = 7
    TRAFFIC_CONE = 8
    TRAILER = 9
    TRUCK = 10
    DRIVEABLE_SURFACE = 11
    OTHER_FLAT = 12
    SIDEWALK = 13
    TERRAIN = 14
    MANMADE = 15
    VEGETATION = 16
    FREE = 17


NUM_CLASSES = len(Occ3DLabel)
"""18: the 17 semantic classes plus free."""

FREE_LABEL = int(Occ3DLabel.FREE)

CLASS_NAMES: tuple[str, ...] = tuple(label.name.lower() for label in Occ3DLabel)
"""Label names indexed by label value (``CLASS_NAMES[4] == "car"``)."""

PALETTE: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0),  # others
    (255, 106, 30),  # barrier
    (255, 188, 203),  # bicycle
    (255, 255, 0),  # bus
    (255, 0, 0),  # car
    (0, 255, 255),  # construction_vehicle
    (205, 179, 0),  # motorcycle
    (0, 155, 249),  # pedestrian
    (255, 239, 144),  # traffic_cone
    (148, 52, 0),  # trailer
    (177, 5, 244),  # truck
    (255, 0, 255),  # driveable_surface
    (139, 137, 137),  # other_flat
    (85, 0, 76),  # sidewalk
    (110, 243, 65),  # terrain
    (230, 230, 251),  # manmade
    (0, 178, 0),  # vegetation
    (255, 255, 255),  # free (not in the paper; white, as usual for empty space)
)
"""RGB (0-255) per label, from the DeGO paper's LaTeX source; ``free`` is white."""

INSTANCE_CLASSES: tuple[int, ...] = tuple(range(1, 11))
"""Things (barrier .. truck), averaged into InsM."""

SCENE_CLASSES: tuple[int, ...] = (11, 13, 14, 15, 16)
"""Stuff (driveable surface, sidewalk, terrain, manmade, vegetation), averaged into ScnM."""

HUMAN_CENTRIC_CLASSES: tuple[int, ...] = (2, 6, 7)
"""Bicycle, motorcycle, pedestrian: the nonrigid, human-driven classes averaged into HCM."""

CLASS_GROUPS: MappingProxyType[str, tuple[int, ...]] = MappingProxyType(
    {"insm": INSTANCE_CLASSES, "scnm": SCENE_CLASSES, "hcm": HUMAN_CENTRIC_CLASSES}
)
"""The paper's group means by name."""

Protocol = Literal["occ3d", "weak"]

PROTOCOL_CLASSES: MappingProxyType[str, tuple[int, ...]] = MappingProxyType(
    {
        "occ3d": tuple(range(17)),
        "weak": (*range(1, 12), *range(13, 17)),
        "surroundocc": tuple(range(1, 17)),
    }
)
"""Classes averaged into mIoU: ``occ3d`` uses 0..16; ``weak`` (GaussianFlowOcc / DeGO)
drops others (0) and other_flat (12), leaving 15 classes; ``surroundocc`` (SurroundOcc's
labels, as GaussianFormer scores them) uses 1..16, where label 0 is noise."""


def protocol_classes(protocol: str) -> tuple[int, ...]:
    """The classes averaged into mIoU under ``protocol`` (a key of :data:`PROTOCOL_CLASSES`)."""
    try:
        return PROTOCOL_CLASSES[protocol]
    except KeyError:
        raise ValueError(
            f"protocol: unknown protocol {protocol!r}; expected one of {sorted(PROTOCOL_CLASSES)}"
        ) from None


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
    "Occ3DLabel",
    "Protocol",
    "protocol_classes",
]
