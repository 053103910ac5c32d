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
from typing import Any

import numpy as np
import torch
from torch import Tensor

from dego._npz import npy_header, read_npz
from dego._policy import check_memory
from dego._typing import typechecked
from dego.classes import NUM_CLASSES
from dego.data.occ3d import LABELS_FILENAME, OCC3D_SHAPE
from dego.evaluation.errors import EvaluationSetupError

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
    """The file of :func:`prediction_candidates` that exists, or ``None``.

    Raises :class:`EvaluationSetupError` naming both when two of them exist (e.g.
    ``<token>.npz`` beside ``<token>.npy``): only one would be read, and which one is the
    sample's prediction is the user's to say."""
    found = [p for p in prediction_candidates(Path(pred_root), scene, token) if p.is_file()]
    if len(found) > 1:
        raise EvaluationSetupError(
            f"--pred: sample {token!r} has {len(found)} prediction files, "
            f"{' and '.join(str(p) for p in found)}; keep one (only one would be read)"
        )
    return found[0] if found else None


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
    shape, dtype = npy_header(path, "a prediction array")
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


# ----------------------------------------------------------------------------------------
# Predictions of any benchmark
# ----------------------------------------------------------------------------------------

FLOW_KEY = "flow"
LOGITS_CHUNK = 4  # channels upsampled at a time: bounds memory on 512 x 512 x 40 grids


def _benchmark_keys(path: Path, keys: list[str], layout_key: str | None) -> str:
    if layout_key is not None and layout_key in keys:  # the GT's own layout (Waymo)
        return layout_key
    return _choose_key(path, [k for k in keys if k != FLOW_KEY])


def upsample_logits(logits: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """``(C, x, y, z)`` logits upsampled to ``shape`` with trilinear interpolation
    (``align_corners=False``) and reduced to labels by argmax (first maximum on ties), as
    OpenOccupancy's ``evaluation_semantic`` does; a few channels at a time, keeping the
    running maximum, so memory stays near two float grids whatever C is."""
    best = torch.full(shape, -torch.inf, dtype=logits.dtype)
    labels = torch.zeros(shape, dtype=torch.int64)
    for first in range(0, logits.shape[0], LOGITS_CHUNK):
        part = torch.nn.functional.interpolate(
            logits[None, first : first + LOGITS_CHUNK],
            size=shape,
            mode="trilinear",
            align_corners=False,
        )[0]
        for offset, channel in enumerate(part):
            better = channel > best
            best = torch.where(better, channel, best)
            labels = torch.where(better, first + offset, labels)
    return labels


@typechecked
def read_prediction(path: PathLike, benchmark: Any) -> tuple[Tensor, Tensor | None]:
    """One prediction of ``benchmark`` (:class:`~dego.evaluation.benchmarks.Benchmark`):
    ``(X, Y, Z)`` int64 labels in its label space (a stored free remapped) and the
    ``(X, Y, Z, 2)`` float32 flow when the file has one (array ``flow``).

    Accepted: an ``.npz`` holding one of :data:`PREDICTION_KEYS` (or the GT layout's own
    array) and optionally ``flow``; an ``.npy`` label grid; for benchmarks with sparse
    ground truth, an ``.npy`` of rows in the GT's layout; for benchmarks that upsample
    (OpenOccupancy), floating ``(C, x, y, z)`` logits.

    Raises:
        FileNotFoundError: no such file.
        ValueError: a wrong shape (naming the benchmark and its grid), labels outside the
            benchmark's range (e.g. Occ3D ids scored as OpenOcc v2), a corrupt file.
    """
    from dego.evaluation.layouts import SparseRows, _labels, densify_rows, layout_of
    from dego.evaluation.layouts import _read_npy as read_any_npy

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such prediction file")
    layout = layout_of(benchmark)
    flow = None
    if path.suffix == ".npy":
        shape, dtype = npy_header(path, f"a {benchmark.name} prediction")
        sparse = len(shape) == 2 and isinstance(layout, SparseRows)
        logits = benchmark.logits and dtype.kind == "f" and len(shape) == 4
        if not sparse and not logits:
            _check_shape(str(path), tuple(shape), benchmark)
        array = read_any_npy(path, f"a {benchmark.name} prediction")
        where = str(path)
        if isinstance(layout, SparseRows) and sparse:
            return densify_rows(where, array, benchmark, layout.order, layout.vote), None
        if logits:
            if array.shape[0] != benchmark.num_classes:
                raise ValueError(
                    f"{where}: logits with {array.shape[0]} channels; {benchmark.name} has "
                    f"{benchmark.num_classes} classes"
                )
            return upsample_logits(torch.from_numpy(array), benchmark.shape), None
    else:
        keys = _npz_keys(path)
        layout_key = getattr(layout, "keys", (None,))[0]
        key = _benchmark_keys(path, keys, layout_key)

        def check_header(name: str, got: tuple[int, ...], dtype: np.dtype) -> None:
            want = benchmark.shape if name == key else (*benchmark.shape, 2)
            if name == key and dtype.kind not in "iu":
                raise ValueError(f"array {name!r}: expected integer labels, got dtype {dtype}")
            if tuple(got) != tuple(want):
                raise ValueError(_shape_text(f"array {name!r}", tuple(got), benchmark, want))

        wanted = [key, FLOW_KEY] if FLOW_KEY in keys else [key]
        arrays = read_npz(path, wanted, holds="a prediction archive", check_header=check_header)
        array, where = arrays[key], f"{path}: array {key!r}"
        if FLOW_KEY in arrays:
            if arrays[FLOW_KEY].dtype.kind != "f":
                raise ValueError(f"{path}: array 'flow' must be floating")
            flow = torch.from_numpy(arrays[FLOW_KEY].astype(np.float32))
    if array.dtype.kind not in "iu":
        raise ValueError(f"{where}: expected integer labels, got dtype {array.dtype}")
    try:
        labels = _labels(where, array, benchmark, allow_ignore=False)
    except ValueError as exc:
        if benchmark.name == "openocc-v2" and array.size and int(array.max()) == 17:
            raise ValueError(
                f"{exc}; Occ3D-nuScenes labels (17 = free) convert with "
                "dego.evaluation.occ3d_to_openocc"
            ) from None
        raise
    return labels, flow


def _shape_text(where: str, got: tuple[int, ...], benchmark: Any, want: tuple[int, ...]) -> str:
    return (
        f"{where}: shape {got}; the {benchmark.name} grid is {tuple(want)}, so a prediction "
        f"must be {tuple(want)} ({benchmark.prediction})"
    )


def _check_shape(where: str, shape: tuple[int, ...], benchmark: Any) -> None:
    if tuple(shape) != tuple(benchmark.shape):
        raise ValueError(_shape_text(where, tuple(shape), benchmark, benchmark.shape))


__all__ = [
    "PREDICTION_KEYS",
    "find_prediction",
    "load_prediction",
    "prediction_candidates",
    "read_prediction",
    "upsample_logits",
]
