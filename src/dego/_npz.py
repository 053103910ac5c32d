"""Safe ``.npz`` files: atomic writes and validated reads (``allow_pickle=False``)."""

from __future__ import annotations

import io
import math
import os
import stat
import zipfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any, BinaryIO

import numpy as np
from numpy.lib import format as npy_format

from dego._atomic import temporary_name
from dego._policy import check_memory

_ZIP_MAGIC, _EMPTY_ZIP_MAGIC, _NPY_MAGIC = b"PK\x03\x04", b"PK\x05\x06", b"\x93NUMPY"
_NPY_VERSIONS = ((1, 0), (2, 0), (3, 0))
# Deflate codes at least 2 bits per 258-byte match: no stream inflates more than 1032:1.
_DEFLATE_MAX_RATIO = 1032
_MAX_HEADER_BYTES = 1 << 16  # numpy's own max_header_size (10000 characters) applies below
_NOT_REGULAR = (
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)

HeaderCheck = Callable[[str, tuple[int, ...], np.dtype], None]
"""``check_header(key, shape, dtype)`` of :func:`read_npz`: raise ``ValueError`` (a message
naming the array) to refuse a member from its ``.npy`` header, before it is inflated."""


def open_regular_file(path: Path, holds: str) -> BinaryIO:
    """``path`` opened for binary reading, refusing anything but a regular file.

    The file is opened with ``O_NONBLOCK`` (where the platform has it) and checked with
    ``fstat`` on the open descriptor, so a FIFO is refused instead of blocking ``open``
    until a writer appears, and nothing can be swapped in between the check and the read.
    Directories, FIFOs, sockets and devices raise ``FileNotFoundError`` naming ``path``
    and what it is (``holds``: what the file should be); a missing file raises the usual
    ``FileNotFoundError``.
    """
    nonblocking = getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_BINARY", 0) | nonblocking)
    except IsADirectoryError as exc:
        raise FileNotFoundError(f"{path}: is a directory, not {holds}") from exc
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            if stat.S_ISDIR(mode):
                raise FileNotFoundError(f"{path}: is a directory, not {holds}")
            kind = next((what for test, what in _NOT_REGULAR if test(mode)), "special")
            raise FileNotFoundError(f"{path}: is {kind}, not a regular file; expected {holds}")
        if nonblocking:
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def npy_header(path: Path, holds: str) -> tuple[tuple[int, ...], np.dtype]:
    """The shape and dtype a ``.npy`` file declares, read from its header alone (nothing
    else is read); a file that is not a ``.npy`` array is a ``ValueError`` naming ``path``
    and what it should hold, an object array is refused (``allow_pickle=False``)."""
    with open_regular_file(path, holds) as file:
        try:
            version = npy_format.read_magic(file)
            read = (
                npy_format.read_array_header_1_0
                if version == (1, 0)
                else npy_format.read_array_header_2_0
            )
            shape, _, dtype = read(file)
        except Exception as exc:  # bad magic, garbage header
            raise ValueError(
                f"{path}: not a readable .npy array ({exc}); expected {holds}"
            ) from exc
    if dtype.hasobject:
        raise ValueError(f"{path}: holds an object array ({dtype}); refused (allow_pickle=False)")
    return tuple(shape), dtype


