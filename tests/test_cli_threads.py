"""Issue 41 (2): ``--threads N`` on the commands that compute: checked while parsing,
applied before any work (this process, and OMP_NUM_THREADS for the processes it starts)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

import dego.demo.command
import dego.demo.study.command
from dego.cli import main
from dego.evaluation import command as eval_command
from tests.helpers.cli_faults import usage_error
from tests.helpers.repo import ROOT, needs_source_tree


@pytest.fixture
def restored_threads(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    monkeypatch.setenv("OMP_NUM_THREADS", "7")  # restored by monkeypatch afterwards
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("command", ["demo", "study", "train", "eval"])
def test_bad_threads_are_usage_errors(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    extra = ["--gt", str(tmp_path), "--pred", str(tmp_path)] if command == "eval" else []
    for value in ("0", "-2", "two", str(eval_command.MAX_THREADS + 1)):
        assert "--threads" in usage_error([command, *extra, "--threads", value], capsys)


@pytest.mark.parametrize("command", ["demo", "study", "train"])
def test_threads_apply_before_the_work(
    command: str, restored_threads: None, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import os

    seen: list[tuple[int, str | None]] = []

    def started(*args: object, **kwargs: object) -> int:
        seen.append((torch.get_num_threads(), os.environ.get("OMP_NUM_THREADS")))
        return 0

    if command == "train":
        from dego.demo.feedforward import command as train_command

        monkeypatch.setattr(train_command, "run_feedforward_study", started)
    else:
        module = dego.demo.command if command == "demo" else dego.demo.study.command
        monkeypatch.setattr(module, f"run_{command}", started)
    argv = [command, "--quick", "--out", str(tmp_path / "out"), "--threads", "1"]
    if command == "train":
        argv += ["--no-cache"]
    # what follows the stand-in does not matter: the threads were applied before it
    with contextlib.suppress(AttributeError, TypeError):
        main(argv)
    assert seen and seen[0] == (1, "1")


def test_eval_applies_threads(restored_threads: None, monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    seen: list[tuple[int, str | None]] = []

    def evaluate(*args: object, **kwargs: object) -> None:
        seen.append((torch.get_num_threads(), os.environ.get("OMP_NUM_THREADS")))
        raise eval_command.EvaluationSetupError("stop here")

    monkeypatch.setattr(eval_command, "evaluate", evaluate)
    assert main(["eval", "--gt", "g", "--pred", "p", "--threads", "1"]) == 2
    assert seen == [(1, "1")]


# -- issue 51 (1): --threads auto, the default -------------------------------------------------


@pytest.fixture
def auto_ready(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """No OMP_NUM_THREADS (the suite's workers set one) and torch on 2 threads, so that
    ``auto`` has something to decide; both restored afterwards."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)  # restored by monkeypatch afterwards
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def _load(monkeypatch: pytest.MonkeyPatch, busy: bool) -> float:
    """Make ``os.getloadavg`` report a load above this machine's cores (``busy``) or none."""
    import os

    from dego import _cli_args

    load = _cli_args.usable_cores() + 1.1 if busy else 0.0
    monkeypatch.setattr(os, "getloadavg", lambda: (load, load, load))
    return load


@pytest.mark.parametrize(
    ("load", "cores", "expected"),
    [
        (3.1, 2, 1),  # the machine: other jobs on both cores
        (1.0, 2, 1),  # one other job
        (0.8, 2, 1),  # cores - 1.2: one other job, 1.6 minutes after it started
        (0.7, 2, None),  # more than one core free: torch's default
        (0.0, 2, None),  # idle
        (None, 2, None),  # unknown (no os.getloadavg: Windows)
        (float("nan"), 2, None),
        (14.8, 16, 1),
        (14.7, 16, None),
        (0.0, 1, 1),  # one core: one thread, torch's default there too
    ],
)
def test_auto_threads_is_one_on_a_busy_machine(
    load: float | None, cores: int, expected: int | None
) -> None:
    from dego import _cli_args

    assert _cli_args.auto_threads(load, cores) == expected


@pytest.mark.parametrize("command", ["demo", "study", "train", "eval"])
def test_threads_auto_parses_and_is_the_default(command: str) -> None:
    from dego.cli import build_parser

    extra = ["--gt", "g", "--pred", "p"] if command == "eval" else []
    parser = build_parser(load=[command])
    assert parser.parse_args([command, *extra]).threads == "auto"
    assert parser.parse_args([command, *extra, "--threads", "auto"]).threads == "auto"
    assert parser.parse_args([command, *extra, "--threads", "1"]).threads == 1
    help_text = " ".join(parser.parse_args([command, *extra]).command_parser.format_help().split())
    assert "auto (the default)" in help_text and "OMP_NUM_THREADS" in help_text


def test_apply_threads_returns_what_it_set(
    auto_ready: None, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import os

    from dego._cli_args import apply_threads

    _load(monkeypatch, busy=True)
    assert apply_threads(1) == 1 and torch.get_num_threads() == 1
    assert os.environ["OMP_NUM_THREADS"] == "1"
    assert apply_threads(None) is None and torch.get_num_threads() == 1
    assert capsys.readouterr().err == ""  # an explicit count is not announced


@pytest.mark.parametrize("how", ["idle", "unknown", "omp"])
def test_auto_leaves_torch_alone_unless_busy(
    how: str,
    auto_ready: None,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    import os

    from dego._cli_args import apply_threads

    if how == "idle":
        _load(monkeypatch, busy=False)
    elif how == "unknown":
        monkeypatch.delattr(os, "getloadavg")
    else:  # the user's OMP_NUM_THREADS wins, however busy the machine
        _load(monkeypatch, busy=True)
        monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert apply_threads("auto") is None
    assert torch.get_num_threads() == 2
    assert os.environ.get("OMP_NUM_THREADS") == ("2" if how == "omp" else None)
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("command", ["demo", "study", "train", "eval"])
def test_a_busy_machine_runs_the_command_on_one_thread(
    command: str,
    auto_ready: None,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    import os

    from dego import _cli_args

    load = _load(monkeypatch, busy=True)
    seen: list[tuple[int, str | None]] = []

    def started(*args: object, **kwargs: object) -> int:
        seen.append((torch.get_num_threads(), os.environ.get("OMP_NUM_THREADS")))
        if command == "eval":
            raise eval_command.EvaluationSetupError("stop here")
        return 0

    if command == "eval":
        monkeypatch.setattr(eval_command, "evaluate", started)
        argv = ["eval", "--gt", "g", "--pred", "p"]
    else:
        if command == "train":
            from dego.demo.feedforward import command as train_command

            monkeypatch.setattr(train_command, "run_feedforward_study", started)
        else:
            module = dego.demo.command if command == "demo" else dego.demo.study.command
            monkeypatch.setattr(module, f"run_{command}", started)
        argv = [command, "--quick", "--out", str(tmp_path / "out")]
        argv += ["--no-cache"] if command == "train" else []
    with contextlib.suppress(AttributeError, TypeError):  # what follows the stand-in
        main(argv)
    assert seen and seen[0] == (1, "1")
    cores = _cli_args.usable_cores()
    note = f"dego: threads: 1 (auto: load {load:.1f} on {cores} cores; --threads N to choose)"
    assert capsys.readouterr().err.splitlines().count(note) == 1  # once, though eval applies twice


def test_an_idle_machine_keeps_torchs_threads_and_quiet_silences_the_note(
    auto_ready: None, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import os

    seen: list[tuple[int, str | None]] = []

    def evaluate(*args: object, **kwargs: object) -> None:
        seen.append((torch.get_num_threads(), os.environ.get("OMP_NUM_THREADS")))
        raise eval_command.EvaluationSetupError("stop here")

    monkeypatch.setattr(eval_command, "evaluate", evaluate)
    _load(monkeypatch, busy=False)
    assert main(["eval", "--gt", "g", "--pred", "p"]) == 2
    assert "threads" not in capsys.readouterr().err
    _load(monkeypatch, busy=True)
    assert main(["eval", "--gt", "g", "--pred", "p", "--quiet"]) == 2
    assert "threads" not in capsys.readouterr().err
    assert seen == [(2, None), (1, "1")]


@needs_source_tree
def test_the_documented_threshold_is_the_code_s() -> None:
    from dego._cli_args import BUSY_MARGIN, THREADS_HELP

    assert ROOT is not None
    page = " ".join((ROOT / "docs" / "performance.md").read_text().split())
    assert f"minus {BUSY_MARGIN}" in page and f"cores - {BUSY_MARGIN}" in page
    assert f"cores - {BUSY_MARGIN}" in THREADS_HELP
