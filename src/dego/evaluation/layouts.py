"""Ground-truth layouts: where each benchmark keeps one sample's labels, how to read them
into a dense grid of the benchmark's label space, and how to write them (the fixtures of
:func:`dego.data.write_benchmark_tree` go through the same class, so every reader is
tested on files its writer made).

A layout finds the samples of a tree as ``(scene, token, path)``; a token met twice is a
setup error (distributed runs shard by token). Reading checks the keys, the dtype, the
shape and every label before anything is scored; an error names the file, the benchmark
and what was expected.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Float, Integer
from torch import Tensor

from dego._npz import npy_header, read_npz, write_npz
from dego._policy import check_memory
from dego._typing import check_tensor_fields
from dego.data.occ3d import LABELS_FILENAME, Occ3DLabels, load_occ3d_labels, save_occ3d_labels
from dego.evaluation.benchmarks import Benchmark
from dego.evaluation.errors import EvaluationSetupError


@dataclasses.dataclass(frozen=True)
class GroundTruth:
    """One sample's ground truth on the benchmark's grid.

    Attributes:
        semantics: ``(X, Y, Z)`` integer labels in ``0..C-1`` (a stored free remapped to
            the free label) or the benchmark's ignore label: uint8 as Occ3D ships them,
            int64 where a reader remaps or densifies.
        masks: bool ``(X, Y, Z)`` masks by their name in the files.
        flow: ``(X, Y, Z, 2)`` float32 flow (OpenOcc v2), or ``None``.
    """

    semantics: Integer[Tensor, "X Y Z"]
    masks: Mapping[str, Tensor]
    flow: Float[Tensor, "X Y Z 2"] | None = None

    def __post_init__(self) -> None:
        check_tensor_fields(self)
        for name, mask in self.masks.items():
            if mask.dtype != torch.bool or mask.shape != self.semantics.shape:
                raise ValueError(
                    f"masks: {name!r} must be a bool {tuple(self.semantics.shape)} mask, got "
                    f"{mask.dtype} {tuple(mask.shape)}"
                )


@dataclasses.dataclass(frozen=True)
class Entry:
    scene: str
    token: str
    path: Path


def _folders(folder: Path) -> list[Path]:
    try:
        with os.scandir(folder) as entries:
            names = sorted(entry.name for entry in entries)
    except OSError as exc:
        raise EvaluationSetupError(
            f"--gt: {folder}: cannot be read ({exc.strerror or exc}); fix its permissions or "
            "remove it from the tree"
        ) from None
    return [folder / name for name in names]


def _regular(path: Path, expected: str = "a ground-truth file") -> bool:
    """Whether ``path`` is a regular file; a dangling link or a special file is an error."""
    try:
        regular = path.is_file()
        present = regular or os.path.lexists(path)
    except OSError as exc:
        raise EvaluationSetupError(
            f"--gt: {path}: cannot be read ({exc.strerror or exc})"
        ) from None
    if present and not regular:
        what = "a dangling link" if not path.exists() else "not a regular file"
        raise EvaluationSetupError(f"--gt: {path}: {what}; expected {expected}")
    return regular


def check_unique(entries: list[Entry], root: Path) -> list[Entry]:
    """``entries`` sorted by token; a token met twice is an :class:`EvaluationSetupError`
    (workers and ranks shard by token: a duplicate would be counted twice)."""
    seen: dict[str, Path] = {}
    for entry in entries:
        if entry.token in seen:
            raise EvaluationSetupError(
                f"--gt: token {entry.token!r} appears twice under {root}: {seen[entry.token]} "
                f"and {entry.path}; every sample must have one ground-truth file"
            )
        seen[entry.token] = entry.path
    return sorted(entries, key=lambda e: (e.scene, e.token))


def _labels(
    where: str, array: np.ndarray, benchmark: Benchmark, *, allow_ignore: bool = True
) -> Tensor:
    """``array`` as int64 labels of the benchmark (stored free remapped), refusing any
    other value with a message naming the file and the benchmark."""
    if array.dtype.kind not in "iu":
        raise ValueError(
            f"{where}: labels of dtype {array.dtype}; {benchmark.name} expects integer labels "
            f"{benchmark.label_range()}"
        )
    labels = torch.from_numpy(np.ascontiguousarray(array).astype(np.int64, copy=False))
    c = benchmark.num_classes
    allowed = (labels >= 0) & (labels < c)
    if benchmark.stored_free is not None:
        stored = labels == benchmark.stored_free
        labels = torch.where(stored, benchmark.free_label, labels)
        allowed |= stored
    if allow_ignore and benchmark.ignore_label is not None:
        allowed |= labels == benchmark.ignore_label
    if not bool(allowed.all()):
        bad = sorted({int(v) for v in labels[~allowed].unique()[:5]})
        ignore = (
            f", or {benchmark.ignore_label} (ignored)"
            if allow_ignore and benchmark.ignore_label is not None
            else ""
        )
        raise ValueError(
            f"{where}: label(s) {bad} are not {benchmark.name} labels; expected "
            f"{benchmark.label_range()}{ignore}: is this a file of another benchmark?"
        )
    return labels


def _shape_error(where: str, shape: tuple[int, ...], benchmark: Benchmark, what: str) -> str:
    return (
        f"{where}: shape {tuple(shape)}; {benchmark.name} {what} {tuple(benchmark.shape)} "
        "(is this a file of another benchmark?)"
    )


def _mask(where: str, name: str, array: np.ndarray, shape: tuple[int, ...]) -> Tensor:
    if array.dtype != np.bool_ and (
        array.dtype.kind not in "iu" or (array.size and int(array.max()) > 1)
    ):
        raise ValueError(f"{where}: array {name!r} must be a 0/1 or bool mask, got {array.dtype}")
    if array.shape != shape:
        raise ValueError(f"{where}: array {name!r} has shape {array.shape}, expected {shape}")
    return torch.from_numpy(np.ascontiguousarray(array).astype(bool))


class Layout:
    """A ground-truth layout (subclasses: one per file layout)."""

    name = ""
    pattern = ""  # in words, for messages and docs

    def find(self, root: Path) -> list[Entry]:
        raise NotImplementedError

    def read(self, path: Path, benchmark: Benchmark) -> GroundTruth:
        raise NotImplementedError

    def relative(self, scene: str, token: str) -> str:
        """The path of a sample's file under the root."""
        raise NotImplementedError

    def write(self, root: Path, scene: str, token: str, arrays: Mapping[str, np.ndarray]) -> Path:
        raise NotImplementedError

    def samples(self, root: Path, benchmark: Benchmark) -> tuple[Path, list[Entry]]:
        """The root the files are found under and the entries, unique by token."""
        if not root.is_dir():
            raise EvaluationSetupError(f"--gt: {root} is not an existing directory")
        base = self.base(root)
        entries = check_unique(self.find(base), base)
        if not entries:
            raise EvaluationSetupError(
                f"--gt: no {benchmark.name} ground truth under {root}: expected {self.pattern}"
            )
        return base, entries

    def base(self, root: Path) -> Path:
        return root


