"""Reading and writing Occ3D-nuScenes ground truth (``gts/<scene>/<token>/labels.npz``).

Each Occ3D-nuScenes sample is one ``labels.npz`` archive (``numpy.savez_compressed``)
holding three ``(200, 200, 16)`` arrays over :meth:`dego.grid.VoxelGrid.occ3d`, index
order x, y, z:

- ``semantics``: uint8 labels ``0..17`` (:class:`dego.classes.Occ3DLabel`, 17 = free);
- ``mask_lidar``: uint8 0/1, voxels observed by the lidar;
- ``mask_camera``: uint8 0/1, voxels visible from the cameras (the ``occ3d`` evaluation
  mask).

:func:`load_occ3d_labels` reads such a file into :class:`Occ3DLabels` (torch tensors,
masks as ``torch.bool``), :func:`save_occ3d_labels` writes the same layout, and
:class:`Occ3DDataset` iterates over a local copy of the data set for evaluation. Files
are read with ``allow_pickle=False``; anything unreadable or malformed raises an error
that names the file and the offending array.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from jaxtyping import Bool, UInt8
from torch import Tensor
from torch.utils.data import Dataset

from dego._checks import check_int
from dego._npz import read_npz, write_npz
from dego._typing import typechecked
from dego.classes import NUM_CLASSES

OCC3D_SHAPE: tuple[int, int, int] = (200, 200, 16)
"""``(X, Y, Z)`` of every Occ3D-nuScenes grid (``VoxelGrid.occ3d().shape``)."""

LABELS_FILENAME = "labels.npz"
"""Name of the per-sample file in ``gts/<scene>/<token>/``."""

_KEYS = ("semantics", "mask_lidar", "mask_camera")  # the order of the real files
_TORCH_WIDE_UNSIGNED = (torch.uint16, torch.uint32, torch.uint64)  # no min/max on CPU

PathLike = str | os.PathLike[str]
Shape3 = tuple[int, int, int]


# ----------------------------------------------------------------------------------------
# Occ3DLabels
# ----------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class Occ3DLabels:
    """Ground truth of one Occ3D sample: labels and visibility masks on one ``(X, Y, Z)`` grid.

    Fields:
        semantics: ``(X, Y, Z)`` ``torch.uint8`` labels in ``0..num_classes-1``
            (Occ3D-nuScenes: 0..16 semantic classes, 17 = free).
        mask_camera: ``(X, Y, Z)`` ``torch.bool``, True where a camera sees the voxel.
        mask_lidar: ``(X, Y, Z)`` ``torch.bool``, True where the lidar observed the voxel.
        num_classes: labels must be ``< num_classes``; 18 (:data:`dego.classes.NUM_CLASSES`)
            by default, at most 256. Occ3D-nuScenes holds no ignore value (such as 255);
            pass ``num_classes=256`` to keep data sets that do.

    The constructor is strict (exact dtypes, one shape, one device) and raises
    ``TypeError``/``ValueError`` naming the field; :meth:`from_arrays` converts numpy
    arrays or tensors of other integer dtypes (and 0/1 integer masks) first.
    """

    semantics: UInt8[Tensor, "X Y Z"]
    mask_camera: Bool[Tensor, "X Y Z"]
    mask_lidar: Bool[Tensor, "X Y Z"]
    num_classes: int = NUM_CLASSES

    def __post_init__(self) -> None:
        _check_num_classes(self.num_classes)
        expected = {"semantics": torch.uint8, "mask_camera": torch.bool, "mask_lidar": torch.bool}
        for name, dtype in expected.items():
            value = getattr(self, name)
            if not isinstance(value, Tensor):
                raise TypeError(f"{name}: expected a torch.Tensor, got {type(value).__name__}")
            if value.dtype != dtype:
                raise TypeError(
                    f"{name}: expected dtype {dtype}, got {value.dtype}; "
                    "Occ3DLabels.from_arrays converts other integer dtypes and 0/1 masks"
                )
            if value.ndim != 3:
                raise ValueError(f"{name}: expected shape (X, Y, Z), got {tuple(value.shape)}")
        shape, device = self.semantics.shape, self.semantics.device
        for name in ("mask_camera", "mask_lidar"):
            value = getattr(self, name)
            if value.shape != shape:
                raise ValueError(
                    f"{name}: shape {tuple(value.shape)} differs from semantics' {tuple(shape)}"
                )
            if value.device != device:
                raise ValueError(
                    f"{name}: on device {value.device} but semantics is on {device}; "
                    "all fields must be on one device"
                )
        if self.num_classes < 256 and self.semantics.numel():
            high = int(self.semantics.max())
            if high >= self.num_classes:
                raise ValueError(
                    f"semantics: holds label {high}; expected labels in "
                    f"0..{self.num_classes - 1} (num_classes={self.num_classes})"
                )

    @classmethod
    @typechecked
    def from_arrays(
        cls,
        semantics: np.ndarray | Tensor,
        mask_camera: np.ndarray | Tensor,
        mask_lidar: np.ndarray | Tensor,
        *,
        num_classes: int = NUM_CLASSES,
    ) -> Occ3DLabels:
        """Build from ``(X, Y, Z)`` numpy arrays or tensors, converting dtypes with checks.

        ``semantics`` may have any integer dtype (uint8, int8, int16, int32, int64, ...;
        the result does not depend on it) with values in ``0..num_classes-1``; it becomes
        ``torch.uint8``. Masks may be bool or any integer dtype holding only 0 and 1; they
        become ``torch.bool``. Tensors keep their device; numpy arrays become CPU tensors
        (copied only when needed).

        Raises:
            TypeError: bool or floating ``semantics``, floating masks (naming the argument).
            ValueError: a wrong shape or value (a label outside ``0..num_classes-1``, such
                as -1 or 255, named with the range found; a mask value other than 0/1).
        """
        _check_num_classes(num_classes)
        return _labels_from_arrays(
            {"semantics": semantics, "mask_camera": mask_camera, "mask_lidar": mask_lidar},
            prefix="",
            expected_shape=None,
            num_classes=num_classes,
            dtype_error=TypeError,
        )

    @property
    def shape(self) -> Shape3:
        """The grid shape ``(X, Y, Z)``."""
        return tuple(self.semantics.shape)  # type: ignore[return-value]

    @property
    def device(self) -> torch.device:
        return self.semantics.device

    def to(self, device: torch.device | str) -> Occ3DLabels:
        """A copy with every tensor on ``device`` (dtypes are fixed: uint8 and bool)."""
        return dataclasses.replace(
            self,
            semantics=self.semantics.to(device),
            mask_camera=self.mask_camera.to(device),
            mask_lidar=self.mask_lidar.to(device),
        )

    def __repr__(self) -> str:
        return (
            f"Occ3DLabels(shape={self.shape}, num_classes={self.num_classes}, device={self.device})"
        )


def _check_num_classes(num_classes: int) -> None:
    check_int("num_classes", num_classes, 1)
    if num_classes > 256:
        raise ValueError(
            f"num_classes: labels are stored as uint8, so at most 256, got {num_classes}"
        )


def _check_expected_shape(expected_shape: Shape3 | None) -> None:
    if expected_shape is not None and (
        len(expected_shape) != 3 or any(isinstance(n, bool) or n < 1 for n in expected_shape)
    ):
        raise ValueError(f"expected_shape: expected None or 3 ints >= 1, got {expected_shape!r}")


def _value_range(value: np.ndarray | Tensor) -> tuple[int, int]:
    """``(min, max)`` of a non-empty integer array or tensor."""
    if isinstance(value, np.ndarray):
        return int(value.min()), int(value.max())
    if value.dtype in _TORCH_WIDE_UNSIGNED:
        value = value.to(torch.int64)  # uint64 above 2^63 wraps negative: still rejected
    low, high = torch.aminmax(value)
    return int(low), int(high)


def _dtype_kind(value: np.ndarray | Tensor) -> str:
    """numpy's dtype kind: ``b`` bool, ``i``/``u`` integers, ``f``/``c`` floating, ..."""
    if isinstance(value, np.ndarray):
        return value.dtype.kind
    if value.dtype == torch.bool:
        return "b"
    if value.is_floating_point():
        return "f"
    if value.is_complex():
        return "c"
    return "u" if value.dtype in (torch.uint8, *_TORCH_WIDE_UNSIGNED) else "i"


