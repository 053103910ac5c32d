"""dego.evaluate / `dego eval` beyond tests/evaluation/test_evaluation.py: the nuScenes JSON tables as
the origin source (equal to SceneOrigins run directly, and to an infos file of the same
poses), corrupt ground truth, a malicious infos pickle, `dego eval --help`, and the
facts the report states (protocols, origin source, counts, version, units, NaN -> null)."""

from __future__ import annotations

import json
import math
import os
import pickle
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import dego
import dego.cli
from dego.data import LABELS_FILENAME, Occ3DLabels, save_occ3d_labels
from dego.evaluation import EvaluationSetupError
from tests.helpers.evaluation import SHAPE, assert_same_counts, label_grid, run_cli
from tests.helpers.nuscenes_fixtures import make_frames, make_tables, write_infos, write_tables

VERSION = "v1.0-trainval"
RAYS_PER_ORIGIN = 14040


def predict(grid: torch.Tensor, seed: int) -> np.ndarray:
    """A prediction that only uses classes of the GT (so absent classes stay NaN)."""
    draw = torch.rand(SHAPE, generator=torch.Generator().manual_seed(2000 + seed))
    pred = grid.clone()
    pred[draw < 0.05] = 17
    pred[(draw > 0.97) & (grid != 17)] = 10
    return pred.numpy()


def write_sample(gt: Path, pred: Path, scene: str, token: str, seed: int) -> tuple:
    semantics = label_grid(seed)
    mask = torch.rand(SHAPE, generator=torch.Generator().manual_seed(70 + seed)) < 0.8
    save_occ3d_labels(
        gt / "gts" / scene / token / LABELS_FILENAME, Occ3DLabels(semantics, mask, ~mask)
    )
    p = predict(semantics, seed)
    np.savez(pred / f"{token}.npz", pred=p)
    return p, semantics, mask


