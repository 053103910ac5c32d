"""The ``dego`` command under faults: bad flags, bad output paths, a full disk, Ctrl-C.

Nothing here runs a fit: bad flags must be refused before any work starts (the work
functions are replaced by ones that fail the test), writers are driven directly with a
failure injected into the file writes, and the Ctrl-C tests interrupt real processes.
"""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

import dego.demo.command
import dego.demo.feedforward.command
import dego.demo.study.command
import dego.evaluation.command
from dego.cli import main
from tests.helpers.cli_faults import FullDisk, usage_error
from tests.helpers.repo import ROOT, needs_source_tree


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Starting a demo, a study, a training or an evaluation fails the test: validation
    must come first."""

    def started(*args: object, **kwargs: object) -> int:
        raise AssertionError("the work started before the flags were checked")

    monkeypatch.setattr(dego.demo.command, "run_demo", started)
    monkeypatch.setattr(dego.demo.study.command, "run_study", started)
    monkeypatch.setattr(dego.demo.feedforward.command, "run_feedforward_study", started)
    monkeypatch.setattr(dego.evaluation.command, "evaluate", started)


# -- bad flags are usage errors before any work -------------------------------------------


@pytest.mark.parametrize(
    ("arguments", "flag"),
    [
        (["--device", "meta"], "--device"),
        (["--device", "mps"], "--device"),
        (["--device", "cuda:99"], "--device"),
        (["--device", "cpu:3"], "--device"),
        (["--seed", "-1"], "--seed"),
        (["--seed", str(2**70)], "--seed"),
        (["--seed", str(2**32)], "--seed"),
        (["--frames", "100000"], "--frames"),
        (["--iterations", str(10**9)], "--iterations"),
        (["--gaussians", str(10**9)], "--gaussians"),
        (["--frames", "2", "--gaussians", str(2 * 6 * 64 * 176 + 1)], "--gaussians"),
    ],
)
def test_bad_demo_flags_are_usage_errors_before_any_work(
    arguments: list[str], flag: str, no_work: None, capsys: pytest.CaptureFixture[str]
) -> None:
    assert flag in usage_error(["demo", *arguments], capsys)


@pytest.mark.parametrize(
    ("arguments", "flag", "also"),
    [
        (["--seeds", "1,1"], "--seeds", "1"),
        (["--seeds", "0-3,2"], "--seeds", "2"),
        (["--budgets", "500,500"], "--budgets", "500"),
        (["--variants", "static,rigid,static"], "--variants", "static"),
        (["--variants", ","], "--variants", "at least one"),
        (["--seeds", "-1"], "--seeds", ""),
        (["--seeds", str(2**32)], "--seeds", ""),
        (["--seeds", "0-10000000"], "--seeds", ""),
        (["--seeds", f"0-{10**15}"], "--seeds", ""),
        (["--seeds", "5-3"], "--seeds", ""),
        (["--frames", "100000"], "--frames", ""),
        (["--iterations", str(10**9)], "--iterations", ""),
        (["--budgets", str(10**9)], "--budgets", ""),
        (["--mask-prior", "inf"], "--mask-prior", ""),
        (["--device", "meta"], "--device", "meta"),
        (["--device", "cuda:99"], "--device", ""),
    ],
)
def test_bad_study_flags_are_usage_errors_before_any_work(
    arguments: list[str],
    flag: str,
    also: str,
    no_work: None,
    capsys: pytest.CaptureFixture[str],
) -> None:
    line = usage_error(["study", *arguments], capsys)
    assert flag in line and also in line


def test_study_config_refuses_duplicates() -> None:
    from dego.demo.study import StudyConfig

    for field, value in [("seeds", (1, 1)), ("budgets", (300, 300)), ("variants", ("rigid",) * 2)]:
        with pytest.raises(ValueError, match=f"^{field}: .*repeat"):
            StudyConfig(**{field: value})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^seeds: "):
        StudyConfig(seeds=(2**32,))


@pytest.mark.parametrize(
    ("arguments", "flag"),
    [
        (["--device", "meta"], "--device"),
        (["--device", "cuda:99"], "--device"),
        (["--workers", "100000"], "--workers"),
        (["--classes", f"0-{10**15}"], "--classes"),
    ],
)
def test_bad_eval_flags_are_usage_errors(
    arguments: list[str],
    flag: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from dego.evaluation import command

    def started(*args: object, **kwargs: object) -> None:
        raise AssertionError("the evaluation started before the flags were checked")

    monkeypatch.setattr(command, "evaluate", started)
    argv = ["eval", "--gt", str(tmp_path), "--pred", str(tmp_path), *arguments]
    assert flag in usage_error(argv, capsys)


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA exists here")
@pytest.mark.parametrize("command", ["demo", "study", "eval"])
def test_cuda_without_cuda_is_a_usage_error(
    command: str, no_work: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    extra = ["--gt", str(tmp_path), "--pred", str(tmp_path)] if command == "eval" else []
    line = usage_error([command, *extra, "--device", "cuda"], capsys)
    assert "--device" in line and "CUDA" in line


# -- output paths are checked (and created) before any work ---------------------------------


@pytest.mark.parametrize("command", ["demo", "study"])
def test_out_onto_a_file_is_a_usage_error(
    command: str, no_work: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    a_file = tmp_path / "taken"
    a_file.write_text("mine\n")
    assert "--out" in usage_error([command, "--out", str(a_file)], capsys)
    assert "--out" in usage_error([command, "--out", str(a_file / "below")], capsys)
    assert a_file.read_text() == "mine\n"


@pytest.mark.parametrize("command", ["demo", "study"])
def test_out_is_created_before_the_work_starts(
    command: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "new" / "deeper"
    seen = []

    def started(*args: object, **kwargs: object) -> int:
        seen.append(out.is_dir())
        raise KeyboardInterrupt

    if command == "demo":
        monkeypatch.setattr(dego.demo.command, "run_demo", started)
    else:
        monkeypatch.setattr(dego.demo.study.command, "run_study", started)
    assert main([command, "--quick", "--out", str(out)]) == 130
    assert seen == [True]
    assert not (tmp_path / "new").exists()  # interrupted: the folders it made are gone


def test_eval_output_paths_are_checked_before_scoring(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from dego.evaluation import command

    def started(*args: object, **kwargs: object) -> None:
        raise AssertionError("the evaluation started before the output paths were checked")

    monkeypatch.setattr(command, "evaluate", started)
    a_file = tmp_path / "taken"
    a_file.write_text("mine\n")
    base = ["eval", "--gt", str(tmp_path), "--pred", str(tmp_path)]
    for flag, path in [
        ("--json", tmp_path),
        ("--markdown", tmp_path),
        ("--json", a_file / "r.json"),
        ("--markdown", a_file / "sub" / "r.md"),
    ]:
        assert main([*base, flag, str(path)]) == 2, (flag, path)
        _, err = capsys.readouterr()
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and flag in lines[0], err
        assert "Traceback" not in err
    assert a_file.read_text() == "mine\n"


OCCUPIED = {
    "demo": (["demo", "--quick"], "losses.png", ["results.md", "results.json"]),
    "study": (["study", "--quick"], "study.png", ["study.md", "study.json"]),
    "train": (
        ["train", "--quick", "--variants", "static,rigid", "--no-cache"],
        "heldout_rigid.png",
        ["train.md", "train.json"],
    ),
}
"""Per command: its arguments, the output whose name a folder takes, its other outputs."""


@pytest.mark.parametrize("command", ["demo", "study", "train", "eval"])
def test_an_output_name_taken_by_a_folder_is_refused_before_any_work(
    command: str, no_work: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every file a command writes is checked before its work starts: a folder in the
    place of one (the last one written) is a usage error naming it, and the previous
    outputs stay as they were. (Was: demo, study and train ran to the end, then replaced
    the first outputs and failed on the folder with a traceback; eval checked already.)"""
    out = tmp_path / "out"
    if command == "eval":
        flag, taken, others = "--markdown", "report.md", ["report.json"]
        argv = ["eval", "--gt", str(tmp_path), "--pred", str(tmp_path)]
        argv += ["--json", str(out / "report.json"), "--markdown", str(out / taken)]
    else:
        flag, (argv, taken, others) = "--out", OCCUPIED[command]
        argv = [*argv, "--out", str(out)]
    before = _previous_run(out, others)
    (out / taken).mkdir()
    message = f"{flag}: {out / taken} is a directory, expected a file name"
    if command == "eval":
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.strip().splitlines() == [f"error: {message}"], err
    else:
        assert usage_error(argv, capsys) == f"dego {command}: error: {message}"
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
    assert sorted(p.name for p in out.iterdir()) == sorted([*before, taken])


