"""The official metric code of six occupancy benchmarks, run on dego's fixture trees and
compared number by number with :func:`dego.evaluate`.

Usage::

    python benchmarks/official_metrics.py --official /tmp/official --out /tmp/official_check.json

``--official DIR`` holds the official sources, one folder per repository named
``<owner>+<repo>`` with the repository's own paths below it (see ``SOURCES``). Nothing
official is copied into this repository: at run time each official function is either
imported, or, where its module imports CUDA extensions or mmcv / mmdet at the top, picked
out of the source file with ``ast`` and executed by itself (``Official.pick``). Missing
third-party modules the official files import but the scoring never uses (sklearn,
termcolor, the ``chamfer`` CUDA extension, mmengine's logger, prettytable) are stubbed;
numpy >= 1.24 gets back ``np.int`` / ``np.float``.

For every benchmark, the fixture tree of ``dego.evaluation.trees.write_benchmark_tree``
(2 scenes x 3 frames, seed 0, in a temp dir) is read the way the official loader reads it
(the official loader class itself where there is one: ``LoadOccupancy``,
``LoadOccGTFromFileWaymo``, ``LoadOccupancySurroundOcc``, UniScene's ``load_target``),
scored by the official counting code and summarised by the official dataset-level
``evaluate`` functions. Compared with dego's report:

- the pooled counts (confusion matrix, or per-class tp / gt / pred counts);
- the per-class IoU vector, mIoU, the geometric (SC) IoU where the official code has one,
  the further class sets it prints (CVT-Occ's Waymo mIoU without motorcycle);
- the printed (rounded) values, as printed;
- OpenOccupancy twice: full-resolution label predictions, and coarse (17, 128, 128, 10)
  logits that both sides upsample trilinearly;
- RayIoU (Occ3D-nuScenes, SparseOcc's ``main_rayiou``) and OpenOcc v2's RayIoU@1/2/4,
  RayIoU, per-class AVE, mAVE and OccScore of both official scripts. The official ray
  caster is a CUDA kernel, so the official scoring runs on dego's per-ray casts
  (``dego.evaluation.scoring.cast_with_flow``): ``process_one_sample`` answers with them
  inside SparseOcc's ``main_rayiou`` and OccNet's ``ray_metrics.main`` ("dataset"), and
  ``tools/ray_iou/metric.py``'s ``compute`` reads them from gzip pickles stored as
  ``format_results`` / ``ray_casting.py`` store them (float16 distances and flow;
  "server"). The rays, origins and traversal themselves are dego's here.

A value is "identical" when dego's float64 equals the official number exactly (NaN equal
to NaN); otherwise the table gives max |difference|. A benchmark whose official files are
not under ``--official`` is reported as skipped. The JSON (``--out``) holds every compared
value, the official printed output and the timings; the exit status is 1 when a compared
value differs. About 2-3 minutes on 2 CPU cores (most of it OpenOccupancy's 512x512x40
interpolation), 2.2 GB of memory.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import copy
import gzip
import importlib.util
import io
import json
import logging
import math
import os
import pickle
import re
import shutil
import sys
import tempfile
import time
import types
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

SOURCES = {
    "occ3d-nuscenes": "CVPR2023-3D-Occupancy-Prediction+CVPR2023-3D-Occupancy-Prediction",
    "occ3d-waymo": "Tsinghua-MARS-Lab+Occ3D",
    "cvt-occ": "Tsinghua-MARS-Lab+CVT-Occ",
    "surroundocc": "weiyithu+SurroundOcc",
    "gaussianformer": "huang-yh+GaussianFormer",
    "openoccupancy": "JeffWang987+OpenOccupancy",
    "occnet": "OpenDriveLab+OccNet",
    "sparseocc": "MCG-NJU+SparseOcc",
    "uniscene": "Arlo0o+UniScene-Unified-Occupancy-centric-Driving-Scene-Generation",
    "monoscene": "astra-vision+MonoScene",
}
"""The official repositories under ``--official``."""

BENCHMARKS = (
    "occ3d-nuscenes",
    "occ3d-waymo",
    "surroundocc",
    "surroundocc-gf",
    "openoccupancy",
    "openocc-v2",
    "nuplan-occ",
)
SCENES, FRAMES, SEED = 2, 3, 0


# ----------------------------------------------------------------------------------------
# Running official code
# ----------------------------------------------------------------------------------------


class MissingSourceError(Exception):
    """An official file (or a definition in it) is not under ``--official``."""


class Official:
    """The official sources under ``root``: import a file, or execute chosen top-level
    definitions (``"name"``) and methods (``"Class.method"``, as plain functions taking
    ``self``) of a file in a namespace of our choosing."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def file(self, repo: str, relative: str) -> Path:
        path = self.root / SOURCES[repo] / relative
        if not path.is_file():
            raise MissingSourceError(str(path))
        return path

    def module(self, repo: str, relative: str) -> types.ModuleType:
        path = self.file(repo, relative)
        name = "_official_import_" + re.sub(r"\W", "_", f"{repo}/{relative}")
        spec = importlib.util.spec_from_file_location(name, path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        return module

    def pick(
        self, repo: str, relative: str, names: Sequence[str], namespace: dict[str, Any]
    ) -> dict[str, Any]:
        path = self.file(repo, relative)
        tree = ast.parse(path.read_text())
        nodes = []
        for name in names:
            owner, _, member = name.rpartition(".")
            body = tree.body
            if owner:
                classes = [n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == owner]
                if not classes:
                    raise MissingSourceError(f"{path}: no class {owner}")
                body = classes[0].body
            found = [n for n in body if _defines(n, member)]
            if not found:
                raise MissingSourceError(f"{path}: no {name}")
            nodes.append(found[0])
        # a registered module with a stable name: numba's cache (cache=True) pickles it
        module = types.ModuleType("_official_" + re.sub(r"\W", "_", f"{repo}/{relative}"))
        module.__file__ = str(path)
        module.__dict__.update(namespace)
        sys.modules[module.__name__] = module
        exec(compile(ast.Module(body=nodes, type_ignores=[]), str(path), "exec"), module.__dict__)
        return module.__dict__

    def config(self, repo: str, relative: str) -> dict[str, Any]:
        """An mmcv-style config file (plain Python) as its variables."""
        path = self.file(repo, relative)
        scope: dict[str, Any] = {}
        exec(compile(path.read_text(), str(path), "exec"), scope)
        return scope

    def call_expression(self, repo: str, relative: str, callee: str, scope: dict[str, Any]) -> Any:
        """Evaluate the first call ``callee(...)`` written in a file (its arguments as
        written there) with ``callee`` bound in ``scope``."""
        path = self.file(repo, relative)
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id == callee
            ):
                return eval(compile(ast.Expression(node), str(path), "eval"), dict(scope))
        raise MissingSourceError(f"{path}: no call to {callee}")


def _defines(node: ast.stmt, name: str) -> bool:
    if isinstance(node, ast.FunctionDef | ast.ClassDef):
        return node.name == name
    if isinstance(node, ast.Assign):
        return any(isinstance(t, ast.Name) and t.id == name for t in node.targets)
    return False


def step_of(config: dict[str, Any], pipeline: str, kind: str) -> dict[str, Any]:
    """The keyword arguments of the ``kind`` step of a config's pipeline."""
    for step in config[pipeline]:
        if isinstance(step, dict) and step.get("type") == kind:
            return {k: v for k, v in step.items() if k != "type"}
    raise MissingSourceError(f"no {kind} in {pipeline}")


