"""Corrupt ``.npz`` archives (issue 17): every defective zip member, through both loaders
that read with ``dego._npz.read_npz`` (Occ3D labels and the teacher feature cache), is a
ValueError naming the file and the member (or the array, for valid members holding the
wrong dtype or shape)."""

from __future__ import annotations

import io
import re
import struct
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import dego
from dego import load_occ3d_labels
from dego._npz import read_npz
from dego.teacher.cache import FORMAT_VERSION, TeacherFeatureCache

SHAPE = (4, 5, 3)
SETTINGS = settings(
    max_examples=25, suppress_health_check=[HealthCheck.function_scoped_fixture], deadline=None
)


def npy(array: np.ndarray, *, allow_pickle: bool = False) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=allow_pickle)
    return buffer.getvalue()


def occ3d_members() -> dict[str, bytes]:
    rng = np.random.default_rng(0)
    return {
        "semantics.npy": npy(rng.integers(0, 18, SHAPE, dtype=np.uint8)),
        "mask_lidar.npy": npy((rng.random(SHAPE) < 0.5).astype(np.uint8)),
        "mask_camera.npy": npy((rng.random(SHAPE) < 0.5).astype(np.uint8)),
    }


def cache_members() -> dict[str, bytes]:
    return {
        "features.npy": npy(np.ones((2, 3, 4), dtype=np.float16)),
        "format_version.npy": npy(np.asarray(FORMAT_VERSION, dtype=np.int64)),
        "dtype.npy": npy(np.asarray("float16")),
        "sample_id.npy": npy(np.asarray("s")),
        "camera.npy": npy(np.asarray(0, dtype=np.int64)),
    }


def write_zip(path: Path, members: list[tuple[str | zipfile.ZipInfo, bytes]]) -> Path:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zipfile warns about duplicate names
        with zipfile.ZipFile(path, "w") as archive:
            for name, data in members:
                archive.writestr(name, data)
    return path


def entry_path(tmp_path: Path, loader: str) -> Path:
    if loader == "occ3d":
        return tmp_path / "labels.npz"
    return TeacherFeatureCache(tmp_path).path("s", 0)


def load_occ3d(tmp_path: Path, members: list[tuple[str | zipfile.ZipInfo, bytes]]) -> Path:
    path = write_zip(tmp_path / "labels.npz", members)
    load_occ3d_labels(path, expected_shape=None)
    return path


def load_cache(tmp_path: Path, members: list[tuple[str | zipfile.ZipInfo, bytes]]) -> Path:
    cache = TeacherFeatureCache(tmp_path)
    write_zip(cache.path("s", 0), members)
    cache.load("s", 0)
    return cache.path("s", 0)


LOADERS: dict[str, tuple[Callable[..., Path], Callable[[], dict[str, bytes]], str]] = {
    "occ3d": (load_occ3d, occ3d_members, "semantics.npy"),
    "cache": (load_cache, cache_members, "features.npy"),
}


def expect_error(
    tmp_path: Path, loader: str, members: list[tuple[str | zipfile.ZipInfo, bytes]], *needles: str
) -> str:
    """Load ``members`` with ``loader``; assert a ValueError naming the file and ``needles``."""
    load = LOADERS[loader][0]
    path = entry_path(tmp_path, loader)
    with pytest.raises(ValueError) as info:
        load(tmp_path, members)
    message = str(info.value)
    assert str(path) in message, message
    for needle in needles:
        assert needle in message, (needle, message)
    return message


def with_member(
    members: dict[str, bytes], name: str, data: bytes
) -> list[tuple[str | zipfile.ZipInfo, bytes]]:
    return [(key, data if key == name else value) for key, value in members.items()]


@pytest.mark.parametrize("loader", LOADERS)
def test_valid_archives_load(tmp_path: Path, loader: str) -> None:
    load, members, _ = LOADERS[loader]
    load(tmp_path, list(members().items()))


# -- member content -------------------------------------------------------------------
@pytest.mark.parametrize("loader", LOADERS)
@SETTINGS
@given(garbage=st.binary(max_size=200).filter(lambda b: not b.startswith(b"\x93NUMPY")))
def test_garbage_member_names_file_and_member(tmp_path: Path, loader: str, garbage: bytes) -> None:
    _, members, target = LOADERS[loader]
    expect_error(tmp_path, loader, with_member(members(), target, garbage), repr(target))


@pytest.mark.parametrize("loader", LOADERS)
@SETTINGS
@given(data=st.data())
def test_every_truncation_of_a_member_names_file_and_member(
    tmp_path: Path, loader: str, data: st.DataObject
) -> None:
    _, members, target = LOADERS[loader]
    full = members()[target]
    cut = data.draw(st.integers(0, len(full) - 1), label="cut")  # header or data cut short
    expect_error(tmp_path, loader, with_member(members(), target, full[:cut]), repr(target))


