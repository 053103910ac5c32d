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

import ast
import dataclasses
import inspect
import os
import shutil
import signal
import sys
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
from dego._typing import typechecked
from dego._version import __version__
from dego.classes import FREE_LABEL
from dego.data.occ3d import LABELS_FILENAME, load_occ3d_labels
from dego.evaluation.errors import (
    EvaluationSetupError,
    EvaluationWorkerError,
    SampleFailure,
    list_tokens,
)
from dego.evaluation.origins import (
    NO_ORIGINS_MESSAGE,
    DirectoryOrigins,
    OriginsFn,
    OriginSource,
    choose_source,
    load_keyframes,
    open_origins,
)
from dego.evaluation.predictions import find_prediction, load_prediction, prediction_candidates
from dego.evaluation.progress import Progress
from dego.evaluation.report import EvaluationReport
from dego.metrics.counts import gathered_if_different
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


# ----------------------------------------------------------------------------------------
# Setup: every check that can be made before scoring
# ----------------------------------------------------------------------------------------


def _protocols(protocol: str) -> tuple[str, ...]:
    if protocol not in PROTOCOL_CHOICES:
        raise EvaluationSetupError(
            f"protocol: expected one of {list(PROTOCOL_CHOICES)}, got {protocol!r}"
        )
    return PROTOCOLS if protocol == "both" else (protocol,)


def _classes(classes: Sequence[int] | None) -> tuple[int, ...] | None:
    if classes is None:
        return None
    out: list[int] = []
    for c in classes:
        if isinstance(c, bool) or not isinstance(c, int | np.integer) or not 0 <= c < FREE_LABEL:
            raise EvaluationSetupError(
                f"classes: expected class ids in 0..{FREE_LABEL - 1} (17 = free is never "
                f"averaged), got {c!r}"
            )
        if int(c) not in out:
            out.append(int(c))
    if not out:
        raise EvaluationSetupError("classes: expected at least one class id")
    return tuple(out)


def _ground_truth(root: Path) -> tuple[Path, list[tuple[str, str]]]:
    """The folder holding ``<scene>/<token>/labels.npz`` (``root/gts`` as Occ3D ships it,
    or ``root`` itself: the ``gts`` folder, or SparseOcc's ``data/nuscenes/occ3d``) and
    its ``(scene, token)`` samples, sorted."""
    if not root.is_dir():
        raise EvaluationSetupError(f"--gt: {root} is not an existing directory")
    labels_root = root / "gts" if (root / "gts").is_dir() else root
    samples = sorted(_walk_ground_truth(labels_root))
    if not samples:
        raise EvaluationSetupError(
            f"--gt: no ground truth under {root}: expected gts/<scene>/<token>/"
            f"{LABELS_FILENAME} (the Occ3D release) or <scene>/<token>/{LABELS_FILENAME}"
        )
    return labels_root, samples


def _folders(folder: Path) -> list[Path]:
    """The sub-folders of ``folder`` (symlinks to folders included); a folder that cannot
    be listed is a setup error naming it, never a silent omission (as ``glob`` makes it)."""
    try:
        with os.scandir(folder) as entries:
            names = [entry.name for entry in entries]
    except OSError as exc:
        raise EvaluationSetupError(
            f"--gt: {folder}: cannot be read ({exc.strerror or exc}); fix its permissions or "
            "remove it from the tree"
        ) from None
    return [folder / name for name in names if (folder / name).is_dir()]


