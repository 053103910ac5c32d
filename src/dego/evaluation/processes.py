"""Process plumbing of the evaluation engine: CPU counts, stopping spawned workers, the
one-line message of a worker that died, the unguarded-``__main__`` check of ``workers=N``,
and the per-rank plan summaries compared under torch.distributed."""

from __future__ import annotations

import ast
import inspect
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from dego.evaluation.errors import EvaluationSetupError, list_tokens
from dego.metrics.counts import gathered_if_different


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


def _plan_summary(plan: Any) -> dict[str, Any]:
    """What every rank's plan must agree on before the samples are sharded: the samples
    (with whether each has a prediction), the missing policy, protocols, classes and the
    origin source (not the roots' paths, which may differ between nodes)."""
    source = plan.source
    return {
        "samples": [[s.scene, s.token, s.prediction is not None] for s in plan.samples],
        "missing": [plan.missing_policy, list(plan.missing_tokens)],
        "protocols": list(plan.protocols),
        "rayiou": plan.rayiou,
        "benchmark": [plan.benchmark, plan.mave],
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


def _check_plans_agree(plan: Any) -> None:
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


__all__: list[str] = []