@pytest.mark.parametrize("loader", LOADERS)
def test_object_array_member_is_refused_without_unpickling(tmp_path: Path, loader: str) -> None:
    _, members, target = LOADERS[loader]
    bad = npy(np.array([{"a": 1}, None], dtype=object), allow_pickle=True)
    expect_error(
        tmp_path, loader, with_member(members(), target, bad), repr(target), "allow_pickle=False"
    )


def _header(descr: str, shape: tuple[int, ...], version: tuple[int, int] = (1, 0)) -> bytes:
    text = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}"
    text += " " * (63 - len(text) % 64) + "\n"
    size = struct.pack("<H" if version == (1, 0) else "<I", len(text))
    return b"\x93NUMPY" + bytes(version) + size + text.encode("latin1")


@pytest.mark.parametrize("loader", LOADERS)
@pytest.mark.parametrize(
    ("content", "needle"),
    [
        # A header declaring 10^12 values over 8 bytes of data: refused before allocating.
        (_header("|u1", (10**12,)) + b"\x00" * 8, "declares shape (1000000000000,)"),
        (_header("|u1", (2, 2)) + b"\x00" * 9, "holds 9 bytes of data"),
        (_header("|u1", (2, 2), version=(9, 9)) + b"\x00" * 4, "unsupported .npy format"),
        (_header("<x4", (2,)) + b"\x00" * 8, "cannot read array"),  # no such dtype
        (b"\x93NUMPY\x01\x00" + struct.pack("<H", 60000) + b"{" * 60000, "too large to parse"),
    ],
)
def test_bad_headers_name_file_and_member(
    tmp_path: Path, loader: str, content: bytes, needle: str
) -> None:
    _, members, target = LOADERS[loader]
    expect_error(tmp_path, loader, with_member(members(), target, content), repr(target), needle)


@pytest.mark.parametrize("loader", LOADERS)
def test_crc_error_names_file_and_member(tmp_path: Path, loader: str) -> None:
    _, members, target = LOADERS[loader]
    path = entry_path(tmp_path, loader)
    write_zip(path, list(members().items()))  # stored: one flipped byte breaks one CRC
    info = zipfile.ZipFile(path).getinfo(target)
    data = bytearray(path.read_bytes())
    data[info.header_offset + 30 + len(target) + info.file_size - 1] ^= 1  # last data byte
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=re.escape(f"(member {target!r})")) as e:
        if loader == "occ3d":
            load_occ3d_labels(path, expected_shape=None)
        else:
            TeacherFeatureCache(tmp_path).load("s", 0)
    assert str(path) in str(e.value) and "CRC" in str(e.value)


# -- member names ---------------------------------------------------------------------
@pytest.mark.parametrize("loader", LOADERS)
def test_member_name_without_npy_suffix(tmp_path: Path, loader: str) -> None:
    _, members, target = LOADERS[loader]
    good = members()
    renamed = [(k[: -len(".npy")] if k == target else k, v) for k, v in good.items()]
    expect_error(tmp_path, loader, renamed, repr(target[: -len(".npy")]), "lacks the .npy suffix")
    # An extra member without the suffix is just as malformed.
    expect_error(tmp_path, loader, [*good.items(), ("README", b"hi")], "'README'")


@pytest.mark.parametrize("loader", LOADERS)
@pytest.mark.parametrize("directory", ["{target}/", "junk/"])
def test_directory_member(tmp_path: Path, loader: str, directory: str) -> None:
    _, members, target = LOADERS[loader]
    name = directory.format(target=target)
    entries = [*members().items(), (zipfile.ZipInfo(name), b"")]
    expect_error(tmp_path, loader, entries, repr(name), "is a directory")


@pytest.mark.parametrize("loader", LOADERS)
def test_duplicate_member_names(tmp_path: Path, loader: str) -> None:
    _, members, target = LOADERS[loader]
    good = members()
    entries = [*good.items(), (target, good[target])]
    expect_error(tmp_path, loader, entries, repr(target), "appears more than once")


@pytest.mark.parametrize("loader", LOADERS)
def test_missing_member(tmp_path: Path, loader: str) -> None:
    _, members, target = LOADERS[loader]
    entries = [(k, v) for k, v in members().items() if k != target]
    expect_error(tmp_path, loader, entries, "missing array(s)", repr(target[: -len(".npy")]))


