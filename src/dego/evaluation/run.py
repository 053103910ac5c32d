"""The evaluation engine: choose the samples, check the inputs up front, stream the samples
through the metrics (constant memory), share them over processes with torch.distributed,
reduce the integer counts and build the :class:`EvaluationReport`.

One code path serves three ways of running:

- one process (``workers=1``, no torch.distributed): every sample here;
- ``workers=N``: N processes spawned with ``torch.multiprocessing`` form a gloo group (a
  ``FileStore`` in a temporary folder); rank r scores samples ``r::N``, the counts are
  all-reduced (``metric.sync()``), failures gathered with ``all_gather_object``, and rank 0
  sends the totals to the parent, which also draws the progress of all ranks;
- under ``torchrun`` (``RANK`` / ``WORLD_SIZE`` set) or inside an initialised process
  group: every rank scores its shard, the counts are reduced, every rank gets the same
  report (the CLI prints it on rank 0 only).

Counts are int64, so the numbers do not depend on how the samples were shared.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import shutil
import signal
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, TextIO, cast

import numpy as np
import torch
import torch.distributed as dist
import torch.multiprocessing as torch_mp

from dego._checks import check_int
from dego._cores import usable_cores
from dego._typing import typechecked
from dego._version import __version__
from dego.evaluation.benchmarks import DEFAULT_BENCHMARK, MAVE_VARIANTS, Benchmark, get_benchmark
from dego.evaluation.errors import (
    EvaluationSetupError,
    EvaluationWorkerError,
    SampleFailure,
    list_tokens,
)
from dego.evaluation.layouts import GroundTruth, layout_of
from dego.evaluation.origins import (
    NO_ORIGINS_MESSAGE,
    DirectoryOrigins,
    OriginsFn,
    OriginSource,
    choose_source,
    load_keyframes,
    open_origins,
)
from dego.evaluation.predictions import (
    find_prediction,
    load_prediction,
    prediction_candidates,
    read_prediction,
)
from dego.evaluation.processes import (
    _check_plans_agree,
    _exit_message,
    _stop,
    _unguarded_main_line,
)
from dego.evaluation.progress import Progress
from dego.evaluation.report import EvaluationReport
from dego.evaluation.scoring import (
    cast_with_flow,
    mave,
    occ_score,
    ray_flow_counts,
    ray_reports,
    voxel_counts,
    voxel_report,
)
from dego.metrics.occupancy import OccupancyMetrics
from dego.metrics.rayiou import RayIoU
from dego.metrics.report import OccupancyReport
from dego.raycast import cpu_kernel, generate_lidar_rays

PROTOCOLS = ("occ3d", "weak")
PROTOCOL_CHOICES = (*PROTOCOLS, "both")
MISSING_POLICIES = ("error", "free", "skip")

PathLike = str | os.PathLike[str]


@dataclasses.dataclass(frozen=True)
class Sample:
    """One sample to score; ``prediction`` is ``None`` when it is scored as all free."""

    scene: str
    token: str
    prediction: str | None
    gt_file: str = ""


@dataclasses.dataclass(frozen=True)
class Plan:
    """Everything a process needs to score its share (plain data: it travels to workers)."""

    gt: str
    pred: str
    protocols: tuple[str, ...]
    rayiou: bool
    classes: tuple[int, ...] | None
    samples: tuple[Sample, ...]
    samples_total: int
    scene_of: tuple[tuple[str, str], ...]  # token -> scene over the whole GT tree
    missing_policy: str
    missing_tokens: tuple[str, ...]
    source: OriginSource | None
    ignored_sources: tuple[str, ...]
    device: str
    benchmark: str = DEFAULT_BENCHMARK
    mave: str = "dataset"

    @property
    def spec(self) -> Benchmark:
        return get_benchmark(self.benchmark)


# ----------------------------------------------------------------------------------------
# Setup: every check that can be made before scoring
# ----------------------------------------------------------------------------------------


def _protocols(protocol: str, benchmark: Benchmark) -> tuple[str, ...]:
    names = tuple(p.name for p in benchmark.voxel)
    if protocol in ("both", "all"):
        return names
    if protocol not in names:
        if benchmark.name == DEFAULT_BENCHMARK:
            raise EvaluationSetupError(
                f"protocol: expected one of {list(PROTOCOL_CHOICES)}, got {protocol!r}"
            )
        raise EvaluationSetupError(
            f"protocol: {benchmark.name} has no protocol {protocol!r}; expected one of "
            f"{[*names, 'all']}"
        )
    return (protocol,)


def _classes(classes: Sequence[int] | None, benchmark: Benchmark) -> tuple[int, ...] | None:
    if classes is None:
        return None
    out: list[int] = []
    free = benchmark.free_label
    for c in classes:
        if (
            isinstance(c, bool)
            or not isinstance(c, int | np.integer)
            or not 0 <= c < benchmark.num_classes
            or c == free
        ):
            raise EvaluationSetupError(
                f"classes: expected {benchmark.name} class ids in 0..{benchmark.num_classes - 1} "
                f"but {free} ({free} = free is never averaged), got {c!r}"
            )
        if int(c) not in out:
            out.append(int(c))
    if not out:
        raise EvaluationSetupError("classes: expected at least one class id")
    return tuple(out)


def prepare(
    gt: PathLike,
    pred: PathLike,
    *,
    protocol: str = "both",
    rayiou: bool = True,
    classes: Sequence[int] | None = None,
    infos: PathLike | None = None,
    nuscenes: PathLike | None = None,
    version: str = "v1.0-trainval",
    origins: PathLike | None = None,
    missing: str = "error",
    device: str = "cpu",
    benchmark: str = DEFAULT_BENCHMARK,
    mave: str = "dataset",
) -> tuple[Plan, OriginsFn | None]:
    """Select the samples and check predictions and origins for all of them up front.

    Returns the plan and the origins of every sample (``None`` without RayIoU), opened
    once here: this process scores with them, spawned workers open their own. The first
    sample's ground truth and prediction are read here too, so that a tree or a
    prediction of another benchmark is a setup error, not a failure of every sample.
    Raises :class:`EvaluationSetupError` naming the option, file or tokens at fault.
    """
    try:
        spec = get_benchmark(benchmark)
    except ValueError as exc:
        raise EvaluationSetupError(str(exc)) from None
    if mave not in MAVE_VARIANTS:
        raise EvaluationSetupError(f"mave: expected one of {list(MAVE_VARIANTS)}, got {mave!r}")
    protocols, class_ids = _protocols(protocol, spec), _classes(classes, spec)
    rayiou = rayiou and spec.ray is not None
    if missing not in MISSING_POLICIES:
        raise EvaluationSetupError(
            f"missing: expected one of {list(MISSING_POLICIES)}, got {missing!r}"
        )
    source, ignored = choose_source(infos, nuscenes, version, origins)
    if rayiou and source is None:
        raise EvaluationSetupError(NO_ORIGINS_MESSAGE)
    pred_root = Path(pred)
    if not pred_root.is_dir():
        raise EvaluationSetupError(f"--pred: {pred_root} is not a directory")
    layout = layout_of(spec)
    labels_root, entries = layout.samples(Path(gt), spec)
    tree_samples = [(e.scene, e.token) for e in entries]
    files = {e.token: str(e.path) for e in entries}
    scene_of = {token: scene for scene, token in tree_samples}

    keyframes = None
    use_infos = spec.nuscenes and source is not None and source.kind == "infos"
    if source is not None and source.kind != "origins" and (rayiou or use_infos):
        keyframes = load_keyframes(source)
    if use_infos and keyframes is not None and source is not None:
        tokens = [str(k.token) for k in keyframes]  # SparseOcc iterates the infos
        no_gt = [t for t in tokens if t not in scene_of]
        if no_gt:
            raise EvaluationSetupError(
                f"--infos {source.path}: {len(no_gt)} sample(s) have no ground truth under "
                f"{labels_root} (expected {layout.pattern}): {list_tokens(no_gt)}"
            )
        pairs = [(scene_of[t], t) for t in tokens]
        twice = sorted(t for t, n in collections.Counter(tokens).items() if n > 1)
        if twice:
            raise EvaluationSetupError(
                f"--infos {source.path}: token(s) {list_tokens(twice)} appear more than once; "
                "each sample must be scored once"
            )
    else:
        pairs = list(tree_samples)
    if not pairs:
        raise EvaluationSetupError("no samples to score")

    samples, missing_tokens = [], []
    for scene, token in pairs:
        try:
            path = find_prediction(pred_root, scene, token)
            if path is None and spec.layout != "occ3d":
                own = pred_root / layout.relative(scene, token)
                path = own if own.is_file() else None
        except OSError as exc:  # a folder on the way that cannot be read
            raise EvaluationSetupError(
                f"--pred: {exc.filename or pred_root}: cannot be read ({exc.strerror or exc})"
            ) from None
        if path is None:
            missing_tokens.append(token)
            if missing == "skip":
                continue
        samples.append(Sample(scene, token, None if path is None else str(path), files[token]))
    if missing_tokens and missing == "error":
        looked = " or ".join(str(p) for p in prediction_candidates(pred_root, "<scene>", "<token>"))
        raise EvaluationSetupError(
            f"--pred: no prediction for {len(missing_tokens)} of {len(pairs)} samples: "
            f"{list_tokens(missing_tokens)} (looked for {looked}); pass --missing free to "
            "score them as all free or --missing skip to leave them out"
        )
    if not samples:
        raise EvaluationSetupError(
            f"--pred: none of the {len(pairs)} samples has a prediction in {pred_root}"
        )
    if spec.name != DEFAULT_BENCHMARK:
        _check_first(spec, samples[0])
    plan = Plan(
        gt=str(labels_root),
        pred=str(pred_root),
        protocols=protocols,
        rayiou=rayiou,
        classes=class_ids,
        samples=tuple(samples),
        samples_total=len(pairs),
        scene_of=tuple(scene_of.items()),
        missing_policy=missing,
        missing_tokens=tuple(missing_tokens),
        source=source if rayiou else None,
        ignored_sources=ignored if rayiou else (),
        device=device,
        benchmark=spec.name,
        mave=mave,
    )
    origins_fn = None
    # every origin exists (files) or every token is a keyframe (poses); source is not None
    if rayiou and source is not None:
        origins_fn = open_origins(source, scene_of, [s.token for s in samples], keyframes)
    return plan, origins_fn


def _check_first(spec: Benchmark, sample: Sample) -> None:
    """Read the first sample's ground truth and prediction: a file of another benchmark
    is a setup error naming the file and the benchmark."""
    for path, read in (
        (sample.gt_file, lambda p: layout_of(spec).read(Path(p), spec)),
        (sample.prediction, lambda p: read_prediction(p, spec)),
    ):
        if path is None:
            continue
        try:
            read(path)
        except (OSError, ValueError) as exc:
            message = str(exc) if str(path) in str(exc) else f"{path}: {exc}"
            raise EvaluationSetupError(f"--benchmark {spec.name}: {message}") from None


# ----------------------------------------------------------------------------------------
# Scoring: the per-sample loop and the counts
# ----------------------------------------------------------------------------------------


class Tally:
    """The metrics of one process plus the sample / ray counters, the failures and (for
    benchmarks with flow) one mAVE row per sample."""

    def __init__(self, plan: Plan) -> None:
        self.plan = plan
        spec = plan.spec
        device = torch.device(plan.device)
        self.metrics: dict[str, OccupancyMetrics | RayIoU] = {
            name: OccupancyMetrics(
                "occ3d",
                num_classes=spec.num_classes,
                free_label=spec.free_label,
                ignore_label=spec.ignore_label,
                groups={},
                device=device,
            )
            for name in plan.protocols
        }
        if plan.rayiou:
            assert spec.ray is not None
            self.metrics["rayiou"] = RayIoU(
                thresholds=spec.ray.thresholds,
                num_classes=spec.num_classes,
                free_label=spec.free_label,
                class_ids=plan.classes or next(iter(spec.ray.class_sets.values())),
                device=device,
            )
        self.scored = self.origins = self.rays_cast = 0
        self.failed: list[SampleFailure] = []
        self.flow_rows: list[tuple[int, Any, Any]] = []
        self._order = {s.token: i for i, s in enumerate(plan.samples)}

    def _read_gt(self, sample: Sample, device: torch.device) -> GroundTruth:
        spec = self.plan.spec
        gt = layout_of(spec).read(Path(sample.gt_file), spec)
        masks = {k: v.to(device) for k, v in gt.masks.items()}
        return GroundTruth(gt.semantics.to(device), masks, gt.flow)

    def _read_pred(
        self, sample: Sample, gt: GroundTruth, device: torch.device
    ) -> tuple[torch.Tensor, Any]:
        spec = self.plan.spec
        if sample.prediction is None:
            return torch.full(gt.semantics.shape, spec.free_label, device=device), None
        if spec.name == DEFAULT_BENCHMARK:
            shape = cast(tuple[int, int, int], tuple(gt.semantics.shape))
            pred = load_prediction(sample.prediction, expected_shape=shape)
            return pred.to(device), None
        pred, flow = read_prediction(sample.prediction, spec)
        return pred.to(device), flow

    def score(self, sample: Sample, origins_fn: OriginsFn | None) -> None:
        """Read, check and count one sample; a failure is recorded, not raised."""
        device = torch.device(self.plan.device)
        spec = self.plan.spec
        where = sample.gt_file
        flow_row = None
        try:
            gt = self._read_gt(sample, device)
            where = sample.prediction or where
            pred, pred_flow = self._read_pred(sample, gt, device)
            counts: dict[str, tuple[torch.Tensor, ...]] = {}
            k = 0
            for name, metric in self.metrics.items():
                if isinstance(metric, RayIoU):
                    assert origins_fn is not None and self.plan.source is not None
                    where = (
                        str(origins_fn.path(sample.token))
                        if isinstance(origins_fn, DirectoryOrigins)
                        else self.plan.source.description
                    )
                    origins = origins_fn(sample.token)
                    k = int(origins.shape[0])
                    if spec.ray is not None and spec.ray.flow_classes:
                        counts[name], flow_row = self._flow_counts(gt, pred, pred_flow, origins)
                    else:
                        counts[name] = metric._spec.counts(
                            pred, gt.semantics, origins, rays=metric.rays
                        )
                else:
                    protocol = spec.protocol(name)
                    counts[name] = voxel_counts(spec, protocol, pred, gt)
        except (OSError, ValueError, TypeError, KeyError) as exc:
            message = str(exc) if where in str(exc) else f"{where}: {exc}"
            self.failed.append(SampleFailure(sample.token, where, message))
            return
        for name, metric in self.metrics.items():  # all read: add them together
            for count_name, count in zip(metric.COUNTS, counts[name], strict=True):
                getattr(metric, count_name).add_(count.to(getattr(metric, count_name).device))
            metric._changed()
        if flow_row is not None:
            self.flow_rows.append((self._order[sample.token], *flow_row))
        self.scored += 1
        if "rayiou" in self.metrics:
            self.origins += k
            self.rays_cast += k * int(cast(RayIoU, self.metrics["rayiou"]).rays.shape[0])

    def _flow_counts(
        self, gt: GroundTruth, pred: torch.Tensor, pred_flow: Any, origins: torch.Tensor
    ) -> tuple[tuple[torch.Tensor, ...], tuple[Any, Any]]:
        spec = self.plan.spec
        if gt.flow is None:
            raise ValueError("the ground truth has no flow")
        if pred_flow is None:  # no predicted flow: zero, as OccNet's ray_casting.py sets it
            pred_flow = torch.zeros_like(gt.flow)
        rays = cast(RayIoU, self.metrics["rayiou"]).rays
        missed = "scored" if self.plan.mave == "server" else "none"
        out = cast_with_flow(
            spec,
            pred.cpu(),
            gt.semantics.cpu(),
            pred_flow,
            gt.flow,
            origins.cpu(),
            rays.cpu(),
            missed=missed,
        )
        counts, sums, numbers = ray_flow_counts(spec, out, self.plan.mave)
        return counts, (sums, numbers)

    def sync(self) -> None:
        """All-reduce the counts, gather the failures (a no-op outside torch.distributed)."""
        if not (dist.is_available() and dist.is_initialized()):
            return
        for metric in self.metrics.values():
            metric.sync()
        totals = torch.tensor([self.scored, self.origins, self.rays_cast], dtype=torch.int64)
        if dist.get_backend() == "nccl":  # a group the caller made for training
            totals = totals.to(torch.device("cuda", torch.cuda.current_device()))
        dist.all_reduce(totals, op=dist.ReduceOp.SUM)
        self.scored, self.origins, self.rays_cast = (int(v) for v in totals)
        gathered: list[Any] = [None] * dist.get_world_size()
        dist.all_gather_object(gathered, (self.failed, self.flow_rows))
        order = self._order
        failed = [f for part in gathered for f in part[0]]
        self.failed = sorted(failed, key=lambda f: order.get(f.token, len(order)))
        self.flow_rows = sorted(row for part in gathered for row in part[1])

    def state(self) -> dict[str, Any]:
        """The (synced) totals as plain data: numpy counts, ints, failures, mAVE rows."""
        return {
            "counts": {
                name: {
                    c: t.cpu().numpy() for c, t in zip(metric.COUNTS, metric._totals(), strict=True)
                }
                for name, metric in self.metrics.items()
            },
            "scored": self.scored,
            "origins": self.origins,
            "rays_cast": self.rays_cast,
            "failed": list(self.failed),
            "flow_rows": [(i, np.asarray(a), np.asarray(b)) for i, a, b in sorted(self.flow_rows)],
        }


def score_shard(
    plan: Plan,
    rank: int = 0,
    world_size: int = 1,
    *,
    on_sample: Callable[[], None] | None = None,
    origins_fn: OriginsFn | None = None,
) -> Tally:
    """Score samples ``rank::world_size`` of the plan, one at a time (constant memory);
    ``origins_fn``: the samples' origins when already open (:func:`prepare`)."""
    shard = plan.samples[rank::world_size]
    if origins_fn is None and plan.rayiou and plan.source is not None:
        origins_fn = open_origins(plan.source, dict(plan.scene_of), [s.token for s in shard])
    tally = Tally(plan)
    for sample in shard:
        tally.score(sample, origins_fn)
        if on_sample is not None:
            on_sample()
    return tally


