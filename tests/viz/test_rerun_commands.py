"""``dego demo --rerun``, ``dego eval --rerun --limit`` and ``dego view``: flags checked
before any work, recordings read back with rerun's own reader."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import dego.demo.command
from dego import NUM_CLASSES
from dego.cli import main
from tests.helpers.cli_faults import usage_error
from tests.helpers.evaluation import TOKENS, make_tree
from tests.helpers.repo import ROOT, needs_source_tree
from tests.helpers.rrd import column, read_recording

rr = pytest.importorskip("rerun")
pytest.importorskip("datafusion", reason="reading recordings back needs rerun-sdk[catalog]")


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    def started(*args: object, **kwargs: object) -> int:
        raise AssertionError("the work started before the flags were checked")

    from dego.evaluation import command

    monkeypatch.setattr(dego.demo.command, "run_demo", started)
    monkeypatch.setattr(command, "evaluate", started)


@pytest.mark.parametrize("command", ["demo", "eval"])
def test_rerun_to_an_unwritable_place_is_a_usage_error_before_any_work(
    command: str, no_work: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = (
        ["eval", "--gt", str(tmp_path), "--pred", str(tmp_path)]
        if command == "eval"
        else ["demo", "--quick", "--out", str(tmp_path / "out")]
    )
    a_file = tmp_path / "taken"
    a_file.write_text("mine\n")
    for target, words in [
        (a_file / "demo.rrd", "--rerun"),
        (tmp_path, "--rerun"),
        (tmp_path / "demo.txt", ".rrd"),
    ]:
        line = usage_error([*base, "--rerun", str(target)], capsys)
        assert "--rerun" in line and words in line, line
    assert a_file.read_text() == "mine\n"


def test_rerun_without_the_extra_is_a_usage_error_naming_it(
    no_work: None,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)
    monkeypatch.setattr("importlib.util.find_spec", lambda name, *a: None)
    line = usage_error(["demo", "--quick", "--rerun", str(tmp_path / "d.rrd")], capsys)
    assert 'pip install -e ".[rerun]"' in line


def test_eval_limit_needs_rerun(
    no_work: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = ["eval", "--gt", str(tmp_path), "--pred", str(tmp_path)]
    assert "--limit" in usage_error([*base, "--limit", "3"], capsys)
    assert "--limit" in usage_error(
        [*base, "--rerun", str(tmp_path / "a.rrd"), "--limit", "0"], capsys
    )


def test_eval_records_ground_truth_and_prediction(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    tree = make_tree(tmp_path)
    path = tmp_path / "rec" / "eval.rrd"
    argv = ["eval", "--gt", str(tree["gt"]), "--pred", str(tree["pred"]), "--no-rayiou"]
    assert main([*argv, "--quiet", "--rerun", str(path), "--limit", "4"]) == 0
    out = capsys.readouterr().out
    assert f"wrote {path} (4 samples" in out
    data = read_recording(path, index="sample")
    assert data["sample"] == [0, 1, 2, 3]
    for i, token in enumerate(sorted(TOKENS)[:4]):
        pred, gt, mask, _ = tree["arrays"][token]
        for entity, labels in (("ground_truth", gt.numpy()), ("prediction", pred)):
            scored = mask.numpy() & (labels != 17)
            ids = np.asarray(column(data, f"world/occupancy/{entity}", "class_id")[i])
            expected = np.bincount(labels[scored], minlength=NUM_CLASSES)
            np.testing.assert_array_equal(np.bincount(ids, minlength=NUM_CLASSES), expected)
        assert token in column(data, "sample", "TextDocument:text")[i][0]


@pytest.mark.slow
@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (Linux)")
def test_eval_rerun_on_a_full_disk_is_one_error_line_after_the_scores(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    tree = make_tree(tmp_path)
    path = tmp_path / "rec" / "eval.rrd"
    full = tmp_path / "rec.full.tmp"
    full.symlink_to("/dev/full")  # every write fails with ENOSPC
    monkeypatch.setattr("dego.viz.rerun.temporary_name", lambda target: full)
    argv = ["eval", "--gt", str(tree["gt"]), "--pred", str(tree["pred"]), "--no-rayiou"]
    assert main([*argv, "--quiet", "--rerun", str(path), "--limit", "2"]) == 1
    captured = capsys.readouterr()
    assert "mIoU" in captured.out  # scored first
    errors = [line for line in captured.err.splitlines() if line.startswith("error:")]
    assert errors == [errors[0]] and f"cannot write the recording {path}: " in errors[0]
    assert "Traceback" not in captured.err
    assert not path.exists() and not full.exists() and not path.parent.exists()


@pytest.mark.slow
@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (Linux)")
def test_demo_rerun_on_a_full_disk_is_one_error_line_and_the_results_are_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "rec" / "demo.rrd"
    full = tmp_path / "rec.full.tmp"
    full.symlink_to("/dev/full")  # every write fails with ENOSPC
    monkeypatch.setattr("dego.viz.rerun.temporary_name", lambda target: full)
    argv = ["demo", "--frames", "2", "--iterations", "1", "--gaussians", "60", "--no-pictures"]
    assert main([*argv, "--out", str(tmp_path / "out"), "--rerun", str(path)]) == 1
    captured = capsys.readouterr()
    errors = [line for line in captured.err.splitlines() if line.startswith("error:")]
    assert errors == [errors[0]] and f"cannot write the recording {path}: " in errors[0]
    assert "Traceback" not in captured.err
    assert (tmp_path / "out" / "results.json").exists()  # the run is not lost
    assert not path.exists() and not full.exists()


def test_view_of_a_directory_says_it_is_one_and_what_it_expects(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    line = usage_error(["view", str(tmp_path)], capsys)
    assert f"{tmp_path} is a directory" in line and "FILE.rrd" in line, line
    assert "no such file" not in line


def test_view_checks_the_file_and_starts_rerun(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from dego.viz import viewer

    assert "no such file" in usage_error(["view", str(tmp_path / "none.rrd")], capsys)
    other = tmp_path / "other.rrd"
    other.write_text("not a recording")
    assert "not a rerun recording" in usage_error(["view", str(other)], capsys)
    recording = tmp_path / "r.rrd"
    with dego.viz.rerun.recording_file(recording):
        pass
    calls: list[list[str]] = []
    monkeypatch.setattr(viewer.subprocess, "call", lambda argv: calls.append(argv) or 0)
    assert main(["view", str(recording), "--web"]) == 0
    web = ["--web-viewer", "--web-viewer-port", "9090", "--port", "9876"]
    assert calls == [[sys.executable, "-m", "rerun", str(recording), "--bind", "127.0.0.1", *web]]
    monkeypatch.setattr(viewer, "has_screen", lambda: False)
    assert main(["view", str(recording)]) == 1
    assert "--web" in capsys.readouterr().err
    monkeypatch.setattr(viewer, "has_screen", lambda: True)
    assert main(["view", str(recording)]) == 0
    assert calls[-1] == [sys.executable, "-m", "rerun", str(recording), "--bind", "127.0.0.1"]
    monkeypatch.setattr("importlib.util.find_spec", lambda name, *a: None)
    assert main(["view", str(recording)]) == 1
    assert 'pip install -e ".[rerun]"' in capsys.readouterr().err


def test_view_serves_this_machine_only_unless_asked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 51: ``dego view --web`` left rerun's servers on its default address, 0.0.0.0
    (every interface: anyone on the network could read the recording), on fixed ports.
    Now 127.0.0.1 unless ``--bind`` says otherwise; ``--port`` / ``--grpc-port`` choose
    the web page's and the recording's ports."""
    from dego.viz import viewer
    from dego.viz.rerun import recording_file

    recording = tmp_path / "r.rrd"
    with recording_file(recording):
        pass
    calls: list[list[str]] = []
    monkeypatch.setattr(viewer.subprocess, "call", lambda argv: calls.append(argv) or 0)
    monkeypatch.setattr(viewer, "has_screen", lambda: True)

    def rerun_flags(*flags: str) -> list[str]:
        assert main(["view", str(recording), *flags]) == 0
        assert calls[-1][:4] == [sys.executable, "-m", "rerun", str(recording)]
        return calls[-1][4:]

    web = ["--web-viewer", "--web-viewer-port"]
    assert rerun_flags("--web") == ["--bind", "127.0.0.1", *web, "9090", "--port", "9876"]
    note = capsys.readouterr().err
    assert "this machine only (127.0.0.1; over SSH forward ports 9090 and 9876;" in note
    assert rerun_flags("--web", "--bind", "0.0.0.0", "--port", "8080", "--grpc-port", "8081") == [
        *("--bind", "0.0.0.0", *web, "8080", "--port", "8081")
    ]
    assert "on 0.0.0.0, ports 8080 and 8081" in capsys.readouterr().err
    assert rerun_flags("--web", "--bind", "::1") == [
        "--bind",
        "::1",
        *web,
        "9090",
        "--port",
        "9876",
    ]
    assert rerun_flags() == ["--bind", "127.0.0.1"]  # the native viewer's server too
    assert rerun_flags("--grpc-port", "9999", "--bind", "0.0.0.0") == [
        *("--bind", "0.0.0.0", "--port", "9999")
    ]
    capsys.readouterr()
    for flags, words in [
        (["--web", "--bind", "localhost"], "argument --bind: expected an IP address"),
        (["--web", "--port", "0"], "argument --port"),
        (["--web", "--port", "65536"], "argument --port"),
        (["--grpc-port", "x"], "argument --grpc-port"),
        (["--port", "8080"], "--port: the web viewer's port, only with --web"),
    ]:
        line = usage_error(["view", str(recording), *flags], capsys)
        assert words in line, line
    assert len(calls) == 5  # none for the usage errors


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/net/tcp")
def test_view_web_listens_on_loopback_on_the_ports_asked_for(tmp_path: Path) -> None:
    """The real rerun: ``dego view --web --port P --grpc-port G`` listens on 127.0.0.1:P and
    127.0.0.1:G, on no other address (``/proc/net/tcp``'s listening sockets)."""
    import contextlib
    import os
    import signal
    import socket
    import subprocess
    import time

    from dego.viz.rerun import recording_file

    recording = tmp_path / "r.rrd"
    with recording_file(recording):
        pass
    ports = []
    for _ in range(2):
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            ports.append(probe.getsockname()[1])
    page, grpc = ports
    argv = ["view", str(recording), "--web", "--port", str(page), "--grpc-port", str(grpc)]
    process = subprocess.Popen(
        [sys.executable, "-m", "dego", *argv],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )

    def listening() -> set[tuple[str, int]]:
        found = set()
        for table in ("/proc/net/tcp", "/proc/net/tcp6"):
            if not Path(table).exists():
                continue
            for row in Path(table).read_text().splitlines()[1:]:
                local, state = row.split()[1], row.split()[3]
                address, port = local.split(":")
                if state == "0A" and int(port, 16) in ports:  # LISTEN
                    found.add((address, int(port, 16)))
        return found

    try:
        deadline = time.monotonic() + 60
        while {port for _, port in listening()} != set(ports) and time.monotonic() < deadline:
            assert process.poll() is None, "rerun ended early"
            time.sleep(0.2)
        assert listening() == {("0100007F", page), ("0100007F", grpc)}  # 127.0.0.1 only
    finally:  # dego and the rerun it started: the session's process group
        os.killpg(process.pid, signal.SIGTERM)
        deadline = time.monotonic() + 10
        while listening() and time.monotonic() < deadline:
            time.sleep(0.1)
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=max(deadline - time.monotonic(), 0.1))
        if listening() or process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()


