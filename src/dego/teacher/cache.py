"""On-disk cache of teacher feature maps, one ``.npz`` file per (sample, camera)."""

from __future__ import annotations

import os
import re
import stat
import time
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from dego._npz import read_npz, write_npz
from dego._typing import typechecked

FORMAT_VERSION = 1
"""Version of the ``.npz`` layout written by :class:`TeacherFeatureCache`."""

_CACHE_DTYPES: dict[torch.dtype, np.dtype[np.floating]] = {
    torch.float16: np.dtype(np.float16),
    torch.float32: np.dtype(np.float32),
}
_SAFE_ID = re.compile(r"[A-Za-z0-9_\-][A-Za-z0-9_.\-]{0,199}")
_REQUIRED = ("features", "format_version", "dtype", "sample_id", "camera")
_SCALARS = {
    "format_version": "integer",
    "camera": "integer",
    "dtype": "string",
    "sample_id": "string",
}
# dego._atomic.temporary_name of an entry (write_npz writes it first): ".<name>.<uuid4 hex>.tmp"
_TEMPORARY = re.compile(r"\.[A-Za-z0-9_\-][A-Za-z0-9_.\-]{0,199}_cam_\d+\.npz\.[0-9a-f]{32}\.tmp")
_STALE_TEMPORARY_SECONDS = 3600.0
"""Temporary files of interrupted saves older than this (by mtime) are removed when a cache
is opened; younger ones may belong to a save still running in another process."""


def _check_key(sample_id: str, camera: int) -> None:
    if not _SAFE_ID.fullmatch(sample_id) or ".." in sample_id:
        raise ValueError(
            f"sample_id: {sample_id!r} is not a safe file name; expected 1 to 200 characters "
            "from A-Z a-z 0-9 _ - . , not starting with '.', without '..' or path separators"
        )
    if isinstance(camera, bool) or not 0 <= camera < 2**63:
        raise ValueError(f"camera: expected an int >= 0 (and < 2**63), got {camera!r}")