def _walk_ground_truth(labels_root: Path) -> list[tuple[str, str]]:
    """``(scene, token)`` of every ``<scene>/<token>/labels.npz``; a ``labels.npz`` that is
    a dangling link or not a regular file, or a folder that cannot be read, is a setup
    error (a token folder without ``labels.npz`` is not a sample)."""
    samples = []
    for scene in _folders(labels_root):
        for token in _folders(scene):
            labels = token / LABELS_FILENAME
            try:
                regular = labels.is_file()
                present = regular or os.path.lexists(labels)
            except OSError as exc:
                raise EvaluationSetupError(
                    f"--gt: {labels}: cannot be read ({exc.strerror or exc})"
                ) from None
            if present and not regular:
                what = "a dangling link" if not labels.exists() else "not a regular file"
                raise EvaluationSetupError(
                    f"--gt: {labels}: {what}; expected the sample's labels archive"
                )
            if regular:
                samples.append((scene.name, token.name))
    return samples


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
) -> tuple[Plan, OriginsFn | None]:
    """Select the samples and check predictions and origins for all of them up front.

    Returns the plan and the origins of every sample (``None`` without RayIoU), opened
    once here: this process scores with them, spawned workers open their own.
    Raises :class:`EvaluationSetupError` naming the option, file or tokens at fault.
    """
    protocols, class_ids = _protocols(protocol), _classes(classes)
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
    labels_root, tree_samples = _ground_truth(Path(gt))
    scene_of = {token: scene for scene, token in tree_samples}

    keyframes = None
    if source is not None and source.kind != "origins" and (rayiou or source.kind == "infos"):
        keyframes = load_keyframes(source)
    if source is not None and source.kind == "infos" and keyframes is not None:
        tokens = [str(k.token) for k in keyframes]  # SparseOcc iterates the infos
        no_gt = [t for t in tokens if t not in scene_of]
        if no_gt:
            raise EvaluationSetupError(
                f"--infos {source.path}: {len(no_gt)} sample(s) have no ground truth under "
                f"{labels_root} (expected <scene>/<token>/{LABELS_FILENAME}): "
                f"{list_tokens(no_gt)}"
            )
        pairs = [(scene_of[t], t) for t in tokens]
    else:
        pairs = list(tree_samples)
    if not pairs:
        raise EvaluationSetupError("no samples to score")

    samples, missing_tokens = [], []
    for scene, token in pairs:
        try:
            path = find_prediction(pred_root, scene, token)
        except OSError as exc:  # a folder on the way that cannot be read
            raise EvaluationSetupError(
                f"--pred: {exc.filename or pred_root}: cannot be read ({exc.strerror or exc})"
            ) from None
        if path is None:
            missing_tokens.append(token)
            if missing == "skip":
                continue
        samples.append(Sample(scene, token, None if path is None else str(path)))
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
    )
    origins_fn = None
    # every origin exists (files) or every token is a keyframe (poses); source is not None
    if rayiou and source is not None:
        origins_fn = open_origins(source, scene_of, [s.token for s in samples], keyframes)
    return plan, origins_fn


# ----------------------------------------------------------------------------------------
# Scoring: the per-sample loop and the counts
# ----------------------------------------------------------------------------------------


