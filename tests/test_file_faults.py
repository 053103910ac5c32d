"""File faults (issue 26): zip bombs and implausible member sizes in ``.npz`` archives are
refused before anything is inflated, and FIFOs (or other non-regular files) where a data
file should be are refused instead of blocking forever in ``open``."""

from __future__ import annotations

import contextlib
import functools
import io
import os
import pickle
import struct
import threading
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from numpy.lib import format as npy_format

from dego import load_occ3d_labels
from dego._npz import read_npz
from dego.data.infos import load_infos
from dego.data.safe_pickle import load_pickle
from dego.teacher.cache import TeacherFeatureCache

BOMB_SHAPE = (1_000_000, 40, 40)  # uint8: 1.6 GB of zeros in ~1.55 MB of deflate
BOMB_BYTES = 1_600_000_000
_CHUNK = 1 << 24


# -- hand-written zip archives -----------------------------------------------------------
def _npy_header(shape: tuple[int, ...], descr: str = "|u1") -> bytes:
    buffer = io.BytesIO()
    npy_format.write_array_header_1_0(
        buffer, {"descr": descr, "fortran_order": False, "shape": shape}
    )
    return buffer.getvalue()


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()


def _deflate(data: bytes, *, final: bool = True) -> bytes:
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    return compressor.compress(data) + compressor.flush(
        zlib.Z_FINISH if final else zlib.Z_FULL_FLUSH
    )


Member = tuple[str, bytes, int, int, int]  # name, stored data, crc32, file_size, method


def _member(name: str, raw: bytes) -> Member:
    """A genuine deflated member holding ``raw``."""
    return name, _deflate(raw), zlib.crc32(raw), len(raw), zipfile.ZIP_DEFLATED


def _write_zip(
    path: Path, members: list[Member], *, compress_sizes: dict[str, int] | None = None
) -> Path:
    """A zip written field by field, so that the sizes it declares can lie (``compress_sizes``
    overrides the declared compressed size of a member)."""
    compress_sizes = compress_sizes or {}
    out, central = bytearray(), bytearray()
    for name, data, crc, file_size, method in members:
        encoded = name.encode()
        declared = compress_sizes.get(name, len(data))
        fields = (20, 0, method, 0, 0x21, crc, declared, file_size, len(encoded))
        central += struct.pack("<IH", 0x02014B50, 20)
        central += struct.pack("<HHHHHIIIHHHHHII", *fields, 0, 0, 0, 0, 0, len(out)) + encoded
        out += struct.pack("<IHHHHHIIIHH", 0x04034B50, *fields, 0) + encoded + data
    end = struct.pack(
        "<IHHHHIIH", 0x06054B50, 0, 0, len(members), len(members), len(central), len(out), 0
    )
    path.write_bytes(bytes(out + central + end))
    return path


@functools.cache
def _bomb() -> Member:
    """A valid ``semantics.npy`` member: BOMB_SHAPE zeros, built without compressing 1.6 GB
    (a full flush resets the compressor, so every 16 MiB block of zeros deflates to the same
    bytes, which are repeated)."""
    header = _npy_header(BOMB_SHAPE)
    count, rest = divmod(BOMB_BYTES, _CHUNK)
    chunk = bytes(_CHUNK)
    data = (
        _deflate(header, final=False) + _deflate(chunk, final=False) * count + _deflate(bytes(rest))
    )
    crc = zlib.crc32(header)
    for _ in range(count):
        crc = zlib.crc32(chunk, crc)
    crc = zlib.crc32(bytes(rest), crc)
    return "semantics.npy", data, crc, len(header) + BOMB_BYTES, zipfile.ZIP_DEFLATED


def _masks(shape: tuple[int, ...] = (200, 200, 16)) -> list[Member]:
    mask = np.ones(shape, np.uint8)
    return [_member("mask_lidar.npy", _npy(mask)), _member("mask_camera.npy", _npy(mask))]