class NpzTree(Layout):
    """``<scene>/<token>/labels.npz`` (Occ3D-nuScenes, OpenOcc v2), under ``gts/`` or not."""

    name = "occ3d"
    pattern = (
        f"gts/<scene>/<token>/{LABELS_FILENAME} (the Occ3D release) or "
        f"<scene>/<token>/{LABELS_FILENAME}"
    )

    def base(self, root: Path) -> Path:
        return root / "gts" if (root / "gts").is_dir() else root

    def find(self, root: Path) -> list[Entry]:
        entries = []
        for scene in _folders(root):
            if not scene.is_dir():
                continue
            for token in _folders(scene):
                labels = token / LABELS_FILENAME
                if token.is_dir() and _regular(labels, "the sample's labels archive"):
                    entries.append(Entry(scene.name, token.name, token / LABELS_FILENAME))
        return entries

    def relative(self, scene: str, token: str) -> str:
        return f"{scene}/{token}/{LABELS_FILENAME}"

    def read(self, path: Path, benchmark: Benchmark) -> GroundTruth:
        labels = load_occ3d_labels(path, num_classes=benchmark.num_classes)
        return GroundTruth(
            labels.semantics,
            {"mask_camera": labels.mask_camera, "mask_lidar": labels.mask_lidar},
        )

    def write(self, root: Path, scene: str, token: str, arrays: Mapping[str, np.ndarray]) -> Path:
        path = root / "gts" / self.relative(scene, token)
        labels = Occ3DLabels(
            torch.from_numpy(arrays["semantics"]),
            torch.from_numpy(arrays["mask_camera"]),
            torch.from_numpy(arrays["mask_lidar"]),
        )
        return save_occ3d_labels(path, labels)