def build_report(
    plan: Plan, state: Mapping[str, Any], world_size: int, seconds: float
) -> EvaluationReport:
    """The :class:`EvaluationReport` of pooled totals (:meth:`Tally.state`)."""
    spec = plan.spec
    counts = {
        metric: {name: torch.as_tensor(np.asarray(c)) for name, c in parts.items()}
        for metric, parts in state["counts"].items()
    }
    protocols: dict[str, OccupancyReport] = {}
    ray_sets: dict[str, Any] = {}
    rays_scored = 0
    ave, mave_value, score = None, None, None
    scored = int(state["scored"])
    if scored > 0:
        for name in plan.protocols:
            if int(counts[name]["confusion"].sum()) == 0:
                continue
            protocols[name] = voxel_report(
                spec,
                spec.protocol(name),
                counts[name]["confusion"],
                counts[name]["geometric"],
                scored,
                plan.classes,
            )
        if plan.rayiou:
            ray = counts["rayiou"]
            rays_scored = int(ray["gt_count"].sum())
            if rays_scored > 0:
                ray_sets = ray_reports(
                    spec, ray["gt_count"], ray["pred_count"], ray["true_positives"], plan.classes
                )
                if spec.ray is not None and spec.ray.flow_classes:
                    rows = [(a, b) for _, a, b in state.get("flow_rows", [])]
                    ave, mave_value = mave(spec, rows)
                    score = occ_score(next(iter(ray_sets.values())).rayiou, mave_value)
    ray_report = next(iter(ray_sets.values()), None)
    return EvaluationReport(
        protocols=protocols,
        rayiou=ray_report,
        counts=counts,
        classes=plan.classes,
        gt=plan.gt,
        pred=plan.pred,
        origin_source=None if plan.source is None else plan.source.description,
        ignored_sources=plan.ignored_sources,
        samples_total=plan.samples_total,
        samples_scored=scored,
        origins_total=int(state["origins"]),
        rays_per_origin=_rays_per_origin(),
        rays_cast=int(state["rays_cast"]),
        rays_scored=rays_scored,
        missing_policy=plan.missing_policy,
        missing_tokens=plan.missing_tokens,
        failed=tuple(state["failed"]),
        world_size=world_size,
        seconds=seconds,
        version=__version__,
        traversal=cpu_kernel() if torch.device(plan.device).type == "cpu" else "torch",
        benchmark=spec.name,
        rules=tuple(spec.rules()),
        rayiou_sets=ray_sets,
        flow=None
        if ave is None
        else {
            "variant": plan.mave,
            "ave": {
                spec.class_names[c]: float(v)
                for c, v in zip(spec.ray.flow_classes, ave, strict=True)  # type: ignore[union-attr]
            },
            "mave": mave_value,
            "occ_score": score,
        },
    )


