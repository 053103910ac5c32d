"""Occ3D-nuScenes labels.npz I/O: round trips, the real files' layout, clear errors, dataset."""

from __future__ import annotations

import io
import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from dego.classes import FREE_LABEL, NUM_CLASSES
from dego.data.occ3d import (
    LABELS_FILENAME,
    OCC3D_SHAPE,
    Occ3DDataset,
    Occ3DLabels,
    Occ3DSample,
    load_occ3d_labels,
    save_occ3d_labels,
)
from dego.grid import VoxelGrid

SMALL = (4, 5, 3)


def _arrays(shape: tuple[int, ...] = OCC3D_SHAPE, seed: int = 0) -> dict[str, np.ndarray]:
    """uint8 arrays laid out like a real labels.npz: mostly free, some labels, 0/1 masks."""
    rng = np.random.default_rng(seed)
    semantics = np.full(shape, FREE_LABEL, dtype=np.uint8)
    occupied = rng.random(shape) < 0.2
    semantics[occupied] = rng.integers(0, FREE_LABEL, occupied.sum(), dtype=np.uint8)
    return {
        "semantics": semantics,
        "mask_lidar": (rng.random(shape) < 0.5).astype(np.uint8),
        "mask_camera": (rng.random(shape) < 0.7).astype(np.uint8),
    }


def _labels(shape: tuple[int, ...] = OCC3D_SHAPE, seed: int = 0) -> Occ3DLabels:
    a = _arrays(shape, seed)
    return Occ3DLabels.from_arrays(a["semantics"], a["mask_camera"], a["mask_lidar"])


def _assert_matches(labels: Occ3DLabels, arrays: dict[str, np.ndarray]) -> None:
    assert labels.semantics.dtype == torch.uint8
    assert labels.mask_camera.dtype == labels.mask_lidar.dtype == torch.bool
    assert np.array_equal(labels.semantics.numpy(), arrays["semantics"])
    assert np.array_equal(labels.mask_camera.numpy(), arrays["mask_camera"].astype(bool))
    assert np.array_equal(labels.mask_lidar.numpy(), arrays["mask_lidar"].astype(bool))


def _write_npz(path: Path, **arrays: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)
    return path


def _assert_equal(a: Occ3DLabels, b: Occ3DLabels) -> None:
    assert torch.equal(a.semantics, b.semantics)
    assert torch.equal(a.mask_camera, b.mask_camera)
    assert torch.equal(a.mask_lidar, b.mask_lidar)


# -- round trips and the real layout -----------------------------------------------------
@pytest.mark.parametrize("compressed", [True, False])
def test_round_trip_writes_the_real_layout(tmp_path: Path, compressed: bool) -> None:
    labels = _labels(seed=1)
    path = save_occ3d_labels(tmp_path / "a" / "b" / LABELS_FILENAME, labels, compressed=compressed)
    assert path == tmp_path / "a" / "b" / LABELS_FILENAME
    assert sorted(p.name for p in path.parent.iterdir()) == [LABELS_FILENAME]  # no temp left
    _assert_equal(load_occ3d_labels(path), labels)
    with np.load(path, allow_pickle=False) as npz:
        assert npz.files == ["semantics", "mask_lidar", "mask_camera"]
        for key in npz.files:
            assert npz[key].dtype == np.uint8 and npz[key].shape == OCC3D_SHAPE
        assert set(np.unique(npz["mask_camera"])) <= {0, 1}
    kinds = {info.compress_type for info in zipfile.ZipFile(path).infolist()}
    assert kinds == {zipfile.ZIP_DEFLATED if compressed else zipfile.ZIP_STORED}


def test_save_overwrites_and_keeps_the_exact_name(tmp_path: Path) -> None:
    path = tmp_path / "labels.bin"
    save_occ3d_labels(path, _labels(SMALL, seed=0))
    save_occ3d_labels(str(path), _labels(SMALL, seed=1))
    assert [p.name for p in tmp_path.iterdir()] == ["labels.bin"]
    _assert_equal(load_occ3d_labels(path, expected_shape=None), _labels(SMALL, seed=1))
    with pytest.raises(IsADirectoryError, match="path"):
        save_occ3d_labels(tmp_path, _labels(SMALL))