class _Registry:
    """mmcv / mmdet registries: ``@REGISTRY.register_module()`` leaves the class alone."""

    @staticmethod
    def register_module(*args: Any, **kwargs: Any) -> Callable[[Any], Any]:
        return lambda obj: obj


REGISTRY = _Registry()


class _MMLogger:
    @staticmethod
    def get_instance(name: str) -> logging.Logger:
        return logging.getLogger(name)


class RecordingTable:
    """prettytable's ``PrettyTable`` as the official summaries use it, keeping the rows
    (the unrounded values) and printing them with ``float_format``."""

    def __init__(self, field_names: Sequence[str] | None = None) -> None:
        self.field_names = list(field_names or [])
        self.rows: list[list[Any]] = []
        self.float_format = ""

    def add_row(self, row: Sequence[Any], divider: bool = False) -> None:
        self.rows.append(list(row))

    def __str__(self) -> str:
        def cell(value: Any) -> str:
            if isinstance(value, float | np.floating) and self.float_format:
                return format(float(value), self.float_format + "f")
            return str(value)

        lines = [" | ".join(self.field_names)]
        lines += [" | ".join(cell(v) for v in row) for row in self.rows]
        return "\n".join(lines)


class _CudaFreeTorch:
    """``torch`` for official code that allocates with ``device='cuda'``: the same module,
    tensors on the CPU."""

    def __getattr__(self, name: str) -> Any:
        return getattr(torch, name)

    @staticmethod
    def zeros(*args: Any, device: Any = None, **kwargs: Any) -> torch.Tensor:
        return torch.zeros(*args, **kwargs)


def install_stubs() -> None:
    """Numpy aliases and stand-ins for modules the official files import but their scoring
    never uses (only where the real module is not installed)."""
    for alias, value in (("int", int), ("float", float), ("bool", bool)):
        if not hasattr(np, alias):
            setattr(np, alias, value)
    stubs: dict[str, dict[str, Any]] = {
        "sklearn": {},
        "sklearn.neighbors": {"KDTree": None},
        "sklearn.metrics": {"accuracy_score": None, "precision_recall_fscore_support": None},
        "termcolor": {"colored": lambda text, *args, **kwargs: text},
        "chamfer": {"forward": None},  # SurroundOcc's CUDA extension (reconstruction only)
        "mmengine": {"MMLogger": _MMLogger},
    }
    missing = {n.split(".")[0] for n in stubs if importlib.util.find_spec(n.split(".")[0]) is None}
    for name, attributes in stubs.items():
        if name.split(".")[0] in missing:
            module = types.ModuleType(name)
            module.__dict__.update(attributes)
            sys.modules[name] = module


class Capture:
    """Run a call with its printed output kept and, through ``sys.setprofile``, the local
    variables of the chosen official functions recorded each time they return (the
    official code keeps most unrounded values in locals and only prints them)."""

    def __init__(self, *functions: Callable[..., Any]) -> None:
        self._codes = {f.__code__: f.__name__ for f in functions}  # type: ignore[attr-defined]
        self.locals: dict[str, list[dict[str, Any]]] = {}
        self.text = ""

    def __call__(self, function: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        printed = io.StringIO()

        def profile(frame: types.FrameType, event: str, arg: Any) -> None:
            if event == "return" and frame.f_code in self._codes:
                self.locals.setdefault(self._codes[frame.f_code], []).append(dict(frame.f_locals))

        previous = sys.getprofile()
        with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(io.StringIO()):
            sys.setprofile(profile)
            try:
                result = function(*args, **kwargs)
            finally:
                sys.setprofile(previous)
        self.text += printed.getvalue()
        return result

    def last(self, name: str) -> dict[str, Any]:
        return self.locals[name][-1]


@contextlib.contextmanager
def cpu_cuda() -> Any:
    """``Tensor.cuda()`` as a no-op (GaussianFormer's ``MeanIoU.reset``)."""
    saved = torch.Tensor.cuda
    torch.Tensor.cuda = lambda self, *args, **kwargs: self  # type: ignore[method-assign]
    try:
        yield
    finally:
        torch.Tensor.cuda = saved  # type: ignore[method-assign]


@contextlib.contextmanager
def working_directory(path: Path) -> Any:
    saved = Path.cwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(saved)


def tqdm_quiet(iterable: Any = None, *args: Any, **kwargs: Any) -> Any:
    """``tqdm`` for the official loops: the iterable itself."""
    return iterable


def _load_pickle(path: str) -> Any:
    with open(path, "rb") as file:
        return pickle.load(file)


# ----------------------------------------------------------------------------------------
# Comparison table
# ----------------------------------------------------------------------------------------


def _plain(value: Any) -> Any:
    """JSON-ready: NaN / inf as strings."""
    array = np.asarray(value)
    if array.dtype.kind in "fc":
        out = [_number(float(v)) for v in array.reshape(-1)]
        return (
            out[0] if array.ndim == 0 else np.array(out, dtype=object).reshape(array.shape).tolist()
        )
    return array.tolist()


def _number(value: float) -> float | str:
    return value if math.isfinite(value) else str(value)


class Table:
    def __init__(self) -> None:
        self.rows: list[dict[str, Any]] = []

    def add(self, benchmark: str, quantity: str, dego: Any, official: Any, note: str = "") -> None:
        a = np.asarray(dego, dtype=np.float64)
        b = np.asarray(official, dtype=np.float64)
        identical = a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=True))
        if a.shape != b.shape or (np.isnan(a) != np.isnan(b)).any():
            diff = math.inf
        else:
            d = np.abs(a - b)[~np.isnan(a)]
            diff = float(d.max()) if d.size else 0.0
        self.rows.append(
            {
                "benchmark": benchmark,
                "quantity": quantity,
                "dego": _plain(a),
                "official": _plain(b),
                "shape": list(a.shape),
                "identical": identical,
                "max_abs_diff": _number(diff),
                "note": note,
            }
        )

    def add_text(
        self, benchmark: str, quantity: str, dego: Sequence[str], official: Sequence[str]
    ) -> None:
        """Printed values, compared as the strings printed."""
        self._row(benchmark, quantity, list(dego), list(official), list(dego) == list(official))

    def skip(self, benchmark: str, reason: str) -> None:
        self._row(benchmark, "(skipped)", None, None, None, note=reason)

    def _row(
        self, benchmark: str, quantity: str, dego: Any, official: Any, same: Any, note: str = ""
    ) -> None:
        shape = [] if official is None else [len(official)]
        self.rows.append(
            {
                "benchmark": benchmark,
                "quantity": quantity,
                "dego": dego,
                "official": official,
                "shape": shape,
                "identical": same,
                "max_abs_diff": None,
                "note": note,
            }
        )

    def markdown(self) -> str:
        lines = [
            "| benchmark | quantity | dego | official | max abs diff | identical |",
            "|---|---|---|---|---|---|",
        ]
        for row in self.rows:
            ident = {True: "yes", False: "**NO**", None: "-"}[row["identical"]]
            diff = row["max_abs_diff"]
            diff_text = "-" if diff is None else (diff if isinstance(diff, str) else f"{diff:.3g}")
            lines.append(
                f"| {row['benchmark']} | {row['quantity']} | {_brief(row['dego'], row['shape'])} "
                f"| {_brief(row['official'], row['shape'])} | {diff_text} | {ident} |"
            )
        return "\n".join(lines)


def _brief(value: Any, shape: Sequence[int]) -> str:
    if value is None:
        return "-"
    if not shape:
        return repr(value) if not isinstance(value, str) else value
    if isinstance(value, list) and value and isinstance(value[0], str):
        return " ".join(value) if len(value) <= 3 else f"{len(value)} printed values"
    return "x".join(str(n) for n in shape) + " values"