def _rays_per_origin() -> int:
    return int(generate_lidar_rays().shape[0])


# ----------------------------------------------------------------------------------------
# Running: one process, spawned workers, torchrun
# ----------------------------------------------------------------------------------------


def launched_by_torchrun() -> bool:
    """``RANK`` and ``WORLD_SIZE`` are set (torchrun, or any env:// launcher)."""
    return "RANK" in os.environ and "WORLD_SIZE" in os.environ


def _worker(
    rank: int, plan: Plan, world_size: int, store: str, events: Any, report_progress: bool
) -> None:
    """One spawned worker: gloo group, its shard, the reduce; rank 0 sends the totals.
    Ctrl-C (SIGINT to the whole process group) is the parent's to handle: it stops the
    workers, which print nothing."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if "OMP_NUM_THREADS" not in os.environ:  # dego eval --threads N sets it for the workers
        torch.set_num_threads(max(1, usable_cores() // world_size))
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=world_size)
    try:
        on_sample = (lambda: events.put(("tick", rank))) if report_progress else None
        tally = score_shard(plan, rank, world_size, on_sample=on_sample)
        tally.sync()
        if rank == 0:
            events.put(("result", tally.state()))
    finally:
        dist.destroy_process_group()


def _run_workers(
    plan: Plan, workers: int, progress: Progress, *, target: Callable[..., None] | None = None
) -> dict[str, Any]:
    """The plan scored by ``workers`` spawned processes (``target``: :func:`_worker`)."""
    scratch = tempfile.mkdtemp(prefix="dego-eval-")
    processes: Sequence[Any] = ()
    try:
        events = torch_mp.get_context("spawn").SimpleQueue()
        context = torch_mp.start_processes(
            target or _worker,
            args=(plan, workers, str(Path(scratch) / "store"), events, progress.enabled),
            nprocs=workers,
            join=False,
            start_method="spawn",
        )
        processes = context.processes
        result: dict[str, Any] | None = None

        def drain() -> None:
            nonlocal result
            while not events.empty():
                kind, payload = events.get()
                if kind == "tick":
                    progress.update()
                else:
                    result = payload

        try:
            while not context.join(timeout=0.1):
                drain()
        except torch_mp.ProcessExitedException as error:
            raise EvaluationWorkerError(_exit_message(error)) from None
        drain()
    finally:
        _stop(processes)  # Ctrl-C, or a worker that died: the others go before their store
        shutil.rmtree(scratch, ignore_errors=True)
    if result is None:
        raise RuntimeError("evaluation workers ended without sending their totals")
    return result


def _run_here(plan: Plan, origins_fn: OriginsFn | None, progress: Progress) -> dict[str, Any]:
    """This process's shard (all samples outside torch.distributed), reduced over ranks."""
    rank, world = 0, 1
    if dist.is_available() and dist.is_initialized():
        rank, world = dist.get_rank(), dist.get_world_size()
    tally = score_shard(plan, rank, world, on_sample=progress.update, origins_fn=origins_fn)
    tally.sync()
    return tally.state()