def write_npz(path: Path, arrays: Mapping[str, np.ndarray], *, compressed: bool) -> None:
    """Write ``arrays`` to exactly ``path`` through a temporary file in the same directory
    and ``os.replace``, so readers never see a partial file; parents are created."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(path)  # os.open honours the umask, unlike mkstemp's 0600
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as file:
            # the keys are array names: numpy's stubs would also match them to allow_pickle
            named: dict[str, Any] = dict(arrays)
            (np.savez_compressed if compressed else np.savez)(file, **named)
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def read_npz(
    path: Path,
    keys: Sequence[str] | None = None,
    *,
    holds: str = "an .npz archive",
    check_header: HeaderCheck | None = None,
) -> dict[str, np.ndarray]:
    """The arrays ``keys`` (default: all) of the ``.npz`` at ``path``, read with
    ``allow_pickle=False``; ``holds`` describes what the file should be, for the messages.

    The archive must be what ``numpy.savez`` writes: a regular file (a FIFO, socket,
    device or directory is a ``FileNotFoundError``, raised without blocking), a zip whose
    members are all files named ``<key>.npy``, each name once, stored or deflated.
    Anything else is a ``ValueError`` naming the path (and the member): not a zip, a
    damaged zip, a directory member, a member name without ``.npy``, a duplicated name, a
    missing key, and, for the members read, sizes the archive cannot hold (a compressed
    size beyond the file, an uncompressed size beyond deflate's 1032:1, another
    compression method) and content that is not a complete ``.npy`` array (garbage,
    truncated or oversized header, object arrays, a header whose shape and dtype disagree
    with the member's size, CRC errors).

    Nothing is inflated before every requested member has passed these checks on its
    declared sizes and its ``.npy`` header: ``check_header(key, shape, dtype)``, when given,
    is called then for each (in the order of ``keys``) and may raise ``ValueError`` (its
    message is prefixed with the path), e.g. for a shape other than the one expected; the
    bytes the headers declare then go through the memory guard
    (:func:`dego._policy.check_memory`) before anything is allocated.
    """
    # Our own file handle: np.load leaks its handle when the zip directory is corrupt.
    with open_regular_file(path, holds) as file:
        archive_size = os.fstat(file.fileno()).st_size
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
                    f"{path}: missing array(s) {missing}; found {sorted(members)}, expected {holds}"
                )
            headers: dict[str, tuple[tuple[int, ...], np.dtype, int]] = {}
            for key in wanted:
                info = members[key]
                _check_sizes(path, key, info, archive_size)
                shape, dtype, nbytes = _read_header(path, archive, key, info)
                headers[key] = shape, dtype, nbytes
                if check_header is not None:
                    try:
                        check_header(key, shape, dtype)
                    except ValueError as exc:
                        raise ValueError(f"{path}: {exc}") from exc
            # The headers agree with the members' sizes: guard what read_array will allocate.
            sizes = [
                f"array {key!r}: shape {shape}, {dtype}"
                for key, (shape, dtype, _) in headers.items()
            ]
            if len(sizes) > 4:
                sizes[3:] = [f"... and {len(sizes) - 3} more arrays"]
            check_memory(str(path), sum(n for _, _, n in headers.values()), "; ".join(sizes))
            return {key: _read_member(path, archive, key, members[key]) for key in wanted}


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


def _where(path: Path, key: str, info: zipfile.ZipInfo) -> str:
    return f"{path}: cannot read array {key!r} (member {info.filename!r})"


def _check_sizes(path: Path, key: str, info: zipfile.ZipInfo, archive_size: int) -> None:
    """Refuse a member whose declared sizes the archive cannot hold (before inflating)."""
    problem = None
    if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
        problem = (
            f"it is compressed with zip method {info.compress_type}; numpy.savez writes "
            "stored or deflated members only"
        )
    elif info.header_offset + info.compress_size > archive_size:
        problem = (
            f"it declares {info.compress_size} compressed bytes at offset "
            f"{info.header_offset}, beyond the end of the {archive_size}-byte archive"
        )
    elif info.compress_type == zipfile.ZIP_STORED and info.file_size != info.compress_size:
        problem = (
            f"it is stored uncompressed but declares {info.file_size} bytes in {info.compress_size}"
        )
    elif info.file_size > _DEFLATE_MAX_RATIO * info.compress_size:
        problem = (
            f"it declares {info.file_size} bytes inflated from {info.compress_size} "
            f"compressed bytes, above deflate's maximum ratio of {_DEFLATE_MAX_RATIO}:1 "
            "(a forged size or a zip bomb)"
        )
    if problem is not None:
        raise ValueError(f"{_where(path, key, info)}: {problem}; refused before inflating it")


def _read_header(
    path: Path, archive: zipfile.ZipFile, key: str, info: zipfile.ZipInfo
) -> tuple[tuple[int, ...], np.dtype, int]:
    """``(shape, dtype, nbytes)`` of member ``info``, from its header alone."""
    try:
        with archive.open(info) as member:
            return _check_header(member, info)
    except (PermissionError, MemoryError):
        raise
    except Exception as exc:  # bad magic or header, zlib/EOF errors, unsupported compression
        raise ValueError(f"{_where(path, key, info)}: {_reason(exc)}") from exc


def _read_member(
    path: Path, archive: zipfile.ZipFile, key: str, info: zipfile.ZipInfo
) -> np.ndarray:
    """The array in member ``info`` (its header already checked); any defect is a
    ValueError naming path, key and member."""
    where = _where(path, key, info)
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
    # Read the header's declared length first: a 2.0 header may declare up to 4 GiB, which
    # numpy would read (inflating it) before comparing with its max_header_size.
    length = member.read(2 if version == (1, 0) else 4)  # numpy reports a short read
    declared = int.from_bytes(length, "little")
    if declared > _MAX_HEADER_BYTES:
        raise _MemberError("its .npy header is too large to parse safely")
    header = io.BytesIO(length + member.read(declared))
    try:
        if version == (1, 0):
            shape, _, dtype = npy_format.read_array_header_1_0(header)
        else:  # 3.0 differs from 2.0 only in the header text's encoding (utf8 vs latin1)
            shape, _, dtype = npy_format.read_array_header_2_0(header)
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