def printed_round(values: Any, digits: int) -> list[str]:
    """``str(round(v * 100, digits))`` with ``v`` a numpy float64 (the Occ3D prints)."""
    return [str(round(np.float64(v) * 100, digits)) for v in np.atleast_1d(values)]


def confusion_of(report: Any, protocol: str) -> np.ndarray:
    return np.asarray(report.counts[protocol]["confusion"], dtype=np.int64)


def geometric_of(report: Any, protocol: str) -> np.ndarray:
    """dego's (2, 2) occupied / free counts (rows gt; 0 occupied, 1 free)."""
    return np.asarray(report.counts[protocol]["geometric"], dtype=np.int64)


def add_ray_counts(table: Table, name: str, ours: Any, official: Any) -> None:
    """Compare dego's pooled ray counts with the official ``gt_cnt``, ``pred_cnt`` and
    ``tp_cnt``."""
    c = len(official["gt_cnt"])
    table.add(
        name,
        f"ray counts gt / pred ({c})",
        [ours["gt_count"].numpy(), ours["pred_count"].numpy()],
        [official["gt_cnt"], official["pred_cnt"]],
    )
    table.add(name, f"ray true positives 3x{c}", ours["true_positives"].numpy(), official["tp_cnt"])


def recording(base: type) -> tuple[type, list[Any]]:
    """A subclass of ``base`` that keeps every instance made, to read its state after."""
    made: list[Any] = []

    class Recorded(base):  # type: ignore[misc,valid-type]
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            made.append(self)

    return Recorded, made


# ----------------------------------------------------------------------------------------
# The benchmarks
# ----------------------------------------------------------------------------------------


def occ3d_nuscenes(off: Official, work: Path, table: Table) -> dict[str, Any]:
    """Occ3D-nuScenes: the CVPR 2023 devkit's ``NuSceneOcc.evaluate_miou`` (camera mask,
    ``Metric_mIoU(num_classes=18)``, ``count_miou``)."""
    import dego
    from dego.evaluation.trees import write_benchmark_tree

    name = "occ3d-nuscenes"
    metrics = off.module(name, "projects/mmdet3d_plugin/datasets/occ_metrics.py")
    recorded_metric, made = recording(metrics.Metric_mIoU)

    dataset = off.pick(
        name,
        "projects/mmdet3d_plugin/datasets/nuscenes_occ.py",
        ["NuSceneOcc.load_annotations", "NuSceneOcc.evaluate_miou"],
        {
            "np": np,
            "os": os,
            "tqdm": tqdm_quiet,
            "mmcv": types.SimpleNamespace(load=_load_pickle),
            "Metric_mIoU": recorded_metric,
            "Metric_FScore": metrics.Metric_FScore,
        },
    )
    tree = write_benchmark_tree(name, work / name, scenes=SCENES, frames=FRAMES, seed=SEED)
    report = dego.evaluate(tree.gt, tree.pred, benchmark=name, infos=tree.infos)
    ours = report.protocols["occ3d"]

    self = types.SimpleNamespace(load_interval=1, data_root=str(tree.gt), eval_fscore=False)
    self.data_infos = dataset["load_annotations"](self, str(tree.infos))  # sorted by timestamp
    for info in self.data_infos:  # what the devkit's converter adds to each info
        info["occ_gt_path"] = f"gts/{info['scene_name']}/{info['token']}/labels.npz"
    predictions = [np.load(tree.pred / f"{i['token']}.npz")["pred"] for i in self.data_infos]
    capture = Capture()
    capture(dataset["evaluate_miou"], self, predictions)
    metric = made[-1]
    iou = metric.per_class_iu(metric.hist)

    table.add(name, "confusion 18x18 (camera mask)", confusion_of(report, "occ3d"), metric.hist)
    table.add(name, "per-class IoU (ids 0-17)", ours.per_class.numpy(), iou)
    table.add(
        name,
        "mIoU (17 classes)",
        ours.miou,
        np.nanmean(iou[: metric.num_classes - 1]),
        "official: count_miou's printed expression, unrounded",
    )
    printed = re.findall(r"===> .+? - IoU = (\S+)", capture.text)
    table.add_text(
        name, "printed per-class IoU x100 (round 2)", printed_round(ours.per_class[:17], 2), printed
    )
    printed_miou = re.findall(r"===> mIoU of \d+ samples: (\S+)", capture.text)
    table.add_text(name, "printed mIoU x100 (round 2)", printed_round(ours.miou, 2), printed_miou)
    info = {"printed": capture.text, "samples": len(predictions)}
    try:
        info["rayiou"] = sparseocc_rayiou(off, tree, report, table)
    except MissingSourceError as exc:
        table.skip(f"{name} RayIoU", f"official source missing: {exc}")
    return info


def sparseocc_rayiou(off: Official, tree: Any, report: Any, table: Table) -> dict[str, Any]:
    """Occ3D-nuScenes RayIoU: SparseOcc's ``main_rayiou`` / ``calc_rayiou`` on dego's casts
    (its ``process_one_sample`` is the CUDA DVR kernel)."""
    from dego.evaluation.benchmarks import get_benchmark

    name = "occ3d-nuscenes RayIoU"
    sparse = off.pick(
        "sparseocc",
        "loaders/ray_metrics.py",
        ["generate_lidar_rays", "calc_rayiou", "main_rayiou"],
        {
            "np": np,
            "torch": torch,
            "math": math,
            "copy": copy,
            "tqdm": tqdm_quiet,
            "PrettyTable": RecordingTable,
        },
    )
    samples, rays = dego_casts("occ3d-nuscenes", tree)
    official_rays = torch.from_numpy(sparse["generate_lidar_rays"]())
    table.add(
        name, "LiDAR ray directions (generate_lidar_rays)", rays.numpy(), official_rays.numpy()
    )
    queue = [(s[f"sem_{side}"], s[f"pcd_{side}"]) for s in samples for side in ("pred", "gt")]

    def process_one_sample(
        sem: Any, lidar_rays: Any, output_origin: Any, instance_pred: Any = None, **kwargs: Any
    ) -> np.ndarray:
        """The CUDA DVR cast replaced by dego's (checked to be for the same inputs)."""
        expected_sem, rows = queue.pop(0)
        if not (np.array_equal(sem.numpy(), expected_sem) and torch.equal(lidar_rays, rays)):
            raise RuntimeError("process_one_sample: called with other inputs than cast")
        return rows

    sparse["process_one_sample"] = process_one_sample
    class_names = list(get_benchmark("occ3d-nuscenes").class_names)  # ids 0-17, 17 = free
    capture = Capture(sparse["main_rayiou"], sparse["calc_rayiou"])
    out = capture(
        sparse["main_rayiou"],
        [s["sem_pred"] for s in samples],
        [s["sem_gt"] for s in samples],
        [s["origins"] for s in samples],
        class_names,
    )
    if queue:
        raise RuntimeError("main_rayiou did not cast every sample")
    counts, main_locals = capture.last("calc_rayiou"), capture.last("main_rayiou")
    assert report.rayiou is not None
    ray_counts = report.counts["rayiou"]
    add_ray_counts(table, name, ray_counts, counts)
    table.add(
        name,
        "per-class RayIoU 3x17",
        report.rayiou.per_class[:, :17].numpy(),
        main_locals["iou_list"],
    )
    table.add(
        name,
        "RayIoU@1 / @2 / @4",
        list(report.rayiou.at),
        [out["RayIoU@1"], out["RayIoU@2"], out["RayIoU@4"]],
    )
    table.add(name, "RayIoU (17 classes)", report.rayiou.rayiou, out["RayIoU"])
    return {"printed": capture.text, "official": {k: float(v) for k, v in out.items()}}