class Tally:
    """The metrics of one process plus the sample / ray counters and the failures."""

    def __init__(self, plan: Plan) -> None:
        self.plan = plan
        device = torch.device(plan.device)
        self.metrics: dict[str, OccupancyMetrics | RayIoU] = {
            name: OccupancyMetrics(name, device=device) for name in plan.protocols
        }
        if plan.rayiou:
            self.metrics["rayiou"] = RayIoU(class_ids=plan.classes, device=device)
        self.scored = self.origins = self.rays_cast = 0
        self.failed: list[SampleFailure] = []

    def score(self, sample: Sample, origins_fn: OriginsFn | None) -> None:
        """Read, check and count one sample; a failure is recorded, not raised."""
        device = torch.device(self.plan.device)
        gt_path = Path(self.plan.gt) / sample.scene / sample.token / LABELS_FILENAME
        where = str(gt_path)
        try:
            labels = load_occ3d_labels(gt_path).to(device)
            if sample.prediction is None:
                pred = torch.full(labels.shape, FREE_LABEL, dtype=torch.uint8, device=device)
            else:
                where = sample.prediction
                pred = load_prediction(sample.prediction, expected_shape=labels.shape).to(device)
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
                    counts[name] = metric._spec.counts(
                        pred, labels.semantics, origins, rays=metric.rays
                    )
                else:
                    counts[name] = metric._spec.counts(pred, labels.semantics, labels.mask_camera)
        except (OSError, ValueError, TypeError, KeyError) as exc:
            message = str(exc) if where in str(exc) else f"{where}: {exc}"
            self.failed.append(SampleFailure(sample.token, where, message))
            return
        for name, metric in self.metrics.items():  # all read: add them together
            for count_name, count in zip(metric.COUNTS, counts[name], strict=True):
                getattr(metric, count_name).add_(count.to(getattr(metric, count_name).device))
            metric._changed()
        self.scored += 1
        if "rayiou" in self.metrics:
            self.origins += k
            self.rays_cast += k * int(cast(RayIoU, self.metrics["rayiou"]).rays.shape[0])

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
        dist.all_gather_object(gathered, self.failed)
        order = {s.token: i for i, s in enumerate(self.plan.samples)}
        failed = [f for part in gathered for f in part]
        self.failed = sorted(failed, key=lambda f: order.get(f.token, len(order)))

    def state(self) -> dict[str, Any]:
        """The (synced) totals as plain data: numpy counts, ints, failures."""
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
    counts = {
        metric: {name: torch.as_tensor(np.asarray(c)) for name, c in parts.items()}
        for metric, parts in state["counts"].items()
    }
    protocols: dict[str, OccupancyReport] = {}
    ray_report = None
    rays_scored = 0
    if state["scored"] > 0:
        for name in plan.protocols:
            spec = OccupancyMetrics(name)._spec
            report = spec.report(counts[name]["confusion"], counts[name]["geometric"])
            if plan.classes is not None:
                report = OccupancyReport.from_per_class(
                    report.per_class,
                    evaluated_classes=plan.classes,
                    groups=report.groups,
                    class_names=report.class_names,
                    iou=report.iou,
                    protocol=report.protocol,
                )
            protocols[name] = report
        if plan.rayiou:
            ray = counts["rayiou"]
            rays_scored = int(ray["gt_count"].sum())
            if rays_scored > 0:
                ray_spec = RayIoU(class_ids=plan.classes)._spec
                ray_report = ray_spec.report(
                    ray["gt_count"], ray["pred_count"], ray["true_positives"]
                )
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
        samples_scored=int(state["scored"]),
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
    )


def _rays_per_origin() -> int:
    return int(generate_lidar_rays().shape[0])


