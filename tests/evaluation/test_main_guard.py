"""Issue 41 (8): ``dego.evaluate(workers=2)`` in a script without a main guard is one clear
RuntimeError before any process starts (spawned workers would import the script and run
the evaluation again: 155 lines of tracebacks before)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.evaluation import make_tree
from tests.helpers.repo import ROOT

CALL = "dego.evaluate({gt!r}, {pred!r}, rayiou=False, workers=2, progress=False)"


def run_script(path: Path, body: str) -> subprocess.CompletedProcess[str]:
    path.write_text(body)
    env = dict(os.environ)
    if ROOT is not None:  # the source tree's dego, as the tests import it
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src"), env.get("PYTHONPATH", "")])
    return subprocess.run(
        [sys.executable, str(path)], capture_output=True, text=True, timeout=300, env=env
    )


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> dict:
    return make_tree(tmp_path_factory.mktemp("tree"))


@pytest.mark.slow
@pytest.mark.parametrize("wrapped", [False, True], ids=["top-level", "in-main-function"])
def test_an_unguarded_call_is_one_runtime_error(tree: dict, tmp_path: Path, wrapped: bool) -> None:
    call = CALL.format(gt=str(tree["gt"]), pred=str(tree["pred"]))
    body = "import dego\n" + (f"def main():\n    {call}\n\nmain()\n" if wrapped else call + "\n")
    result = run_script(tmp_path / "unguarded.py", body)
    assert result.returncode == 1
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("RuntimeError: workers=2: ") and 'if __name__ == "__main__":' in last
    assert "unguarded.py, line" in last
    assert len(result.stderr.splitlines()) < 20  # the parent's short traceback, no worker's


@pytest.mark.slow
def test_a_guarded_call_runs_its_workers(tree: dict, tmp_path: Path) -> None:
    call = CALL.format(gt=str(tree["gt"]), pred=str(tree["pred"]))
    body = f'import dego\n\nif __name__ == "__main__":\n    report = {call}\n    print(report.complete)\n'
    result = run_script(tmp_path / "guarded.py", body)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "True"