def occ3d_waymo(off: Official, work: Path, table: Table) -> dict[str, Any]:
    """Occ3D-Waymo: Occ3D's ``LoadOccGTFromFileWaymo`` and ``CustomWaymoDataset_T.evaluate``
    (``Metric_mIoU()``: infov AND camera mask, 23 -> 15), and CVT-Occ's loader, count matrix
    and ``Metric_mIoU.print`` (its 14-class mIoU without motorcycle)."""
    import dego
    from dego.evaluation.trees import write_benchmark_tree

    name = "occ3d-waymo"
    metrics = off.module(name, "projects/mmdet3d_plugin/datasets/occ_metrics.py")
    recorded_metric, made = recording(metrics.Metric_mIoU)

    loading = off.pick(
        name,
        "projects/mmdet3d_plugin/datasets/pipelines/loading.py",
        ["LoadOccGTFromFileWaymo"],
        {"np": np, "os": os, "PIPELINES": REGISTRY},
    )
    dataset = off.pick(
        name,
        "projects/mmdet3d_plugin/datasets/waymo_occ.py",
        ["CustomWaymoDataset_T.evaluate"],
        {
            "tqdm": tqdm_quiet,
            "Metric_mIoU": recorded_metric,
            "Metric_FScore": metrics.Metric_FScore,
        },
    )
    config = off.config(name, "projects/configs/bevformer/bevformer_base_occ_waymo.py")
    tree = write_benchmark_tree(name, work / name, scenes=SCENES, frames=FRAMES, seed=SEED)
    report = dego.evaluate(tree.gt, tree.pred, benchmark=name, rayiou=False)
    ours = report.protocols["occ3d-waymo"]

    kwargs = step_of(config, "test_pipeline", "LoadOccGTFromFileWaymo")
    loader = loading["LoadOccGTFromFileWaymo"](**{**kwargs, "data_root": str(tree.gt)})
    files = sorted(tree.gt.glob("*/*_04.npz"))
    occ_results, samples = [], []
    for file in files:
        scene, frame = file.parent.name, file.name[: -len("_04.npz")]
        # KITTI-format Waymo sample name: <split digit><scene:03d><frame:03d>
        gt = loader({"pts_filename": f"samples/0{scene}{frame}.bin"})
        pred = np.load(tree.pred / f"{scene}_{frame}.npz")["pred"]
        samples.append((gt, pred))
        occ_results.append(  # OccFormerWaymo.forward_test's output
            {
                "voxel_semantics": gt["voxel_semantics"].astype(np.uint8),
                "voxel_semantics_preds": pred.astype(np.uint8),
                "mask_infov": gt["mask_infov"],
                "mask_lidar": gt["mask_lidar"],
                "mask_camera": gt["mask_camera"],
            }
        )
    capture = Capture()
    capture(dataset["evaluate"], types.SimpleNamespace(), occ_results, metric="mIoU")
    metric = made[-1]
    iou = metric.per_class_iu(metric.hist)
    table.add(
        name, "confusion 16x16 (infov & camera)", confusion_of(report, "occ3d-waymo"), metric.hist
    )
    table.add(name, "per-class IoU (ids 0-15)", ours.per_class.numpy(), iou)
    table.add(
        name,
        "mIoU (15 classes)",
        ours.miou,
        np.nanmean(iou[:-1]),
        "official: print()'s expression, unrounded",
    )
    printed = re.findall(r"===> class .+? IoU = (\S+)", capture.text)
    table.add_text(
        name, "printed per-class IoU x100 (round 2)", printed_round(ours.per_class, 2), printed
    )
    printed_miou = re.findall(r"===> mIoU of \d+ samples: (\S+)", capture.text)
    table.add_text(name, "printed mIoU x100 (round 2)", printed_round(ours.miou, 2), printed_miou)

    # CVT-Occ (the follow-up official code): loader, count matrix in the head, print()
    cvt_metrics = off.module("cvt-occ", "projects/mmdet3d_plugin/datasets/occ_metrics.py")
    cvt_loading = off.pick(
        "cvt-occ",
        "projects/mmdet3d_plugin/datasets/pipelines/loading.py",
        ["LoadOccGTFromFileWaymo"],
        {"np": np, "os": os, "PIPELINES": REGISTRY},
    )
    head = off.pick(
        "cvt-occ",
        "projects/mmdet3d_plugin/bevformer/dense_heads/occformer_head_waymo.py",
        ["CVTOccHeadWaymo.compute_count_matrix"],
        {"torch": _CudaFreeTorch()},
    )
    cvt_config = off.config("cvt-occ", "projects/configs/cvtocc/cvtocc_waymo.py")
    cvt_kwargs = step_of(cvt_config, "test_pipeline", "LoadOccGTFromFileWaymo")
    cvt_loader = cvt_loading["LoadOccGTFromFileWaymo"](**{**cvt_kwargs, "data_root": str(tree.gt)})
    dataset_kwargs = {
        k: v for k, v in cvt_config["data"]["test"].items() if k not in ("type", "pipeline")
    }
    cvt_metric = cvt_metrics.Metric_mIoU(**dataset_kwargs)
    head_self = types.SimpleNamespace(num_classes=cvt_kwargs["num_classes"])
    free = cvt_kwargs["FREE_LABEL"]
    for file in files:
        scene, frame = file.parent.name, file.name[: -len("_04.npz")]
        gt = cvt_loader({"pts_filename": f"samples/0{scene}{frame}.bin"})
        pred = np.load(tree.pred / f"{scene}_{frame}.npz")["pred"].astype(np.int64)
        pred[pred == free] = cvt_kwargs["num_classes"] - 1  # CVT-Occ's head: raw argmax 0..15
        mask = torch.from_numpy(gt["valid_mask"])
        count = head["compute_count_matrix"](
            head_self,
            torch.from_numpy(gt["voxel_semantics"].astype(np.int64))[mask],
            torch.from_numpy(pred)[mask],
        )
        cvt_metric.add_batch(count_matrix=count.cpu().numpy())
    runner = types.SimpleNamespace(log_buffer=types.SimpleNamespace(output={}, ready=False))
    cvt_capture = Capture(cvt_metrics.Metric_mIoU.print_iou)
    scratch = work / "cvt-occ-cwd"
    (scratch / "work_dirs").mkdir(parents=True, exist_ok=True)  # print() appends a time stamp there
    with working_directory(scratch):
        cvt_capture(cvt_metric.print, runner=runner)
    seen = cvt_capture.last("print_iou")
    no_motor = "14 classes (no motorcycle)"
    table.add(name, "CVT-Occ confusion 16x16", confusion_of(report, "occ3d-waymo"), cvt_metric.hist)
    table.add(name, "CVT-Occ per-class IoU", ours.per_class.numpy(), seen["mIoU"])
    table.add(
        name,
        "CVT-Occ mIoU without motorcycle (14)",
        ours.group_means[no_motor],
        np.nanmean(seen["IoU_motor_free"]),
        "official: nanmean of print_iou's IoU_motor_free, unrounded",
    )
    output = runner.log_buffer.output
    table.add_text(
        name,
        "CVT-Occ logged mIoU / mIoU w/o motorcycle (round 2)",
        printed_round([ours.miou, ours.group_means[no_motor]], 2),
        [str(output["mIoU of non free"]), str(output["mIoU without MOTORCYCLE(waymo)"])],
    )
    return {"printed": capture.text, "cvt_occ_printed": cvt_capture.text, "samples": len(files)}


