"""RayIoU (SparseOcc): ray-based occupancy IoU at 1, 2 and 4 m, in pure torch.

LiDAR-like rays are cast from up to 8 origins through the predicted and the ground-truth
label grids (:func:`dego.raycast.cast_rays`). Only rays whose ground-truth hit is not
free are scored: a ray is a true positive for class c at threshold t when both hits
have label c and ``|d_pred - d_gt| < t`` (strict). Counts are pooled over the data set:
``IoU[t, c] = tp / (gt_cnt + pred_cnt - tp)``, RayIoU@t is the nanmean over the 17
non-free classes, RayIoU the mean over thresholds. Every rule is SparseOcc's
(listed in docs/rayiou.md, "The rules").
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from dego import _serialization, _units
from dego._compile import eager_only
from dego._geometry import rotation_matrices
from dego._policy import check_finite, check_memory, run_checks
from dego._typing import check_tensor_fields, typechecked
from dego.classes import FREE_LABEL, NUM_CLASSES
from dego.grid import VoxelGrid
from dego.metrics.confusion import as_label_tensor, labels_in_range
from dego.metrics.counts import CountingMetric, class_names
from dego.metrics.report import _nanmean  # numpy's summation order, as SparseOcc / OccNet
from dego.raycast import cast_bytes, cast_product, cast_sizes, generate_lidar_rays

DEFAULT_THRESHOLDS = (1.0, 2.0, 4.0)


def pose_matrices(name: str, pose: Tensor) -> Tensor:
    """``(F, 4, 4)`` float64 from ``(F, 4, 4)`` matrices or ``(F, 7)`` translation + wxyz."""
    pose = pose.double()
    if not bool(torch.isfinite(pose).all()):
        raise ValueError(f"{name}: {int((~torch.isfinite(pose)).sum())} values are not finite")
    if pose.ndim == 3 and pose.shape[-2:] == (4, 4):
        return pose
    if pose.ndim == 2 and pose.shape[-1] == 7:
        matrix = torch.eye(4, dtype=torch.float64).repeat(pose.shape[0], 1, 1)
        matrix[:, :3, :3] = rotation_matrices(pose[:, 3:])
        matrix[:, :3, 3] = pose[:, :3]
        return matrix
    raise ValueError(
        f"{name}: expected (F, 4, 4) matrices or (F, 7) translation + wxyz, got {tuple(pose.shape)}"
    )


@typechecked
def lidar_origins(
    ego2global: Tensor,
    lidar2ego: Tensor,
    reference_index: int,
    max_origins: int = 8,
    xy_limit: float = 39.0,
) -> Float[Tensor, "K 3"]:
    """RayIoU ray origins in the reference frame's ego coordinates (SparseOcc's rule).

    Every frame's LiDAR position, ``inv(G_ref L_ref) G_f L_f`` (G = ego2global, L =
    lidar2ego), is taken to the reference LiDAR frame and then to the reference ego frame
    with ``L_ref``; origins with ``|x| < xy_limit`` and ``|y| < xy_limit`` are kept (no z
    check), and if more than ``max_origins`` remain, those at indices
    ``round(linspace(0, n - 1, max_origins))``.

    Args:
        ego2global: per-frame ego poses of the scene's keyframes in temporal order,
            ``(F, 4, 4)`` or ``(F, 7)`` (translation, then wxyz quaternion).
        lidar2ego: per-frame LiDAR extrinsics, same layout and order.
        reference_index: the evaluated frame.

    Returns:
        ``(K, 3)`` float64 origins, K <= ``max_origins``.
    """
    g, lid = pose_matrices("ego2global", ego2global), pose_matrices("lidar2ego", lidar2ego)
    frames = g.shape[0]
    if lid.shape[0] != frames:
        raise ValueError(f"lidar2ego: {lid.shape[0]} frames, ego2global has {frames}")
    if not -frames <= reference_index < frames:
        raise IndexError(f"reference_index: {reference_index} is out of range for {frames}")
    if max_origins < 1:
        raise ValueError(f"max_origins: expected an int >= 1, got {max_origins}")
    ref = reference_index % frames
    sensor = g @ lid  # (F, 4, 4) lidar -> global
    # every frame's lidar origin in the reference lidar frame, rounded to float32 as the
    # reference does; the reference frame's own origin is exactly 0
    relative = (torch.linalg.inv(sensor[ref]) @ sensor)[:, :3, 3].float().double()
    relative[ref] = 0
    origins = relative @ lid[ref, :3, :3].T + lid[ref, :3, 3]  # reference ego frame
    keep = (origins[:, 0].abs() < xy_limit) & (origins[:, 1].abs() < xy_limit)
    origins = origins[keep]
    if origins.shape[0] > max_origins:
        picked = np.round(np.linspace(0, origins.shape[0] - 1, max_origins)).astype(np.int64)
        origins = origins[torch.from_numpy(picked)]
    return origins


@dataclasses.dataclass(frozen=True, eq=False)
class RayIoUReport(_serialization.DictForm):
    """RayIoU scores (fractions; NaN for classes absent from gt and predictions). Printed
    (:meth:`table`) in percent, like every dego report.

    Attributes:
        thresholds: the distance thresholds in metres.
        per_class: ``(len(thresholds), C)`` float64 IoU of every label (free included, NaN).
        at: RayIoU per threshold (nanmean over ``class_ids``).
        rayiou: mean of ``at`` (SparseOcc's nanmean over the whole array).
        class_ids: the classes averaged.
        class_names: names of all C labels.
    """

    def __post_init__(self) -> None:
        check_tensor_fields(self)

    thresholds: tuple[float, ...]
    per_class: Tensor
    at: tuple[float, ...]
    rayiou: float
    class_ids: tuple[int, ...]
    class_names: tuple[str, ...]

    def as_dict(self, *, percent: bool = False) -> dict[str, float]:
        """``{"rayiou", "rayiou@<t>", "rayiou@<t>/<class>"}`` for loggers, fractions (like
        :meth:`OccupancyReport.as_dict`). ``percent=True`` (deprecated) rounds percentages
        to 2 decimals under the same keys: print :meth:`table` for the papers' numbers.
        """
        if percent:
            _units.warn_percent_keys("RayIoUReport.as_dict(percent=True)")

        def fmt(v: float) -> float:
            return round(_units.percent(v), 2) if percent else v

        out = {"rayiou": fmt(self.rayiou)}
        for i, t in enumerate(self.thresholds):
            out[f"rayiou@{t:g}"] = fmt(self.at[i])
            for c in self.class_ids:
                out[f"rayiou@{t:g}/{self.class_names[c]}"] = fmt(float(self.per_class[i, c]))
        return out

    def table(self, percent: bool = True) -> str:
        """A text table of per-class IoU at every threshold and the means, in percent with
        2 decimals like every dego table (``percent=False``: fractions with 3 decimals,
        SparseOcc's printout). The first line names the unit; '-' for absent classes."""

        def fmt(value: float) -> str:
            return _fmt(_units.percent(value), ".2f") if percent else _fmt(value)

        unit = "percent" if percent else "fractions"
        head = " | ".join(f"{'IoU@' + format(t, 'g'):>7}" for t in self.thresholds)
        lines = [
            f"RayIoU in {unit}, per class at each distance threshold (m)",
            f"| {'class':<22} | {head} |",
            f"|{'-' * 24}|" + "|".join("-" * 9 for _ in self.thresholds) + "|",
        ]
        for c in self.class_ids:
            values = " | ".join(
                fmt(float(self.per_class[i, c])) for i in range(len(self.thresholds))
            )
            lines.append(f"| {self.class_names[c]:<22} | {values} |")
        means = " | ".join(fmt(v) for v in self.at)
        lines.append(f"| {'MEAN':<22} | {means} |")
        lines.append(f"RayIoU {fmt(self.rayiou).strip()} (mean over {len(self.class_ids)} classes)")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.table()


def _fmt(value: float, spec: str = ".3f") -> str:
    return f"{'-':>7}" if math.isnan(value) else f"{value:>7{spec}}"


def _masked_bincount(labels: Tensor, mask: Tensor, num_classes: int) -> Tensor:
    """``(C,)`` int64 counts of ``labels`` (in ``0..C-1``) where ``mask`` is True."""
    counts = torch.zeros(num_classes, dtype=torch.int64, device=labels.device)
    return counts.scatter_add_(0, labels, mask.to(torch.int64))


@dataclasses.dataclass(frozen=True, eq=False)
class RayIoUSpec:
    """A validated RayIoU configuration and its two steps, shared by :class:`RayIoU` and
    ``dego.compat.torchmetrics.RayIoUMetric``: casting and counting one sample
    (:meth:`counts`) and summarising pooled counts (:meth:`report`)."""

    thresholds: tuple[float, ...]
    num_classes: int
    free_label: int
    class_ids: tuple[int, ...]
    grid: VoxelGrid
    rays: Tensor  # (R, 3) float32, on the CPU
    rays_digest: str

    @classmethod
    def make(
        cls,
        thresholds: Sequence[float],
        num_classes: int,
        free_label: int,
        class_ids: Sequence[int] | None,
        grid: VoxelGrid | None,
        rays: Tensor | None,
    ) -> RayIoUSpec:
        """Check the arguments of :class:`RayIoU` (errors name them)."""
        thresholds = tuple(float(t) for t in thresholds)
        if not thresholds or any(not math.isfinite(t) or t <= 0 for t in thresholds):
            raise ValueError(f"thresholds: expected positive distances, got {thresholds!r}")
        if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 2:
            raise ValueError(f"num_classes: expected an int >= 2, got {num_classes!r}")
        if not 0 <= free_label < num_classes:
            raise ValueError(f"free_label: {free_label} must lie in 0..{num_classes - 1}")
        if class_ids is None:
            class_ids = [c for c in range(num_classes) if c != free_label]
        class_ids = tuple(int(c) for c in class_ids)
        if not class_ids or any(not 0 <= c < num_classes or c == free_label for c in class_ids):
            raise ValueError(
                f"class_ids: expected non-free ids in 0..{num_classes - 1}, got {class_ids!r}"
            )
        if rays is None:
            rays = generate_lidar_rays()
        if not isinstance(rays, Tensor) or not rays.is_floating_point():
            kind = rays.dtype if isinstance(rays, Tensor) else type(rays).__name__
            raise TypeError(f"rays: expected a floating (R, 3) tensor of directions, got {kind}")
        if rays.ndim != 2 or rays.shape[-1] != 3 or rays.shape[0] == 0:
            raise ValueError(f"rays: expected (R, 3) directions, got {tuple(rays.shape)}")
        check_finite("rays", rays)
        rays = rays.detach().float().cpu()  # SparseOcc's rays are float32
        zero = (rays == 0).all(-1)
        if bool(zero.any()):
            raise ValueError(
                f"rays: {int(zero.sum())} of {rays.shape[0]} directions are zero vectors "
                "(or underflow float32); expected non-zero directions"
            )
        return cls(
            thresholds=thresholds,
            num_classes=num_classes,
            free_label=free_label,
            class_ids=class_ids,
            grid=VoxelGrid.occ3d() if grid is None else grid,
            rays=rays,
            # identifies the ray pattern in the configuration (merge / load_state_dict check it)
            rays_digest=hashlib.sha256(rays.numpy().tobytes()).hexdigest()[:16],
        )

    @property
    def class_names(self) -> tuple[str, ...]:
        return class_names(self.num_classes)

    def config(self) -> dict[str, Any]:
        """The configuration as plain data (compared by merge / load_state_dict, saved)."""
        return {
            "thresholds": list(self.thresholds),
            "num_classes": self.num_classes,
            "free_label": self.free_label,
            "class_ids": list(self.class_ids),
            "grid": [list(self.grid.lower), list(self.grid.upper), list(self.grid.voxel_size)],
            "rays": [int(self.rays.shape[0]), self.rays_digest],
        }

    def count_shapes(self) -> dict[str, tuple[int, ...]]:
        """The shapes of the int64 counts, by name (the state of both metric classes)."""
        c = self.num_classes
        return {"gt_count": (c,), "pred_count": (c,), "true_positives": (len(self.thresholds), c)}

    def check_labels(self, name: str, labels: Tensor | np.ndarray) -> Tensor:
        if isinstance(labels, np.ndarray):
            labels = as_label_tensor(name, labels) if labels.dtype.kind in "iu" else labels
        if (
            not isinstance(labels, Tensor)
            or labels.is_floating_point()
            or labels.is_complex()
            or labels.dtype == torch.bool
        ):
            kind = (
                labels.dtype if isinstance(labels, Tensor | np.ndarray) else type(labels).__name__
            )
            raise TypeError(f"{name}: expected an integer label grid, got {kind}")
        labels = as_label_tensor(name, labels)  # any integer dtype
        if tuple(labels.shape) != self.grid.shape:
            raise ValueError(
                f"{name}: expected shape {self.grid.shape} (the grid), got {tuple(labels.shape)}"
            )
        if labels.numel() and not labels_in_range(labels, self.num_classes):
            c = self.num_classes

            def error() -> Exception:
                low, high = (int(v) for v in torch.aminmax(labels))
                bad = low if low < 0 else high
                return ValueError(
                    f"{name}: labels must lie in 0..{c - 1}, found {bad} "
                    f"(values {low}..{high}); RayIoU has no ignore label"
                )

            ok = ((labels >= 0) & (labels < c)).all()
            run_checks([(ok, f"{name}: labels must lie in 0..{c - 1}", error)])
        return labels

    # Ray traversal is data-dependent: under torch.compile a sample is cast and scored
    # eagerly, as one graph break.
    @eager_only
    def counts(
        self,
        pred: Tensor | np.ndarray,
        gt: Tensor | np.ndarray,
        origins: Tensor | np.ndarray,
        rays: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """``gt_count (C,)``, ``pred_count (C,)`` and ``true_positives (T, C)`` of one
        sample, on ``gt``'s device (the checks and errors of :meth:`RayIoU.update`).
        ``rays``: this configuration's rays already on a device (default: ``self.rays``)."""
        pred, gt = self.check_labels("pred", pred), self.check_labels("gt", gt)
        if isinstance(origins, np.ndarray):
            origins = torch.from_numpy(np.ascontiguousarray(origins))
        if not isinstance(origins, Tensor):
            raise TypeError(
                f"origins: expected a (K, 3) tensor or array, got {type(origins).__name__}"
            )
        if origins.dtype == torch.bool or origins.is_complex():
            raise TypeError(f"origins: expected real coordinates, got {origins.dtype}")
        if origins.ndim != 2 or origins.shape[-1] != 3:
            raise ValueError(f"origins: expected (K, 3), got {tuple(origins.shape)}")
        if origins.shape[0] == 0:
            raise ValueError("origins: need at least one origin, got K = 0")
        if origins.is_floating_point():
            check_finite("origins", origins)
        # both casts' results, then per ray: distances and labels gathered, the error and a
        # bool per threshold
        rays = self.rays if rays is None else rays
        n, t = origins.shape[0] * rays.shape[0], len(self.thresholds)
        per_ray = 2 * 12 + 48 + 2 * t
        check_memory("RayIoU.update", cast_bytes(n, self.grid, per_ray), cast_sizes(n, self.grid))
        device = gt.device
        pred = pred.to(device)
        # SparseOcc's convention: float64 origins, float32 rays
        origins, rays = origins.to(device, torch.float64), rays.to(device, torch.float32)
        grid, free = self.grid, self.free_label
        what = "RayIoU.update"
        # one traversal for both grids: they share every ray
        (gt_distance, pred_distance), (gt_label, pred_label) = cast_product(
            [gt, pred], origins, rays, grid, free, what
        )
        # Masked counts rather than boolean indexing: no data-dependent shape (compiles).
        scored = gt_label != self.free_label
        error = (pred_distance - gt_distance).abs()
        c = self.num_classes
        agree = scored & (gt_label == pred_label)
        thresholds = torch.tensor(self.thresholds, dtype=error.dtype, device=device)
        close = error[None] < thresholds[:, None]  # (thresholds, rays)
        tp = torch.stack([_masked_bincount(gt_label, agree & row, c) for row in close])
        gt_count = _masked_bincount(gt_label, scored, c)
        return gt_count, _masked_bincount(pred_label, scored, c), tp

    def report(self, gt: Tensor, pred: Tensor, tp: Tensor) -> RayIoUReport:
        """The :class:`RayIoUReport` of pooled counts."""
        if int(gt.sum()) == 0:
            raise RuntimeError("compute: no scored ray yet (every gt ray hit free space?)")
        per_class = tp.double() / (gt + pred - tp).double()  # (thresholds, C)
        per_class = per_class.cpu()
        ids = list(self.class_ids)
        at = tuple(_nanmean(row[ids]) for row in per_class)
        return RayIoUReport(
            thresholds=self.thresholds,
            per_class=per_class,
            at=at,
            rayiou=_nanmean(per_class[:, ids].reshape(-1)),
            class_ids=self.class_ids,
            class_names=self.class_names,
        )


class RayIoU(CountingMetric):
    """Data-set RayIoU with a torchmetrics-style ``update / compute / reset / merge / sync``.

    Args:
        thresholds: distance thresholds in metres (SparseOcc: 1, 2, 4).
        num_classes: C, labels including free (18).
        free_label: the empty label (17).
        class_ids: the classes averaged into RayIoU (default: every label but free, i.e.
            the 17 classes SparseOcc averages, others and other_flat included).
        grid: the label grids' voxel grid (default Occ3D).
        rays: ``(R, 3)`` ray directions (default :func:`dego.raycast.generate_lidar_rays`),
            finite and non-zero, of any length; stored as float32 like SparseOcc's.
        device: where the state lives.

    State (int64 buffers): ``gt_count (C,)``, ``pred_count (C,)``, ``true_positives
    (len(thresholds), C)``, pooled over every scored ray; out of ``state_dict`` unless
    :meth:`persistent` is called. ``dego.compat.torchmetrics.RayIoUMetric`` is the same
    metric as a ``torchmetrics.Metric``.
    """

    COUNTS = ("gt_count", "pred_count", "true_positives")
    gt_count: Tensor
    pred_count: Tensor
    true_positives: Tensor
    rays: Tensor

    def __init__(
        self,
        thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
        num_classes: int = NUM_CLASSES,
        free_label: int = FREE_LABEL,
        class_ids: Sequence[int] | None = None,
        grid: VoxelGrid | None = None,
        rays: Tensor | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self._spec = RayIoUSpec.make(thresholds, num_classes, free_label, class_ids, grid, rays)
        self.register_buffer("rays", self._spec.rays.clone(), persistent=False)
        for name, shape in self._spec.count_shapes().items():
            self._add_count(name, torch.zeros(shape, dtype=torch.int64, device=device))

    # the configuration, read-only
    thresholds = property(lambda self: self._spec.thresholds, doc="Thresholds in metres.")
    num_classes = property(lambda self: self._spec.num_classes, doc="C, labels including free.")
    free_label = property(lambda self: self._spec.free_label, doc="The empty label.")
    class_ids = property(lambda self: self._spec.class_ids, doc="The classes averaged.")
    grid = property(lambda self: self._spec.grid, doc="The label grids' voxel grid.")

    @typechecked
    def update(
        self,
        pred: Tensor | np.ndarray,
        gt: Tensor | np.ndarray,
        origins: Tensor | np.ndarray,
    ) -> None:
        """Cast and score one sample.

        Args:
            pred: ``(X, Y, Z)`` predicted labels in ``0..C-1`` on the metric's grid, any
                integer dtype (uint8 as Occ3D ships them, int8 ... int64; the counts do not
                depend on it), torch or numpy.
            gt: ``(X, Y, Z)`` ground-truth labels, same grid and range.
            origins: ``(K, 3)`` ray origins in metres (ego frame; :func:`lidar_origins`);
                K >= 1, finite, any real dtype (used in float64, as SparseOcc does).
                Origins outside the grid are allowed (their rays may never enter).

        Raises:
            TypeError: bool or floating labels, bool or complex origins.
            ValueError: a wrong shape; a label outside ``0..C-1`` (named with the value;
                there is no ignore label: -1 or 255 are refused); no origin; non-finite
                origins; an estimated memory need above :func:`dego.set_memory_limit`'s
                limit (checked before casting).
        """
        gt_count, pred_count, tp = self._spec.counts(pred, gt, origins, rays=self.rays)
        self.gt_count += gt_count.to(self.gt_count.device)
        self.pred_count += pred_count.to(self.pred_count.device)
        self.true_positives += tp.to(self.true_positives.device)
        self._changed()

    def compute(self) -> RayIoUReport:
        """IoU per threshold and class, RayIoU@t and RayIoU of everything seen."""
        return self._spec.report(*self._totals())

    def _config(self) -> dict[str, Any]:
        return self._spec.config()

    def extra_repr(self) -> str:
        return f"thresholds={self.thresholds}, num_classes={self.num_classes}"


__all__ = ["DEFAULT_THRESHOLDS", "RayIoU", "RayIoUReport", "lidar_origins"]