needs_rerun = pytest.mark.skipif(
    importlib.util.find_spec("rerun") is None, reason="--rerun needs rerun-sdk"
)


@needs_rerun
@pytest.mark.parametrize("spelling", ["the same", "relative and absolute", "a symbolic link"])
@pytest.mark.parametrize("flag", ["--json", "--markdown"])
def test_eval_rerun_onto_a_report_is_refused_before_scoring(
    spelling: str,
    flag: str,
    no_work: None,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Was: exit 0, the report overwritten by the recording."""
    monkeypatch.chdir(tmp_path)
    recording = tmp_path / "r.rrd"
    report: Path = recording
    if spelling == "relative and absolute":
        report = Path("r.rrd")
    elif spelling == "a symbolic link":
        report = tmp_path / "link.txt"
        report.symlink_to(recording)
    argv = ["eval", "--gt", str(tmp_path), "--pred", str(tmp_path), flag, str(report)]
    assert main([*argv, "--rerun", str(recording)]) == 2
    err = capsys.readouterr().err
    assert err.strip().splitlines() == [f"error: {flag} and --rerun name the same file, {report}"]
    assert not recording.exists()


@needs_rerun
def test_demo_rerun_onto_one_of_its_outputs_is_refused_before_any_work(
    no_work: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    before = _previous_run(out, ["results.md", "results.json"])
    link = tmp_path / "demo.rrd"
    link.symlink_to(out / "results.json")
    line = usage_error(["demo", "--quick", "--out", str(out), "--rerun", str(link)], capsys)
    assert line == f"dego demo: error: --rerun and --out name the same file, {link}"
    assert _contents(out) == before


# -- every output is written whole or not at all ---------------------------------------------


def _previous_run(out: Path, names: list[str]) -> dict[str, bytes]:
    out.mkdir(parents=True, exist_ok=True)
    for name in names:
        (out / name).write_bytes(f"previous {name}\n".encode())
    return {name: (out / name).read_bytes() for name in names}


def _contents(out: Path) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in out.iterdir()}


def test_demo_results_are_written_whole_or_not_at_all(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "demo"
    before = _previous_run(out, ["results.json", "results.md"])
    budget = {"frames": 2, "iterations": 3, "gaussians": 300}
    arguments = (out, "| table |", ["rigid - static: +1.0"], {}, {}, {}, 0, budget)
    FullDisk(monkeypatch, tmp_path.resolve())
    with pytest.raises(OSError, match="No space left"):
        dego.demo.command._write_results(*arguments, torch.device("cpu"))
    assert _contents(out) == before  # the previous run, whole; no temporary files
    monkeypatch.undo()
    dego.demo.command._write_results(*arguments, torch.device("cpu"))
    assert set(_contents(out)) == set(before)
    assert b"| table |" in (out / "results.md").read_bytes()


def test_study_report_is_written_whole_or_not_at_all(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from dego.demo.study import MASK_METRICS, METRICS, StudyConfig, StudyRun, write_study

    out = tmp_path / "study"
    before = _previous_run(out, ["study.md", "study.json"])
    runs = [
        StudyRun(
            seed,
            10,
            variant,
            dict.fromkeys(METRICS, 1.0 + seed),
            dict.fromkeys(MASK_METRICS, 0.5),
            0.0,
            1.0,
        )
        for seed in range(2)
        for variant in ("static", "rigid")
    ]
    config = StudyConfig(seeds=(0, 1), budgets=(10,), variants=("static", "rigid"))
    FullDisk(monkeypatch, tmp_path.resolve())
    with pytest.raises(OSError, match="No space left"):
        write_study(runs, config, out, pictures=False)
    assert _contents(out) == before
    monkeypatch.undo()
    write_study(runs, config, out, pictures=False)
    assert set(_contents(out)) == set(before)
    assert (out / "study.md").read_text().startswith("# dego study")


def test_atomic_writer_is_all_or_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from dego._atomic import write_files, write_text

    before = _previous_run(tmp_path, ["a.txt", "b.bin"])
    files = {tmp_path / "a.txt": "new a\n", tmp_path / "b.bin": b"new b\n"}
    FullDisk(monkeypatch, tmp_path.resolve())
    with pytest.raises(OSError, match="No space left") as error:
        write_files(files)
    assert error.value.filename == str(tmp_path / "b.bin")  # the file, not a temporary one
    assert _contents(tmp_path) == before
    monkeypatch.undo()
    assert write_files(files) == list(files)
    assert _contents(tmp_path) == {"a.txt": b"new a\n", "b.bin": b"new b\n"}
    write_text(tmp_path / "sub" / "c.txt", "c\n")  # parents are created
    assert (tmp_path / "sub" / "c.txt").read_text() == "c\n"


def test_atomic_writer_refuses_a_folder_in_a_file_s_place_before_moving_any(
    tmp_path: Path,
) -> None:
    """Was: a.txt replaced, then the rename onto the folder failed: half-new files."""
    from dego._atomic import write_files

    before = _previous_run(tmp_path, ["a.txt", "c.txt"])
    (tmp_path / "b.png").mkdir()
    files = {tmp_path / name: f"new {name}\n" for name in ("a.txt", "b.png", "c.txt")}
    with pytest.raises(IsADirectoryError) as error:
        write_files(files)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.png", "c.txt"]
    assert error.value.filename == str(tmp_path / "b.png")


def test_atomic_writer_puts_back_what_it_replaced_when_a_move_fails(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A move that fails midway (here the third) leaves the files as they were: the
    replaced ones get their previous content back, a new one is removed again; the error
    names the target, not the temporary file."""
    import errno

    from dego._atomic import write_files

    before = _previous_run(tmp_path, ["a.txt", "c.txt"])
    files = {tmp_path / name: f"new {name}\n" for name in ("a.txt", "b.txt", "c.txt")}
    real_replace, moves = os.replace, []

    def replace(src: str | os.PathLike, dst: str | os.PathLike) -> None:
        if Path(src).name.endswith(".tmp") and not Path(dst).name.endswith(".tmp"):
            moves.append(Path(dst).name)
            if len(moves) == 3:
                raise OSError(errno.EIO, os.strerror(errno.EIO), os.fspath(src), os.fspath(dst))
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(OSError, match="Input/output error") as error:
        write_files(files)
    assert moves[:3] == ["a.txt", "b.txt", "c.txt"]  # then a.txt is put back
    assert _contents(tmp_path) == before  # b.txt (new) is gone again; no temporary files
    assert error.value.filename == str(tmp_path / "c.txt")
    monkeypatch.undo()
    write_files(files)
    assert _contents(tmp_path) == {path.name: f"new {path.name}\n".encode() for path in files}


# -- Ctrl-C -----------------------------------------------------------------------------------


_CAUGHT_INTERRUPT = """
import ctypes, sys

def interrupt_caught_inside_pyrun_string():
    run = ctypes.pythonapi.PyRun_String
    run.restype = ctypes.py_object
    run.argtypes = [ctypes.c_char_p, ctypes.c_int, ctypes.py_object, ctypes.py_object]
    try:  # what an extension calling PyRun_String during a Ctrl-C leaves behind
        run(b"raise KeyboardInterrupt", 257, {}, {})
    except KeyboardInterrupt:
        pass

def hook(event, args):  # as dego starts (a later PyRun_String that succeeds clears the note)
    if event == "import" and args[0] == "dego._entry" and not hasattr(sys, "_dego_hit"):
        sys._dego_hit = True
        interrupt_caught_inside_pyrun_string()

sys.addaudithook(hook)
"""


def test_python_m_dego_keeps_its_status_after_a_caught_interrupt(tmp_path: Path) -> None:
    # CPython remembers a KeyboardInterrupt that left PyRun_String, caught or not, and under
    # -m ends the process by SIGINT (returncode -2) instead of with main's status: the
    # cause of a Ctrl-C test that once ended with -2 after printing "dego: interrupted".
    (tmp_path / "sitecustomize.py").write_text(_CAUGHT_INTERRUPT)
    path = os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])
    done = subprocess.run(
        [sys.executable, "-m", "dego", "--version"],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": path},
        timeout=120,
    )
    assert done.returncode == 0, (done.returncode, done.stderr)
    assert done.stdout.startswith("dego ")