@pytest.fixture
def no_inflating(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Replace numpy's ``read_array`` (which inflates a member) with one that records the
    call and fails; the test asserts the list stays empty."""
    calls: list[str] = []

    def refuse(*args: object, **kwargs: object) -> None:
        calls.append("read_array")
        raise AssertionError("read_array was called: the member is being inflated")

    monkeypatch.setattr(npy_format, "read_array", refuse)
    return calls


# -- zip bombs ----------------------------------------------------------------------------
@pytest.mark.slow
def test_zip_bomb_labels_are_refused_from_the_header(
    tmp_path: Path, no_inflating: list[str]
) -> None:
    bomb = _bomb()
    path = _write_zip(tmp_path / "labels.npz", [bomb, *_masks()])
    assert path.stat().st_size < 2_000_000  # the 1.56 MB file
    with pytest.raises(ValueError) as info:
        load_occ3d_labels(path)
    message = str(info.value)
    assert str(path) in message and "semantics" in message, message
    assert "(1000000, 40, 40)" in message and "(200, 200, 16)" in message, message
    assert no_inflating == []


def test_occ3d_header_dtype_and_mask_shape_are_checked_before_reading(
    tmp_path: Path, no_inflating: list[str]
) -> None:
    floats = _member("semantics.npy", _npy(np.zeros((200, 200, 16), np.float32)))
    path = _write_zip(tmp_path / "labels.npz", [floats, *_masks()])
    with pytest.raises(ValueError, match=r"semantics: expected integer labels, got dtype float32"):
        load_occ3d_labels(path)
    semantics = _member("semantics.npy", _npy(np.zeros((4, 5, 3), np.uint8)))
    path = _write_zip(tmp_path / "labels.npz", [semantics, *_masks((4, 5, 6))])
    with pytest.raises(ValueError, match=r"mask_lidar: shape \(4, 5, 6\) differs from semantics'"):
        load_occ3d_labels(path, expected_shape=None)
    assert no_inflating == []


def test_read_npz_header_check_runs_before_inflating(
    tmp_path: Path, no_inflating: list[str]
) -> None:
    path = _write_zip(tmp_path / "a.npz", [_member("x.npy", _npy(np.zeros((3, 4))))])
    seen = []

    def check(key: str, shape: tuple[int, ...], dtype: np.dtype) -> None:
        seen.append((key, shape, dtype))
        raise ValueError(f"{key}: shape {shape} is not wanted")

    with pytest.raises(ValueError, match=r"a\.npz: x: shape \(3, 4\) is not wanted"):
        read_npz(path, check_header=check)
    assert seen == [("x", (3, 4), np.dtype(np.float64))] and no_inflating == []


def test_implausible_compression_ratio_is_refused(tmp_path: Path, no_inflating: list[str]) -> None:
    # The header and its declared size agree (1.6 GB) but the member holds ~100 bytes of
    # deflate: no deflate stream inflates more than ~1032:1.
    header = _npy_header(BOMB_SHAPE)
    liar = (
        "big.npy",
        _deflate(header + bytes(64)),
        0,
        len(header) + BOMB_BYTES,
        zipfile.ZIP_DEFLATED,
    )
    path = _write_zip(tmp_path / "a.npz", [liar])
    with pytest.raises(ValueError) as info:
        read_npz(path)
    message = str(info.value)
    assert str(path) in message and "'big.npy'" in message and "1032" in message, message
    assert no_inflating == []


def test_compressed_size_beyond_the_archive_is_refused(
    tmp_path: Path, no_inflating: list[str]
) -> None:
    header = _npy_header((100_000,))
    member = (
        "big.npy",
        _deflate(header + bytes(100_000)),
        0,
        len(header) + 100_000,
        zipfile.ZIP_DEFLATED,
    )
    path = _write_zip(tmp_path / "a.npz", [member], compress_sizes={"big.npy": 10**6})
    with pytest.raises(ValueError) as info:
        read_npz(path)
    message = str(info.value)
    assert str(path) in message and "'big.npy'" in message and "archive" in message, message
    assert no_inflating == []


def test_compression_other_than_numpys_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "a.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_BZIP2) as archive:
        archive.writestr("x.npy", _npy(np.zeros(10)))
    with pytest.raises(ValueError, match=r"'x\.npy'.*compress"):
        read_npz(path)


def test_genuine_archives_still_load(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    arrays = {
        "noise": rng.random((50, 7)),
        "zeros": np.zeros((300, 300), np.uint8),
        "e": np.zeros(0),
    }
    for writer in (np.savez, np.savez_compressed):
        writer(tmp_path / "a.npz", **arrays)
        loaded = read_npz(tmp_path / "a.npz")
        assert all(np.array_equal(loaded[k], v) for k, v in arrays.items())
    members = [_member("x.npy", _npy(np.arange(5)))]
    assert read_npz(_write_zip(tmp_path / "b.npz", members))["x"].tolist() == list(range(5))


# -- FIFOs --------------------------------------------------------------------------------
needs_fifo = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no os.mkfifo here")


def _call_bounded(
    fn: Callable[[], object], fifo: Path, timeout: float = 20.0
) -> BaseException | None:
    """Run ``fn`` in a thread; fail (instead of hanging) if it does not return in time.

    A reader blocked in ``open`` of the FIFO is released by opening its write end."""
    outcome: list[BaseException | None] = []

    def target() -> None:
        try:
            fn()
        except BaseException as exc:  # handed to the test
            outcome.append(exc)
        else:
            outcome.append(None)

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(timeout)
    if thread.is_alive():
        with contextlib.suppress(OSError):  # no reader left: nothing to release
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        thread.join(10)
        pytest.fail(f"reading the FIFO {fifo} blocked for {timeout} s")
    return outcome[0]


def _fifo(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    os.mkfifo(path)
    return path


@needs_fifo
@pytest.mark.parametrize(
    "reader",
    [
        pytest.param(lambda p: load_occ3d_labels(p), id="load_occ3d_labels"),
        pytest.param(lambda p: read_npz(p), id="read_npz"),
        pytest.param(lambda p: load_pickle(p), id="load_pickle"),
        pytest.param(lambda p: load_infos(p), id="load_infos"),
    ],
)
def test_fifo_is_refused_without_blocking(tmp_path: Path, reader: Callable[[Path], object]) -> None:
    fifo = _fifo(tmp_path / "data.file")
    error = _call_bounded(lambda: reader(fifo), fifo)
    assert isinstance(error, FileNotFoundError), error
    assert str(fifo) in str(error) and "regular file" in str(error), error


@needs_fifo
def test_fifo_in_the_teacher_cache_is_not_an_entry(tmp_path: Path) -> None:
    cache = TeacherFeatureCache(tmp_path)
    fifo = _fifo(cache.path("s", 0))
    error = _call_bounded(lambda: cache.load("s", 0), fifo)
    assert isinstance(error, FileNotFoundError), error
    assert ("s", 0) not in cache and cache.keys() == []


def test_regular_files_still_load_through_the_same_checks(tmp_path: Path) -> None:
    path = tmp_path / "p.pkl"
    path.write_bytes(pickle.dumps({"a": [1, 2.5]}))
    assert load_pickle(path) == {"a": [1, 2.5]}
    with pytest.raises(FileNotFoundError, match="directory"):
        read_npz(tmp_path)
    with pytest.raises(FileNotFoundError):
        read_npz(tmp_path / "missing.npz")


def _write_members(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return path


def _npy(array: np.ndarray, version: tuple[int, int] | None = None) -> bytes:
    buffer = io.BytesIO()
    npy_format.write_array(buffer, array, version=version, allow_pickle=False)
    return buffer.getvalue()


@pytest.mark.parametrize("version", [(1, 0), (2, 0), (3, 0)])
def test_every_npy_header_version_is_read(tmp_path: Path, version: tuple[int, int]) -> None:
    """1.0 headers declare their length in 2 bytes, 2.0 and 3.0 in 4 (read before parsing)."""
    array = np.arange(24, dtype=np.int16).reshape(2, 3, 4)
    path = _write_members(tmp_path / "a.npz", {"a.npy": _npy(array, version)})
    np.testing.assert_array_equal(read_npz(path)["a"], array)


@pytest.mark.parametrize("error", [MemoryError, PermissionError])
def test_resource_errors_of_the_zip_reader_are_not_disguised(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, error: type[Exception]
) -> None:
    path = _write_members(tmp_path / "a.npz", {"a.npy": _npy(np.zeros(3))})

    def failing(*args: object, **kwargs: object) -> None:
        raise error("resource")

    monkeypatch.setattr(zipfile, "ZipFile", failing)
    with pytest.raises(error, match="resource"):
        read_npz(path)


@pytest.mark.parametrize(("count", "listed"), [(4, 4), (5, 3)])
def test_the_memory_message_lists_up_to_four_arrays(
    tmp_path: Path, count: int, listed: int
) -> None:
    import dego

    members = {f"a{i}.npy": _npy(np.zeros(8)) for i in range(count)}
    path = _write_members(tmp_path / "a.npz", members)
    with dego.memory_limit(16), pytest.raises(ValueError, match="memory limit") as info:
        read_npz(path)
    message = str(info.value)
    assert sum(f"array 'a{i}'" in message for i in range(count)) == listed
    assert ("more arrays" in message) == (count > 4)
