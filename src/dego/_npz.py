"""Safe ``.npz`` files: atomic writes and validated reads (``allow_pickle=False``)."""

from __future__ import annotations

import math
import os
import uuid
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO

import numpy as np
from numpy.lib import format as npy_format

from dego._policy import check_memory

_ZIP_MAGIC, _EMPTY_ZIP_MAGIC, _NPY_MAGIC = b"PK\x03\x04", b"PK\x05\x06", b"\x93NUMPY"
_NPY_VERSIONS = ((1, 0), (2, 0), (3, 0))


def write_npz(path: Path, arrays: Mapping[str, np.ndarray], *, compressed: bool) -> None:
    """Write ``arrays`` to exactly ``path`` through a temporary file in the same directory
    and ``os.replace``, so readers never see a partial file; parents are created."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # A leading '.' keeps temporary names apart from real entries; os.open honours the
    # umask, unlike tempfile.mkstemp's 0600.
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as file:
            (np.savez_compressed if compressed else np.savez)(file, **arrays)
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def read_npz(
    path: Path, keys: Sequence[str] | None = None, *, holds: str = "an .npz archive"
) -> dict[str, np.ndarray]:
    """The arrays ``keys`` (default: all) of the ``.npz`` at ``path``, read with
    ``allow_pickle=False``; ``holds`` describes what the file should be, for the messages.

    The archive must be what ``numpy.savez`` writes: a zip whose members are all files
    named ``<key>.npy``, each name once. Anything else is a ``ValueError`` naming the path
    (and the member): not a zip, a damaged zip, a directory member, a member name without
    ``.npy``, a duplicated name, a missing key, and, for the members read, content that is
    not a complete ``.npy`` array (garbage, truncated or oversized header, object arrays,
    a header whose shape and dtype disagree with the member's size, CRC errors). Only the
    requested members are read; the sizes their headers declare go through the memory
    guard (:func:`dego._policy.check_memory`) before anything is allocated.
    """
    try:
        # Our own file handle: np.load leaks its handle when the zip directory is corrupt.
        with path.open("rb") as file:
            magic = file.read(6)
            file.seek(0)
            if not magic.startswith((_ZIP_MAGIC, _EMPTY_ZIP_MAGIC)):
                what = "is not a zip archive"
                if not magic:
                    what = "is empty"
                elif magic == _NPY_MAGIC:
                    what = "holds a single .npy array"
                raise ValueError(f"{path}: {what}; expected {holds}")
            try:
                archive = zipfile.ZipFile(file)
            except (PermissionError, MemoryError):
                raise
            except Exception as exc:  # zipfile errors of truncated or damaged archives
                raise ValueError(f"{path}: not a readable .npz archive ({exc})") from exc
            with archive:
                members = _members(path, archive, holds)
                wanted = list(members) if keys is None else list(keys)
                missing = [key for key in wanted if key not in members]
                if missing:
                    raise ValueError(
                        f"{path}: missing array(s) {missing}; found {sorted(members)}, "
                        f"expected {holds}"
                    )
                return {key: _read_member(path, archive, key, members[key]) for key in wanted}
    except IsADirectoryError as exc:
        raise FileNotFoundError(f"{path}: is a directory, not {holds}") from exc


def _members(path: Path, archive: zipfile.ZipFile, holds: str) -> dict[str, zipfile.ZipInfo]:
    """``key -> ZipInfo`` of every member, after checking the names as ``numpy.savez``
    writes them: files only, each named ``<key>.npy``, no name twice."""
    members: dict[str, zipfile.ZipInfo] = {}
    seen: set[str] = set()
    for info in archive.infolist():
        name = info.filename
        problem = None
        if info.is_dir():
            problem = "is a directory, not an .npy array"
        elif name in seen:
            problem = "appears more than once, so the array it holds is ambiguous"
        elif not name.endswith(".npy"):
            problem = "is not an .npy array (its name lacks the .npy suffix)"
        if problem is not None:
            raise ValueError(f"{path}: member {name!r} {problem}; expected {holds}")
        seen.add(name)
        members[name[: -len(".npy")]] = info
    return members


def _read_member(
    path: Path, archive: zipfile.ZipFile, key: str, info: zipfile.ZipInfo
) -> np.ndarray:
    """The array in member ``info``; any defect is a ValueError naming path, key and member."""
    where = f"{path}: cannot read array {key!r} (member {info.filename!r})"
    try:
        with archive.open(info) as member:
            shape, dtype, nbytes = _check_header(member, info)
    except (PermissionError, MemoryError):
        raise
    except Exception as exc:  # bad magic or header, zlib/EOF errors, unsupported compression
        raise ValueError(f"{where}: {_reason(exc)}") from exc
    # The header agrees with the member's size: guard the allocation read_array will make.
    check_memory(str(path), nbytes, f"array {key!r}: shape {shape}, {dtype}")
    try:
        with archive.open(info) as member:
            array = npy_format.read_array(member, allow_pickle=False)
            if member.read(1):  # reaching the end also makes zipfile check the CRC
                raise _MemberError("it holds data after the array")
    except (PermissionError, MemoryError):
        raise
    except Exception as exc:  # CRC/zlib/EOF errors
        raise ValueError(f"{where}: {_reason(exc)}") from exc
    if not isinstance(array, np.ndarray):  # read_array returns arrays; stay defensive
        raise ValueError(f"{where}: it does not hold an array")
    return array


def _check_header(
    member: IO[bytes], info: zipfile.ZipInfo
) -> tuple[tuple[int, ...], np.dtype, int]:
    """``(shape, dtype, nbytes)`` from an ``.npy`` header, checked against the member size."""
    version = npy_format.read_magic(member)
    if version not in _NPY_VERSIONS:
        raise _MemberError(f"unsupported .npy format version {version}")
    try:
        if version == (1, 0):
            shape, _, dtype = npy_format.read_array_header_1_0(member)
        else:  # 3.0 differs from 2.0 only in the header text's encoding (utf8 vs latin1)
            shape, _, dtype = npy_format.read_array_header_2_0(member)
    except ValueError as exc:
        if "max_header_size" in str(exc):  # numpy's advice there is to trust the file
            raise _MemberError("its .npy header is too large to parse safely") from exc
        raise
    if dtype.hasobject:
        raise _MemberError(
            f"it holds an object array ({dtype}), which would need unpickling; refused "
            "(allow_pickle=False)"
        )
    nbytes = math.prod(shape) * dtype.itemsize
    held = info.file_size - member.tell()
    if nbytes != held:
        raise _MemberError(
            f"its header declares shape {shape} of {dtype} ({nbytes} bytes) but the member "
            f"holds {held} bytes of data"
        )
    return shape, dtype, nbytes


def _reason(exc: Exception) -> str:
    if isinstance(exc, (_MemberError, ValueError)):
        return str(exc)
    return f"{type(exc).__name__}: {exc}"


class _MemberError(Exception):
    """A defect found in a member by this module (reported as a ValueError)."""