@pytest.fixture(scope="module")
def nus(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Two scenes (3 + 2 keyframes): an Occ3D GT tree, predictions, the nuScenes tables
    and an infos pickle of the same poses."""
    root = tmp_path_factory.mktemp("nus")
    frames = make_frames(seed=3, lengths=(3, 2))
    assert len({f.scene_name for f in frames}) == 2
    gt, pred = root / "gt", root / "pred"
    pred.mkdir()
    arrays = {
        f.token: write_sample(gt, pred, f.scene_name, f.token, i) for i, f in enumerate(frames)
    }
    tables = write_tables(root / "nuscenes", make_tables(frames), VERSION)
    infos = write_infos(root / "nuscenes_infos_val.pkl", frames)
    return {
        "root": root,
        "frames": frames,
        "gt": gt,
        "pred": pred,
        "arrays": arrays,
        "tables": tables,
        "infos": infos,
        "scene_of": {f.token: f.scene_name for f in frames},
    }


@pytest.fixture(scope="module")
def nus_report(nus: dict[str, Any]) -> dego.EvaluationReport:
    return dego.evaluate(nus["gt"], nus["pred"], nuscenes=nus["tables"], version=VERSION)


def direct(nus: dict[str, Any], tokens=None, *, origins=None) -> dict[str, Any]:
    """The metrics run directly on the same arrays (RayIoU when ``origins`` is given)."""
    metrics: dict[str, Any] = {
        "occ3d": dego.OccupancyMetrics("occ3d"),
        "weak": dego.OccupancyMetrics("weak"),
    }
    if origins is not None:
        metrics["rayiou"] = dego.RayIoU()
    for token in tokens or list(nus["arrays"]):
        pred, gt, mask = nus["arrays"][token]
        metrics["occ3d"].update(pred, gt, mask)
        metrics["weak"].update(pred, gt, mask)
        if origins is not None:
            metrics["rayiou"].update(pred, gt, origins(token))
    return metrics


# ----------------------------------------------------------------------------------------
# --nuscenes ROOT --version: the JSON tables give the origins
# ----------------------------------------------------------------------------------------


@pytest.mark.slow
def test_nuscenes_tables_give_scene_origins_and_agree_with_infos(
    nus: dict[str, Any], nus_report: dego.EvaluationReport
) -> None:
    report, tokens = nus_report, list(nus["arrays"])
    assert report.samples_total == report.samples_scored == len(tokens) == 5
    assert report.complete and report.failed == ()
    assert report.origin_source == f"nuscenes: {nus['tables']} ({VERSION})"
    assert report.ignored_sources == ()
    keyframes = dego.load_nuscenes_keyframes(nus["tables"], VERSION)
    scene_origins = dego.SceneOrigins(keyframes, scene_of=nus["scene_of"])
    expected = direct(nus, origins=scene_origins)
    assert_same_counts(report, expected)
    sizes = [len(scene_origins(t)) for t in tokens]
    assert max(sizes) > 1  # the scene's other keyframes, not a single origin
    assert report.origins_total == sum(sizes)
    assert report.rays_cast == sum(sizes) * RAYS_PER_ORIGIN
    assert report.rays_scored == int(expected["rayiou"].gt_count.sum()) > 0
    assert report.rayiou is not None
    assert report.rayiou.rayiou == expected["rayiou"].compute().rayiou
    # an infos file of the same poses: the same samples, origins and counts
    via_infos = dego.evaluate(nus["gt"], nus["pred"], infos=nus["infos"])
    assert via_infos.origin_source == f"infos: {nus['infos']}"
    assert via_infos.samples_scored == 5 and via_infos.origins_total == report.origins_total
    for metric, counts in report.counts.items():
        for name, count in counts.items():
            assert torch.equal(via_infos.counts[metric][name], count), (metric, name)


def test_wrong_version_is_a_setup_error(nus: dict[str, Any]) -> None:
    with pytest.raises(EvaluationSetupError, match=r"--nuscenes .*v1\.0-mini"):
        dego.evaluate(nus["gt"], nus["pred"], nuscenes=nus["tables"], version="v1.0-mini")


def test_gt_token_absent_from_the_tables(
    nus: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    first = nus["frames"][0]
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    pred.mkdir()
    write_sample(gt, pred, first.scene_name, first.token, 0)
    write_sample(gt, pred, first.scene_name, "tok-absent", 1)
    with pytest.raises(EvaluationSetupError, match=r"not keyframes there: 'tok-absent'$"):
        dego.evaluate(gt, pred, nuscenes=nus["tables"], version=VERSION)
    # the CLI, with tables of another version: --nuscenes-version reaches the reader
    mini = write_tables(tmp_path / "mini", make_tables(nus["frames"]), "v1.0-mini")
    args = ["--gt", str(gt), "--pred", str(pred), "--nuscenes", str(mini)]
    code, out, err = run_cli([*args, "--nuscenes-version", "v1.0-mini"], capsys)
    assert code == 2 and out == ""
    assert err.startswith(f"error: --nuscenes {mini}: 1 sample(s)") and "'tok-absent'" in err
    assert "Traceback" not in err and err.count("\n") == 1


def test_a_deeply_nested_table_is_one_error_line(
    nus: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 38 (5): ``"[" * 100000 + "]" * 100000`` as sample.json escaped as a
    RecursionError traceback (exit 1)."""
    tables = tmp_path / "nuscenes"
    shutil.copytree(nus["tables"], tables)
    (tables / VERSION / "sample.json").write_text("[" * 100_000 + "]" * 100_000)
    args = ["--gt", str(nus["gt"]), "--pred", str(nus["pred"]), "--nuscenes", str(tables)]
    code, out, err = run_cli([*args, "--nuscenes-version", VERSION], capsys)
    assert code == 2 and out == ""
    assert err.startswith("error: ") and "sample.json: not a readable JSON table" in err
    assert "Traceback" not in err and err.count("\n") == 1


# ----------------------------------------------------------------------------------------
# corrupt ground truth: collected per sample, the others scored
# ----------------------------------------------------------------------------------------

CORRUPT = {
    "truncated": lambda data: data[: len(data) // 2],
    "garbage": lambda data: b"PK\x03\x04" + bytes(range(256)) * 4,
}


@pytest.mark.parametrize("case", sorted(CORRUPT))
def test_corrupt_ground_truth_is_collected_and_the_others_scored(
    case: str, nus: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    gt = Path(shutil.copytree(nus["gt"], tmp_path / "gt"))
    bad_frame = nus["frames"][3]
    bad = gt / "gts" / bad_frame.scene_name / bad_frame.token / LABELS_FILENAME
    bad.write_bytes(CORRUPT[case](bad.read_bytes()))
    report = dego.evaluate(gt, nus["pred"], rayiou=False)
    assert not report.complete and report.samples_total == 5 and report.samples_scored == 4
    [failure] = report.failed
    assert failure.token == bad_frame.token and failure.file == str(bad)
    assert str(bad) in failure.message and "not a readable" in failure.message
    others = [t for t in nus["arrays"] if t != bad_frame.token]
    assert_same_counts(report, direct(nus, others))
    if case != "garbage":  # the CLI once is enough
        return
    json_path = tmp_path / "r.json"
    args = ["--gt", str(gt), "--pred", str(nus["pred"]), "--no-rayiou", "--quiet"]
    code, out, err = run_cli([*args, "--json", str(json_path)], capsys)
    assert code == 1
    assert "INCOMPLETE: 1 of 5 samples failed" in out
    assert err.startswith("error: 1 sample(s) failed:")
    assert f"  {bad_frame.token}: " in err and str(bad) in err
    data = json.loads(json_path.read_text())
    assert data["complete"] is False and data["samples"] == 4
    assert [f["token"] for f in data["failed"]] == [bad_frame.token]


# ----------------------------------------------------------------------------------------
# a malicious infos pickle: refused before anything runs
# ----------------------------------------------------------------------------------------


class _Reduce:
    def __init__(self, *reduced: Any) -> None:
        self.reduced = reduced

    def __reduce__(self) -> Any:
        return self.reduced


@pytest.mark.parametrize("rayiou", [True, False], ids=["rayiou", "no-rayiou"])
def test_infos_pickle_with_a_disallowed_global_is_refused(
    rayiou: bool, nus: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    marker = tmp_path / "marker"
    evil = tmp_path / "nuscenes_infos_val.pkl"
    info = {"token": nus["frames"][0].token, "x": _Reduce(os.system, (f"touch {marker}",))}
    evil.write_bytes(pickle.dumps({"infos": [info]}, protocol=2))
    args = ["--gt", str(nus["gt"]), "--pred", str(nus["pred"]), "--infos", str(evil)]
    code, out, err = run_cli([*args] if rayiou else [*args, "--no-rayiou"], capsys)
    assert code == 2 and out == ""
    assert err.startswith(f"error: --infos {evil}: ")
    assert f"refused the global {os.system.__module__}.system" in err
    assert "Traceback" not in err and err.count("\n") == 1
    with pytest.raises(EvaluationSetupError, match=r"refused the global .*system"):
        dego.evaluate(nus["gt"], nus["pred"], infos=evil, rayiou=rayiou)
    assert not marker.exists()


# ----------------------------------------------------------------------------------------
# --help
# ----------------------------------------------------------------------------------------


def test_eval_help(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        dego.cli.main(["eval", "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: ")
    options = ("--infos", "--nuscenes", "--nuscenes-version", "--origins", "--workers", "--missing")
    for option in options:
        assert option in out, option
    assert "--version" not in out.replace("--nuscenes-version", "")


@pytest.mark.parametrize("argv", [["--version"], ["--version", "v1.0-mini"]])
def test_eval_version_is_not_the_nuscenes_version(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        dego.cli.main(["eval", "--gt", "g", "--pred", "p", *argv])
    assert exit_info.value.code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--nuscenes-version" in line and "dego --version" in line


# ----------------------------------------------------------------------------------------
# the report
# ----------------------------------------------------------------------------------------


def _no_nan(name: str) -> Any:
    raise AssertionError(f"JSON holds {name}")


def test_report_states_what_was_scored(
    nus: dict[str, Any], nus_report: dego.EvaluationReport
) -> None:
    report = nus_report
    source = f"nuscenes: {nus['tables']} ({VERSION})"
    rays = (
        f"{report.origins_total} origins x {RAYS_PER_ORIGIN:,} = {report.rays_cast:,} rays "
        f"cast per grid, {report.rays_scored:,} scored"
    )
    md = report.to_markdown()
    assert md.startswith("# dego eval\n")
    assert f"dego {dego.__version__} eval: 5 of 5 samples scored" in md
    assert "protocols: occ3d, weak" in md
    assert "## Voxel IoU (percent), occ3d protocol" in md
    assert "## Voxel IoU (percent), weak protocol" in md
    assert f"RayIoU origins: {source}" in md and f"## RayIoU (percent), origins {source}" in md
    assert rays in md
    assert "percentages with 2 decimals" in md
    assert report.rayiou is not None
    assert f"RayIoU **{report.rayiou.rayiou * 100:.2f}**" in md
    # tables: percent, and they say so
    text = report.tables()
    assert "All scores below are percentages with 2 decimals." in text
    assert "== voxel IoU, occ3d protocol (percent) ==" in text
    assert f"== RayIoU (percent), origins {source} ==" in text
    assert f"RayIoU {report.rayiou.rayiou * 100:.2f} " in text
    assert rays in text and str(report) == text
    for name in ("occ3d", "weak"):
        assert f"{report.protocols[name].miou * 100:.2f}" in text
    # JSON: percent, NaN (a class absent from GT and predictions) -> null
    occ = report.protocols["occ3d"]
    absent = [c for c in occ.evaluated_classes if math.isnan(float(occ.per_class[c]))]
    assert absent, "the fixture should leave some class out of GT and predictions"
    data = json.loads(report.to_json(), parse_constant=_no_nan)
    assert data["units"] == "percent" and data["dego_version"] == dego.__version__
    assert data["origins"]["source"] == source and data["samples"] == 5
    assert data["occ3d"]["miou"] == 100 * occ.miou and 0.0 <= data["occ3d"]["miou"] <= 100.0
    for c in absent:
        name = occ.class_names[c]
        assert data["occ3d"]["per_class"][name] is None, name
        if c in report.rayiou.class_ids:
            assert all(v is None for v in data["rayiou"]["per_class"][name].values()), name
    assert "NaN" not in report.to_json()