@typechecked
def evaluate(
    gt: PathLike,
    pred: PathLike,
    *,
    protocol: str = "both",
    rayiou: bool = True,
    classes: Sequence[int] | None = None,
    infos: PathLike | None = None,
    nuscenes: PathLike | None = None,
    version: str = "v1.0-trainval",
    origins: PathLike | None = None,
    missing: str = "error",
    workers: int = 1,
    device: str = "cpu",
    progress: bool = False,
    progress_stream: TextIO | None = None,
    benchmark: str = DEFAULT_BENCHMARK,
    mave: str = "dataset",
) -> EvaluationReport:
    """Score a folder of occupancy predictions against a benchmark's ground truth, on CPU.

    Args:
        gt: the ground-truth root in the benchmark's layout (Occ3D-nuScenes: the Occ3D
            root holding ``gts/<scene>/<token>/labels.npz``; ``dego eval --benchmarks``
            and docs/evaluation.md list every layout).
        pred: the predictions: ``<token>.npz`` (array ``pred``, ``arr_0`` or
            ``semantics``), ``<token>.npy``, or ``<scene>/<token>/labels.npz`` (also under
            ``gts/``); ``(200, 200, 16)`` integer labels, 17 = free. Other benchmarks:
            their own grid and ids (``BENCHMARKS[name].prediction``), also in the GT's
            layout, and OpenOccupancy's logits (:func:`read_prediction`).
        protocol: ``"occ3d"``, ``"weak"`` or ``"both"`` (Occ3D-nuScenes); for another
            benchmark one of its protocols (``BENCHMARKS[name].voxel``) or ``"all"``.
        rayiou: also compute RayIoU (needs an origin source).
        classes: the classes averaged into mIoU and RayIoU instead of the protocol's default.
        infos: an mmdet3d ``nuscenes_infos_val.pkl``: its tokens, in file order, are the
            samples scored, and its poses give the origins (preferred source).
        nuscenes: a nuScenes root whose JSON tables (of ``version``) give the poses.
        version: the nuScenes version folder under ``nuscenes`` (``v1.0-trainval``).
        origins: a folder of ``<token>.npy`` ``(K, 3)`` origins in the ego frame.
        missing: a sample without a prediction is an ``"error"`` (checked up front),
            scored as all ``"free"``, or ``"skip"``-ped.
        workers: local processes sharing the samples through torch.distributed (gloo).
            Under torchrun (``RANK`` / ``WORLD_SIZE`` set) or in an initialised process
            group, the ranks share the samples instead and every rank gets the report.
        device: where the metrics run.
        progress: show progress on ``progress_stream`` (stderr).
        benchmark: the benchmark whose rules score the predictions (a key of
            :data:`dego.evaluation.BENCHMARKS`; ``"occ3d-nuscenes"`` by default).
        mave: OpenOcc v2's RayIoU / mAVE script: ``"dataset"`` (the default) or
            ``"server"`` (:data:`dego.evaluation.benchmarks.MAVE_VARIANTS`).

    Returns:
        An :class:`EvaluationReport` (its metric reports hold fractions; its tables and
        JSON show percent). A sample that fails to read or validate is listed in
        ``report.failed`` and the others are scored.

    Raises:
        RuntimeError: ``workers > 1`` called at the top level of a script without
            ``if __name__ == "__main__":`` (its spawned workers would run it again).
        EvaluationSetupError: (a ``ValueError``) no samples, missing predictions or
            origins, an infos token without ground truth, bad options.
    """
    workers = check_int("workers", workers, 1)
    unguarded = _unguarded_main_line() if workers > 1 else None
    if unguarded is not None:
        raise RuntimeError(
            f"workers={workers}: {unguarded[0]}, line {unguarded[1]}, calls dego.evaluate at "
            'its top level without `if __name__ == "__main__":`, and each worker process '
            "(started with spawn) imports that file and would run it again; put the call "
            "under that guard, or pass workers=1"
        )
    start = time.perf_counter()
    plan, origins_fn = prepare(
        gt,
        pred,
        protocol=protocol,
        rayiou=rayiou,
        classes=classes,
        infos=infos,
        nuscenes=nuscenes,
        version=version,
        origins=origins,
        missing=missing,
        device=device,
        benchmark=benchmark,
        mave=mave,
    )
    distributed = dist.is_available() and (dist.is_initialized() or launched_by_torchrun())
    if distributed and workers > 1:
        raise EvaluationSetupError(
            "workers: already running under torch.distributed (torchrun); the ranks share "
            "the samples, leave --workers at 1"
        )
    created_group = False
    if distributed and not dist.is_initialized():
        if "OMP_NUM_THREADS" not in os.environ:
            local = int(os.environ.get("LOCAL_WORLD_SIZE", os.environ["WORLD_SIZE"]))
            torch.set_num_threads(max(1, usable_cores() // max(local, 1)))
        dist.init_process_group("gloo", init_method="env://")
        created_group = True
    try:
        if distributed:
            _check_plans_agree(plan)
        rank = dist.get_rank() if distributed else 0
        world = dist.get_world_size() if distributed else workers
        shard_total = len(plan.samples[rank::world]) if distributed else len(plan.samples)
        with Progress(shard_total, enabled=progress and rank == 0, stream=progress_stream) as bar:
            if workers > 1:
                state = _run_workers(plan, workers, bar)
            else:
                state = _run_here(plan, origins_fn, bar)
    finally:
        if created_group:
            dist.destroy_process_group()
    return build_report(plan, state, world, time.perf_counter() - start)


__all__ = [
    "MISSING_POLICIES",
    "PROTOCOLS",
    "PROTOCOL_CHOICES",
    "Plan",
    "Sample",
    "Tally",
    "build_report",
    "evaluate",
    "launched_by_torchrun",
    "prepare",
    "score_shard",
]