# -- valid members holding the wrong arrays -------------------------------------------
@pytest.mark.parametrize(
    ("member", "array", "needles"),
    [
        ("semantics.npy", np.zeros(SHAPE, np.float32), ["semantics: expected integer labels"]),
        ("semantics.npy", np.zeros(SHAPE, bool), ["semantics: expected integer labels"]),
        ("semantics.npy", np.zeros(SHAPE, "U1"), ["semantics: expected integer labels"]),
        ("semantics.npy", np.zeros((4, 5), np.uint8), ["semantics: expected shape (X, Y, Z)"]),
        ("semantics.npy", np.zeros((), np.uint8), ["semantics: expected shape (X, Y, Z)"]),
        ("semantics.npy", np.full(SHAPE, 18, np.uint8), ["semantics: labels range over"]),
        ("mask_camera.npy", np.zeros(SHAPE, np.float64), ["mask_camera: expected a bool mask"]),
        (
            "mask_camera.npy",
            np.zeros(SHAPE, [("a", "u1")]),
            ["mask_camera: expected a bool mask"],
        ),
        ("mask_lidar.npy", np.full(SHAPE, 2, np.uint8), ["mask_lidar: holds values other"]),
        ("mask_lidar.npy", np.zeros((4, 5, 2), np.uint8), ["mask_lidar: shape (4, 5, 2) differs"]),
    ],
)
def test_occ3d_wrong_dtypes_and_shapes_name_file_and_array(
    tmp_path: Path, member: str, array: np.ndarray, needles: list[str]
) -> None:
    entries = with_member(occ3d_members(), member, npy(array))
    expect_error(tmp_path, "occ3d", entries, *needles)


@pytest.mark.parametrize(
    ("member", "array", "needles"),
    [
        ("features.npy", np.ones((2, 3, 4), np.float32), ["features: stored dtype float32"]),
        ("features.npy", np.ones((2, 3, 4), ">f2"), ["features: stored dtype >f2"]),
        ("features.npy", np.ones((2, 3, 4), np.int16), ["features: stored dtype int16"]),
        ("features.npy", np.ones((2, 3), np.float16), ["features: must be (C, H, W)"]),
        ("features.npy", np.full((1, 1, 1), np.inf, np.float16), ["features: hold NaN or inf"]),
        ("camera.npy", np.asarray([0, 0]), ["camera: expected a scalar integer", "(2,)"]),
        ("camera.npy", np.asarray(0.0), ["camera: expected a scalar integer", "float64"]),
        ("camera.npy", np.asarray("0"), ["camera: expected a scalar integer"]),
        ("sample_id.npy", np.asarray(b"s"), ["sample_id: expected a scalar string", "|S1"]),
        ("sample_id.npy", np.asarray(["s"]), ["sample_id: expected a scalar string"]),
        ("dtype.npy", np.asarray(16), ["dtype: expected a scalar string"]),
        ("format_version.npy", np.asarray([1]), ["format_version: expected a scalar integer"]),
        ("format_version.npy", np.asarray(1.0), ["format_version: expected a scalar integer"]),
    ],
)
def test_cache_wrong_dtypes_and_shapes_name_file_and_array(
    tmp_path: Path, member: str, array: np.ndarray, needles: list[str]
) -> None:
    entries = with_member(cache_members(), member, npy(array))
    expect_error(tmp_path, "cache", entries, *needles)


# -- memory guard and read_npz itself -------------------------------------------------
def test_member_sizes_go_through_the_memory_guard(tmp_path: Path) -> None:
    path = write_zip(tmp_path / "a.npz", [("big.npy", npy(np.zeros(4096, np.uint8)))])
    with dego.memory_limit(1000), pytest.raises(ValueError, match="memory limit") as info:
        read_npz(path)
    assert str(path) in str(info.value) and "'big'" in str(info.value)
    with dego.memory_limit(4096):
        assert read_npz(path)["big"].shape == (4096,)


@SETTINGS
@given(
    arrays=st.dictionaries(
        st.text("abcxyz_", min_size=1, max_size=5),
        st.sampled_from(
            [
                np.arange(6, dtype=np.float32).reshape(2, 3),
                np.asfortranarray(np.arange(6, dtype=">i4").reshape(2, 3)),
                np.zeros((0, 3), np.float16),
                np.asarray("text"),
                np.zeros(2, [("a", "<f8"), ("b", "u1", (2,))]),
            ]
        ),
        max_size=4,
    ),
    compressed=st.booleans(),
)
def test_read_npz_round_trips_what_numpy_writes(
    tmp_path: Path, arrays: dict[str, np.ndarray], compressed: bool
) -> None:
    path = tmp_path / "r.npz"
    (np.savez_compressed if compressed else np.savez)(path, **arrays)
    loaded = read_npz(path)
    assert sorted(loaded) == sorted(arrays)
    for key, value in arrays.items():
        assert loaded[key].dtype == value.dtype and np.array_equal(loaded[key], value)


def test_cache_load_of_valid_entry_with_extra_members(tmp_path: Path) -> None:
    # Extra, well-formed arrays are ignored (only the cache's own arrays are read).
    members = [*cache_members().items(), ("extra.npy", npy(np.zeros(3)))]
    write_zip(TeacherFeatureCache(tmp_path).path("s", 0), members)
    assert TeacherFeatureCache(tmp_path).load("s", 0).shape == (2, 3, 4)
    assert torch.equal(
        TeacherFeatureCache(tmp_path).load("s", 0, dtype=torch.float64),
        torch.ones(2, 3, 4, dtype=torch.float64),
    )
