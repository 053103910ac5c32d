"""Helpers of tests/demo/test_train_command.py, also used by tests/demo/test_feedforward.py:
cached scenes without rendering them (a few milliseconds instead of seconds a scene)."""

from __future__ import annotations

import pytest
import torch

import dego.demo.feedforward.data as data_module
from dego.demo.feedforward.data import SceneRecord
from dego.grid import VoxelGrid


def tiny_record(seed: int) -> SceneRecord:
    """A small :class:`SceneRecord` whose shapes agree (3 frames, one 8x8 camera, one
    agent): what the cache writes and reads back, not a rendered scene."""
    t, v, h, w, a = 3, 1, 8, 8, 1
    grid = VoxelGrid.occ3d()
    shape = tuple(grid.shape)
    return SceneRecord(
        seed=seed,
        times=torch.tensor([-1.0, 0.0, 1.0]),
        reference=1,
        world_to_cam=torch.eye(4).expand(t, v, 4, 4).clone(),
        intrinsics=torch.eye(3).expand(t, v, 3, 3).clone(),
        images=torch.zeros(v, 3, h, w),
        depth=torch.ones(t, v, h, w),
        semantics=torch.zeros(t, v, h, w, dtype=torch.long),
        supervised=torch.ones(t, v, h, w, dtype=torch.bool),
        occupancy=torch.zeros(shape, dtype=torch.long),
        mask_camera=torch.ones(shape, dtype=torch.bool),
        instances=torch.zeros(shape, dtype=torch.long),
        agent_labels=torch.zeros(a, dtype=torch.long),
        agent_articulated=torch.zeros(a, dtype=torch.bool),
        agent_moving=torch.zeros(a, dtype=torch.bool),
        agent_translations=torch.zeros(t, a, 3),
        ray_origins=torch.zeros(2, 3),
        grid=grid,
    )


def render_tiny(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """:func:`~dego.demo.feedforward.load_scenes` renders :func:`tiny_record` s instead of
    synthetic scenes; returns the seeds rendered, in order."""
    rendered: list[int] = []

    def from_scene(cls: type[SceneRecord], seed: int) -> SceneRecord:
        rendered.append(seed)
        return tiny_record(seed)

    monkeypatch.setattr(data_module, "SyntheticScene", lambda seed, **kwargs: seed)
    monkeypatch.setattr(SceneRecord, "from_scene", classmethod(from_scene))
    return rendered