def test_loads_a_file_stored_like_the_real_data(tmp_path: Path) -> None:
    arrays = _arrays(seed=2)
    path = tmp_path / "gts" / "scene-0001" / "tok" / "labels.npz"
    path.parent.mkdir(parents=True)
    np.savez_compressed(
        path,
        semantics=arrays["semantics"],
        mask_lidar=arrays["mask_lidar"],
        mask_camera=arrays["mask_camera"],
    )
    labels = load_occ3d_labels(path)
    assert labels.shape == OCC3D_SHAPE == VoxelGrid.occ3d().shape
    assert labels.device == torch.device("cpu") and labels.num_classes == NUM_CLASSES
    _assert_matches(labels, arrays)


def test_bool_masks_and_wider_integer_semantics_are_accepted(tmp_path: Path) -> None:
    arrays = _arrays(SMALL, seed=3)
    path = _write_npz(
        tmp_path / "x.npz",
        semantics=arrays["semantics"].astype(">i8"),  # big-endian int64
        mask_lidar=arrays["mask_lidar"].astype(bool),
        mask_camera=arrays["mask_camera"].astype(np.int32),
        extra=np.zeros(3),  # other members are ignored
    )
    _assert_matches(load_occ3d_labels(path, expected_shape=None), arrays)


# -- malformed files -----------------------------------------------------------------------
@pytest.mark.parametrize("key", ["mask_camera", "mask_lidar"])
def test_mask_with_values_other_than_0_1_is_rejected(tmp_path: Path, key: str) -> None:
    arrays = _arrays(SMALL)
    arrays[key][1, 2, 0] = 2
    path = _write_npz(tmp_path / "m.npz", **arrays)
    with pytest.raises(ValueError, match=f"{key}: holds values other than 0/1") as info:
        load_occ3d_labels(path, expected_shape=None)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("key", ["semantics", "mask_camera", "mask_lidar"])
def test_missing_key_is_named(tmp_path: Path, key: str) -> None:
    arrays = _arrays(SMALL)
    del arrays[key]
    path = _write_npz(tmp_path / "k.npz", **arrays)
    with pytest.raises(ValueError, match=f"missing array\\(s\\) \\['{key}'\\]") as info:
        load_occ3d_labels(path, expected_shape=None)
    assert str(path) in str(info.value)


def test_wrong_shapes(tmp_path: Path) -> None:
    path = _write_npz(tmp_path / "s.npz", **_arrays(SMALL))
    with pytest.raises(ValueError, match=r"semantics: shape \(4, 5, 3\) differs from expected"):
        load_occ3d_labels(path)
    with pytest.raises(ValueError, match="differs from expected_shape"):
        load_occ3d_labels(path, expected_shape=(4, 5, 4))
    assert load_occ3d_labels(path, expected_shape=SMALL).shape == SMALL
    arrays = _arrays(SMALL)
    arrays["mask_lidar"] = arrays["mask_lidar"][:, :, :2]
    path = _write_npz(tmp_path / "t.npz", **arrays)
    with pytest.raises(ValueError, match=r"mask_lidar: shape \(4, 5, 2\) differs from semantics"):
        load_occ3d_labels(path, expected_shape=None)
    arrays = _arrays(SMALL)
    arrays["semantics"] = arrays["semantics"][0]
    path = _write_npz(tmp_path / "u.npz", **arrays)
    with pytest.raises(ValueError, match=r"semantics: expected shape \(X, Y, Z\), got \(5, 3\)"):
        load_occ3d_labels(path, expected_shape=None)


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("semantics", np.float32, "semantics: expected integer labels, got dtype float32"),
        ("semantics", np.bool_, "semantics: expected integer labels, got dtype bool"),
        ("mask_camera", np.float64, "mask_camera: expected a bool mask or integers 0/1"),
    ],
)
def test_wrong_dtypes(tmp_path: Path, key: str, value: type, message: str) -> None:
    arrays = _arrays(SMALL)
    arrays[key] = arrays[key].astype(value)
    path = _write_npz(tmp_path / "d.npz", **arrays)
    with pytest.raises(ValueError, match=message) as info:
        load_occ3d_labels(path, expected_shape=None)
    assert str(path) in str(info.value)


