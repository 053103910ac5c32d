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
