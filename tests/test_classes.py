"""Occ3D-nuScenes labels, palette and metric groups."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from dego import (
    CLASS_GROUPS,
    CLASS_NAMES,
    FREE_LABEL,
    HUMAN_CENTRIC_CLASSES,
    INSTANCE_CLASSES,
    NUM_CLASSES,
    PALETTE,
    SCENE_CLASSES,
    Occ3DLabel,
    protocol_classes,
)

# The class colours of the DeGO paper's figures: the `\definecolor{...}{RGB}{...}` lines of its
# LaTeX source (dego-paper.tex, lines 320-336), copied verbatim so this test needs nothing
# outside the repository.
PAPER_COLOURS = Path(__file__).resolve().parent / "fixtures" / "paper_palette.tex"


def test_labels_and_names() -> None:
    assert NUM_CLASSES == 18 and FREE_LABEL == 17 == Occ3DLabel.FREE
    assert CLASS_NAMES[0] == "others" and CLASS_NAMES[4] == "car" and CLASS_NAMES[17] == "free"
    assert CLASS_NAMES[5] == "construction_vehicle" and CLASS_NAMES[11] == "driveable_surface"
    assert CLASS_NAMES[12] == "other_flat" and CLASS_NAMES[16] == "vegetation"
    assert [int(label) for label in Occ3DLabel] == list(range(18))


def test_groups_and_protocols() -> None:
    assert INSTANCE_CLASSES == tuple(range(1, 11))
    assert SCENE_CLASSES == (11, 13, 14, 15, 16)
    assert HUMAN_CENTRIC_CLASSES == (2, 6, 7)
    assert dict(CLASS_GROUPS) == {
        "insm": INSTANCE_CLASSES,
        "scnm": SCENE_CLASSES,
        "hcm": HUMAN_CENTRIC_CLASSES,
    }
    assert protocol_classes("occ3d") == tuple(range(17))
    assert protocol_classes("weak") == (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 13, 14, 15, 16)
    assert len(protocol_classes("weak")) == 15
    with pytest.raises(ValueError, match="protocol: unknown protocol 'nuscenes'"):
        protocol_classes("nuscenes")
    with pytest.raises(TypeError):
        CLASS_GROUPS["insm"] = ()  # read-only


def test_palette_values() -> None:
    assert len(PALETTE) == NUM_CLASSES
    assert all(len(rgb) == 3 and all(0 <= c <= 255 for c in rgb) for rgb in PALETTE)
    assert PALETTE[Occ3DLabel.CAR] == (255, 0, 0)
    assert PALETTE[Occ3DLabel.PEDESTRIAN] == (0, 155, 249)
    assert PALETTE[Occ3DLabel.OTHER_FLAT] == (139, 137, 137)
    assert PALETTE[Occ3DLabel.OTHERS] == (0, 0, 0)


def test_palette_matches_the_paper_source() -> None:
    colours = dict(
        re.findall(r"\\definecolor\{(\w+)\}\{RGB\}\{([\d, ]+)\}", PAPER_COLOURS.read_text())
    )
    assert len(colours) == 17, sorted(colours)
    paper_name = {
        "others": "others",
        "barrier": "barrier",
        "bicycle": "bicycle",
        "bus": "bus",
        "car": "car",
        "construction_vehicle": "construct",
        "motorcycle": "motor",
        "pedestrian": "pedestrian",
        "traffic_cone": "traffic",
        "trailer": "trailer",
        "truck": "truck",
        "driveable_surface": "driveable",
        "other_flat": "other",
        "sidewalk": "sidewalk",
        "terrain": "terrain",
        "manmade": "manmade",
        "vegetation": "vegetation",
    }
    for label, name in enumerate(CLASS_NAMES[:17]):
        expected = tuple(int(c) for c in colours[paper_name[name]].split(","))
        assert PALETTE[label] == expected, name
