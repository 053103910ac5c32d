"""Safe ``.npz`` files: atomic writes and validated reads (``allow_pickle=False``)."""

from __future__ import annotations

import os
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

_ZIP_MAGIC, _EMPTY_ZIP_MAGIC, _NPY_MAGIC = b"PK\x03\x04", b"PK\x05\x06", b"\x93NUMPY"


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
    ``allow_pickle=False``. Anything unreadable or missing is a ValueError naming the path
    (and the key); ``holds`` describes what the file should be, for the messages."""
    try:
        # Our own file handle: np.load leaks its handle when the zip directory is corrupt.
        with path.open("rb") as file:
            # np.load reports any unknown content as refused pickle data: say what it is.
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
                loaded = np.load(file, allow_pickle=False)
            except (PermissionError, MemoryError):
                raise
            except Exception as exc:  # zipfile errors of truncated or damaged archives
                raise ValueError(f"{path}: not a readable .npz archive ({exc})") from exc
            with loaded as npz:
                wanted = list(npz.files) if keys is None else list(keys)
                missing = [key for key in wanted if key not in npz.files]
                if missing:
                    raise ValueError(
                        f"{path}: missing array(s) {missing}; found {sorted(npz.files)}, "
                        f"expected {holds}"
                    )
                arrays = {}
                for key in wanted:
                    try:
                        arrays[key] = npz[key]
                    except (PermissionError, MemoryError):
                        raise
                    except Exception as exc:  # zlib/CRC errors, object arrays, bad headers
                        raise ValueError(f"{path}: cannot read array {key!r} ({exc})") from exc
                return arrays
    except IsADirectoryError as exc:
        raise FileNotFoundError(f"{path}: is a directory, not {holds}") from exc