def _to_tensor(value: np.ndarray | Tensor) -> Tensor:
    if isinstance(value, Tensor):
        return value
    if not value.dtype.isnative:
        value = value.astype(value.dtype.newbyteorder("="))
    if not value.flags.writeable:
        value = value.copy()
    return torch.from_numpy(value)


def _check_kind(
    prefix: str,
    name: str,
    kind: str,
    dtype: object,
    shape: Sequence[int],
    dtype_error: type[Exception],
) -> None:
    """The dtype kind (numpy's ``kind``) and rank of array ``name``."""
    if name == "semantics" and kind not in "iu":
        raise dtype_error(f"{prefix}semantics: expected integer labels, got dtype {dtype}")
    if name != "semantics" and kind not in "biu":
        raise dtype_error(
            f"{prefix}{name}: expected a bool mask or integers 0/1, got dtype {dtype}"
        )
    if len(shape) != 3:
        raise ValueError(f"{prefix}{name}: expected shape (X, Y, Z), got {tuple(shape)}")


def _check_grid(
    prefix: str,
    name: str,
    shape: tuple[int, ...],
    expected_shape: Shape3 | None,
    semantics_shape: tuple[int, ...],
) -> None:
    """Semantics' shape against ``expected_shape``, a mask's against semantics'."""
    if name == "semantics":
        if expected_shape is not None and shape != tuple(expected_shape):
            raise ValueError(
                f"{prefix}semantics: shape {shape} differs from expected_shape "
                f"{tuple(expected_shape)} (pass expected_shape=None to accept any grid)"
            )
    elif shape != semantics_shape:
        raise ValueError(f"{prefix}{name}: shape {shape} differs from semantics' {semantics_shape}")


