"""load_nuscenes_keyframes: the nuScenes JSON tables -> Keyframe, without the devkit."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import torch

import dego
from dego.data import load_infos, load_nuscenes_keyframes
from tests.helpers.nuscenes_fixtures import make_frames, make_tables, write_infos, write_tables

TABLES = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor")


@pytest.fixture(scope="module")
def frames() -> list[Any]:
    return make_frames(seed=5, lengths=(5, 6))


@pytest.fixture()
def tables(frames: list[Any]) -> dict[str, list[dict[str, Any]]]:
    return make_tables(frames)


def test_tables_give_the_infos_keyframes_in_temporal_order(
    frames: list[Any], tables: dict[str, Any], tmp_path: Path
) -> None:
    root = write_tables(tmp_path / "nuscenes", tables)
    got = load_nuscenes_keyframes(root)
    want = load_infos(write_infos(tmp_path / "infos.pkl", frames))
    assert [k.token for k in got] == [f.token for f in frames]  # sample.json is shuffled
    for a, b in zip(got, want, strict=True):
        assert (a.token, a.scene, a.timestamp) == (b.token, b.scene, b.timestamp)
        torch.testing.assert_close(a.lidar2ego, b.lidar2ego, rtol=0, atol=1e-12)
        torch.testing.assert_close(a.ego2global, b.ego2global, rtol=0, atol=1e-12)
    assert dego.load_nuscenes_keyframes is load_nuscenes_keyframes


def test_scene_table_order_is_kept(tables: dict[str, Any], tmp_path: Path) -> None:
    tables["scene"].reverse()
    got = load_nuscenes_keyframes(write_tables(tmp_path, tables, "v1.0-mini"), "v1.0-mini")
    names = [k.scene for k in got]
    assert names == sorted(names, key=[s["name"] for s in tables["scene"]].index)


def test_missing_paths_name_them(tables: dict[str, Any], tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nowhere"):
        load_nuscenes_keyframes(tmp_path / "nowhere")
    with pytest.raises(FileNotFoundError, match=r"v1\.0-trainval"):
        load_nuscenes_keyframes(tmp_path)
    root = write_tables(tmp_path / "root", tables)
    for name in TABLES:
        path = root / "v1.0-trainval" / f"{name}.json"
        text = path.read_text()
        path.unlink()
        with pytest.raises(FileNotFoundError, match=rf"{name}\.json"):
            load_nuscenes_keyframes(root)
        path.write_text(text)


def _first_lidar_key_frame(tables: dict[str, Any]) -> dict[str, Any]:
    lidar = next(s["token"] for s in tables["sensor"] if s["channel"] == "LIDAR_TOP")
    cs = {c["token"] for c in tables["calibrated_sensor"] if c["sensor_token"] == lidar}
    return next(
        r for r in tables["sample_data"] if r["is_key_frame"] and r["calibrated_sensor_token"] in cs
    )


def _drop_lidar_key_frame(tables: dict[str, Any]) -> str:
    row = _first_lidar_key_frame(tables)
    tables["sample_data"].remove(row)
    return rf"sample_data\.json: sample '{row['sample_token']}' has no LIDAR_TOP key frame"


def _dangling_ego_pose(tables: dict[str, Any]) -> str:
    row = _first_lidar_key_frame(tables)
    row["ego_pose_token"] = "ghost-pose"
    return r"ego_pose\.json: token 'ghost-pose'"


def _dangling_next(tables: dict[str, Any]) -> str:
    sample = next(s for s in tables["sample"] if s["next"])
    sample["next"] = "ghost-sample"
    return rf"sample\.json: sample '{sample['token']}' next 'ghost-sample' is not in sample\.json"


def _dangling_first(tables: dict[str, Any]) -> str:
    tables["scene"][1]["first_sample_token"] = "ghost-first"
    return r"scene\.json: scene '.+' first_sample_token 'ghost-first'"


def _dangling_calibration(tables: dict[str, Any]) -> str:
    row = _first_lidar_key_frame(tables)
    row["calibrated_sensor_token"] = "ghost-cs"
    return r"sample_data\.json: row '.+' references calibrated_sensor 'ghost-cs'"


def _dangling_sensor(tables: dict[str, Any]) -> str:
    tables["calibrated_sensor"][0]["sensor_token"] = "ghost-sensor"
    return r"sensor\.json: token 'ghost-sensor'"


def _unreachable_sample(tables: dict[str, Any]) -> str:
    extra = dict(tables["sample"][0], token="orphan", prev="", next="")
    tables["sample"].append(extra)
    return r"sample\.json: sample 'orphan' is not reachable"


def _missing_field(tables: dict[str, Any]) -> str:
    token = _first_lidar_key_frame(tables)["ego_pose_token"]
    del next(p for p in tables["ego_pose"] if p["token"] == token)["rotation"]
    return r"ego_pose\.json: row '.+' has no field 'rotation'"


def _two_lidar_key_frames(tables: dict[str, Any]) -> str:
    row = _first_lidar_key_frame(tables)
    tables["sample_data"].append(dict(row, token="twin"))
    return r"two LIDAR_TOP key frames"


@pytest.mark.parametrize(
    "edit",
    [
        _drop_lidar_key_frame,
        _dangling_ego_pose,
        _dangling_next,
        _dangling_first,
        _dangling_calibration,
        _dangling_sensor,
        _unreachable_sample,
        _missing_field,
        _two_lidar_key_frames,
    ],
)
def test_bad_tables_name_table_and_token(tables: dict[str, Any], tmp_path: Path, edit: Any) -> None:
    pattern = edit(tables)
    root = write_tables(tmp_path, tables)
    with pytest.raises(ValueError, match=pattern):
        load_nuscenes_keyframes(root)


def test_corrupt_table(tables: dict[str, Any], tmp_path: Path) -> None:
    root = write_tables(tmp_path, tables)
    (root / "v1.0-trainval" / "ego_pose.json").write_text(json.dumps(tables["ego_pose"])[:-40])
    with pytest.raises(ValueError, match=r"ego_pose\.json: not a readable JSON table"):
        load_nuscenes_keyframes(root)