def surroundocc(off: Official, work: Path, table: Table) -> dict[str, Any]:
    """SurroundOcc: ``LoadOccupancy(use_semantic=True)``, ``evaluation_semantic`` per
    sample, ``CustomNuScenesOccDataset.evaluate``."""
    import dego
    from dego.evaluation.trees import write_benchmark_tree

    name = "surroundocc"
    config = off.config(name, "projects/configs/surroundocc/surroundocc.py")
    loading = off.pick(
        name,
        "projects/mmdet3d_plugin/datasets/pipelines/loading.py",
        ["LoadOccupancy"],
        {"np": np, "PIPELINES": REGISTRY},
    )
    evaluation = off.module(name, "projects/mmdet3d_plugin/datasets/evaluation_metrics.py")
    dataset = off.pick(
        name,
        "projects/mmdet3d_plugin/datasets/nuscenes_occupancy_dataset.py",
        ["CustomNuScenesOccDataset.evaluate"],
        {"np": np},
    )
    tree = write_benchmark_tree(name, work / name, scenes=SCENES, frames=FRAMES, seed=SEED)
    report = dego.evaluate(tree.gt, tree.pred, benchmark=name, rayiou=False)
    ours = report.protocols["surroundocc"]

    loader = loading["LoadOccupancy"](**step_of(config, "test_pipeline", "LoadOccupancy"))
    test = config["data"]["test"]
    img_metas = {"occ_size": test["occ_size"], "pc_range": test["pc_range"]}
    class_num = len(test["classes"]) + 1
    results = []
    files = sorted(tree.gt.rglob("*.npy"))
    for file in files:
        gt_rows = loader({"occ_path": str(file)})["gt_occ"]
        pred = np.load(tree.pred / file.name).astype(np.int64)  # argmax output: int64
        results.extend(
            evaluation.evaluation_semantic(
                torch.from_numpy(pred)[None], torch.from_numpy(gt_rows)[None], img_metas, class_num
            )
        )
    self = types.SimpleNamespace(
        use_semantic=True,
        class_names=test["classes"],
        format_results=lambda results, jsonfile_prefix=None: (results, None),
    )
    capture = Capture()
    out = capture(dataset["evaluate"], self, list(results))

    confusion, geometric = confusion_of(report, name), geometric_of(report, name)
    counts = np.stack([confusion.diagonal(), confusion.sum(1), confusion.sum(0)], 1)
    counts[0] = [geometric[0, 0], geometric[0].sum(), geometric[:, 0].sum()]
    table.add(
        name,
        "summed per-sample counts 17x3 [tp, gt, pred] (slot 0 geometry)",
        counts,
        np.sum(results, 0),
    )
    names = list(test["classes"])
    table.add(name, "per-class IoU (1-16)", ours.per_class[1:].numpy(), [out[n] for n in names])
    table.add(name, "geometric IoU ('IoU')", ours.iou, out["IoU"])
    table.add(name, "mIoU", ours.miou, out["mIoU"], "official values are unrounded fractions")
    return {"official": {k: float(v) for k, v in out.items()}, "samples": len(files)}


def surroundocc_gf(off: Official, work: Path, table: Table) -> dict[str, Any]:
    """SurroundOcc labels scored GaussianFormer's way: ``LoadOccupancySurroundOcc``,
    eval.py's ``MeanIoU(...)`` with ``_after_step`` per sample, ``_after_epoch``."""
    import dego
    from dego.evaluation.trees import write_benchmark_tree

    name, repo = "surroundocc-gf", "gaussianformer"
    config = off.config(repo, "config/_base_/surroundocc.py")
    transforms = off.pick(
        repo,
        "dataset/transform_3d.py",
        ["LoadOccupancySurroundOcc"],
        {"np": np, "os": os, "torch": torch, "OPENOCC_TRANSFORMS": REGISTRY},
    )
    metric_util = off.module(repo, "misc/metric_util.py")
    metric = off.call_expression(repo, "eval.py", "MeanIoU", {"MeanIoU": metric_util.MeanIoU})
    tree = write_benchmark_tree(name, work / name, scenes=SCENES, frames=FRAMES, seed=SEED)
    report = dego.evaluate(tree.gt, tree.pred, benchmark=name, rayiou=False)
    ours = report.protocols["gaussianformer"]

    kwargs = step_of(config, "test_pipeline", "LoadOccupancySurroundOcc")
    loader = transforms["LoadOccupancySurroundOcc"](**{**kwargs, "occ_path": str(tree.gt)})
    logger = metric_util.logger
    log = io.StringIO()
    handler = logging.StreamHandler(log)
    saved = (logger.level, logger.propagate)
    logger.setLevel(logging.INFO)
    logger.propagate = False
    logger.addHandler(handler)
    capture = Capture(metric_util.MeanIoU._after_epoch)
    files = sorted(tree.gt.rglob("*.npy"))
    try:
        with cpu_cuda():
            metric.reset()
            for file in files:
                sample = loader({"pts_filename": f"samples/LIDAR_TOP/{file.stem}"})
                label = torch.from_numpy(sample["occ_label"])[None].flatten(1)  # _sampling
                mask = torch.from_numpy(sample["occ_cam_mask"])[None]
                pred = torch.from_numpy(np.load(tree.pred / file.name).astype(np.int64))
                metric._after_step(pred.flatten(), label[0], mask[0].flatten())
            miou_x100, occ_iou_x100 = capture(metric._after_epoch)
    finally:
        logger.removeHandler(handler)
        logger.setLevel(saved[0])
        logger.propagate = saved[1]
    local = capture.last("_after_epoch")

    confusion, geometric = (
        confusion_of(report, "gaussianformer"),
        geometric_of(report, "gaussianformer"),
    )
    ids = list(metric.class_indices)
    ours_counts = np.stack(
        [
            np.append(confusion.sum(1)[ids], geometric[0].sum()),
            np.append(confusion.diagonal()[ids], geometric[0, 0]),
            np.append(confusion.sum(0)[ids], geometric[:, 0].sum()),
        ]
    )
    official_counts = np.stack(
        [metric.total_seen.numpy(), metric.total_correct.numpy(), metric.total_positive.numpy()]
    )
    table.add(
        name,
        "float32 totals 3x17 [seen, correct, positive] (last: geometry)",
        ours_counts,
        official_counts,
    )
    table.add(
        name,
        "per-class IoU (1-16)",
        ours.per_class[ids].numpy(),
        np.asarray(local["ious"], dtype=np.float64),
    )
    table.add(name, "mIoU (np.mean(ious))", ours.miou, local["miou"])
    table.add(name, "returned mIoU x100", ours.miou * 100, miou_x100)
    table.add(name, "geometric IoU (occ_iou, float32)", ours.iou, float(local["occ_iou"]))
    table.add(
        name,
        "returned occ_iou x100 (float32)",
        float(np.float32(ours.iou) * np.float32(100)),
        float(occ_iou_x100),
    )
    logged = re.findall(r"^.+? : (\S+)%, ", log.getvalue(), re.MULTILINE)
    table.add_text(
        name,
        "logged per-class IoU '%.2f%%'",
        ["%.2f" % (v * 100) for v in ours.per_class[ids].tolist()],
        logged,
    )
    return {"logged": log.getvalue(), "samples": len(files)}


