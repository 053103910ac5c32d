"""`dego eval` over several processes through torch.distributed (gloo, real processes):
``--workers 2`` (spawned) and a 2-rank torchrun give the numbers of one process."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch.distributed as dist

from dego.cli import main as cli_main
from tests.helpers.evaluation import TOKENS, direct, make_tree

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not dist.is_available(), reason="torch.distributed is not available"),
]


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    return make_tree(tmp_path_factory.mktemp("occ3d"))


def test_two_spawned_workers_equal_one_process(
    tree: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pred = Path(shutil.copytree(tree["pred"], tmp_path / "pred"))
    (pred / "tok-b0.npy").write_bytes(b"garbage")  # scored by rank 1: its failure is gathered
    json_path = tmp_path / "r.json"
    code = cli_main(
        [
            *("eval", "--gt", str(tree["gt"]), "--pred", str(pred)),
            *("--origins", str(tree["origins"]), "--workers", "2", "--json", str(json_path)),
        ]
    )
    out, err = capsys.readouterr()
    assert code == 1, err
    data = json.loads(json_path.read_text())
    assert data["world_size"] == 2 and data["samples"] == 5
    assert [f["token"] for f in data["failed"]] == ["tok-b0"]
    expected = direct(tree, [t for t in TOKENS if t != "tok-b0"], rayiou=True)
    for name, metric in expected.items():
        for count in metric.COUNTS:
            assert data["counts"][name][count] == getattr(metric, count).tolist(), (name, count)
    assert data["rayiou"]["rayiou"] == 100 * expected["rayiou"].compute().rayiou
    assert data["weak"]["miou"] == 100 * expected["weak"].compute().miou
    assert data["rays"]["scored"] == int(expected["rayiou"].gt_count.sum())
    assert "eval: 6/6 samples (100%)" in err  # the parent drew the progress of both ranks
    assert "INCOMPLETE" in out


def test_torchrun_two_ranks_equal_one_process(tree: dict, tmp_path: Path) -> None:
    json_path = tmp_path / "r.json"
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    command += ["--nproc_per_node", "2", "-m", "dego", "eval", "--gt", str(tree["gt"])]
    command += ["--pred", str(tree["pred"]), "--no-rayiou", "--json", str(json_path)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=240)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.count("protocol: weak") == 1  # rank 0 prints, once
    data = json.loads(json_path.read_text())
    assert data["world_size"] == 2 and data["samples"] == 6 and data["complete"]
    expected = direct(tree)
    for name in ("occ3d", "weak"):
        assert data["counts"][name]["confusion"] == expected[name].confusion.tolist()
        assert data["counts"][name]["geometric"] == expected[name].geometric.tolist()
        assert data[name]["miou"] == 100 * expected[name].compute().miou


RANK_DIRECTORY = r"""
import os, sys
os.chdir(os.environ["DEGO_TEST_ROOT"] + "/rank" + os.environ["LOCAL_RANK"])
from dego.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_torchrun_ranks_seeing_different_trees_refuse(tree: dict, tmp_path: Path) -> None:
    """Issue 38 (1): rank 1's --gt lacked a sample (a partial copy on a second node); both
    ranks exited 0 and rank 0's report differed from one process's. The same flags, run
    from a folder per rank: every rank now refuses, naming what differs, before scoring."""
    for rank in (0, 1):
        shutil.copytree(tree["gt"], tmp_path / f"rank{rank}" / "gt")
        shutil.copytree(tree["pred"], tmp_path / f"rank{rank}" / "pred")
    shutil.rmtree(tmp_path / "rank1" / "gt" / "gts" / "scene-b" / "tok-b1")
    script = tmp_path / "per_rank.py"
    script.write_text(RANK_DIRECTORY)
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    command += ["--nproc_per_node", "2", str(script), "eval", "--gt", "gt", "--pred", "pred"]
    command += ["--no-rayiou", "--quiet"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "DEGO_TEST_ROOT": str(tmp_path)}
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=240)
    assert result.returncode != 0
    # every rank raises; torchrun may stop a rank once the other has exited, so one or two
    # lines, and its own launcher's traceback, but no frame of dego's
    lines = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert 1 <= len(lines) <= 2, result.stderr[-3000:]
    for line in lines:
        assert "the ranks see different evaluations" in line
        assert "samples: 6 on rank 0, 5 on rank 1 (rank 1 lacks 'tok-b1')" in line
    frames = [line for line in result.stderr.splitlines() if line.strip().startswith("File ")]
    assert not [f for f in frames if "/dego/" in f and "torch" not in f], frames