def _labels_from_arrays(
    arrays: Mapping[str, np.ndarray | Tensor],
    *,
    prefix: str,
    expected_shape: Shape3 | None,
    num_classes: int,
    dtype_error: type[Exception] = ValueError,
) -> Occ3DLabels:
    """Validate and convert the three arrays; errors start with ``prefix`` + the array name.

    A wrong dtype raises ``dtype_error``: ``TypeError`` for arrays passed in, ``ValueError``
    for the arrays of a file (malformed data).
    """
    for name, value in arrays.items():
        if not isinstance(value, np.ndarray | Tensor):
            raise TypeError(
                f"{prefix}{name}: expected a numpy array or torch.Tensor, got "
                f"{type(value).__name__}"
            )
        _check_kind(prefix, name, _dtype_kind(value), value.dtype, value.shape, dtype_error)
    shape = tuple(arrays["semantics"].shape)
    for name in ("semantics", "mask_camera", "mask_lidar"):
        _check_grid(prefix, name, tuple(arrays[name].shape), expected_shape, shape)

    semantics = arrays["semantics"]
    if semantics.size if isinstance(semantics, np.ndarray) else semantics.numel():
        low, high = _value_range(semantics)
        if low < 0 or high >= num_classes:
            raise ValueError(
                f"{prefix}semantics: labels range over {low}..{high}; expected labels in "
                f"0..{num_classes - 1} (num_classes={num_classes})"
            )
    semantics = _to_tensor(semantics).to(torch.uint8)

    masks = {}
    for name in ("mask_camera", "mask_lidar"):
        mask = arrays[name]
        if _dtype_kind(mask) != "b":
            if mask.size if isinstance(mask, np.ndarray) else mask.numel():
                low, high = _value_range(mask)
                if low < 0 or high > 1:
                    raise ValueError(
                        f"{prefix}{name}: holds values other than 0/1 (range {low}..{high}); "
                        "expected a bool mask or integers 0/1"
                    )
            mask = mask != 0
        masks[name] = _to_tensor(mask)
    return Occ3DLabels(semantics, masks["mask_camera"], masks["mask_lidar"], num_classes)