def openoccupancy(off: Official, work: Path, table: Table) -> dict[str, Any]:
    """OpenOccupancy: ``LoadOccupancy`` (majority vote by ``nb_process_label``),
    ``OccNet.evaluation_semantic`` (SC and SSC), ``NuscOCCDataset.evaluate``. Twice: with
    the fixture's full-resolution label predictions (as one-hot logits) and with coarse
    (17, 128, 128, 10) logits upsampled by the official trilinear interpolation."""
    import numba

    import dego
    from dego.evaluation.trees import write_benchmark_tree

    name = "openoccupancy"
    config = off.config(name, "projects/configs/baselines/CAM-R50_img1600_128x128x10.py")
    loading = off.pick(
        name,
        "projects/occ_plugin/datasets/pipelines/loading.py",
        ["nb_process_label", "LoadOccupancy"],
        {"np": np, "nb": numba, "torch": torch, "copy": copy, "os": os, "PIPELINES": REGISTRY},
    )
    occnet = off.pick(
        name,
        "projects/occ_plugin/occupancy/detectors/occnet.py",
        ["fast_hist", "OccNet.evaluation_semantic"],
        {"np": np, "torch": torch, "F": torch.nn.functional, "copy": copy},
    )
    formatting = off.pick(
        name,
        "projects/occ_plugin/utils/formating.py",
        ["cm_to_ious", "format_SC_results", "format_SSC_results"],
        {"np": np, "PrettyTable": RecordingTable},
    )
    dataset = off.pick(
        name,
        "projects/occ_plugin/datasets/nuscenes_occ_dataset.py",
        ["NuscOCCDataset.evaluate"],
        {
            "cm_to_ious": formatting["cm_to_ious"],
            "format_SC_results": formatting["format_SC_results"],
            "format_SSC_results": formatting["format_SSC_results"],
        },
    )
    tree = write_benchmark_tree(name, work / name, scenes=SCENES, frames=FRAMES, seed=SEED)
    kwargs = step_of(config, "test_pipeline", "LoadOccupancy")
    loader = loading["LoadOccupancy"](**{**kwargs, "occ_path": str(tree.gt)})
    model = types.SimpleNamespace(empty_idx=config["empty_idx"])
    num_cls = config["num_cls"]
    files = sorted(tree.gt.glob("scene_*/occupancy/*.npy"))
    ground_truth = {}
    for file in files:
        results = {
            "scene_token": file.parent.parent.name[len("scene_") :],
            "lidar_token": file.stem,
            "bda_mat": torch.eye(3),  # test time: no BEV augmentation
        }
        ground_truth[file.stem] = torch.from_numpy(loader(results)["gt_occ"])[None]

    # coarse logits for the second run: noise plus a bump at the fine prediction's class
    logits_dir = work / "openoccupancy-logits"
    logits_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(SEED)
    for file in files:
        fine = np.load(tree.pred / file.name)
        coarse = fine[2::4, 2::4, 2::4].astype(np.int64)
        logits = rng.standard_normal((num_cls, *coarse.shape)).astype(np.float32)
        np.put_along_axis(logits, coarse[None], 3.0, axis=0)
        np.save(logits_dir / file.name, logits)

    info: dict[str, Any] = {"samples": len(files)}
    for variant, pred_root in (("labels", tree.pred), ("coarse logits", logits_dir)):
        report = dego.evaluate(tree.gt, pred_root, benchmark=name, rayiou=False)
        ours = report.protocols["ssc"]
        sc_hists, ssc_hists = [], []
        for file in files:
            array = np.load(pred_root / file.name)
            if variant == "labels":  # the argmax of one-hot logits is the label
                pred = torch.zeros((1, num_cls, *array.shape), dtype=torch.float32)
                pred.scatter_(1, torch.from_numpy(array.astype(np.int64))[None, None], 1.0)
            else:
                pred = torch.from_numpy(array)[None]
            gt = ground_truth[file.stem]
            sc_hists.append(occnet["evaluation_semantic"](model, pred, gt, "SC")[0])
            ssc_hists.append(occnet["evaluation_semantic"](model, pred, gt, "SSC")[0])
            del pred
        capture = Capture(formatting["cm_to_ious"], formatting["format_SSC_results"])
        out = capture(
            dataset["evaluate"],
            types.SimpleNamespace(),
            {"SC_metric": sc_hists, "SSC_metric": ssc_hists},
        )
        sc_ious, ssc_ious = (c["mean_ious"] for c in capture.locals["cm_to_ious"])
        mean = capture.last("format_SSC_results")["mean_ious"]
        g = geometric_of(report, "ssc")
        label = f"{name} ({variant})"
        table.add(label, "SSC confusion 17x17", confusion_of(report, "ssc"), sum(ssc_hists))
        table.add(
            label,
            "SC confusion 2x2 (0 empty, 1 occupied)",
            [[g[1, 1], g[1, 0]], [g[0, 1], g[0, 0]]],
            sum(sc_hists),
        )
        table.add(
            label,
            "per-class IoU (0 free, 1-16)",
            ours.per_class.numpy(),
            np.asarray(ssc_ious, dtype=np.float64),
        )
        table.add(
            label,
            "SSC mean (1-16)",
            ours.miou,
            mean,
            "format_SSC_results: sum(...) / 16, unrounded",
        )
        table.add(label, "SC IoU (non-empty)", ours.iou, sc_ious[1])
        names = ["free", *formatting_names(out)]
        table.add(
            label,
            "printed SSC_* and SSC_mean (np.round 3)",
            np.round(np.append(ours.per_class.numpy(), ours.miou), 3),
            [out[f"SSC_{n}"] for n in names] + [out["SSC_mean"]],
        )
        table.add(
            label, "printed SC_non-empty (np.round 3)", np.round(ours.iou, 3), out["SC_non-empty"]
        )
        info[variant] = {k: float(v) for k, v in out.items()}
    return info


def formatting_names(eval_results: dict[str, Any]) -> list[str]:
    """The 16 class names of ``SSC_<name>`` keys, in the order ``format_SSC_results``
    writes them (after ``SSC_free``)."""
    return [
        k[len("SSC_") :]
        for k in eval_results
        if k.startswith("SSC_") and k not in ("SSC_free", "SSC_mean")
    ]


