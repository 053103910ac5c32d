"""dego's occupancy metrics as ``torchmetrics.Metric`` subclasses, for Lightning and
``MetricCollection``.

:class:`OccupancyMetric` and :class:`RayIoUMetric` count and score with the very code of
:class:`dego.OccupancyMetrics` and :class:`dego.metrics.RayIoU` (the same checks, the same
int64 counts, the same reports); what they add is torchmetrics' machinery: states declared
with ``add_state`` (summed across ranks by torchmetrics' own sync, out of ``state_dict``
unless ``persistent(True)``), ``forward`` returning the batch's value, ``compute`` returning
tensors that ``LightningModule.log`` accepts, and :meth:`OccupancyMetric.report` returning
dego's full report of the (synced) states.

Each metric also holds a ``config_fingerprint`` state (a digest of its configuration), so
that counts made under two configurations are never silently pooled: torchmetrics' automatic
compute groups never merge two differently configured metrics (their states differ), and a
metric whose state was shared with (``MetricCollection(compute_groups=[[...]])``), merged
with (``merge_state``), synced with (another rank) or loaded from another configuration
raises ``ValueError`` naming both configurations when it computes.

torchmetrics is an optional dependency: ``pip install -e ".[torchmetrics]"`` from the clone
(``[lightning]`` adds Lightning).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

try:
    from torchmetrics import Metric
    from torchmetrics.utilities.distributed import gather_all_tensors
except ModuleNotFoundError as err:  # pragma: no cover - exercised without the extra
    raise ModuleNotFoundError(
        "dego.compat.torchmetrics needs torchmetrics: "
        'pip install -e ".[torchmetrics]" in your dego clone (or "torchmetrics>=1.3")',
        name=err.name,
    ) from err

from dego._typing import typechecked
from dego.classes import FREE_LABEL, NUM_CLASSES
from dego.grid import VoxelGrid
from dego.metrics.counts import DIGEST_BYTES as _DIGEST_BYTES
from dego.metrics.counts import check_same_identity, config_digest
from dego.metrics.occupancy import OMITTED, OccupancySpec, Omitted
from dego.metrics.rayiou import DEFAULT_THRESHOLDS, RayIoUReport, RayIoUSpec
from dego.metrics.report import OccupancyReport

_KNOWN_CONFIGS: dict[tuple[int, ...], dict[str, Any]] = {}
"""Configurations by fingerprint, to name them in errors (filled by every metric made here)."""


def _fingerprint(config: dict[str, Any]) -> tuple[int, ...]:
    """The configuration's :func:`dego.metrics.counts.config_digest` (16 ints 0..255, the
    digest ``CountingMetric.sync`` compares across ranks).

    Small values on purpose: torchmetrics compares states with ``allclose`` when it forms
    compute groups, which would not tell large integers apart.
    """
    digest = config_digest(config)
    _KNOWN_CONFIGS.setdefault(digest, config)
    return digest


def _describe(fingerprint: tuple[int, ...]) -> str:
    config = _KNOWN_CONFIGS.get(fingerprint)
    if config is None:
        return (
            f"an unknown configuration (fingerprint {bytes(fingerprint).hex()}, made in "
            "another process or loaded)"
        )
    return str(config)


def _difference(theirs: tuple[int, ...], ours: dict[str, Any]) -> str:
    """``" (protocol 'weak' vs 'occ3d')"``: where a known configuration differs, or ``""``."""
    config = _KNOWN_CONFIGS.get(theirs)
    if config is None:
        return ""
    keys = [k for k in {**config, **ours} if config.get(k) != ours.get(k)]
    return " (" + ", ".join(f"{k} {config.get(k)!r} vs {ours.get(k)!r}" for k in keys) + ")"


def _fingerprints(state: Any) -> set[tuple[int, ...]]:
    rows = torch.as_tensor(state).reshape(-1, _DIGEST_BYTES).tolist()
    return {tuple(int(v) for v in row) for row in rows}


def _fingerprint_range(stacked: Tensor) -> Tensor:
    """``dist_reduce_fx`` of ``config_fingerprint``: the first and the last (in lexicographic
    order) of every fingerprint in the stacked states. The result equals a metric's own
    ``[f, f]`` only if every state pooled into it had fingerprint ``f`` (an element-wise
    ``max`` could mix two digests into a third)."""
    rows = sorted(_fingerprints(stacked))
    return torch.tensor([rows[0], rows[-1]], dtype=stacked.dtype, device=stacked.device)


class _DegoCountsMetric(Metric):
    """What both adapters share: the int64 count states of a dego spec, the configuration
    fingerprint, the choice of ``value`` and ``report()``."""

    is_differentiable = False
    higher_is_better = True
    # Every count is a sum over samples (and the fingerprint's reduction is associative), so
    # torchmetrics' forward updates once and merges the batch's state into the global one.
    full_state_update = False
    plot_lower_bound = 0.0
    plot_upper_bound = 1.0

    config_fingerprint: Tensor
    _DICT_VALUES: Mapping[str, Callable[[str], bool]] = {}
    _REPR_KEYS: tuple[str, ...] = ()

    def _setup(
        self,
        spec: Any,
        value: str,
        keys: Sequence[str],
        default: str,
        device: torch.device | str | None,
    ) -> None:
        self._spec = spec
        choices = {*keys, *self._DICT_VALUES, "all"}
        if not isinstance(value, str) or value not in choices:
            named = [*sorted(self._DICT_VALUES), "all"]
            raise ValueError(
                f"value: expected {default!r} (the default), "
                + ", ".join(repr(v) for v in named)
                + f" or a key of the report's as_dict() ({', '.join(list(keys)[:4])}, ...), "
                f"got {value!r}"
            )
        self.value = value
        self._dego_config = {"metric": type(self).__name__, **spec.config()}
        self._own_fingerprint = _fingerprint(self._dego_config)
        # The first state: torchmetrics < 1.4 compares only the first state of two metrics
        # when it forms compute groups.
        self.add_state(
            "config_fingerprint",
            torch.tensor([self._own_fingerprint] * 2, dtype=torch.int64),
            dist_reduce_fx=_fingerprint_range,
            persistent=False,
        )
        for name, shape in spec.count_shapes().items():
            self.add_state(
                name, torch.zeros(shape, dtype=torch.int64), dist_reduce_fx="sum", persistent=False
            )
        if device is not None:
            self.to(device)

    # -- configuration checks -----------------------------------------------------------
    def _sync_dist(
        self, dist_sync_fn: Callable = gather_all_tensors, process_group: Any = None
    ) -> None:
        """torchmetrics' sync, after the check that every rank holds the same metric: two
        ranks with different metrics (an OccupancyMetric here, a RayIoUMetric there) have
        states of other names and shapes, on which gloo's gather aborts; now every rank
        raises ``ValueError`` naming both first
        (:func:`dego.metrics.counts.check_same_identity`)."""
        group = process_group or self.process_group
        counts = {n: list(getattr(self, n).shape) for n in self._spec.count_shapes()}
        identity = {"metric": type(self).__name__, "config": self._dego_config, "counts": counts}
        device = self.config_fingerprint.device
        if torch.distributed.get_backend(group) == "nccl" and device.type != "cuda":
            device = torch.device("cuda", torch.cuda.current_device())
        check_same_identity(identity, group, device)
        super()._sync_dist(dist_sync_fn, process_group)

    def _check_config(self) -> None:
        seen = _fingerprints(self.config_fingerprint)
        if seen == {self._own_fingerprint}:
            return
        others = [f for f in sorted(seen) if f != self._own_fingerprint]
        raise ValueError(
            f"{type(self).__name__}: counts of another configuration were pooled into this "
            f"metric's state{''.join(_difference(f, self._dego_config) for f in others)}: "
            f"{'; '.join(_describe(f) for f in others)} into {self._dego_config}. Metrics that "
            "share state (one MetricCollection compute group, merge_state, the ranks of a "
            "sync) must have the same configuration: put differently configured dego metrics "
            "in separate compute groups"
        )

    def _load_from_state_dict(
        self,
        state_dict: dict[str, Any],
        prefix: str,
        local_metadata: dict[str, Any],
        strict: bool,
        missing_keys: list[str],
        unexpected_keys: list[str],
        error_msgs: list[str],
    ) -> None:
        # Checked before torchmetrics loads any state, so that a refused state_dict leaves
        # this metric as it was (dego's rule; see CountingMetric).
        key = prefix + "config_fingerprint"
        if key in state_dict:
            saved = _fingerprints(state_dict[key])
            if saved != {self._own_fingerprint}:
                described = "; ".join(_describe(f) for f in sorted(saved))
                if any(self._persistent.values()):
                    raise ValueError(
                        f"state_dict: saved configuration {described} differs from "
                        f"{self._dego_config}"
                    )
                warnings.warn(
                    f"state_dict: saved configuration {described} differs from "
                    f"{self._dego_config}; the saved counts are ignored (the states are not "
                    "persistent; call .persistent(True) to make this an error)",
                    UserWarning,
                    stacklevel=4,
                )
                for name in self._defaults:
                    state_dict.pop(prefix + name, None)
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )

    def _apply(self, fn: Callable, exclude_state: Sequence[str] = ()) -> torch.nn.Module:
        # set_dtype changes the dtype of the values compute() returns; the counts stay int64
        if self._dtype_convert:
            exclude_state = (*exclude_state, *self._defaults)
        return super()._apply(fn, exclude_state=exclude_state)

    # -- results --------------------------------------------------------------------------
    def _select(self, values: dict[str, float]) -> Tensor | dict[str, Tensor]:
        def as_tensor(v: float) -> Tensor:
            return torch.tensor(v, dtype=self.dtype, device=self.device)

        if self.value == "all":
            return {k: as_tensor(v) for k, v in values.items()}
        if self.value in self._DICT_VALUES:
            keep = self._DICT_VALUES[self.value]
            return {k: as_tensor(v) for k, v in values.items() if keep(k)}
        return as_tensor(values[self.value])

    def _with_synced_states(self, fn: Callable[[], Any]) -> Any:
        """``fn()`` on the states synced across ranks, as ``compute`` sees them."""
        if self._is_synced or not self.sync_on_compute:
            return fn()
        with self.sync_context(dist_sync_fn=self.dist_sync_fn):
            return fn()

    @typechecked
    def plot(
        self,
        val: Tensor
        | dict[str, Tensor]
        | Sequence[Tensor]
        | Sequence[dict[str, Tensor]]
        | None = None,
        ax: Any = None,
    ) -> Any:
        """torchmetrics' plot of the chosen ``value``: ``val`` one value (a scalar tensor or
        a dict of them, as :meth:`compute` returns) or a sequence of them (one per epoch,
        drawn as a curve); ``None`` plots :meth:`compute` now. Returns ``(figure, axes)``
        (needs matplotlib)."""
        return self._plot(val, ax)

    def extra_repr(self) -> str:
        shown = {k: self._dego_config[k] for k in self._REPR_KEYS}
        return ", ".join([f"value={self.value!r}", *(f"{k}={v!r}" for k, v in shown.items())])


class OccupancyMetric(_DegoCountsMetric):
    """:class:`dego.OccupancyMetrics` as a ``torchmetrics.Metric``: pooled voxel IoU / mIoU
    under the ``weak``, ``occ3d`` or ``surroundocc`` protocol.

    Args:
        protocol: as :class:`dego.OccupancyMetrics` (``"weak"``, ``"occ3d"``,
            ``"surroundocc"``).
        num_classes: C, labels including free (18).
        free_label: the empty-space label (17).
        ignore_label: gt value whose voxels are skipped (255), or ``None``.
        groups: class groups averaged into the group means (default InsM / ScnM / HCM).
        device: where the states live (or move the metric with ``.to(device)``).
        value: what :meth:`compute` (and ``forward``) return: ``"miou"`` (the default),
            ``"iou"`` (geometric), a group (``"insm"``, ``"scnm"``, ``"hcm"``) or
            ``"iou/<class name>"`` as a scalar tensor; ``"per_class"`` (the
            ``"iou/<class>"`` of the evaluated classes) or ``"all"`` (every key of
            :meth:`dego.OccupancyReport.as_dict`) as a dict of scalar tensors, which
            ``MetricCollection`` flattens and ``LightningModule.log_dict`` accepts.
            Fractions in [0, 1]; NaN for an absent class.
        **kwargs: torchmetrics' ``Metric`` options (``dist_sync_on_step``,
            ``process_group``, ``sync_on_compute``, ``compute_with_cache``, ...).

    States (int64, summed across ranks, out of ``state_dict`` until ``persistent(True)``):
    ``confusion (C, C)``, ``geometric (2, 2)``, as in :class:`dego.OccupancyMetrics`, and
    ``config_fingerprint (2, 16)``. The values are tensors of the metric's ``dtype``
    (float32; ``set_dtype(torch.float64)`` for float64) on its device.

    Raises:
        ValueError: a bad configuration (as :class:`dego.OccupancyMetrics`) or ``value``.
    """

    confusion: Tensor
    geometric: Tensor
    _DICT_VALUES: Mapping[str, Callable[[str], bool]] = {
        "per_class": lambda key: key.startswith("iou/")
    }
    _REPR_KEYS = ("protocol", "num_classes", "free_label", "ignore_label")

    def __init__(
        self,
        protocol: str = "weak",
        num_classes: int = NUM_CLASSES,
        free_label: int = FREE_LABEL,
        ignore_label: int | None = 255,
        groups: Mapping[str, Sequence[int]] | None = None,
        device: torch.device | str | None = None,
        *,
        value: str = "miou",
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        spec = OccupancySpec.make(protocol, num_classes, free_label, ignore_label, groups)
        blank = OccupancyReport.from_per_class(  # the keys of a report of this configuration
            [math.nan] * spec.num_classes,
            evaluated_classes=spec.evaluated_classes,
            groups=spec.groups,
            class_names=spec.class_names,
            protocol=spec.protocol,
        )
        self._setup(spec, value, list(blank.as_dict()), "miou", device)

    @typechecked
    def update(
        self,
        pred: Tensor | np.ndarray,
        gt: Tensor | np.ndarray,
        mask: Tensor | np.ndarray | Omitted | None = OMITTED,
    ) -> None:
        """Add one batch of label grids ``(X, Y, Z)`` or ``(B, X, Y, Z)``; arguments, checks
        and errors of :meth:`dego.OccupancyMetrics.update` (an error names the argument):
        under ``"occ3d"`` and ``"weak"``, pass the camera mask, or ``mask=None`` explicitly
        to score every voxel."""
        confusion, geometric = self._spec.counts(pred, gt, mask)
        self.confusion += confusion.to(self.confusion.device)
        self.geometric += geometric.to(self.geometric.device)

    def compute(self) -> Tensor | dict[str, Tensor]:
        """The chosen ``value`` of everything seen (on every rank: torchmetrics syncs first).

        Raises:
            RuntimeError: no voxel evaluated yet.
            ValueError: counts of another configuration in the state (see the module).
        """
        return self._select(self._report(stacklevel=4).as_dict())

    def report(self) -> OccupancyReport:
        """dego's :class:`~dego.OccupancyReport` of the states, synced across ranks as for
        ``compute`` (the local states are kept)."""
        return self._with_synced_states(lambda: self._report(stacklevel=5))

    def _report(self, stacklevel: int) -> OccupancyReport:
        self._check_config()
        return self._spec.report(self.confusion, self.geometric, stacklevel=stacklevel)


class RayIoUMetric(_DegoCountsMetric):
    """:class:`dego.metrics.RayIoU` as a ``torchmetrics.Metric``: SparseOcc's RayIoU at
    1, 2 and 4 m.

    Args:
        thresholds: distance thresholds in metres.
        num_classes: C, labels including free (18).
        free_label: the empty label (17).
        class_ids: the classes averaged (default: every label but free).
        grid: the label grids' voxel grid (default Occ3D).
        rays: ``(R, 3)`` ray directions (default :func:`dego.raycast.generate_lidar_rays`).
        device: where the states live (or move the metric with ``.to(device)``).
        value: what :meth:`compute` (and ``forward``) return: ``"rayiou"`` (the mean over
            thresholds, the default), ``"rayiou@<t>"`` (e.g. ``"rayiou@1"``) or
            ``"rayiou@<t>/<class name>"`` as a scalar tensor; ``"per_threshold"`` (every
            ``"rayiou@<t>"``) or ``"all"`` (every key of
            :meth:`dego.metrics.RayIoUReport.as_dict`) as a dict of scalar tensors.
        **kwargs: torchmetrics' ``Metric`` options.

    States (int64, summed across ranks, out of ``state_dict`` until ``persistent(True)``):
    ``gt_count (C,)``, ``pred_count (C,)``, ``true_positives (T, C)``, as in
    :class:`dego.metrics.RayIoU`, and ``config_fingerprint (2, 16)``.

    Raises:
        ValueError, TypeError: a bad configuration (as :class:`dego.metrics.RayIoU`) or
            ``value``.
    """

    gt_count: Tensor
    pred_count: Tensor
    true_positives: Tensor
    rays: Tensor
    _DICT_VALUES: Mapping[str, Callable[[str], bool]] = {
        "per_threshold": lambda key: key.startswith("rayiou@") and "/" not in key
    }
    _REPR_KEYS = ("thresholds", "num_classes")

    def __init__(
        self,
        thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
        num_classes: int = NUM_CLASSES,
        free_label: int = FREE_LABEL,
        class_ids: Sequence[int] | None = None,
        grid: VoxelGrid | None = None,
        rays: Tensor | None = None,
        device: torch.device | str | None = None,
        *,
        value: str = "rayiou",
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        spec = RayIoUSpec.make(thresholds, num_classes, free_label, class_ids, grid, rays)
        self.register_buffer("rays", spec.rays.clone(), persistent=False)
        blank = RayIoUReport(  # the keys of a report of this configuration
            thresholds=spec.thresholds,
            per_class=torch.full((len(spec.thresholds), spec.num_classes), math.nan),
            at=(math.nan,) * len(spec.thresholds),
            rayiou=math.nan,
            class_ids=spec.class_ids,
            class_names=spec.class_names,
        )
        self._setup(spec, value, list(blank.as_dict()), "rayiou", device)

    @typechecked
    def update(
        self,
        pred: Tensor | np.ndarray,
        gt: Tensor | np.ndarray,
        origins: Tensor | np.ndarray,
    ) -> None:
        """Cast and score one sample ``(X, Y, Z)`` from ``(K, 3)`` origins; arguments, checks
        and errors of :meth:`dego.metrics.RayIoU.update` (an error names the argument)."""
        gt_count, pred_count, tp = self._spec.counts(pred, gt, origins, rays=self.rays)
        self.gt_count += gt_count.to(self.gt_count.device)
        self.pred_count += pred_count.to(self.pred_count.device)
        self.true_positives += tp.to(self.true_positives.device)

    def compute(self) -> Tensor | dict[str, Tensor]:
        """The chosen ``value`` of everything seen (on every rank: torchmetrics syncs first).

        Raises:
            RuntimeError: no scored ray yet.
            ValueError: counts of another configuration in the state (see the module).
        """
        return self._select(self._report().as_dict())

    def report(self) -> RayIoUReport:
        """dego's :class:`~dego.metrics.RayIoUReport` of the states, synced across ranks as
        for ``compute`` (the local states are kept)."""
        return self._with_synced_states(self._report)

    def _report(self) -> RayIoUReport:
        self._check_config()
        return self._spec.report(self.gt_count, self.pred_count, self.true_positives)


__all__ = ["OccupancyMetric", "RayIoUMetric"]