# ----------------------------------------------------------------------------------------
# Files
# ----------------------------------------------------------------------------------------


def _read_npz_arrays(
    path: Path, keys: Sequence[str], expected_shape: Shape3 | None
) -> dict[str, np.ndarray]:
    """The arrays ``keys`` (semantics first), each refused from its ``.npy`` header (dtype,
    rank, shape against ``expected_shape`` and semantics') before it is inflated."""
    shapes: dict[str, tuple[int, ...]] = {}

    def check_header(key: str, shape: tuple[int, ...], dtype: np.dtype) -> None:
        _check_kind("", key, dtype.kind, dtype, shape, ValueError)
        _check_grid("", key, shape, expected_shape, shapes.setdefault("semantics", shape))
        shapes[key] = shape

    return read_npz(
        path,
        keys,
        holds=f"an Occ3D labels file with arrays {list(keys)}",
        check_header=check_header,
    )


@typechecked
def load_occ3d_labels(
    path: PathLike,
    *,
    expected_shape: Shape3 | None = OCC3D_SHAPE,
    num_classes: int = NUM_CLASSES,
) -> Occ3DLabels:
    """Read an Occ3D ``labels.npz`` (``semantics``, ``mask_camera``, ``mask_lidar``).

    Args:
        path: the ``.npz`` file, e.g. ``root/gts/<scene>/<token>/labels.npz``.
        expected_shape: the required ``(X, Y, Z)``, ``(200, 200, 16)`` by default;
            ``None`` accepts any 3D grid (the three arrays must still agree).
        num_classes: labels must lie in ``0..num_classes-1`` (18 by default).

    Returns:
        :class:`Occ3DLabels` on the CPU: semantics ``(X, Y, Z)`` uint8, masks bool.

    Accepts semantics of any integer dtype within range (converted to uint8) and masks
    stored as bool or as integers holding only 0/1 (the real files use uint8). Extra
    arrays in the archive are ignored. Never unpickles (``allow_pickle=False``).

    The dtypes and shapes are checked on the arrays' ``.npy`` headers, before anything is
    inflated: a small file declaring a huge array (a zip bomb) is refused without reading
    it (see :func:`dego._npz.read_npz` for the checks of the archive itself).

    Raises:
        FileNotFoundError: ``path`` does not exist or is not a regular file (a directory,
            a FIFO, a socket or a device: refused without blocking).
        ValueError: the file is not a readable ``.npz`` (truncated, garbage, pickle,
            sizes the archive cannot hold), an array is missing or unreadable, or an
            array has a wrong dtype (float semantics, float masks), shape or value
            (labels out of range, masks with values other than 0/1); the message names
            the file and the array.
    """
    _check_expected_shape(expected_shape)
    _check_num_classes(num_classes)
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such Occ3D labels file")
    arrays = _read_npz_arrays(path, _KEYS, expected_shape)
    return _labels_from_arrays(
        arrays, prefix=f"{path}: ", expected_shape=expected_shape, num_classes=num_classes
    )