def dego_casts(name: str, tree: Any) -> tuple[list[dict[str, Any]], torch.Tensor]:
    """Per sample of the fixture (in the infos' order): the stored arrays the official
    scripts load, the origins, and dego's per-ray casts as the official
    ``process_one_sample`` returns them (float32 rows ``[label, distance]``, plus
    ``flow x, flow y`` for benchmarks with flow). dego's readers must return the stored
    arrays unchanged."""
    from dego.evaluation.benchmarks import get_benchmark
    from dego.evaluation.layouts import layout_of
    from dego.evaluation.predictions import read_prediction
    from dego.evaluation.run import prepare
    from dego.evaluation.scoring import cast_with_flow
    from dego.raycast import generate_lidar_rays

    spec = get_benchmark(name)
    assert spec.ray is not None
    with_flow = bool(spec.ray.flow_classes)
    plan, origins_fn = prepare(tree.gt, tree.pred, benchmark=name, infos=tree.infos)
    assert origins_fn is not None
    rays = generate_lidar_rays()
    samples = []
    for sample in plan.samples:
        assert sample.prediction is not None
        stored_gt, stored_pred = np.load(sample.gt_file), np.load(sample.prediction)
        sem_gt, sem_pred = stored_gt["semantics"], stored_pred["pred"]
        zeros = np.zeros((*sem_gt.shape, 2), np.float32)
        flow_gt = stored_gt["flow"] if with_flow else zeros
        flow_pred = stored_pred["flow"] if "flow" in stored_pred.files else zeros
        gt = layout_of(spec).read(Path(sample.gt_file), spec)
        pred, ours_flow = read_prediction(sample.prediction, spec)
        gt_flow = gt.flow if gt.flow is not None else torch.from_numpy(zeros)
        ours_flow = ours_flow if ours_flow is not None else torch.from_numpy(zeros)
        if not (
            np.array_equal(gt.semantics.numpy(), sem_gt)
            and np.array_equal(pred.numpy(), sem_pred)
            and np.array_equal(gt_flow.numpy(), flow_gt)
            and np.array_equal(ours_flow.numpy(), flow_pred)
        ):
            raise RuntimeError(f"{sample.token}: dego read other arrays than the files hold")
        origins = origins_fn(sample.token)
        cast = cast_with_flow(spec, pred, gt.semantics, ours_flow, gt_flow, origins, rays)
        record = {
            "token": sample.token,
            "sem_gt": sem_gt,
            "sem_pred": sem_pred,
            "flow_gt": flow_gt,
            "flow_pred": flow_pred,
            "origins": origins[None],  # EgoPoseDataset's batch: (1, K, 3)
        }
        for side in ("pred", "gt"):
            columns = [cast[f"{side}_cls"].float()[:, None], cast[f"{side}_dist"].float()[:, None]]
            if with_flow:
                columns.append(cast[f"{side}_flow"].float())
            record[f"pcd_{side}"] = torch.cat(columns, 1).numpy()
        samples.append(record)
    return samples, rays


def openocc_v2(off: Official, work: Path, table: Table) -> dict[str, Any]:
    """OpenOcc v2: dego's casts scored by ``ray_metrics.main`` / ``calc_metrics``
    ("dataset") and by ``tools/ray_iou/metric.py``'s ``compute`` ("server")."""
    import dego
    from dego.evaluation.trees import write_benchmark_tree

    name, repo = "openocc-v2", "occnet"
    rays_module = off.pick(
        repo,
        "projects/mmdet3d_plugin/datasets/ray_metrics.py",
        ["occ_class_names", "flow_class_names", "generate_lidar_rays", "calc_metrics", "main"],
        {
            "np": np,
            "torch": torch,
            "math": math,
            "copy": copy,
            "tqdm": tqdm_quiet,
            "PrettyTable": RecordingTable,
        },
    )
    server = off.module(repo, "tools/ray_iou/metric.py")
    server.tqdm = tqdm_quiet
    tree = write_benchmark_tree(name, work / name, scenes=SCENES, frames=FRAMES, seed=SEED)
    reports = {
        variant: dego.evaluate(tree.gt, tree.pred, benchmark=name, infos=tree.infos, mave=variant)
        for variant in ("dataset", "server")
    }
    samples, rays = dego_casts(name, tree)
    official_rays = torch.from_numpy(rays_module["generate_lidar_rays"]())
    table.add(
        name, "LiDAR ray directions (generate_lidar_rays)", rays.numpy(), official_rays.numpy()
    )
    queue: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    lists: dict[str, list[Any]] = {
        k: [] for k in ("sem_pred", "sem_gt", "flow_pred", "flow_gt", "origins")
    }
    gt_pkl, pred_pkl = {}, {}
    for sample in samples:
        queue += [
            (sample["sem_pred"], sample["flow_pred"], sample["pcd_pred"]),
            (sample["sem_gt"], sample["flow_gt"], sample["pcd_gt"]),
        ]
        for key in lists:
            lists[key].append(sample[key])
        gt_pkl[sample["token"]] = {  # ray_casting.py
            "pcd_cls": sample["pcd_gt"][:, 0].astype(np.uint8),
            "pcd_dist": sample["pcd_gt"][:, 1].astype(np.float16),
            "pcd_flow": sample["pcd_gt"][:, 2:4].astype(np.float16),
        }
        pred_pkl[sample["token"]] = {  # nuscenes_occ.py format_results
            "pcd_cls": sample["pcd_pred"][:, 0].astype(np.int8),
            "pcd_dist": sample["pcd_pred"][:, 1].astype(np.float16),
            "pcd_flow": sample["pcd_pred"][:, 2:4].astype(np.float16),
        }

    def process_one_sample(sem: Any, lidar_rays: Any, output_origin: Any, flow: Any) -> np.ndarray:
        """The CUDA DVR cast replaced by dego's (checked to be for the same inputs)."""
        expected_sem, expected_flow, rows = queue.pop(0)
        if not (
            np.array_equal(sem, expected_sem)
            and np.array_equal(flow, expected_flow)
            and torch.equal(lidar_rays, rays)
        ):
            raise RuntimeError("process_one_sample: called with other inputs than cast")
        return rows

    rays_module["process_one_sample"] = process_one_sample
    dataset_capture = Capture(rays_module["main"], rays_module["calc_metrics"])
    dataset_capture(rays_module["main"], *(lists[k] for k in lists))
    if queue:
        raise RuntimeError("ray_metrics.main did not cast every sample")
    main_locals, counts = dataset_capture.last("main"), dataset_capture.last("calc_metrics")

    # the submission path: gzip pickles, metric.py's compute()
    pkl_dir = work / "openocc-v2-pkl"
    pkl_dir.mkdir(parents=True, exist_ok=True)
    gt_path, pred_path = pkl_dir / "nuscenes_infos_val_occ_pcd.gz", pkl_dir / "submission.gz"
    with gzip.GzipFile(gt_path, "wb", compresslevel=1) as file:
        pickle.dump({"method": "GT", "results": gt_pkl}, file, protocol=pickle.HIGHEST_PROTOCOL)
    pred_path.write_bytes(
        gzip.compress(pickle.dumps({"method": "dego fixture", "results": pred_pkl}), mtime=0)
    )
    server_capture = Capture(server.compute, server.calc_metrics)
    evaluation = server_capture(
        server.compute, argparse.Namespace(pred=str(pred_path), gt=str(gt_path))
    )
    compute_locals, server_counts = (
        server_capture.last("compute"),
        server_capture.last("calc_metrics"),
    )
    public = evaluation["public_score"]

    flow_names = list(rays_module["flow_class_names"])
    for variant, official in (
        (
            "dataset",
            {
                "counts": counts,
                "iou": np.asarray(main_locals["iou_list"]),
                "at": main_locals["table"].rows[-1][1:4],  # the printed MEAN row
                "rayiou": main_locals["miou"],
                "ave": main_locals["ave_list"][: len(flow_names)],
                "mave": main_locals["mave"],
                "occ_score": main_locals["occ_score"],
                "note": "ray_metrics.py main()",
            },
        ),
        (
            "server",
            {
                "counts": server_counts,
                "iou": np.asarray(compute_locals["openocc_iou_list"]),
                "at": [public["RayIoU@1"], public["RayIoU@2"], public["RayIoU@4"]],
                "rayiou": public["RayIoU"],
                "ave": compute_locals["openocc_ave_list"][: len(flow_names)],
                "mave": public["mAVE"],
                "occ_score": public["final_Occ_Score"],
                "note": "metric.py compute()",
            },
        ),
    ):
        report = reports[variant]
        assert report.rayiou is not None and report.flow is not None
        ray_counts = report.counts["rayiou"]
        label = f"{name} ({variant})"
        c = official["counts"]
        add_ray_counts(table, label, ray_counts, c)
        table.add(
            label, "per-class RayIoU 3x16", report.rayiou.per_class[:, :16].numpy(), official["iou"]
        )
        table.add(label, "RayIoU@1 / @2 / @4", list(report.rayiou.at), official["at"])
        table.add(label, "RayIoU", report.rayiou.rayiou, official["rayiou"], official["note"])
        table.add(
            label,
            "AVE per flow class (8)",
            [report.flow["ave"][n] for n in flow_names],
            official["ave"],
        )
        table.add(label, "mAVE", report.flow["mave"], official["mave"])
        table.add(label, "OccScore", report.flow["occ_score"], official["occ_score"])
    printed = re.findall(r"--- Occ score: (\S+)", dataset_capture.text)
    table.add_text(
        f"{name} (dataset)",
        "printed Occ score",
        [str(np.float64(reports["dataset"].flow["occ_score"]))],
        printed,
    )
    return {
        "printed_dataset": dataset_capture.text,
        "printed_server": server_capture.text,
        "samples": len(samples),
        "origins": [int(o.shape[1]) for o in lists["origins"]],
    }