@pytest.mark.parametrize(
    "value, dtype, match",
    [(18, np.uint8, r"\.\.18;"), (255, np.uint8, r"\.\.255;"), (-1, np.int16, r"-1\.\.")],
)
def test_out_of_range_semantics(tmp_path: Path, value: int, dtype: type, match: str) -> None:
    arrays = _arrays(SMALL)
    arrays["semantics"] = arrays["semantics"].astype(dtype)
    arrays["semantics"][0, 0, 0] = value
    path = _write_npz(tmp_path / "r.npz", **arrays)
    with pytest.raises(ValueError, match=f"semantics: labels range over .*{match}") as info:
        load_occ3d_labels(path, expected_shape=None)
    assert str(path) in str(info.value) and "expected labels in 0..17" in str(info.value)
    if value >= 0:
        labels = load_occ3d_labels(path, expected_shape=None, num_classes=256)
        assert int(labels.semantics[0, 0, 0]) == value and labels.num_classes == 256


def _corrupt_files(tmp_path: Path) -> dict[str, Path]:
    good = io.BytesIO()
    np.savez_compressed(good, **_arrays(SMALL))
    data = good.getvalue()
    files = {
        "truncated": data[: len(data) // 2],
        "garbage": b"not an npz archive at all" * 10,
        "empty": b"",
        "npy": b"",
        "pickle": pickle.dumps({"semantics": 1}),
    }
    paths = {}
    for name, content in files.items():
        paths[name] = tmp_path / f"{name}.npz"
        paths[name].write_bytes(content)
    with paths["npy"].open("wb") as file:
        np.save(file, _arrays(SMALL)["semantics"])
    return paths


@pytest.mark.parametrize(
    "kind, match",
    [
        ("truncated", "not a readable .npz archive"),
        ("garbage", "is not a zip archive"),
        ("empty", "is empty"),
        ("npy", "holds a single .npy array"),
        ("pickle", "is not a zip archive"),
    ],
)
def test_corrupt_files_raise_value_error_naming_the_path(
    tmp_path: Path, kind: str, match: str
) -> None:
    path = _corrupt_files(tmp_path)[kind]
    with pytest.raises(ValueError, match=match) as info:
        load_occ3d_labels(path, expected_shape=None)
    assert str(path) in str(info.value)


def test_corrupt_member_names_the_key(tmp_path: Path) -> None:
    path = tmp_path / "crc.npz"
    np.savez(path, **_arrays(SMALL))  # stored, so a flipped byte only breaks one CRC
    with zipfile.ZipFile(path) as archive:
        member = archive.getinfo("mask_lidar.npy")
    data = bytearray(path.read_bytes())
    data[member.header_offset + 30 + len(member.filename) + member.file_size - 1] ^= 1
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="cannot read array 'mask_lidar'") as info:
        load_occ3d_labels(path, expected_shape=None)
    assert str(path) in str(info.value)


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="no such Occ3D labels file") as info:
        load_occ3d_labels(tmp_path / "nope.npz")
    assert str(tmp_path / "nope.npz") in str(info.value)
    with pytest.raises(FileNotFoundError, match="is a directory"):
        load_occ3d_labels(tmp_path)


def test_argument_checks(tmp_path: Path) -> None:
    with pytest.raises(TypeError):
        load_occ3d_labels(3)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="expected_shape"):
        load_occ3d_labels(tmp_path / "x.npz", expected_shape=(200, 0, 16))
    with pytest.raises(ValueError, match="num_classes"):
        load_occ3d_labels(tmp_path / "x.npz", num_classes=257)