@typechecked
def save_occ3d_labels(path: PathLike, labels: Occ3DLabels, *, compressed: bool = True) -> Path:
    """Write ``labels`` in the layout of the real Occ3D-nuScenes files; returns the path.

    The archive holds ``semantics`` (uint8), ``mask_lidar`` and ``mask_camera`` (uint8
    0/1), each ``(X, Y, Z)``, written with ``numpy.savez_compressed`` (or ``numpy.savez``
    when ``compressed=False``) to exactly ``path`` (no ``.npz`` is appended). Parent
    directories are created; the file is written to a temporary name in the same
    directory and moved into place with ``os.replace``, so readers never see a partial
    file and an existing file is replaced atomically. Tensors on any device are copied
    to the CPU first.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"path: {path} is a directory; expected a file name")
    arrays = {
        "semantics": np.ascontiguousarray(labels.semantics.cpu().numpy()),
        "mask_lidar": np.ascontiguousarray(labels.mask_lidar.cpu().numpy().astype(np.uint8)),
        "mask_camera": np.ascontiguousarray(labels.mask_camera.cpu().numpy().astype(np.uint8)),
    }
    write_npz(path, arrays, compressed=compressed)
    return path


# ----------------------------------------------------------------------------------------
# Dataset
# ----------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Occ3DSample:
    """One item of :class:`Occ3DDataset`: the sample's scene name, token and labels."""

    scene_name: str
    token: str
    labels: Occ3DLabels


def _path_component(where: str, field: str, value: object) -> str:
    if not isinstance(value, str):
        raise TypeError(f"{where}: {field} must be a str, got {type(value).__name__}")
    if value in ("", ".", "..") or "/" in value or "\\" in value or "\0" in value:
        raise ValueError(
            f"{where}: {field} {value!r} is not a single directory name "
            "(empty, '.', '..' or containing a path separator)"
        )
    return value


def _parse_info(index: int, info: object) -> tuple[str, str]:
    where = f"infos[{index}]"
    if isinstance(info, Mapping):
        missing = [key for key in ("scene_name", "token") if key not in info]
        if missing:
            raise ValueError(
                f"{where}: missing key(s) {missing}; an info dict needs 'scene_name' and 'token'"
            )
        scene, token = info["scene_name"], info["token"]
    elif isinstance(info, Sequence) and not isinstance(info, str | bytes) and len(info) == 2:
        scene, token = info
    else:
        raise TypeError(
            f"{where}: expected a mapping with 'scene_name' and 'token' or a "
            f"(scene_name, token) pair, got {type(info).__name__}"
        )
    return _path_component(where, "scene_name", scene), _path_component(where, "token", token)


def _check_root(root: PathLike) -> Path:
    if not isinstance(root, str | os.PathLike):
        raise TypeError(f"root: expected a str or os.PathLike, got {type(root).__name__}")
    path = Path(root)
    if not path.is_dir():
        raise FileNotFoundError(f"root: {path} is not an existing directory")
    if not (path / "gts").is_dir():
        raise FileNotFoundError(
            f"root: no 'gts' directory in {path}; expected the Occ3D-nuScenes layout "
            f"root/gts/<scene_name>/<token>/{LABELS_FILENAME}"
        )
    return path


