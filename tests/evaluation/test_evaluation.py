"""dego.evaluate / `dego eval`: reading predictions, scores equal to the metrics run
directly, reports, progress, and every bad-input case (setup errors exit 2, per-sample
failures are collected and exit 1)."""

from __future__ import annotations

import io
import json
import math
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import dego
from dego.evaluation import EvaluationSetupError, Progress, load_prediction
from dego.evaluation.command import parse_classes
from tests.helpers.evaluation import (
    FORMATS,
    LIDAR,
    SCENE_OF,
    SHAPE,
    TOKENS,
    assert_same_counts,
    direct,
    make_tree,
    run_cli,
)


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    return make_tree(tmp_path_factory.mktemp("occ3d"))


def assert_same_occupancy(got: dego.OccupancyReport, expected: dego.OccupancyReport) -> None:
    np.testing.assert_array_equal(got.per_class.numpy(), expected.per_class.numpy())
    assert got.iou == expected.iou
    assert (got.miou == expected.miou) or (math.isnan(got.miou) and math.isnan(expected.miou))
    assert dict(got.group_means) == pytest.approx(dict(expected.group_means), nan_ok=True, abs=0)


# ----------------------------------------------------------------------------------------
# reading predictions
# ----------------------------------------------------------------------------------------


@pytest.mark.slow
def test_every_prediction_format_reads_the_same_labels(tree: dict) -> None:
    for token, fmt in FORMATS.items():
        found = dego.evaluation.find_prediction(tree["pred"], SCENE_OF[token], token)
        assert found is not None, fmt
        labels = load_prediction(found)
        assert labels.dtype == torch.uint8 and tuple(labels.shape) == SHAPE
        np.testing.assert_array_equal(labels.numpy(), tree["arrays"][token][0])


@pytest.mark.parametrize("suffix", [".npz", ".npy"])
def test_a_wrong_shape_is_refused_from_the_header_before_inflating(
    tmp_path: Path, suffix: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 38 (4): a 1.2 MB .npz declaring (400000, 200, 16) cost 1.2 GB and 9 s, and a
    sparse .npy was read in full, before the shape was compared with the grid's."""
    import dego._npz
    import dego.evaluation.predictions

    path = tmp_path / f"huge{suffix}"
    grid = np.zeros((40, *SHAPE[1:]), dtype=np.uint8)  # 10x the expected X
    if suffix == ".npz":
        np.savez_compressed(path, pred=grid)
    else:
        np.save(path, grid)

    def inflated(*args: object, **kwargs: object) -> None:
        raise AssertionError("the array was read before its shape was checked")

    monkeypatch.setattr(dego._npz, "_read_member", inflated)
    monkeypatch.setattr(dego.evaluation.predictions.np, "load", inflated)
    with pytest.raises(ValueError, match=rf"huge\{suffix}.*shape \(40, .*expected"):
        load_prediction(path, expected_shape=SHAPE)
    np.save(tmp_path / "float.npy", grid.astype(np.float32))
    with pytest.raises(ValueError, match=r"float\.npy: expected integer labels"):
        load_prediction(tmp_path / "float.npy", expected_shape=SHAPE)


def test_ambiguous_and_unknown_archives_are_refused(tmp_path: Path) -> None:
    grid = np.zeros(SHAPE, dtype=np.uint8)
    np.savez(tmp_path / "two.npz", pred=grid, arr_0=grid)
    with pytest.raises(ValueError, match=r"two\.npz.*ambiguous.*'pred'.*'arr_0'"):
        load_prediction(tmp_path / "two.npz")
    np.savez(tmp_path / "other.npz", logits=grid)
    with pytest.raises(ValueError, match=r"other\.npz.*logits"):
        load_prediction(tmp_path / "other.npz")
    np.savez(tmp_path / "float.npz", pred=grid.astype(np.float32))
    with pytest.raises(ValueError, match=r"float\.npz: array 'pred'.*float32"):
        load_prediction(tmp_path / "float.npz")
    np.save(tmp_path / "big.npy", np.full(SHAPE, 18, dtype=np.int16))
    with pytest.raises(ValueError, match=r"big\.npy.*18\.\.18"):
        load_prediction(tmp_path / "big.npy")
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match=r"obj\.npy.*object"):
        load_prediction(tmp_path / "obj.npy")