def nuplan_occ(off: Official, work: Path, table: Table) -> dict[str, Any]:
    """NuPlan-Occ: UniScene's ``NuplanDataset.load_target`` (val: z shift, front crop),
    MonoScene's ``SSCMetrics(9).add_batch`` per sample and ``test_epoch_end``."""
    import dego
    from dego.evaluation.trees import write_benchmark_tree

    name = "nuplan-occ"
    params = off.module("uniscene", "SOP/monoscene/monoscene/data/nuplan/params.py")
    dataset = off.pick(
        "uniscene",
        "SOP/monoscene/monoscene/data/nuplan/nuplan_dataset.py",
        ["NuplanDataset.load_target"],
        {"np": np, "os": os},
    )
    ssc = off.module("monoscene", "monoscene/loss/sscMetrics.py")
    model = off.pick(
        "monoscene", "monoscene/models/monoscene.py", ["MonoScene.test_epoch_end"], {"np": np}
    )
    tree = write_benchmark_tree(name, work / name, scenes=SCENES, frames=FRAMES, seed=SEED)
    report = dego.evaluate(tree.gt, tree.pred, benchmark=name, rayiou=False)
    ours = report.protocols["ssc"]

    names = list(params.nuplan_class_names)
    files = sorted(tree.gt.glob("*.npy"))
    self = types.SimpleNamespace(
        infos=[{"token": f.stem} for f in files], occ_path=str(tree.gt), split="val"
    )
    metric = ssc.SSCMetrics(len(names))
    for index, file in enumerate(files):
        target = dataset["load_target"](self, index)
        pred = np.load(tree.pred / file.name).astype(np.int64)  # argmax output: int64
        metric.add_batch(pred[None], target[None])
    stats = metric.get_stats()
    official_counts = np.stack([metric.tps, metric.fps, metric.fns])
    official_completion = [metric.completion_tp, metric.completion_fp, metric.completion_fn]
    capture = Capture()
    capture(
        model["test_epoch_end"], types.SimpleNamespace(class_names=names, test_metrics=metric), []
    )

    confusion, g = confusion_of(report, "ssc"), geometric_of(report, "ssc")
    tp = confusion.diagonal()
    table.add(
        name,
        "tps / fps / fns 3x9",
        np.stack([tp, confusion.sum(0) - tp, confusion.sum(1) - tp]),
        official_counts,
    )
    table.add(name, "completion tp / fp / fn", [g[0, 0], g[1, 0], g[0, 1]], official_completion)
    table.add(name, "per-class iou_ssc (0-8)", ours.per_class.numpy(), stats["iou_ssc"])
    table.add(name, "mIoU (iou_ssc_mean)", ours.miou, stats["iou_ssc_mean"])
    table.add(name, "SC IoU (completion)", ours.iou, stats["iou"])
    sc_tp, sc_fp, sc_fn = (int(v) for v in (g[0, 0], g[1, 0], g[0, 1]))
    table.add(
        name,
        "SC precision / recall",
        [sc_tp / (sc_tp + sc_fp), sc_tp / (sc_tp + sc_fn)],
        [stats["precision"], stats["recall"]],
        "dego side derived from its completion counts (the report has no P/R)",
    )
    first = re.search(r"Precision=(\S+), Recall=(\S+), IoU=(\S+)", capture.text)
    assert first is not None
    per_class = re.findall(r"(-?\d+\.\d{4}), ", capture.text.split("class IoU:")[1])
    miou = re.findall(r"mIoU=(\S+)", capture.text)
    dego_printed = [
        f"{v * 100:.4f}" for v in (sc_tp / (sc_tp + sc_fp), sc_tp / (sc_tp + sc_fn), ours.iou)
    ]
    table.add_text(
        name, "printed Precision / Recall / IoU x100 ({:.4f})", dego_printed, list(first.groups())
    )
    table.add_text(
        name,
        "printed class IoU x100 ({:.4f})",
        [f"{v:.4f}" for v in (ours.per_class.numpy() * 100).tolist()],
        per_class,
    )
    table.add_text(name, "printed mIoU x100 ({:.4f})", [f"{ours.miou * 100:.4f}"], miou)
    return {"printed": capture.text, "samples": len(files)}


CHECKS: dict[str, Callable[[Official, Path, Table], dict[str, Any]]] = {
    "occ3d-nuscenes": occ3d_nuscenes,
    "occ3d-waymo": occ3d_waymo,
    "surroundocc": surroundocc,
    "surroundocc-gf": surroundocc_gf,
    "openoccupancy": openoccupancy,
    "openocc-v2": openocc_v2,
    "nuplan-occ": nuplan_occ,
}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--official", type=Path, required=True, help="the official sources")
    parser.add_argument("--out", type=Path, help="write every compared value here (JSON)")
    parser.add_argument("--benchmarks", nargs="+", choices=BENCHMARKS, default=list(BENCHMARKS))
    parser.add_argument(
        "--work", type=Path, help="keep the fixture trees here (default: a temp dir)"
    )
    args = parser.parse_args(argv)

    # numba caches the official nb_process_label (cache=True): keep it out of --official
    os.environ.setdefault(
        "NUMBA_CACHE_DIR", str(Path(tempfile.gettempdir()) / "dego_official_numba")
    )
    install_stubs()
    official = Official(args.official)
    table = Table()
    details: dict[str, Any] = {}
    work = args.work or Path(tempfile.mkdtemp(prefix="dego_official_"))
    try:
        for benchmark in args.benchmarks:
            start = time.perf_counter()
            try:
                details[benchmark] = CHECKS[benchmark](official, work, table)
            except MissingSourceError as exc:
                table.skip(benchmark, f"official source missing: {exc}")
                details[benchmark] = {"skipped": str(exc)}
            details[benchmark]["seconds"] = round(time.perf_counter() - start, 1)
            print(f"{benchmark}: {details[benchmark]['seconds']} s", file=sys.stderr)
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)

    print(table.markdown())
    for row in table.rows:
        if row["quantity"] == "(skipped)":
            print(f"skipped {row['benchmark']}: {row['note']}")
    compared = [r for r in table.rows if r["identical"] is not None]
    same = sum(r["identical"] for r in compared)
    print(f"\n{same} of {len(compared)} compared quantities identical")
    if args.out is not None:
        args.out.write_text(
            json.dumps(
                {"rows": table.rows, "details": details, "official": str(args.official)}, indent=1
            )
        )
    return 0 if same == len(compared) else 1


if __name__ == "__main__":
    sys.exit(main())