# issue 38 (7, 8): a worker killed, and Ctrl-C, during --workers


def _plan(tree: dict) -> object:
    from dego.evaluation.run import prepare

    plan, _ = prepare(tree["gt"], tree["pred"], rayiou=False)
    return plan


def test_a_killed_worker_is_one_error_line(
    tree: dict, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 38 (7): kill -9 of a worker (the OOM killer's way) ended in a 31-line
    ProcessExitedException traceback."""
    from dego.evaluation import EvaluationWorkerError
    from dego.evaluation import run as evaluation_run
    from dego.evaluation.progress import Progress
    from tests.helpers.eval_workers import killed_worker

    with pytest.raises(EvaluationWorkerError, match=r"worker 1 \(pid \d+\) was killed by SIGKILL"):
        evaluation_run._run_workers(
            _plan(tree), 2, Progress(6, enabled=False), target=killed_worker
        )
    real = evaluation_run._run_workers

    def run_killed(plan: object, workers: int, progress: object) -> object:
        return real(plan, workers, progress, target=killed_worker)

    monkeypatch.setattr(evaluation_run, "_run_workers", run_killed)
    args = ["eval", "--gt", str(tree["gt"]), "--pred", str(tree["pred"]), "--no-rayiou"]
    code = cli_main([*args, "--workers", "2", "--quiet"])
    out, err = capsys.readouterr()
    assert code == 1 and out == ""
    assert err.startswith("error: evaluation worker 1") and err.count("\n") == 1
    assert "fewer --workers" in err


def test_ctrl_c_stops_the_workers_before_their_store_goes(
    tree: dict, capfd: pytest.CaptureFixture[str]
) -> None:
    """Issue 38 (8): Ctrl-C during --workers printed 87 lines of worker tracebacks, and
    SIGINT to the parent alone 25 lines of FileNotFoundError (the store removed under
    running workers). The workers ignore SIGINT; the parent stops them, then cleans up."""
    import glob
    import signal
    import tempfile
    import threading
    import time

    from dego.evaluation import run as evaluation_run
    from dego.evaluation.progress import Progress
    from tests.helpers.eval_workers import busy_worker

    before = set(glob.glob(os.path.join(tempfile.gettempdir(), "dego-eval-*")))
    pids: list[int] = []

    def interrupt() -> None:  # once both workers run: SIGINT to them and to us, as a tty
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            marks = set(glob.glob(os.path.join(tempfile.gettempdir(), "dego-eval-*", "store.*")))
            if len(marks) == 2:
                pids.extend(int(Path(m).read_text()) for m in marks)
                break
            time.sleep(0.05)
        for pid in pids:
            os.kill(pid, signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=interrupt, daemon=True).start()
    with pytest.raises(KeyboardInterrupt):
        evaluation_run._run_workers(_plan(tree), 2, Progress(6, enabled=False), target=busy_worker)
    assert len(pids) == 2
    for pid in pids:  # stopped and reaped
        status = Path(f"/proc/{pid}/status")
        assert not status.exists() or "zombie" in status.read_text()
    assert set(glob.glob(os.path.join(tempfile.gettempdir(), "dego-eval-*"))) == before
    err = capfd.readouterr().err
    assert "Traceback" not in err and "FileNotFoundError" not in err
