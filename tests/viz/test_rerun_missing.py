"""Without rerun-sdk: ``import dego.viz.rerun`` works and every logging call says which
extra to install (runs whether or not rerun is installed: the import is blocked)."""

from __future__ import annotations

import sys

import pytest
import torch

from dego import VoxelGrid
from dego.viz import rerun as dr


def test_without_rerun_the_error_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun -> ImportError
    grid = VoxelGrid(lower=(0.0, 0.0, 0.0), upper=(1.0, 1.0, 1.0), voxel_size=0.5)
    labels = torch.zeros(grid.shape, dtype=torch.uint8)
    with pytest.raises(ImportError, match=r'pip install -e "\.\[rerun\]"') as caught:
        dr.log_occupancy("world/occ", labels, grid)
    assert caught.value.name == "rerun"
    with pytest.raises(ImportError, match=r"\.\[rerun\]"), dr.recording_file("unused.rrd"):
        pass


def test_the_extra_and_the_module_name_one_minimum(source_tree) -> None:
    import tomllib

    extras = tomllib.loads((source_tree / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    assert extras["rerun"] == [f"rerun-sdk>={dr.MIN_RERUN}"]