class OpenOccTree(NpzTree):
    """OpenOcc v2: ``<scene>/<token>/labels.npz`` with ``semantics`` and ``flow``
    ``(X, Y, Z, 2)`` (masks, when present, are not used by its metrics)."""

    name = "openocc"

    def read(self, path: Path, benchmark: Benchmark) -> GroundTruth:
        shape = benchmark.shape

        def check_header(key: str, got: tuple[int, ...], dtype: np.dtype) -> None:
            want = shape if key == "semantics" else (*shape, 2)
            if tuple(got) != want:
                raise ValueError(
                    f"array {key!r} has shape {tuple(got)}; {benchmark.name} expects {want}"
                )

        where = f"{path}"
        arrays = read_npz(
            path,
            ["semantics", "flow"],
            holds=f"a {benchmark.name} labels.npz with arrays 'semantics' and 'flow'",
            check_header=check_header,
        )
        flow = arrays["flow"]
        if flow.dtype.kind != "f":
            raise ValueError(f"{where}: array 'flow' must be floating, got {flow.dtype}")
        labels = _labels(f"{where}: array 'semantics'", arrays["semantics"], benchmark)
        return GroundTruth(labels, {}, torch.from_numpy(flow.astype(np.float32)))

    def write(self, root: Path, scene: str, token: str, arrays: Mapping[str, np.ndarray]) -> Path:
        path = root / "gts" / self.relative(scene, token)
        write_npz(path, dict(arrays), compressed=True)
        return path


class WaymoTree(Layout):
    """Occ3D-Waymo: ``<scene>/<frame>_04.npz`` under the split folder, arrays
    ``voxel_label``, ``origin_voxel_state`` (LiDAR mask), ``final_voxel_state`` (camera
    mask) and ``infov``; the token is ``<scene>_<frame>``."""

    name = "waymo"
    pattern = "<scene>/<frame>_04.npz (voxel_label, origin_voxel_state, final_voxel_state, infov)"
    suffix = "_04.npz"
    keys = ("voxel_label", "origin_voxel_state", "final_voxel_state", "infov")

    def find(self, root: Path) -> list[Entry]:
        entries = []
        for scene in _folders(root):
            if not scene.is_dir():
                continue
            for file in _folders(scene):
                if file.name.endswith(self.suffix) and _regular(file):
                    frame = file.name[: -len(self.suffix)]
                    entries.append(Entry(scene.name, f"{scene.name}_{frame}", file))
        return entries

    def relative(self, scene: str, token: str) -> str:
        return f"{scene}/{token[len(scene) + 1 :]}{self.suffix}"

    def read(self, path: Path, benchmark: Benchmark) -> GroundTruth:
        shape = benchmark.shape

        def check_header(key: str, got: tuple[int, ...], dtype: np.dtype) -> None:
            if tuple(got) != shape:
                raise ValueError(_shape_error(f"array {key!r}", got, benchmark, "expects"))

        arrays = read_npz(
            path,
            list(self.keys),
            holds=f"an {benchmark.name} frame with arrays {list(self.keys)}",
            check_header=check_header,
        )
        labels = _labels(f"{path}: array 'voxel_label'", arrays["voxel_label"], benchmark)
        masks = {k: _mask(str(path), k, arrays[k], shape) for k in self.keys[1:]}
        return GroundTruth(labels, masks)

    def write(self, root: Path, scene: str, token: str, arrays: Mapping[str, np.ndarray]) -> Path:
        path = root / self.relative(scene, token)
        write_npz(path, dict(arrays), compressed=True)
        return path