# ----------------------------------------------------------------------------------------
# Running: one process, spawned workers, torchrun
# ----------------------------------------------------------------------------------------


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


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
        torch.set_num_threads(max(1, _cpus() // world_size))
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=world_size)
    try:
        on_sample = (lambda: events.put(("tick", rank))) if report_progress else None
        tally = score_shard(plan, rank, world_size, on_sample=on_sample)
        tally.sync()
        if rank == 0:
            events.put(("result", tally.state()))
    finally:
        dist.destroy_process_group()


def _stop(processes: Sequence[Any]) -> None:
    """Terminate the workers still running and wait for them (before their store goes)."""
    for process in processes:
        if process.is_alive():
            process.terminate()
    for process in processes:
        process.join(5)
        if process.is_alive():
            process.kill()
            process.join()


def _exit_message(error: Any) -> str:
    """One line for a worker that died: which, how, and what to try."""
    how = (
        f"was killed by {error.signal_name}"
        if error.signal_name
        else f"exited with status {error.exit_code}"
    )
    return (
        f"evaluation worker {error.error_index} (pid {error.error_pid}) {how}; no report was "
        "made. If the machine ran out of memory (the kernel's OOM killer sends SIGKILL), run "
        "again with fewer --workers"
    )


def _unguarded_main_line() -> tuple[str, int] | None:
    """``(file, line)`` of the running top-level statement of the ``__main__`` script when
    spawned processes would run it again (it is not under ``if __name__ == "__main__":``),
    else ``None``. Mirrors ``multiprocessing``'s spawn: a package's ``__main__`` (``python
    -m pkg``), an interactive session or a notebook is not re-run."""
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    path = getattr(main, "__file__", None)
    if main is None or path is None or (spec is not None and spec.name.endswith("__main__")):
        return None
    frame = inspect.currentframe()
    while frame is not None and not (
        frame.f_code.co_name == "<module>" and frame.f_globals.get("__name__") == "__main__"
    ):
        frame = frame.f_back
    if frame is None:
        return None
    line = frame.f_lineno
    try:
        tree = ast.parse(Path(path).read_text(), filename=str(path))
    except (OSError, SyntaxError, ValueError):
        return None
    for node in tree.body:
        if isinstance(node, ast.If) and _is_main_test(node.test):
            end = node.end_lineno or node.lineno
            if node.lineno <= line <= end:
                return None
    return str(path), line


def _is_main_test(test: ast.expr) -> bool:
    """Whether ``test`` is ``__name__ == "__main__"`` (either way round)."""
    if not (isinstance(test, ast.Compare) and len(test.ops) == 1):
        return False
    sides = [test.left, test.comparators[0]]
    names = [s.id for s in sides if isinstance(s, ast.Name)]
    values = [s.value for s in sides if isinstance(s, ast.Constant)]
    return isinstance(test.ops[0], ast.Eq) and names == ["__name__"] and values == ["__main__"]


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


def _plan_summary(plan: Plan) -> dict[str, Any]:
    """What every rank's plan must agree on before the samples are sharded: the samples
    (with whether each has a prediction), the missing policy, protocols, classes and the
    origin source (not the roots' paths, which may differ between nodes)."""
    source = plan.source
    return {
        "samples": [[s.scene, s.token, s.prediction is not None] for s in plan.samples],
        "missing": [plan.missing_policy, list(plan.missing_tokens)],
        "protocols": list(plan.protocols),
        "rayiou": plan.rayiou,
        "classes": None if plan.classes is None else list(plan.classes),
        "origins": None if source is None else [source.kind, source.version],
    }


def _plan_differences(mine: dict[str, Any], theirs: dict[str, Any], rank: int) -> str:
    """What rank ``rank``'s plan summary changes from rank 0's, in a few words."""
    parts = []
    for key in mine:
        if mine[key] == theirs[key]:
            continue
        if key == "samples":
            here = {tuple(s[:2]) for s in mine[key]}
            there = {tuple(s[:2]) for s in theirs[key]}
            lacking = sorted(t for _, t in here - there)
            extra = sorted(t for _, t in there - here)
            text = f"samples: {len(mine[key])} on rank 0, {len(theirs[key])} on rank {rank}"
            if lacking:
                text += f" (rank {rank} lacks {list_tokens(lacking)})"
            if extra:
                text += f" (only rank {rank} has {list_tokens(extra)})"
            if not lacking and not extra:
                text += " (the same tokens; the predictions found differ)"
            parts.append(text)
        else:
            parts.append(f"{key}: {mine[key]!r} on rank 0, {theirs[key]!r} on rank {rank}")
    return "; ".join(parts)


def _check_plans_agree(plan: Plan) -> None:
    """Under torch.distributed, raise :class:`EvaluationSetupError` on every rank when the
    ranks' plans differ (a partial copy of the tree on one node), before anything is
    sharded or pooled: each rank shards its own plan, and mismatched shards would pool
    wrong counts. A digest is compared first; the summaries only when it differs."""
    summaries = gathered_if_different(_plan_summary(plan), None, torch.device("cpu"))
    if summaries is None:
        return
    differences = [
        f"rank {rank}: {_plan_differences(summaries[0], theirs, rank)}"
        for rank, theirs in enumerate(summaries)
        if theirs != summaries[0]
    ]
    raise EvaluationSetupError(
        "the ranks see different evaluations (" + "; ".join(differences) + "): every rank "
        "must see the same ground truth, predictions and options"
    )


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
) -> EvaluationReport:
    """Score a folder of Occ3D-nuScenes predictions against the ground truth, on CPU.

    Args:
        gt: the Occ3D root holding ``gts/<scene>/<token>/labels.npz``.
        pred: the predictions: ``<token>.npz`` (array ``pred``, ``arr_0`` or
            ``semantics``), ``<token>.npy``, or ``<scene>/<token>/labels.npz`` (also under
            ``gts/``); ``(200, 200, 16)`` integer labels, 17 = free.
        protocol: ``"occ3d"``, ``"weak"`` or ``"both"``.
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
            torch.set_num_threads(max(1, _cpus() // max(local, 1)))
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