@pytest.mark.slow
@pytest.mark.parametrize("command", ["demo", "study"])
def test_ctrl_c_ends_with_130_one_line_and_no_partial_outputs(command: str, tmp_path: Path) -> None:
    fresh = tmp_path / "fresh" / "out"  # made by the command: removed again
    kept = tmp_path / "kept"  # a previous run's folder: left as it was
    before = _previous_run(kept, ["results.json" if command == "demo" else "study.json"])
    small = ["--frames", "2", "--iterations", "1000", "--no-pictures"]
    small += ["--gaussians", "300"] if command == "demo" else ["--seeds", "0", "--budgets", "300"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    for out in (fresh, kept):
        process = subprocess.Popen(
            [sys.executable, "-m", "dego", command, *small, "--out", str(out)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        assert process.stdout is not None
        first = process.stdout.readline()  # printed once the flags are checked
        assert first.startswith(f"dego {dego.__version__} {command}"), first
        time.sleep(1.0)  # inside the work (rendering the clip)
        process.send_signal(signal.SIGINT)
        try:
            _, err = process.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            process.kill()
            raise
        assert process.returncode == 130, err
        assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
        assert err.strip().splitlines()[-1] == "dego: interrupted", err
        assert err.count("interrupted") == 1, err
    assert not (tmp_path / "fresh").exists()
    assert _contents(kept) == before


@needs_source_tree
def test_the_documented_flag_bounds_are_the_code_s() -> None:
    """docs/validation.md, docs/study.md and docs/evaluation.md quote these bounds."""
    from dego import _cli_args as cli
    from dego.demo.clip import MAX_DEMO_FRAMES
    from dego.demo.fit import MAX_SEED
    from dego.evaluation.command import MAX_WORKERS

    assert ROOT is not None
    validation = " ".join((ROOT / "docs" / "validation.md").read_text().split())
    assert MAX_SEED == 2**32 - 1 and "0..2^32-1" in validation
    assert f"`--iterations` {cli.MAX_ITERATIONS:,}" in validation
    assert f"`--frames` {MAX_DEMO_FRAMES}" in validation
    assert f"`--workers` {MAX_WORKERS}" in validation
    assert f"at most {cli.MAX_LIST_VALUES} listed" in validation
    study = " ".join((ROOT / "docs" / "study.md").read_text().split())
    assert f"more than {cli.MAX_LIST_VALUES} values, or `--frames` above {MAX_DEMO_FRAMES}" in study
    evaluation = (ROOT / "docs" / "evaluation.md").read_text()
    assert f"N local processes (1-{MAX_WORKERS})" in evaluation
    # the bounds of dego eval's inputs (issue 38)
    from dego.data._pickle_scan import MEMO_SLACK, TUPLE_NODE_ALLOWANCE, TUPLE_NODES_PER_BYTE
    from dego.data.safe_pickle import BUDGET_ALLOWANCE, BUDGET_PER_BYTE
    from dego.metrics.counts import DIGEST_BYTES

    assert f"at most {BUDGET_PER_BYTE} bytes per byte of the file plus {BUDGET_ALLOWANCE:,}" in (
        validation
    )
    assert f"memo indices more than {MEMO_SLACK:,} beyond" in validation
    assert f"exceed {TUPLE_NODES_PER_BYTE} per byte read plus {TUPLE_NODE_ALLOWANCE:,}" in (
        validation
    )
    assert f"compare a {DIGEST_BYTES}-byte digest of their plans" in validation
