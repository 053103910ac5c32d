"""Reading one prediction file: ``<token>.npz`` (key ``pred``, ``arr_0`` or ``semantics``),
``<token>.npy``, or the GT's own layout ``<scene>/<token>/labels.npz``.

Everything is read without unpickling (:func:`dego._npz.read_npz`, ``numpy.load(...,
allow_pickle=False)``) and the sizes a file declares go through the memory guard before
anything is allocated.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from dego._npz import read_npz
from dego._policy import check_memory
from dego._typing import typechecked
from dego.classes import NUM_CLASSES
from dego.data.occ3d import LABELS_FILENAME, OCC3D_SHAPE

PREDICTION_KEYS = ("pred", "arr_0", "semantics")
"""The arrays a flat ``<token>.npz`` may hold its labels under: ``pred`` (SparseOcc),
``arr_0`` (DeGO / GaussianFlowOcc's ``np.savez(path, pred)``) or ``semantics``."""

PathLike = str | os.PathLike[str]


def prediction_candidates(pred_root: Path, scene: str, token: str) -> tuple[Path, ...]:
    """Where the prediction of one sample may be, in the order they are tried."""
    return (
        pred_root / f"{token}.npz",
        pred_root / f"{token}.npy",
        pred_root / scene / token / LABELS_FILENAME,
        pred_root / "gts" / scene / token / LABELS_FILENAME,
    )


@typechecked
def find_prediction(pred_root: PathLike, scene: str, token: str) -> Path | None:
    """The first existing file of :func:`prediction_candidates`, or ``None``."""
    for path in prediction_candidates(Path(pred_root), scene, token):
        if path.is_file():
            return path
    return None


def _npz_keys(path: Path) -> list[str]:
    read_npz(path, [], holds="a prediction archive")  # validates the members, reads nothing
    with zipfile.ZipFile(path) as archive:
        return [name[: -len(".npy")] for name in archive.namelist()]


def _choose_key(path: Path, keys: list[str]) -> str:
    if "mask_camera" in keys and "semantics" in keys:  # the GT layout
        return "semantics"
    known = [k for k in PREDICTION_KEYS if k in keys]
    if len(known) > 1:
        raise ValueError(
            f"{path}: ambiguous prediction archive, it holds several of the accepted arrays "
            f"{known}; keep one of {list(PREDICTION_KEYS)}"
        )
    if not known:
        raise ValueError(
            f"{path}: no prediction array; found {sorted(keys)}, expected one of "
            f"{list(PREDICTION_KEYS)}"
        )
    return known[0]


def _check_declared(
    where: str,
    shape: tuple[int, ...],
    dtype: np.dtype,
    expected_shape: tuple[int, int, int] | None,
) -> None:
    """A prediction's dtype and shape, from its header, before anything is inflated."""
    if dtype.kind not in "iu":
        raise ValueError(f"{where}: expected integer labels, got dtype {dtype}")
    if expected_shape is not None and tuple(shape) != tuple(expected_shape):
        raise ValueError(
            f"{where}: shape {tuple(shape)}, expected {tuple(expected_shape)} "
            "(the ground truth's grid)"
        )


def _read_npy(path: Path, expected_shape: tuple[int, int, int] | None) -> np.ndarray:
    with path.open("rb") as file:
        try:
            version = np.lib.format.read_magic(file)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(file)
            else:
                shape, _, dtype = np.lib.format.read_array_header_2_0(file)
        except Exception as exc:  # bad magic, garbage header
            raise ValueError(f"{path}: not a readable .npy array ({exc})") from exc
    if dtype.hasobject:
        raise ValueError(f"{path}: holds an object array ({dtype}); refused (allow_pickle=False)")
    _check_declared(str(path), shape, dtype, expected_shape)
    check_memory(str(path), int(np.prod(shape)) * dtype.itemsize, f"shape {shape}, {dtype}")
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:  # truncated data
        raise ValueError(f"{path}: not a readable .npy array ({exc})") from exc


@typechecked
def load_prediction(
    path: PathLike,
    *,
    expected_shape: tuple[int, int, int] | None = OCC3D_SHAPE,
    num_classes: int = NUM_CLASSES,
) -> Tensor:
    """The ``(X, Y, Z)`` uint8 labels of one prediction file (``.npz`` or ``.npy``).

    An ``.npz`` in the GT layout (with ``mask_camera``) gives its ``semantics``; any other
    must hold exactly one of :data:`PREDICTION_KEYS` (several: ambiguous, an error). Labels
    may have any integer dtype with values in ``0..num_classes-1`` (17 = free).

    Raises:
        FileNotFoundError: no such file.
        ValueError: a corrupt or ambiguous file, a floating or bool array, a wrong shape or
            a label out of range; the message names the file and the array.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such prediction file")
    # dtype and shape are checked on the headers, before anything is inflated
    if path.suffix == ".npy":
        array, where = _read_npy(path, expected_shape), f"{path}"
    else:
        key = _choose_key(path, _npz_keys(path))

        def check_header(name: str, shape: tuple[int, ...], dtype: np.dtype) -> None:
            _check_declared(f"array {name!r}", shape, dtype, expected_shape)

        array = read_npz(path, [key], holds="a prediction archive", check_header=check_header)[key]
        where = f"{path}: array {key!r}"
    if array.size:
        low, high = int(array.min()), int(array.max())
        if low < 0 or high >= num_classes:
            raise ValueError(
                f"{where}: labels range over {low}..{high}; expected 0..{num_classes - 1}"
            )
    return torch.from_numpy(np.ascontiguousarray(array).astype(np.uint8, copy=False))


__all__ = ["PREDICTION_KEYS", "find_prediction", "load_prediction", "prediction_candidates"]