# -- Occ3DLabels ---------------------------------------------------------------------------
def test_labels_construction_is_validated() -> None:
    labels = _labels(SMALL)
    sem, cam, lid = labels.semantics, labels.mask_camera, labels.mask_lidar
    assert repr(labels) == "Occ3DLabels(shape=(4, 5, 3), num_classes=18, device=cpu)"
    _assert_equal(labels.to("cpu"), labels)
    with pytest.raises(
        TypeError, match=r"semantics: expected dtype torch\.uint8, got torch\.int64"
    ):
        Occ3DLabels(sem.long(), cam, lid)
    with pytest.raises(TypeError, match=r"mask_camera: expected dtype torch\.bool"):
        Occ3DLabels(sem, cam.to(torch.uint8), lid)
    with pytest.raises(TypeError, match=r"mask_lidar: expected a torch\.Tensor"):
        Occ3DLabels(sem, cam, lid.numpy())  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="mask_lidar: shape"):
        Occ3DLabels(sem, cam, lid[:2])
    with pytest.raises(ValueError, match=r"semantics: expected shape \(X, Y, Z\)"):
        Occ3DLabels(sem[None], cam[None], lid[None])
    with pytest.raises(ValueError, match="semantics: holds label 17"):
        Occ3DLabels(sem, cam, lid, num_classes=17)
    with pytest.raises(ValueError, match="num_classes"):
        Occ3DLabels(sem, cam, lid, num_classes=0)


def test_from_arrays_converts_tensors_and_checks_values() -> None:
    arrays = _arrays(SMALL, seed=4)
    labels = Occ3DLabels.from_arrays(
        torch.from_numpy(arrays["semantics"]).to(torch.uint32),
        torch.from_numpy(arrays["mask_camera"]).long(),
        torch.from_numpy(arrays["mask_lidar"]).bool(),
    )
    _assert_matches(labels, arrays)
    with pytest.raises(ValueError, match="mask_camera: holds values other than 0/1"):
        Occ3DLabels.from_arrays(
            arrays["semantics"], arrays["mask_camera"] - 1, arrays["mask_lidar"]
        )
    with pytest.raises(TypeError, match="semantics: expected integer labels"):
        Occ3DLabels.from_arrays(
            torch.from_numpy(arrays["semantics"]).float(),
            arrays["mask_camera"],
            arrays["mask_lidar"],
        )
    with pytest.raises(TypeError, match="semantics: expected integer labels, got dtype bool"):
        Occ3DLabels.from_arrays(
            arrays["semantics"].astype(bool), arrays["mask_camera"], arrays["mask_lidar"]
        )
    with pytest.raises(TypeError, match="mask_lidar: expected a bool mask or integers 0/1"):
        Occ3DLabels.from_arrays(
            arrays["semantics"], arrays["mask_camera"], arrays["mask_lidar"].astype(np.float32)
        )
    empty = np.zeros((0, 2, 2), np.uint8)
    assert Occ3DLabels.from_arrays(empty, empty, empty).shape == (0, 2, 2)


@pytest.mark.parametrize("dtype", [np.uint8, np.int8, np.int16, np.int32, np.int64])
def test_every_integer_dtype_reads_and_writes_the_same(tmp_path: Path, dtype: type) -> None:
    arrays = _arrays(SMALL, seed=6)
    typed = {key: value.astype(dtype) for key, value in arrays.items()}
    labels = Occ3DLabels.from_arrays(typed["semantics"], typed["mask_camera"], typed["mask_lidar"])
    _assert_matches(labels, arrays)
    path = _write_npz(tmp_path / "t.npz", **typed)
    _assert_equal(load_occ3d_labels(path, expected_shape=None), labels)


# -- Occ3DDataset --------------------------------------------------------------------------
SCENES = {"scene-0002": ["tok-b", "tok-a"], "scene-0001": ["tok-c", "tok-d"]}


def _fake_tree(root: Path) -> dict[tuple[str, str], Occ3DLabels]:
    written = {}
    for i, (scene, tokens) in enumerate(SCENES.items()):
        for j, token in enumerate(tokens):
            labels = _labels(SMALL, seed=10 * i + j)
            save_occ3d_labels(root / "gts" / scene / token / LABELS_FILENAME, labels)
            written[scene, token] = labels
    return written