class Occ3DDataset(Dataset[Occ3DSample]):
    """The Occ3D-nuScenes ground truth of chosen samples in a local copy of the data set.

    Expects the layout of the Occ3D-nuScenes release::

        root/gts/<scene_name>/<token>/labels.npz

    Args:
        root: the directory that holds ``gts`` (e.g. ``data/occ3d-nus``).
        infos: the samples, in order: mappings with keys ``scene_name`` and ``token``
            (such as the entries of a nuScenes info file, which you load yourself; the
            library never unpickles anything) or ``(scene_name, token)`` pairs. Both are
            used as single directory names (no path separators, not ``..``).
        expected_shape: grid shape every file must have, ``(200, 200, 16)`` by default;
            ``None`` accepts any.
        num_classes: labels must lie in ``0..num_classes-1`` (18 by default).

    ``dataset[i]`` reads sample ``i`` (negative indices count from the end) and returns
    an :class:`Occ3DSample`; iterating reads the samples in order; ``dataset.samples``
    lists the ``(scene_name, token)`` pairs and ``dataset.path(i)`` gives sample ``i``'s
    file. Files are read lazily: a missing one raises ``FileNotFoundError`` naming the
    expected path when it is accessed, and a malformed one ``ValueError`` naming the file
    (see :func:`load_occ3d_labels`). It is a map-style ``torch.utils.data.Dataset``; with
    a ``DataLoader`` use ``batch_size=None`` (samples pass through unchanged) or a
    ``collate_fn`` of your own.

    Example::

        dataset = Occ3DDataset("data/occ3d-nus", infos)  # or Occ3DDataset.from_directory(root)
        metrics = OccupancyMetrics(protocol="occ3d")
        for sample in dataset:
            pred = my_model_labels(sample.scene_name, sample.token)  # (200, 200, 16)
            metrics.update(pred, sample.labels.semantics, sample.labels.mask_camera)
        print(metrics.compute())
    """

    @typechecked
    def __init__(
        self,
        root: PathLike,
        infos: Sequence[Mapping[str, Any] | Sequence[str]],
        *,
        expected_shape: Shape3 | None = OCC3D_SHAPE,
        num_classes: int = NUM_CLASSES,
    ) -> None:
        self.root = _check_root(root)
        if isinstance(infos, str | bytes | Mapping) or not isinstance(infos, Sequence):
            raise TypeError(
                "infos: expected a sequence of info mappings or (scene_name, token) pairs, "
                f"got {type(infos).__name__}"
            )
        _check_expected_shape(expected_shape)
        _check_num_classes(num_classes)
        self.samples: tuple[tuple[str, str], ...] = tuple(
            _parse_info(i, info) for i, info in enumerate(infos)
        )
        self.expected_shape: Shape3 | None = None
        if expected_shape is not None:
            x, y, z = expected_shape
            self.expected_shape = (x, y, z)
        self.num_classes = num_classes

    @classmethod
    @typechecked
    def from_directory(
        cls,
        root: PathLike,
        *,
        expected_shape: Shape3 | None = OCC3D_SHAPE,
        num_classes: int = NUM_CLASSES,
    ) -> Occ3DDataset:
        """Every ``root/gts/<scene_name>/<token>/labels.npz`` present, sorted by (scene, token).

        Raises ``FileNotFoundError`` if ``root`` or ``root/gts`` is missing or no labels
        file is found (an evaluation over zero samples is never what was meant).
        """
        root_path = _check_root(root)
        found = sorted(
            (path.parent.parent.name, path.parent.name)
            for path in (root_path / "gts").glob(f"*/*/{LABELS_FILENAME}")
            if path.is_file()
        )
        if not found:
            raise FileNotFoundError(
                f"root: no files matching gts/*/*/{LABELS_FILENAME} under {root_path}"
            )
        return cls(root_path, found, expected_shape=expected_shape, num_classes=num_classes)

    def __len__(self) -> int:
        return len(self.samples)

    def _index(self, index: int) -> int:
        n = len(self.samples)
        if not -n <= index < n:
            raise IndexError(f"index: {index} out of range for {n} samples")
        return index % n

    @typechecked
    def path(self, index: int) -> Path:
        """The labels file of sample ``index``: ``root/gts/<scene_name>/<token>/labels.npz``."""
        scene, token = self.samples[self._index(index)]
        return self.root / "gts" / scene / token / LABELS_FILENAME

    @typechecked
    def __getitem__(self, index: int) -> Occ3DSample:
        i = self._index(index)
        scene, token = self.samples[i]
        path = self.path(i)
        if not path.is_file():
            raise FileNotFoundError(
                f"sample {i} (scene_name {scene!r}, token {token!r}): missing labels file {path}"
            )
        labels = load_occ3d_labels(
            path, expected_shape=self.expected_shape, num_classes=self.num_classes
        )
        return Occ3DSample(scene, token, labels)

    def __iter__(self) -> Iterator[Occ3DSample]:
        for i in range(len(self.samples)):
            yield self[i]

    def __repr__(self) -> str:
        return f"Occ3DDataset(root={str(self.root)!r}, samples={len(self.samples)})"


__all__ = [
    "LABELS_FILENAME",
    "OCC3D_SHAPE",
    "Occ3DDataset",
    "Occ3DLabels",
    "Occ3DSample",
    "load_occ3d_labels",
    "save_occ3d_labels",
]