class TeacherFeatureCache:
    """Teacher feature maps ``(C, H, W)`` stored per (sample id, camera) under ``root``.

    Each entry is ``root / f"{sample_id}_cam_{camera}.npz"``, written with ``numpy.savez``
    (uncompressed) through a temporary file and ``os.replace``, so readers never see a
    half-written entry. It holds ``features`` in the cache dtype plus ``format_version``,
    ``dtype``, ``sample_id`` and ``camera``, which :meth:`load` checks (with
    ``allow_pickle=False``) together with the shape and finiteness of the map.

    Args:
        root: cache directory (created on the first :meth:`save`).
        dtype: storage dtype, ``torch.float16`` (default) or ``torch.float32``. float16
            keeps ~3 significant digits (relative rounding error <= 2^-11 for
            |x| in [6.1e-5, 65504]), loses relative precision below 6.1e-5 and cannot
            hold |x| > 65504 (:meth:`save` refuses such maps rather than writing inf).

    Size: the official cache stores, per (sample, camera), a torch ``.pt`` dict with the
    float32 ``(1, 2048, 18, 50)`` VGGT block-22 map and the float32 ``(3, 252, 700)``
    input image, about 9.5 MB. Here the same map alone in float16 is about 3.7 MB, a
    factor of about 2.6 smaller (measured in ``tests/teacher/test_cache.py``), with no
    pickle on load. ``savez_compressed`` saved only ~8% on such maps at ~100x the write
    time, so entries are not compressed.
    """

    def __init__(self, root: str | os.PathLike[str], dtype: torch.dtype = torch.float16) -> None:
        if not isinstance(root, (str, os.PathLike)):
            raise TypeError(f"root: expected a str or os.PathLike, got {type(root).__name__}")
        if dtype not in _CACHE_DTYPES:
            raise ValueError(f"dtype: expected torch.float16 or torch.float32, got {dtype!r}")
        self.root = Path(root)
        self.dtype = dtype
        self._np_dtype = _CACHE_DTYPES[dtype]
        _remove_stale_temporaries(self.root, _STALE_TEMPORARY_SECONDS)

    def __repr__(self) -> str:
        return f"TeacherFeatureCache(root={str(self.root)!r}, dtype={self.dtype})"

    @typechecked
    def path(self, sample_id: str, camera: int) -> Path:
        """The file of entry ``(sample_id, camera)`` (which may not exist)."""
        _check_key(sample_id, camera)
        return self.root / f"{sample_id}_cam_{camera}.npz"

    @typechecked
    def __contains__(self, key: tuple[str, int]) -> bool:
        """``(sample_id, camera) in cache``: whether the entry's file exists."""
        return self.path(*key).is_file()

    @typechecked
    def nbytes(self, sample_id: str, camera: int) -> int:
        """Size on disk, in bytes, of entry ``(sample_id, camera)``."""
        path = self.path(sample_id, camera)
        if not path.is_file():
            raise FileNotFoundError(self._missing(sample_id, camera, path))
        return path.stat().st_size

    @typechecked
    def keys(self) -> list[tuple[str, int]]:
        """The ``(sample_id, camera)`` entries present, sorted."""
        if not self.root.is_dir():
            return []
        found = []
        for path in self.root.glob("*_cam_*.npz"):
            sample_id, _, camera = path.name[: -len(".npz")].rpartition("_cam_")
            if (
                camera.isdigit()
                and _SAFE_ID.fullmatch(sample_id)
                and ".." not in sample_id
                and path.is_file()  # not a directory, FIFO or other non-regular file
            ):
                found.append((sample_id, int(camera)))
        return sorted(found)

    @typechecked
    def save(self, sample_id: str, camera: int, features: Float[Tensor, "C H W"]) -> Path:
        """Store a ``(C, H, W)`` map (any float dtype and device) in the cache dtype.

        Overwrites an existing entry atomically. Raises ValueError if ``features`` holds
        NaN/inf or values outside the cache dtype's range. Returns the written path.
        """
        path = self.path(sample_id, camera)
        values = features.detach()
        if values.dtype in (torch.float16, torch.bfloat16):
            values = values.float()
        # numpy rounds float64 -> float16 correctly (torch would round twice via float32).
        array = values.cpu().numpy()
        if not np.isfinite(array).all():
            raise ValueError(f"features: holds NaN or inf (sample {sample_id!r}, camera {camera})")
        limit = float(np.finfo(self._np_dtype).max)
        peak = float(np.abs(array).max()) if array.size else 0.0
        if peak > limit:
            raise ValueError(
                f"features: |values| up to {peak:.6g} exceed {self._np_dtype.name}'s range "
                f"(+-{limit:.6g}) and would be stored as inf; rescale them or use "
                "TeacherFeatureCache(..., dtype=torch.float32)"
            )
        arrays = {
            "features": np.ascontiguousarray(array.astype(self._np_dtype)),
            "format_version": np.asarray(FORMAT_VERSION, dtype=np.int64),
            "dtype": np.asarray(self._np_dtype.name),
            "sample_id": np.asarray(sample_id),
            "camera": np.asarray(camera, dtype=np.int64),
        }
        write_npz(path, arrays, compressed=False)
        return path

    @typechecked
    def load(
        self,
        sample_id: str,
        camera: int,
        *,
        expected_shape: tuple[int, int, int] | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> Float[Tensor, "C H W"]:
        """Read entry ``(sample_id, camera)`` as a ``(C, H, W)`` tensor.

        Args:
            expected_shape: if given, the stored ``(C, H, W)`` must equal it.
            device: where to put the result (CPU by default); the stored dtype is moved
                first and converted there.
            dtype: floating dtype of the result, float32 by default.

        Raises:
            FileNotFoundError: no such entry.
            ValueError: the file is not a readable ``.npz`` of this format (truncated,
                garbage, a member that is not a valid ``.npy`` array, a directory member,
                a member name without ``.npy`` or twice, missing arrays, object arrays),
                a metadata array is not the scalar it should be, the features' dtype
                differs from the cache's, its key differs from the requested one, its
                shape is wrong or its values are not finite; the message names the path
                and the array (and the zip member when the member itself is bad).
        """
        if expected_shape is not None and any(isinstance(n, bool) or n < 1 for n in expected_shape):
            raise ValueError(f"expected_shape: expected 3 ints >= 1, got {expected_shape!r}")
        out_dtype = torch.float32 if dtype is None else dtype
        if not out_dtype.is_floating_point:
            raise ValueError(f"dtype: expected a floating dtype, got {dtype!r}")
        path = self.path(sample_id, camera)
        if not path.is_file():
            raise FileNotFoundError(self._missing(sample_id, camera, path))
        arrays = read_npz(
            path,
            _REQUIRED,
            holds="a teacher feature cache entry",
            check_header=lambda key, shape, dtype: _check_header(key, shape, dtype, expected_shape),
        )
        features = self._validate(path, arrays, sample_id, camera, expected_shape)
        if not features.flags.writeable:
            features = features.copy()
        return torch.from_numpy(features).to(device=device).to(dtype=out_dtype)

    # -- helpers ----------------------------------------------------------------------
    def _missing(self, sample_id: str, camera: int, path: Path) -> str:
        return f"no cached teacher features for sample {sample_id!r} camera {camera} ({path})"

    def _validate(
        self,
        path: Path,
        arrays: dict[str, np.ndarray],
        sample_id: str,
        camera: int,
        expected_shape: tuple[int, int, int] | None,
    ) -> np.ndarray:
        version = _scalar_int(path, arrays, "format_version")
        if version != FORMAT_VERSION:
            raise ValueError(
                f"{path}: format_version {version}, this reader handles {FORMAT_VERSION}"
            )
        stored = _scalar_str(path, arrays, "dtype")
        features = arrays["features"]
        if stored != self._np_dtype.name or features.dtype != self._np_dtype:
            raise ValueError(
                f"{path}: features: stored dtype {features.dtype} (metadata {stored!r}) "
                f"differs from this cache's {self._np_dtype.name}"
            )
        stored_id = _scalar_str(path, arrays, "sample_id")
        stored_camera = _scalar_int(path, arrays, "camera")
        if (stored_id, stored_camera) != (sample_id, camera):
            raise ValueError(
                f"{path}: holds sample {stored_id!r} camera {stored_camera!r}, "
                f"not sample {sample_id!r} camera {camera}"
            )
        if features.ndim != 3:
            raise ValueError(
                f"{path}: features: must be (C, H, W), got shape {tuple(features.shape)}"
            )
        if expected_shape is not None and tuple(features.shape) != tuple(expected_shape):
            raise ValueError(
                f"{path}: features: shape {tuple(features.shape)}, "
                f"expected_shape is {tuple(expected_shape)}"
            )
        if not np.isfinite(features).all():
            raise ValueError(f"{path}: features: hold NaN or inf")
        return features


def _check_header(
    key: str,
    shape: tuple[int, ...],
    dtype: np.dtype,
    expected_shape: tuple[int, int, int] | None,
) -> None:
    """The shape checks of :meth:`TeacherFeatureCache._validate` that an ``.npy`` header
    allows, run before the array is inflated (a huge declared shape is refused unread)."""
    if key in _SCALARS and shape != ():
        raise ValueError(f"{key}: expected a scalar {_SCALARS[key]}, got shape {shape} of {dtype}")
    if key == "features" and len(shape) != 3:
        raise ValueError(f"features: must be (C, H, W), got shape {shape}")
    if key == "features" and expected_shape is not None and shape != tuple(expected_shape):
        raise ValueError(f"features: shape {shape}, expected_shape is {tuple(expected_shape)}")


def _remove_stale_temporaries(root: Path, max_age: float) -> None:
    """Remove the temporary files of interrupted saves in ``root`` older than ``max_age``
    seconds (regular files named as ``dego._atomic.temporary_name`` names an entry's);
    anything that cannot be removed (a read-only cache) is left, silently."""
    try:
        entries = os.scandir(root)
    except OSError:  # no directory yet (created on the first save), or unreadable
        return
    cutoff = time.time() - max_age
    with entries:
        for entry in entries:
            if not _TEMPORARY.fullmatch(entry.name):
                continue
            try:
                info = entry.stat(follow_symlinks=False)
                if stat.S_ISREG(info.st_mode) and info.st_mtime < cutoff:
                    os.unlink(entry.path)
            except OSError:  # removed meanwhile, or not ours to remove
                continue


def _scalar_int(path: Path, arrays: dict[str, np.ndarray], key: str) -> int:
    """Metadata ``key``: a 0-d integer array, as :meth:`TeacherFeatureCache.save` writes."""
    array = arrays[key]
    if array.shape != () or array.dtype.kind not in "iu":
        raise ValueError(
            f"{path}: {key}: expected a scalar integer, got shape {array.shape} of {array.dtype}"
        )
    return int(array)


def _scalar_str(path: Path, arrays: dict[str, np.ndarray], key: str) -> str:
    """Metadata ``key``: a 0-d unicode array, as :meth:`TeacherFeatureCache.save` writes."""
    array = arrays[key]
    if array.shape != () or array.dtype.kind != "U":
        raise ValueError(
            f"{path}: {key}: expected a scalar string, got shape {array.shape} of {array.dtype}"
        )
    return str(array[()])


__all__ = ["FORMAT_VERSION", "TeacherFeatureCache"]