def _read_npy(path: Path, holds: str) -> np.ndarray:
    """A ``.npy`` read without unpickling, its declared size through the memory guard."""
    if not _regular(path):
        raise FileNotFoundError(f"{path}: no such file")
    shape, dtype = npy_header(path, holds)
    check_memory(str(path), int(np.prod(shape)) * dtype.itemsize, f"shape {shape}, {dtype}")
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:
        raise ValueError(f"{path}: not a readable .npy array ({exc})") from exc


def densify_rows(
    where: str, rows: np.ndarray, benchmark: Benchmark, order: str, vote: bool
) -> Tensor:
    """Sparse ``(N, >=4)`` rows (voxel indices in ``order``, the label last) as a dense
    ``(X, Y, Z)`` int64 grid filled with the free label. Label 0 (noise) becomes the
    benchmark's ignore label (255) where it has one, as SurroundOcc's and OpenOccupancy's
    loaders do; ``vote``: several rows of one voxel take the most frequent label (ties:
    the smallest, 255 included, as OpenOccupancy's ``nb_process_label``), else the last
    row wins (numpy assignment)."""
    if rows.ndim != 2 or rows.shape[1] < 4:
        raise ValueError(
            f"{where}: shape {rows.shape}; {benchmark.name} expects sparse rows (N, 4) of "
            f"{', '.join(order)}, label (is this a file of another benchmark?)"
        )
    if rows.dtype.kind == "f":
        if not np.isfinite(rows).all() or (rows != np.round(rows)).any():
            raise ValueError(f"{where}: the rows must hold whole numbers")
    elif rows.dtype.kind not in "iu":
        raise ValueError(f"{where}: rows of dtype {rows.dtype}; expected integers")
    rows = rows.astype(np.int64)
    coords = {axis: rows[:, i] for i, axis in enumerate(order)}
    index = np.stack([coords["x"], coords["y"], coords["z"]], 1)
    shape = np.asarray(benchmark.shape)
    outside = ((index < 0) | (index >= shape)).any(1)
    if outside.any():
        first = tuple(int(v) for v in index[outside][0])
        raise ValueError(
            f"{where}: {int(outside.sum())} row(s) lie outside the {benchmark.name} grid "
            f"{tuple(benchmark.shape)} (first: x, y, z = {first}); expected rows of "
            f"{', '.join(order)}, label"
        )
    raw = rows[:, -1]
    bad = (raw < 0) | (raw >= benchmark.num_classes)
    if bad.any():
        raise ValueError(
            f"{where}: row label(s) {sorted(set(raw[bad].tolist()))[:5]} are not "
            f"{benchmark.name} labels 0..{benchmark.num_classes - 1} (is this a file of "
            "another benchmark?)"
        )
    noise = benchmark.ignore_label if benchmark.ignore_label is not None else 0
    label = np.where(raw == 0, noise, raw)
    dense = np.full(benchmark.shape, benchmark.free_label, dtype=np.int64)
    flat = np.ravel_multi_index(index.T, benchmark.shape)
    if vote:
        # majority per voxel, ties to the smallest label: sort by (voxel, label), count runs
        order_ = np.lexsort((label, flat))
        flat_s, label_s = flat[order_], label[order_]
        run = np.flatnonzero(np.diff(flat_s) | np.diff(label_s)) + 1
        starts = np.concatenate([[0], run])
        counts = np.diff(np.concatenate([starts, [len(flat_s)]]))
        voxel, value = flat_s[starts], label_s[starts]
        # per voxel, the run with the largest count; among equals the first (smallest label)
        best = np.lexsort((value, -counts, voxel))
        keep = best[np.concatenate([[True], np.diff(voxel[best]) != 0])]
        dense.reshape(-1)[voxel[keep]] = value[keep]
    else:
        dense.reshape(-1)[flat] = label
    return torch.from_numpy(dense)


