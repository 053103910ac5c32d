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
    assert 'pip install "dego-occupancy[rerun]"' in line


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
    assert calls == [[sys.executable, "-m", "rerun", str(recording), "--web-viewer"]]
    monkeypatch.setattr(viewer, "has_screen", lambda: False)
    assert main(["view", str(recording)]) == 1
    assert "--web" in capsys.readouterr().err
    monkeypatch.setattr(viewer, "has_screen", lambda: True)
    assert main(["view", str(recording)]) == 0
    assert calls[-1] == [sys.executable, "-m", "rerun", str(recording)]
    monkeypatch.setattr("importlib.util.find_spec", lambda name, *a: None)
    assert main(["view", str(recording)]) == 1
    assert 'pip install "dego-occupancy[rerun]"' in capsys.readouterr().err


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