@pytest.mark.parametrize("style", ["dicts", "tuples", "lists"])
def test_dataset_over_a_fake_tree(tmp_path: Path, style: str) -> None:
    written = _fake_tree(tmp_path)
    keys = list(written)  # file order: scene-0002 first
    if style == "dicts":
        infos: list = [{"scene_name": s, "token": t, "other": 1} for s, t in keys]
    elif style == "tuples":
        infos = keys
    else:
        infos = [list(key) for key in keys]
    dataset = Occ3DDataset(str(tmp_path), infos, expected_shape=SMALL)
    assert len(dataset) == 4 and dataset.samples == tuple(keys)
    assert dataset.path(1) == tmp_path / "gts" / "scene-0002" / "tok-a" / LABELS_FILENAME
    samples = list(dataset)
    assert [(s.scene_name, s.token) for s in samples] == keys
    for sample in samples:
        assert isinstance(sample, Occ3DSample)
        _assert_equal(sample.labels, written[sample.scene_name, sample.token])
    assert dataset[-1].token == "tok-d"
    with pytest.raises(IndexError, match="index: 4 out of range for 4 samples"):
        dataset[4]
    loader = DataLoader(dataset, batch_size=None)
    assert [s.token for s in loader] == [t for _, t in keys]


def test_from_directory_discovers_sorted_samples(tmp_path: Path) -> None:
    written = _fake_tree(tmp_path)
    (tmp_path / "gts" / "scene-0001" / "not-a-sample.txt").write_text("x")
    (tmp_path / "gts" / "scene-0001" / "empty-token").mkdir()
    dataset = Occ3DDataset.from_directory(tmp_path, expected_shape=None)
    assert dataset.samples == tuple(sorted(written))
    _assert_equal(dataset[0].labels, written["scene-0001", "tok-c"])
    (tmp_path / "other" / "gts").mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match=r"no files matching gts/\*/\*/labels\.npz"):
        Occ3DDataset.from_directory(tmp_path / "other")


def test_missing_sample_names_the_expected_path(tmp_path: Path) -> None:
    _fake_tree(tmp_path)
    samples = [("scene-0001", "tok-c"), ("scene-0001", "missing")]
    dataset = Occ3DDataset(tmp_path, samples, expected_shape=None)
    assert dataset[0].token == "tok-c"
    with pytest.raises(ValueError, match=r"tok-c/labels\.npz: semantics: shape \(4, 5, 3\)"):
        Occ3DDataset(tmp_path, samples)[0]  # the default expected_shape is (200, 200, 16)
    expected = tmp_path / "gts" / "scene-0001" / "missing" / LABELS_FILENAME
    with pytest.raises(FileNotFoundError, match=r"sample 1 .*'missing'") as info:
        dataset[1]
    assert str(expected) in str(info.value)


def test_dataset_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"root: .* is not an existing directory"):
        Occ3DDataset(tmp_path / "nowhere", [])
    with pytest.raises(FileNotFoundError, match="root: no 'gts' directory"):
        Occ3DDataset(tmp_path, [])
    (tmp_path / "gts").mkdir()
    assert len(Occ3DDataset(tmp_path, [])) == 0
    with pytest.raises(ValueError, match=r"infos\[1\]: missing key\(s\) \['token'\]"):
        Occ3DDataset(tmp_path, [("a", "b"), {"scene_name": "a"}])
    with pytest.raises(ValueError, match=r"infos\[0\]: token '\.\.' is not a single directory"):
        Occ3DDataset(tmp_path, [("a", "..")])
    with pytest.raises(ValueError, match=r"infos\[0\]: scene_name 'a/b'"):
        Occ3DDataset(tmp_path, [{"scene_name": "a/b", "token": "t"}])
    with pytest.raises(TypeError, match=r"infos\[0\]: token must be a str"):
        Occ3DDataset(tmp_path, [{"scene_name": "a", "token": 3}])
    with pytest.raises(TypeError):
        Occ3DDataset(tmp_path, {"scene_name": "a", "token": "t"})  # type: ignore[arg-type]
