"""SceneOrigins against an independent statement of SparseOcc's EgoPoseDataset rules."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import dego
from dego.data import Keyframe, SceneOrigins, load_infos
from tests.helpers.nuscenes_fixtures import make_frames, reference_infos, write_infos
from tests.reference.sparseocc_origins import sparseocc_origins


@pytest.fixture(scope="module")
def frames() -> list[Any]:
    return make_frames(seed=0)


@pytest.fixture(scope="module")
def keyframes(frames: list[Any], tmp_path_factory: pytest.TempPathFactory) -> tuple[Keyframe, ...]:
    path = tmp_path_factory.mktemp("infos") / "nuscenes_infos_val.pkl"
    return load_infos(write_infos(path, frames))


def _compare(origins: SceneOrigins, reference: dict[str, tuple[np.ndarray, int]]) -> None:
    assert set(origins.tokens) == set(reference)
    for token, (want, _) in reference.items():
        got = origins(token)
        assert got.dtype == torch.float64 and got.shape == want.shape, token
        np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-5)


def test_origins_match_sparseocc_for_every_sample(
    frames: list[Any], keyframes: tuple[Keyframe, ...]
) -> None:
    origins = SceneOrigins(keyframes)
    reference = sparseocc_origins(reference_infos(frames))
    _compare(origins, reference)
    counts = [count for _, count in reference.values()]
    scene_sizes = {f.token: sum(g.scene_name == f.scene_name for g in frames) for f in frames}
    assert max(counts) > 8  # the linspace pick is exercised
    assert any(count < scene_sizes[token] for token, (_, count) in reference.items())  # 39 m
    assert origins.tokens == tuple(f.token for f in frames)
    assert len(origins) == len(frames) and frames[0].token in origins and "x" not in origins
    assert dego.SceneOrigins is SceneOrigins


def test_single_frame_scene_origin_is_the_lidar_mount(
    frames: list[Any], keyframes: tuple[Keyframe, ...]
) -> None:
    last = keyframes[-1]  # the 1-frame scene
    got = SceneOrigins(keyframes)(last.token)
    assert got.shape == (1, 3)
    torch.testing.assert_close(got[0], last.lidar2ego[:3, 3], rtol=0, atol=0)


def test_scene_interleaving_and_options_follow_the_reference(
    frames: list[Any], keyframes: tuple[Keyframe, ...]
) -> None:
    # SparseOcc groups by scene and keeps the given order inside each scene
    order = sorted(range(len(frames)), key=lambda i: (i * 7919) % len(frames))
    shuffled = [keyframes[i] for i in order]
    _compare(SceneOrigins(shuffled), sparseocc_origins(reference_infos([frames[i] for i in order])))
    _compare(
        SceneOrigins(keyframes, max_origins=3, xy_limit=20.0),
        sparseocc_origins(reference_infos(frames), max_origins=3, xy_limit=20.0),
    )


def test_scene_of_regroups_and_leaves_out_uncovered_tokens(
    frames: list[Any], keyframes: tuple[Keyframe, ...]
) -> None:
    anonymous = [dataclasses.replace(k, scene="") for k in keyframes]
    kept = [f for i, f in enumerate(frames) if i % 5 != 2]
    scene_of = {f.token: f.scene_name for f in kept}  # as read from gts/<scene>/<token>
    origins = SceneOrigins(anonymous, scene_of=scene_of)
    _compare(origins, sparseocc_origins(reference_infos(kept)))
    assert origins.tokens == tuple(f.token for f in kept)
    dropped = frames[2].token
    assert dropped not in origins
    with pytest.raises(KeyError, match=dropped):
        origins(dropped)
    assert origins.scene(kept[0].token) == kept[0].scene_name


def test_bad_input(keyframes: tuple[Keyframe, ...]) -> None:
    origins = SceneOrigins(keyframes)
    with pytest.raises(KeyError, match="no-such-token"):
        origins("no-such-token")
    with pytest.raises(ValueError, match=r"keyframes\[3\]: duplicate token"):
        SceneOrigins([*keyframes[:3], keyframes[0]])
    with pytest.raises(ValueError, match=r"keyframes\[0\].*no scene; pass scene_of"):
        SceneOrigins([dataclasses.replace(keyframes[0], scene="")])
    with pytest.raises(ValueError, match="max_origins"):
        SceneOrigins(keyframes, max_origins=0)
    with pytest.raises(ValueError, match="xy_limit"):
        SceneOrigins(keyframes, xy_limit=-1.0)
    k = keyframes[0]
    with pytest.raises(ValueError, match="lidar2ego"):
        Keyframe(k.token, k.scene, k.timestamp, k.lidar2ego.float(), k.ego2global)
    bad = k.ego2global.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match="ego2global: holds non-finite"):
        Keyframe(k.token, k.scene, k.timestamp, k.lidar2ego, bad)


def test_tables_and_infos_give_the_same_origins(
    frames: list[Any], keyframes: tuple[Keyframe, ...], tmp_path: Path
) -> None:
    from tests.helpers.nuscenes_fixtures import make_tables, write_tables

    root = write_tables(tmp_path, make_tables(frames))
    from_tables = SceneOrigins(dego.load_nuscenes_keyframes(root))
    from_infos = SceneOrigins(keyframes)
    for token in from_infos.tokens:
        torch.testing.assert_close(from_tables(token), from_infos(token), rtol=0, atol=1e-9)