# ----------------------------------------------------------------------------------------
# scores
# ----------------------------------------------------------------------------------------


@pytest.mark.slow
def test_cli_with_rayiou_matches_the_metrics_and_writes_reports(
    tree: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    json_path, md_path = tmp_path / "r.json", tmp_path / "r.md"
    code, out, err = run_cli(
        [
            *("--gt", str(tree["gt"]), "--pred", str(tree["pred"])),
            *("--origins", str(tree["origins"]), "--json", str(json_path)),
            *("--markdown", str(md_path), "--quiet"),
        ],
        capsys,
    )
    assert code == 0, err
    assert err == ""  # --quiet: no progress
    expected = direct(tree, rayiou=True)
    data = json.loads(json_path.read_text())
    # JSON: percent, protocols, origin source, sample and ray counts, version
    assert data["units"] == "percent" and data["complete"] is True
    assert data["dego_version"] == dego.__version__
    assert data["protocols"] == ["occ3d", "weak"]
    assert data["samples"] == data["samples_total"] == 6
    assert data["origins"]["source"] == f"origins: {tree['origins']}"
    k = sum(len(tree["arrays"][t][3]) for t in TOKENS)
    assert data["origins"]["total"] == k
    assert data["rays"] == {
        "per_origin": 14040,
        "cast": k * 14040,
        "scored": int(expected["rayiou"].gt_count.sum()),
        "traversal": dego.raycast.cpu_kernel(),
    }
    for name in ("occ3d", "weak"):
        report = expected[name].compute()
        assert data[name]["miou"] == 100 * report.miou and data[name]["iou"] == 100 * report.iou
        assert data["counts"][name]["confusion"] == expected[name].confusion.tolist()
    ray = expected["rayiou"].compute()
    assert data["rayiou"]["rayiou"] == 100 * ray.rayiou
    assert data["counts"]["rayiou"]["true_positives"] == expected["rayiou"].true_positives.tolist()
    assert data["missing"] == {"policy": "error", "tokens": []} and data["failed"] == []
    # stdout: percent with 2 decimals everywhere, stated
    assert "percentages with 2 decimals" in out
    assert "protocol: occ3d" in out and "protocol: weak" in out
    assert f"{expected['occ3d'].compute().miou * 100:.2f}" in out
    assert f"RayIoU {ray.rayiou * 100:.2f}" in out
    assert f"{k * 14040:,} rays cast per grid" in out
    # markdown: the same facts in percent
    md = md_path.read_text()
    assert md.startswith("# dego eval\n")
    assert f"dego {dego.__version__} eval: 6 of 6 samples" in md
    assert f"RayIoU origins: origins: {tree['origins']}" in md
    assert f"RayIoU **{ray.rayiou * 100:.2f}**" in md
    assert "occ3d protocol" in md and "weak protocol" in md
    assert "policy error" in md


def test_evaluate_equals_the_metrics_run_directly(tree: dict) -> None:
    report = dego.evaluate(tree["gt"], tree["pred"], rayiou=False)
    expected = direct(tree)
    assert_same_counts(report, expected)
    for name in ("occ3d", "weak"):
        assert_same_occupancy(report.protocols[name], expected[name].compute())
    assert report.rayiou is None and report.origin_source is None
    assert report.samples_scored == 6 and report.complete and report.world_size == 1


def test_gt_may_be_the_folder_of_scenes_itself(tree: dict) -> None:
    """``--gt`` is the Occ3D root holding ``gts/``, or the folder of ``<scene>/<token>``
    itself (``gts/``, or SparseOcc's ``data/nuscenes/occ3d``): the same scores."""
    via_root = dego.evaluate(tree["gt"], tree["pred"], rayiou=False)
    via_gts = dego.evaluate(tree["gt"] / "gts", tree["pred"], rayiou=False)
    assert via_gts.gt == str(tree["gt"] / "gts") == via_root.gt
    for name in ("occ3d", "weak"):
        for count in ("confusion", "geometric"):
            assert torch.equal(via_gts.counts[name][count], via_root.counts[name][count])


def test_classes_and_single_protocol(
    tree: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert parse_classes("1-11,13-16") == (*range(1, 12), *range(13, 17))
    json_path = tmp_path / "r.json"
    args = ["--gt", str(tree["gt"]), "--pred", str(tree["pred"]), "--no-rayiou", "--quiet"]
    code, out, _ = run_cli(
        [*args, "--protocol", "occ3d", "--classes", "1-11,13-16", "--json", str(json_path)], capsys
    )
    assert code == 0
    base = direct(tree)["occ3d"].compute()
    expected = dego.OccupancyReport.from_per_class(
        base.per_class,
        evaluated_classes=parse_classes("1-11,13-16"),
        groups=base.groups,
        class_names=base.class_names,
        iou=base.iou,
        protocol="occ3d",
    )
    data = json.loads(json_path.read_text())
    assert data["protocols"] == ["occ3d"] and "weak" not in data
    assert data["classes"] == list(expected.evaluated_classes)
    assert data["occ3d"]["miou"] == 100 * expected.miou
    assert "classes averaged (--classes): 1, 2" in out and "mIoU over 15 classes" in out
    code, _, err = run_cli([*args, "--classes", "3,17"], capsys)
    assert code == 2 and err.startswith("error: classes:")


def test_reports_are_written_whole_or_not_at_all(
    tree: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from tests.helpers.cli_faults import FullDisk

    out = tmp_path / "reports"
    out.mkdir()
    json_path, md_path = out / "r.json", out / "r.md"
    json_path.write_text("previous json\n")
    md_path.write_text("previous md\n")
    args = ["--gt", str(tree["gt"]), "--pred", str(tree["pred"]), "--no-rayiou", "--quiet"]
    args += ["--json", str(json_path), "--markdown", str(md_path)]
    FullDisk(monkeypatch, out.resolve())  # the second report fills the disk
    with pytest.raises(OSError, match="No space left"):
        run_cli(args, capsys)
    assert sorted(p.name for p in out.iterdir()) == ["r.json", "r.md"]  # no temporary files
    assert json_path.read_text() == "previous json\n" and md_path.read_text() == "previous md\n"
    monkeypatch.undo()
    code, _, _ = run_cli(args, capsys)
    assert code == 0 and json.loads(json_path.read_text())["samples"] == len(TOKENS)
    assert sorted(p.name for p in out.iterdir()) == ["r.json", "r.md"]


@pytest.mark.slow
def test_python_m_dego_eval(tree: dict, tmp_path: Path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "dego", "eval", "--gt", str(tree["gt"])]
    command += ["--pred", str(tree["pred"]), "--no-rayiou", "--protocol", "weak"]
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "protocol: weak" in result.stdout
    assert "eval: 6/6 samples (100%)" in result.stderr  # plain progress lines off a TTY


# ----------------------------------------------------------------------------------------
# missing predictions
# ----------------------------------------------------------------------------------------


@pytest.fixture
def pred_copy(tree: dict, tmp_path: Path) -> Path:
    return Path(shutil.copytree(tree["pred"], tmp_path / "pred"))


def test_missing_prediction_is_an_up_front_error(
    tree: dict, pred_copy: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (pred_copy / "tok-a1.npz").unlink()
    args = ["--gt", str(tree["gt"]), "--pred", str(pred_copy), "--no-rayiou"]
    code, out, err = run_cli(args, capsys)
    assert code == 2 and out == ""
    assert err.startswith("error: --pred: no prediction for 1 of 6 samples: 'tok-a1'")
    assert "--missing" in err and "Traceback" not in err and err.count("\n") == 1


def test_two_prediction_files_for_one_sample_are_a_setup_error(
    tree: dict, pred_copy: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A ``<token>.npz`` beside a ``<token>.npy``: one of them used to be read silently."""
    npz, npy = pred_copy / "tok-a1.npz", pred_copy / "tok-a1.npy"
    np.save(npy, tree["arrays"]["tok-a1"][0])
    with pytest.raises(EvaluationSetupError) as caught:
        dego.evaluate(tree["gt"], pred_copy, rayiou=False)
    message = str(caught.value)
    assert "'tok-a1'" in message and str(npz) in message and str(npy) in message
    with pytest.raises(EvaluationSetupError, match=r"tok-a1\.npz and .*tok-a1\.npy"):
        dego.evaluation.find_prediction(pred_copy, SCENE_OF["tok-a1"], "tok-a1")
    args = ["--gt", str(tree["gt"]), "--pred", str(pred_copy), "--no-rayiou"]
    code, out, err = run_cli(args, capsys)
    assert code == 2 and out == ""
    assert err.startswith("error: --pred: sample 'tok-a1' has 2 prediction files")
    assert str(npz) in err and str(npy) in err
    assert "Traceback" not in err and err.count("\n") == 1


def test_missing_free_and_skip(
    tree: dict, pred_copy: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (pred_copy / "tok-a1.npz").unlink()
    free = dego.evaluate(tree["gt"], pred_copy, rayiou=False, missing="free")
    assert free.scored_as_free == ("tok-a1",) and free.samples_scored == 6
    assert_same_counts(free, direct(tree, free=("tok-a1",)))
    json_path = tmp_path / "skip.json"
    args = ["--gt", str(tree["gt"]), "--pred", str(pred_copy), "--no-rayiou", "--quiet"]
    code, out, _ = run_cli([*args, "--missing", "skip", "--json", str(json_path)], capsys)
    assert code == 0 and "policy skip, 1 skipped: tok-a1" in out
    data = json.loads(json_path.read_text())
    assert data["skipped"] == ["tok-a1"] and data["samples"] == 5
    assert data["missing"] == {"policy": "skip", "tokens": ["tok-a1"]}
    others = [t for t in TOKENS if t != "tok-a1"]
    assert data["counts"]["weak"]["confusion"] == direct(tree, others)["weak"].confusion.tolist()


# ----------------------------------------------------------------------------------------
# bad input: collected per sample (exit 1) or setup errors (exit 2)
# ----------------------------------------------------------------------------------------

BAD_FILES = {
    "float": (lambda p: np.savez(p, pred=np.zeros(SHAPE, np.float32)), r"'pred'.*float32"),
    "shape": (
        lambda p: np.savez(p, pred=np.zeros((200, 200, 8), np.uint8)),
        r"shape \(200, 200, 8\)",
    ),
    "range": (lambda p: np.savez(p, pred=np.full(SHAPE, 20, np.uint8)), r"20\.\.20"),
    "corrupt": (lambda p: p.write_bytes(b"PK\x03\x04 not really a zip"), r"not a readable"),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_prediction_is_collected_and_the_others_scored(
    case: str, tree: dict, pred_copy: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    write, message = BAD_FILES[case]
    bad = pred_copy / "tok-b0.npz"
    (pred_copy / "tok-b0.npy").unlink()  # tok-b0 was the .npy sample
    write(bad)
    json_path, md_path = tmp_path / "r.json", tmp_path / "r.md"
    args = ["--gt", str(tree["gt"]), "--pred", str(pred_copy), "--no-rayiou", "--quiet"]
    code, out, err = run_cli([*args, "--json", str(json_path), "--markdown", str(md_path)], capsys)
    assert code == 1
    assert "INCOMPLETE: 1 of 6 samples failed" in out
    assert "tok-b0" in err and str(bad) in err
    data = json.loads(json_path.read_text())
    assert data["complete"] is False and data["samples"] == 5
    [failure] = data["failed"]
    assert failure["token"] == "tok-b0" and failure["file"] == str(bad)
    assert str(bad) in failure["message"]
    import re

    assert re.search(message, failure["message"]), failure["message"]
    others = [t for t in TOKENS if t != "tok-b0"]
    assert data["counts"]["occ3d"]["confusion"] == direct(tree, others)["occ3d"].confusion.tolist()
    assert "(INCOMPLETE)" in md_path.read_text()


def test_setup_errors(tree: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty" / "gts").mkdir(parents=True)
    cases = {
        "empty gt": (
            ["--gt", str(tmp_path / "empty"), "--pred", str(tree["pred"]), "--no-rayiou"],
            "--gt",
        ),
        "no origins": (["--gt", str(tree["gt"]), "--pred", str(tree["pred"])], "--infos"),
        "no pred dir": (
            ["--gt", str(tree["gt"]), "--pred", str(tmp_path / "nope"), "--no-rayiou"],
            "--pred",
        ),
    }
    for name, (args, needle) in cases.items():
        code, out, err = run_cli(args, capsys)
        assert code == 2 and out == "", name
        assert err.startswith("error: ") and needle in err and "Traceback" not in err, name
    origins = Path(shutil.copytree(tree["origins"], tmp_path / "origins"))
    (origins / "tok-b2.npy").unlink()
    with pytest.raises(EvaluationSetupError, match=r"'tok-b2'.*tok-b2\.npy"):
        dego.evaluate(tree["gt"], tree["pred"], origins=origins)


# ----------------------------------------------------------------------------------------
# infos (mmdet3d 0.x layout) as the origin source and the sample list
# ----------------------------------------------------------------------------------------


def write_infos(path: Path, tokens: list[str]) -> Path:
    infos = []
    for i, token in enumerate(tokens):
        yaw = 0.1 * i
        infos.append(
            {
                "token": token,
                "scene_name": SCENE_OF.get(token, "scene-c"),
                "timestamp": 1_600_000_000_000_000 + 500_000 * i,
                "lidar2ego_translation": list(LIDAR),
                "lidar2ego_rotation": [0.7071068, 0.0, 0.0, -0.7071068],
                "ego2global_translation": [100.0 + 4.0 * i, 50.0 + i, 0.0],
                "ego2global_rotation": [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)],
            }
        )
    with path.open("wb") as file:
        pickle.dump({"infos": infos, "metadata": {"version": "v1.0-trainval"}}, file)
    return path


def test_infos_select_the_samples_and_give_the_origins(
    tree: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    tokens = ["tok-b1", "tok-a0", "tok-b0"]  # infos order, a subset of the GT tree
    infos = write_infos(tmp_path / "nuscenes_infos_val.pkl", tokens)
    report = dego.evaluate(
        tree["gt"], tree["pred"], infos=infos, origins=tree["origins"], protocol="weak"
    )
    assert report.origin_source == f"infos: {infos}"
    assert report.ignored_sources == (f"origins: {tree['origins']}",)
    assert report.samples_total == report.samples_scored == 3
    scene_origins = dego.SceneOrigins(dego.load_infos(infos), scene_of=SCENE_OF)
    weak, ray = dego.OccupancyMetrics("weak"), dego.RayIoU()
    for token in tokens:
        pred, gt, mask, _ = tree["arrays"][token]
        weak.update(pred, gt, mask)
        ray.update(pred, gt, scene_origins(token))
    assert_same_counts(report, {"weak": weak, "rayiou": ray})
    assert report.origins_total == sum(len(scene_origins(t)) for t in tokens)
    # an infos token without ground truth: a setup error naming it
    write_infos(tmp_path / "bad.pkl", ["tok-a0", "tok-zz"])
    code, _, err = run_cli(
        [
            "--gt",
            str(tree["gt"]),
            "--pred",
            str(tree["pred"]),
            "--infos",
            str(tmp_path / "bad.pkl"),
        ],
        capsys,
    )
    assert code == 2 and "'tok-zz'" in err and "no ground truth" in err


# ----------------------------------------------------------------------------------------
# progress
# ----------------------------------------------------------------------------------------


def test_plain_progress_lines_every_tenth_or_30_s() -> None:
    now = [0.0]
    stream = io.StringIO()
    progress = Progress(20, stream=stream, use_tqdm=False, clock=lambda: now[0])
    for _ in range(20):
        now[0] += 1.0
        progress.update()
    progress.close()
    lines = stream.getvalue().splitlines()
    assert len(lines) == 10  # every 2 samples (10%)
    assert lines[0] == "eval: 2/20 samples (10%), 1.00 samples/s, ETA 0:00:18"
    assert lines[-1].startswith("eval: 20/20 samples (100%)")
    slow, stream = Progress(1000, stream=io.StringIO(), use_tqdm=False, clock=lambda: now[0]), None
    for _ in range(3):
        now[0] += 31.0
        slow.update()
    assert len(slow.stream.getvalue().splitlines()) == 3  # every 30 s, well before 10%
    quiet = Progress(5, enabled=False, stream=io.StringIO())
    quiet.update(5)
    assert quiet.stream.getvalue() == ""


def test_tqdm_bar_with_rate_and_eta() -> None:
    pytest.importorskip("tqdm")
    stream = io.StringIO()
    with Progress(4, stream=stream, use_tqdm=True) as progress:
        assert progress.bar is not None
        progress.update(4)
    text = stream.getvalue()
    assert "4/4" in text and "sample/s" in text


# ----------------------------------------------------------------------------------------
# issue 38 (2, 6): what the walks cannot read is an error, never a silent omission
# ----------------------------------------------------------------------------------------


def _deny(monkeypatch: pytest.MonkeyPatch, denied: Path) -> None:
    """``os.scandir`` of ``denied`` and ``stat`` below it fail with EACCES, as for a folder
    at mode 000 under a non-root user (the tests run as root, who reads everything)."""
    import errno

    real_scandir, real_stat = os.scandir, os.stat

    def scandir(path: object = ".") -> object:
        if Path(os.fspath(path)) == denied:
            raise PermissionError(errno.EACCES, "Permission denied", os.fspath(path))
        return real_scandir(path)

    def stat(path: object, *args: object, **kwargs: object) -> os.stat_result:
        if denied in Path(os.fspath(path)).parents:
            raise PermissionError(errno.EACCES, "Permission denied", os.fspath(path))
        return real_stat(path, *args, **kwargs)

    monkeypatch.setattr(os, "scandir", scandir)
    monkeypatch.setattr(os, "stat", stat)


def test_an_unreadable_gt_scene_is_a_setup_error(
    tree: dict, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 38 (2): ``gts/scene-a`` at mode 000 left its samples out of numerator and
    denominator alike ("2 of 2 samples scored", exit 0)."""
    scene = tree["gt"] / "gts" / SCENE_OF[TOKENS[0]]
    _deny(monkeypatch, scene)
    args = ["--gt", str(tree["gt"]), "--pred", str(tree["pred"]), "--no-rayiou", "--quiet"]
    code, out, err = run_cli(args, capsys)
    assert code == 2 and out == ""
    assert (
        err == f"error: --gt: {scene}: cannot be read (Permission denied); fix its "
        "permissions or remove it from the tree\n"
    )


@pytest.mark.parametrize("kind", ["dangling", "directory"])
def test_a_labels_archive_that_is_no_file_is_a_setup_error(
    tree: dict, tmp_path: Path, kind: str, capsys: pytest.CaptureFixture[str]
) -> None:
    gt = tmp_path / "gt"
    shutil.copytree(tree["gt"], gt)
    labels = gt / "gts" / SCENE_OF[TOKENS[1]] / TOKENS[1] / "labels.npz"
    labels.unlink()
    if kind == "dangling":
        labels.symlink_to(tmp_path / "nowhere.npz")
    else:
        labels.mkdir()
    args = ["--gt", str(gt), "--pred", str(tree["pred"]), "--no-rayiou", "--quiet"]
    code, out, err = run_cli(args, capsys)
    what = "a dangling link" if kind == "dangling" else "not a regular file"
    assert code == 2 and out == ""
    assert err == f"error: --gt: {labels}: {what}; expected the sample's labels archive\n"


def test_an_unreadable_pred_folder_is_one_error_line(
    tree: dict, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 38 (6): a PermissionError traceback from ``is_file()`` (exit 1)."""
    pred = Path(tree["pred"])
    args = ["--gt", str(tree["gt"]), "--pred", str(pred), "--no-rayiou", "--quiet"]
    _deny(monkeypatch, pred)
    code, out, err = run_cli(args, capsys)
    assert code == 2 and out == ""
    assert err.startswith(f"error: --pred: {pred}/") and "cannot be read (Permission denied)" in err
    assert err.count("\n") == 1
