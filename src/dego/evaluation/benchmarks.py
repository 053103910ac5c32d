"""One declarative spec per occupancy benchmark: grid and frame, class ids and names, the
free id, the ignore rule, masks, how per-class IoU and the means are computed, the class
sets, and the ground-truth layout. The readers (:mod:`dego.evaluation.layouts`), the
scoring loop (:mod:`dego.evaluation.run`) and the report take a :class:`Benchmark`; adding
a benchmark is a new spec (and, for a new file layout, a reader), never a branch in the
scoring loop.

Every rule below was read from the official metric code named in ``official`` (see
docs/evaluation.md, one section per benchmark, and docs/validation.md for the runs of the
official scripts on dego's fixtures).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from types import MappingProxyType

from dego._typing import typechecked
from dego.classes import CLASS_GROUPS, CLASS_NAMES, PROTOCOL_CLASSES
from dego.grid import VoxelGrid
from dego.metrics.report import AVERAGING_RULES

PER_CLASS_RULES = ("ratio", "absent-is-one-float32", "sample-mean", "epsilon")
"""How a voxel protocol turns pooled counts into per-class IoU:

- ``"ratio"``: ``tp / (tp + fp + fn)`` in float64, NaN for 0/0 (Occ3D, OpenOccupancy);
- ``"absent-is-one-float32"``: the same in float32, 1 for a class without ground truth
  (GaussianFormer's ``MeanIoU``, whose counters are float32 CUDA tensors);
- ``"sample-mean"``: the counts divided by the number of samples first, then the ratio
  (SurroundOcc averages the per-sample count arrays with ``np.mean(0)``);
- ``"epsilon"``: ``tp / (tp + fp + fn + 1e-5)`` (MonoScene's ``SSCMetrics``)."""

AVERAGING = AVERAGING_RULES
"""How per-class IoU becomes mIoU (:data:`dego.metrics.report.AVERAGING_RULES`)."""

MAVE_VARIANTS = ("dataset", "server")
"""OpenOcc v2's two official RayIoU / mAVE scripts: ``"dataset"``
(``projects/mmdet3d_plugin/datasets/ray_metrics.py``: float32 distances and flow, mAVE
over true-positive rays, the definition in the challenge README; the default) and
``"server"`` (``tools/ray_iou/ray_casting.py`` + ``metric.py``, the submission path:
distances and flow stored as float16, and mAVE over every non-free ray of each sample in
which the class has a true positive)."""


@dataclasses.dataclass(frozen=True)
class VoxelProtocol:
    """A voxel IoU protocol of a benchmark.

    Attributes:
        name: its key in reports (``"occ3d"``, ``"weak"``, ...).
        summary: one line: what it is, after whose code.
        classes: the class ids averaged into mIoU.
        class_sets: further named means over the same per-class IoU (InsM, ScnM, HCM,
            Waymo's 14 classes without motorcycle, ...).
        removed_classes: GT classes whose voxels are dropped before counting.
        masks: names of the GT masks ANDed into the evaluated voxels (empty: every voxel
            but the ignored ones).
        per_class: one of :data:`PER_CLASS_RULES`.
        averaging: one of :data:`AVERAGING`.
    """

    name: str
    summary: str
    classes: tuple[int, ...]
    class_sets: Mapping[str, tuple[int, ...]] = dataclasses.field(
        default_factory=lambda: MappingProxyType({})
    )
    removed_classes: tuple[int, ...] = ()
    masks: tuple[str, ...] = ()
    per_class: str = "ratio"
    averaging: str = "nanmean"


@dataclasses.dataclass(frozen=True)
class RayProtocol:
    """RayIoU (SparseOcc's rays and origins) and, where the benchmark has flow, mAVE.

    Attributes:
        class_sets: named class sets averaged into RayIoU; the first is the headline.
        thresholds: distance thresholds in metres.
        flow_classes: classes whose velocity error is averaged into mAVE (empty: no mAVE).
        mave_threshold: the distance threshold whose true positives mAVE uses.
    """

    class_sets: Mapping[str, tuple[int, ...]]
    thresholds: tuple[float, ...] = (1.0, 2.0, 4.0)
    flow_classes: tuple[int, ...] = ()
    mave_threshold: float = 2.0


@dataclasses.dataclass(frozen=True)
class Benchmark:
    """An occupancy benchmark as data (see the module docstring).

    Attributes:
        name: its ``--benchmark`` name.
        description: one line for ``dego eval --benchmarks``.
        grid: the evaluated grid (shape, voxel size, range).
        frame: the coordinate frame of the grid, in words.
        class_names: names by label id, the free label included.
        free_label: the empty label in the scored label space.
        stored_free: the value files store for free when it is not ``free_label``
            (Occ3D-Waymo stores 23 and remaps it to 15 in ground truth and predictions).
        ignore_label: the GT value that is never scored (255), or ``None``.
        layout: the ground-truth layout, a key of ``dego.evaluation.layouts.LAYOUTS``.
        voxel: the voxel protocols, in report order.
        ray: RayIoU (and mAVE), or ``None``.
        official: the official metric code (repository and files).
        prediction: what a prediction file holds, in words.
        logits: predictions may be logits on a coarser grid, upsampled as the official
            code does (trilinear, ``align_corners=False``) before the argmax.
        nuscenes: samples are nuScenes keyframes (an infos file or the nuScenes tables
            give the samples' order and the ray origins).
    """

    name: str
    description: str
    grid: VoxelGrid
    frame: str
    class_names: tuple[str, ...]
    free_label: int
    layout: str
    voxel: tuple[VoxelProtocol, ...]
    official: str
    prediction: str
    stored_free: int | None = None
    ignore_label: int | None = None
    ray: RayProtocol | None = None
    logits: bool = False
    nuscenes: bool = False

    @property
    def num_classes(self) -> int:
        """C: labels including free."""
        return len(self.class_names)

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.grid.shape

    def protocol(self, name: str) -> VoxelProtocol:
        for protocol in self.voxel:
            if protocol.name == name:
                return protocol
        raise KeyError(name)

    def label_range(self) -> str:
        """The labels a file of this benchmark may hold, in words."""
        text = f"0..{self.num_classes - 1} ({self.free_label} = free"
        if self.stored_free is not None:
            text += f", stored as {self.stored_free}"
        return text + ")"

    def rules(self) -> list[str]:
        """The report header: every rule that decides the numbers, one per line."""
        lower, upper = self.grid.lower, self.grid.upper
        size = self.grid.voxel_size
        x, y, z = self.grid.shape
        lines = [
            f"benchmark: {self.name} ({self.official})",
            f"grid: {x} x {y} x {z} at {_num(size[0])} m over "
            f"[{', '.join(_num(v) for v in (*lower, *upper))}], frame: {self.frame}",
            f"labels: {self.label_range()}"
            + ("" if self.ignore_label is None else f"; GT {self.ignore_label} ignored"),
        ]
        for protocol in self.voxel:
            mask = " AND ".join(protocol.masks) if protocol.masks else "none"
            removed = (
                f"; GT {', '.join(map(str, protocol.removed_classes))} removed"
                if protocol.removed_classes
                else ""
            )
            lines.append(
                f"voxel protocol {protocol.name}: mask {mask}{removed}; per-class IoU "
                f"{protocol.per_class}; mIoU = {protocol.averaging} over "
                f"{_ids(protocol.classes)} ({len(protocol.classes)} classes)"
            )
            for set_name, ids in protocol.class_sets.items():
                lines.append(f"  {set_name}: {protocol.averaging} over {_ids(ids)}")
        if self.ray is not None:
            sets = "; ".join(
                f"{name} over {_ids(ids)}" for name, ids in self.ray.class_sets.items()
            )
            lines.append(
                f"RayIoU at {', '.join(_num(t) for t in self.ray.thresholds)} m, free "
                f"{self.free_label}: {sets}"
            )
            if self.ray.flow_classes:
                lines.append(
                    f"mAVE: flow error of {_ids(self.ray.flow_classes)} at "
                    f"{_num(self.ray.mave_threshold)} m; OccScore = 0.9 RayIoU + 0.1 "
                    "max(1 - mAVE, 0)"
                )
        return lines


def _num(value: float) -> str:
    return f"{value:g}"


def _ids(ids: tuple[int, ...]) -> str:
    """``(1, 2, 3, 5)`` -> ``"1-3, 5"``."""
    runs: list[list[int]] = []
    for i in ids:
        if runs and i == runs[-1][-1] + 1:
            runs[-1].append(i)
        else:
            runs.append([i])
    return ", ".join(f"{r[0]}-{r[-1]}" if len(r) > 2 else ", ".join(map(str, r)) for r in runs)


def _sets(**sets: tuple[int, ...]) -> MappingProxyType[str, tuple[int, ...]]:
    return MappingProxyType(dict(sets))


NUSCENES_16 = CLASS_NAMES[1:17]
"""barrier .. vegetation: the 16 nuScenes-lidarseg classes SurroundOcc and OpenOccupancy
number 1..16, as Occ3D-nuScenes does."""

WAYMO_CLASS_NAMES = (
    "general_object",
    "vehicle",
    "pedestrian",
    "sign",
    "cyclist",
    "traffic_light",
    "pole",
    "construction_cone",
    "bicycle",
    "motorcycle",
    "building",
    "vegetation",
    "tree_trunk",
    "road",
    "walkable",
    "free",
)
"""Occ3D-Waymo labels 0..14 as the Occ3D README lists them, and free (15; stored as 23).
(``occ_metrics.py`` prints ids 2..4 in another order; the README and ``tools/eval_waymo.py``
agree on this one.)"""

OPENOCC_CLASS_NAMES = (
    "car",
    "truck",
    "trailer",
    "bus",
    "construction_vehicle",
    "bicycle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "barrier",
    "driveable_surface",
    "other_flat",
    "sidewalk",
    "terrain",
    "manmade",
    "vegetation",
    "free",
)
"""OpenOcc v2 labels (OccNet's ``occ_class_names``): 0 car .. 15 vegetation, 16 free; no
``others``."""

NUPLAN_CLASS_NAMES = (
    "empty",
    "background",
    "vehicle",
    "bicycle",
    "pedestrian",
    "traffic_cone",
    "barrier",
    "czone_sign",
    "generic_object",
)
"""NuPlan-Occ labels (UniScene's ``nuplan_class_names``): 0 empty .. 8 generic_object."""

_NUSCENES_GRID = VoxelGrid((-50.0, -50.0, -5.0), (50.0, 50.0, 3.0), 0.5)
_WAYMO_CLASSES = tuple(range(15))

BENCHMARKS: MappingProxyType[str, Benchmark] = MappingProxyType(
    {
        b.name: b
        for b in (
            Benchmark(
                name="occ3d-nuscenes",
                description="Occ3D-nuScenes (CVPR 2023 challenge): 200x200x16 at 0.4 m, "
                "camera mask, mIoU over 17 classes (occ3d) and 15 (weak), RayIoU",
                grid=VoxelGrid.occ3d(),
                frame="ego",
                class_names=CLASS_NAMES,
                free_label=17,
                layout="occ3d",
                voxel=(
                    VoxelProtocol(
                        "occ3d",
                        "the Occ3D devkit's Metric_mIoU, camera mask",
                        PROTOCOL_CLASSES["occ3d"],
                        MappingProxyType(dict(CLASS_GROUPS)),
                        masks=("mask_camera",),
                    ),
                    VoxelProtocol(
                        "weak",
                        "GaussianFlowOcc / DeGO: others and other_flat removed",
                        PROTOCOL_CLASSES["weak"],
                        MappingProxyType(dict(CLASS_GROUPS)),
                        removed_classes=(0, 12),
                        masks=("mask_camera",),
                    ),
                ),
                ray=RayProtocol(
                    _sets(
                        **{
                            "17 classes (SparseOcc, GaussianFlowOcc's published)": tuple(range(17)),
                            "15 classes (the weak set)": PROTOCOL_CLASSES["weak"],
                        }
                    )
                ),
                official="Occ3D devkit occ_metrics.py; SparseOcc loaders/ray_metrics.py",
                prediction="(200, 200, 16) integer labels 0..17",
                nuscenes=True,
            ),
            Benchmark(
                name="occ3d-waymo",
                description="Occ3D-Waymo: 200x200x16 at 0.4 m, infov AND camera mask, free "
                "23 -> 15, mIoU over 15 classes (and 14 without motorcycle)",
                grid=VoxelGrid.occ3d(),
                frame="vehicle (Waymo)",
                class_names=WAYMO_CLASS_NAMES,
                free_label=15,
                stored_free=23,
                ignore_label=255,
                layout="waymo",
                voxel=(
                    VoxelProtocol(
                        "occ3d-waymo",
                        "Occ3D's Metric_mIoU for Waymo (use_infov_mask, use_image_mask)",
                        _WAYMO_CLASSES,
                        _sets(
                            **{
                                "14 classes (no motorcycle)": tuple(
                                    c for c in _WAYMO_CLASSES if c != 9
                                )
                            }
                        ),
                        masks=("infov", "final_voxel_state"),
                    ),
                ),
                official="Tsinghua-MARS-Lab/Occ3D projects/mmdet3d_plugin/datasets/"
                "occ_metrics.py (Metric_mIoU, FREE_LABEL=23)",
                prediction="(200, 200, 16) integer labels 0..15, or 23 for free",
            ),
            Benchmark(
                name="surroundocc",
                description="SurroundOcc: sparse (x, y, z, label) rows, 200x200x16 at 0.5 m, "
                "0 empty, noise ignored, mIoU = mean over 1-16 of per-sample-mean counts",
                grid=_NUSCENES_GRID,
                frame="LIDAR_TOP",
                class_names=("empty", *NUSCENES_16),
                free_label=0,
                ignore_label=255,
                layout="surroundocc",
                voxel=(
                    VoxelProtocol(
                        "surroundocc",
                        "SurroundOcc's evaluation_semantic (label 0 rows -> 255, ignored)",
                        tuple(range(1, 17)),
                        per_class="sample-mean",
                        averaging="mean",
                    ),
                ),
                official="weiyithu/SurroundOcc evaluation_metrics.py, "
                "nuscenes_occupancy_dataset.py, pipelines/loading.py",
                prediction="(200, 200, 16) integer labels 0..16 (0 = empty)",
            ),
            Benchmark(
                name="surroundocc-gf",
                description="SurroundOcc labels scored GaussianFormer's way: empty 17, noise "
                "voxels removed, float32 counts, a class without GT scores 1",
                grid=_NUSCENES_GRID,
                frame="LIDAR_TOP",
                class_names=("noise", *NUSCENES_16, "empty"),
                free_label=17,
                layout="surroundocc",
                voxel=(
                    VoxelProtocol(
                        "gaussianformer",
                        "GaussianFormer's MeanIoU (class_indices 1..16, empty 17, "
                        "occ_mask = label != 0)",
                        tuple(range(1, 17)),
                        removed_classes=(0,),
                        per_class="absent-is-one-float32",
                        averaging="mean",
                    ),
                ),
                official="huang-yh/GaussianFormer misc/metric_util.py (MeanIoU), eval.py, "
                "dataset/transform_3d.py",
                prediction="(200, 200, 16) integer labels 0..17 (17 = empty)",
            ),
            Benchmark(
                name="openoccupancy",
                description="OpenOccupancy: sparse (z, y, x, label) rows with majority vote, "
                "512x512x40 at 0.2 m, noise ignored, SSC mIoU over 1-16 and SC IoU",
                grid=VoxelGrid((-51.2, -51.2, -5.0), (51.2, 51.2, 3.0), 0.2),
                frame="LIDAR_TOP",
                class_names=("empty", *NUSCENES_16),
                free_label=0,
                ignore_label=255,
                layout="openoccupancy",
                voxel=(
                    VoxelProtocol(
                        "ssc",
                        "OpenOccupancy's OccNet.evaluation_semantic + cm_to_ious",
                        tuple(range(1, 17)),
                        averaging="sequential-mean",
                    ),
                ),
                official="JeffWang987/OpenOccupancy occnet.py (evaluation_semantic), "
                "utils/formating.py, pipelines/loading.py (LoadOccupancy)",
                prediction="(512, 512, 40) integer labels 0..16, or (17, X, Y, Z) logits "
                "upsampled trilinearly to the grid",
                logits=True,
            ),
            Benchmark(
                name="openocc-v2",
                description="OpenOcc v2 (CVPR 2024 challenge): Occ3D grid, ids 0 car..15 "
                "vegetation, 16 free, RayIoU at 1/2/4 m, mAVE, OccScore",
                grid=VoxelGrid.occ3d(),
                frame="ego",
                class_names=OPENOCC_CLASS_NAMES,
                free_label=16,
                layout="openocc",
                voxel=(),
                ray=RayProtocol(
                    _sets(**{"16 classes": tuple(range(16))}),
                    flow_classes=tuple(range(8)),
                ),
                official="OpenDriveLab/OccNet (challenge): projects/mmdet3d_plugin/"
                "datasets/ray_metrics.py and tools/ray_iou/{ray_casting,metric}.py",
                prediction="(200, 200, 16) integer labels 0..16 and, for mAVE, flow "
                "(200, 200, 16, 2)",
                nuscenes=True,
            ),
            Benchmark(
                name="nuplan-occ",
                description="NuPlan-Occ (UniScene, MonoScene protocol): 400x400x32 files, "
                "val z shift, front 200x200x32 crop at 0.25 m, mIoU over 8 classes",
                grid=VoxelGrid((0.0, -25.0, -5.0), (50.0, 25.0, 3.0), 0.25),
                frame="ego (front half)",
                class_names=NUPLAN_CLASS_NAMES,
                free_label=0,
                ignore_label=255,
                layout="nuplan",
                voxel=(
                    VoxelProtocol(
                        "ssc",
                        "MonoScene's SSCMetrics (iou_ssc with +1e-5, completion IoU)",
                        tuple(range(1, 9)),
                        per_class="epsilon",
                        averaging="mean",
                    ),
                ),
                official="UniScene SOP/monoscene: data/nuplan/nuplan_dataset.py, "
                "MonoScene loss/sscMetrics.py",
                prediction="(200, 200, 32) integer labels 0..8 on the evaluated crop",
            ),
        )
    }
)
"""Every benchmark ``dego eval --benchmark`` scores, by name."""

DEFAULT_BENCHMARK = "occ3d-nuscenes"

OCC3D_TO_OPENOCC: tuple[int, ...] = (16, 9, 5, 3, 0, 4, 6, 7, 8, 2, 1, 10, 11, 12, 13, 14, 15, 16)
"""OpenOcc v2 id of each Occ3D-nuScenes id 0..17 (``OCC3D_TO_OPENOCC[occ3d_id]``): the
same nuScenes classes renumbered; Occ3D's ``others`` (0), which OpenOcc v2 lacks, and free
(17) become free (16)."""


@typechecked
def get_benchmark(name: str) -> Benchmark:
    """The :class:`Benchmark` called ``name``; a ``ValueError`` listing them otherwise."""
    try:
        return BENCHMARKS[name]
    except KeyError:
        raise ValueError(
            f"benchmark: no benchmark {name!r}; expected one of {list(BENCHMARKS)} "
            "(dego eval --benchmarks lists them)"
        ) from None


def benchmark_list() -> str:
    """``dego eval --benchmarks``: one line per benchmark."""
    width = max(len(n) for n in BENCHMARKS)
    return "\n".join(f"{b.name:<{width}}  {b.description}" for b in BENCHMARKS.values())


__all__ = [
    "AVERAGING",
    "BENCHMARKS",
    "DEFAULT_BENCHMARK",
    "MAVE_VARIANTS",
    "OCC3D_TO_OPENOCC",
    "PER_CLASS_RULES",
    "Benchmark",
    "RayProtocol",
    "VoxelProtocol",
    "benchmark_list",
    "get_benchmark",
]