@pytest.mark.slow
def test_demo_records_the_clip_and_every_variant(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "demo.rrd"
    argv = ["demo", "--frames", "2", "--iterations", "1", "--gaussians", "60", "--no-pictures"]
    assert main([*argv, "--out", str(tmp_path / "out"), "--rerun", str(path)]) == 0
    assert f"wrote {path}" in capsys.readouterr().out
    data = read_recording(path)
    assert data["frame"] == [-1, 0]  # the clip's frame offsets
    names = {name.split(":")[0] for name in data}
    for variant in ("static", "rigid", "decoupled", "true-motion"):
        assert f"/world/gaussians/{variant}" in names
        ellipsoids = column(data, f"world/gaussians/{variant}", "Ellipsoids3D:centers")
        assert [len(e) for e in ellipsoids] == [60, 60]
    assert "/world/rigidity/decoupled" in names and "/world/rigidity/static" not in names
    assert "/world/ego/occupancy/ground-truth" in names and "/bev/ground-truth" in names
    assert "/world/cameras/CAM_FRONT" in names and "/world/cameras/CAM_FRONT/image" in names
    scene = dego.SyntheticScene(0, num_frames=2, frame_dt=dego.demo.DEMO_FRAME_DT)
    for index, frame in enumerate(scene.frames()):
        scored = frame.mask_camera & (frame.occupancy != 17)
        ids = np.asarray(column(data, "world/ego/occupancy/ground-truth", "class_id")[index])
        expected = torch.bincount(frame.occupancy[scored].long(), minlength=NUM_CLASSES)
        np.testing.assert_array_equal(np.bincount(ids, minlength=NUM_CLASSES), expected.numpy())
        pose = column(data, "world/ego", "Transform3D:translation")[index][0]
        np.testing.assert_allclose(pose, frame.ego_pose[:3, 3].numpy(), atol=1e-5)


@needs_source_tree
def test_viewing_page_states_the_default_ports() -> None:
    from dego.viz.viewer import GRPC_PORT, WEB_VIEWER_PORT

    assert ROOT is not None
    page = " ".join((ROOT / "docs" / "viewing.md").read_text().split())
    assert f"(with `--web`, default {WEB_VIEWER_PORT})" in page
    assert f"(default {GRPC_PORT})" in page
    assert "127.0.0.1 only" in page