class SparseRows(Layout):
    """Sparse rows of occupied voxels, label last: SurroundOcc (``<token>.npy`` with
    ``x, y, z, label``, the token the LiDAR file name) and OpenOccupancy
    (``scene_<scene>/occupancy/<token>.npy`` with ``z, y, x, label``)."""

    def __init__(self, name: str, order: str, nested: bool, vote: bool) -> None:
        self.name, self.order, self.nested, self.vote = name, order, nested, vote
        columns = ", ".join([*order, "label"])
        where = "scene_<scene>/occupancy/<token>.npy" if nested else "[samples/]<token>.npy"
        self.pattern = f"{where} with rows ({columns})"

    def base(self, root: Path) -> Path:
        if not self.nested and (root / "samples").is_dir():
            return root / "samples"
        return root

    def find(self, root: Path) -> list[Entry]:
        entries = []
        if self.nested:
            for scene in _folders(root):
                folder = scene / "occupancy"
                if not (scene.name.startswith("scene_") and folder.is_dir()):
                    continue
                for file in _folders(folder):
                    if file.suffix == ".npy" and _regular(file):
                        entries.append(Entry(scene.name[len("scene_") :], file.stem, file))
        else:
            for file in _folders(root):
                if file.suffix == ".npy" and _regular(file):
                    entries.append(Entry("", file.name[: -len(".npy")], file))
        return entries

    def relative(self, scene: str, token: str) -> str:
        return f"scene_{scene}/occupancy/{token}.npy" if self.nested else f"{token}.npy"

    def read(self, path: Path, benchmark: Benchmark) -> GroundTruth:
        rows = _read_npy(path, f"{benchmark.name} rows")
        dense = densify_rows(str(path), rows, benchmark, self.order, self.vote)
        return GroundTruth(dense, {})

    def write(self, root: Path, scene: str, token: str, arrays: Mapping[str, np.ndarray]) -> Path:
        path = root / self.relative(scene, token)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, arrays["rows"], allow_pickle=False)
        return path


class NuPlanFiles(Layout):
    """NuPlan-Occ: dense ``<token>.npy`` (400, 400, 32); the val files' z range is moved up
    8 voxels (8 empty layers below, the top 8 dropped) and the front crop
    ``[200:, 100:300, :]`` (200, 200, 32) is scored, as UniScene's loader does."""

    name = "nuplan"
    pattern = "<token>.npy, dense (400, 400, 32) labels"
    stored_shape = (400, 400, 32)
    z_shift = 8

    def find(self, root: Path) -> list[Entry]:
        return [
            Entry("", file.stem, file)
            for file in _folders(root)
            if file.suffix == ".npy" and _regular(file)
        ]

    def relative(self, scene: str, token: str) -> str:
        return f"{token}.npy"

    def read(self, path: Path, benchmark: Benchmark) -> GroundTruth:
        array = _read_npy(path, f"a {benchmark.name} label grid")
        if array.shape != self.stored_shape:
            raise ValueError(
                f"{path}: shape {array.shape}; {benchmark.name} files are dense "
                f"{self.stored_shape} grids (is this a file of another benchmark?)"
            )
        labels = _labels(str(path), array, benchmark)
        empty = torch.full((*labels.shape[:2], self.z_shift), benchmark.free_label)
        shifted = torch.cat([empty, labels[:, :, : labels.shape[2] - self.z_shift]], 2)
        x, y = self.stored_shape[0] // 2, self.stored_shape[1] // 4
        return GroundTruth(shifted[x:, y : 3 * y, :].contiguous(), {})

    def write(self, root: Path, scene: str, token: str, arrays: Mapping[str, np.ndarray]) -> Path:
        path = root / self.relative(scene, token)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, arrays["labels"], allow_pickle=False)
        return path


LAYOUTS: Mapping[str, Layout] = {
    "occ3d": NpzTree(),
    "openocc": OpenOccTree(),
    "waymo": WaymoTree(),
    "surroundocc": SparseRows("surroundocc", "xyz", nested=False, vote=False),
    "openoccupancy": SparseRows("openoccupancy", "zyx", nested=True, vote=True),
    "nuplan": NuPlanFiles(),
}
"""Every ground-truth layout, by the name a :class:`~dego.evaluation.benchmarks.Benchmark`
gives in ``layout``."""


def layout_of(benchmark: Benchmark) -> Layout:
    return LAYOUTS[benchmark.layout]


__all__ = ["LAYOUTS", "Entry", "GroundTruth", "Layout", "densify_rows", "layout_of"]
