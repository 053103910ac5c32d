"""Every benchmark of ``dego eval --benchmark`` on a fixture tree in its layout, checked
against an oracle written here from each official script's rules (plain numpy, per
sample, per class; no dego scoring code), plus the bad inputs the issue names."""

from __future__ import annotations

import gzip
import json
import math
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

import dego
from dego.evaluation.benchmarks import BENCHMARKS, OCC3D_TO_OPENOCC, get_benchmark
from dego.evaluation.errors import EvaluationSetupError
from dego.evaluation.layouts import layout_of
from dego.evaluation.openocc import occ3d_to_openocc, write_openocc_submission
from dego.evaluation.predictions import read_prediction, upsample_logits
from dego.evaluation.scoring import class_iou, mave, occ_score, ray_flow_counts
from dego.evaluation.trees import write_benchmark_tree


class _Trees(dict):
    """Fixture trees written on first use (one keyframe; two for the pooled checks)."""

    def __init__(self, root: Path) -> None:
        super().__init__()
        self.root = root

    def __missing__(self, name: str) -> object:
        self[name] = write_benchmark_tree(name, self.root / name, frames=2)
        return self[name]


@pytest.fixture(scope="module")
def trees(tmp_path_factory: pytest.TempPathFactory) -> _Trees:
    return _Trees(tmp_path_factory.mktemp("trees"))


def _pairs(tree: object, name: str) -> list[tuple[np.ndarray, np.ndarray, dict]]:
    spec = get_benchmark(name)
    layout = layout_of(spec)
    _, entries = layout.samples(Path(tree.gt), spec)  # type: ignore[attr-defined]
    out = []
    for e in entries:
        gt = layout.read(e.path, spec)
        pred_file = next(Path(tree.pred).glob(f"{e.token}.np*"))  # type: ignore[attr-defined]
        pred, _ = read_prediction(pred_file, spec)
        masks = {k: v.numpy() for k, v in gt.masks.items()}
        out.append((pred.numpy(), gt.semantics.numpy(), masks))
    return out


def _oracle_waymo(pairs):  # Occ3D Metric_mIoU, free 23 -> 15, infov & camera
    hist = np.zeros((16, 16))
    for pred, gt, masks in pairs:
        m = masks["infov"] & masks["final_voxel_state"]
        g, p = gt[m], pred[m]
        k = (g >= 0) & (g < 16)
        hist += np.bincount(16 * g[k] + p[k], minlength=256).reshape(16, 16)
    iou = np.diag(hist) / (hist.sum(1) + hist.sum(0) - np.diag(hist))
    return iou, np.nanmean(iou[:15])


def _oracle_surroundocc(pairs):  # per-sample [tp, gt, pred] triples, mean over samples
    results = []
    for pred, gt, _ in pairs:
        m = gt != 255
        g, p = gt[m], pred[m]
        score = np.zeros((17, 3))
        score[0] = [((g != 0) & (p != 0)).sum(), (g != 0).sum(), (p != 0).sum()]
        for j in range(1, 17):
            score[j] = [((g == j) & (p == j)).sum(), (g == j).sum(), (p == j).sum()]
        results.append(score)
    r = np.stack(results).mean(0)
    iou = [r[i, 0] / (r[i, 1] + r[i, 2] - r[i, 0]) for i in range(17)]
    return np.array(iou), np.mean(np.array(iou)[1:])


def _oracle_gf(pairs):  # GaussianFormer MeanIoU: float32 counters, absent class -> 1
    seen, correct, positive = (np.zeros(17, dtype=np.float32) for _ in range(3))
    for pred, gt, _ in pairs:
        m = gt != 0
        g, p = gt[m], pred[m]
        for i, c in enumerate(range(1, 17)):
            seen[i] += (g == c).sum()
            correct[i] += ((g == c) & (p == c)).sum()
            positive[i] += (p == c).sum()
        seen[-1] += (g != 17).sum()
        correct[-1] += ((g != 17) & (p != 17)).sum()
        positive[-1] += (p != 17).sum()
    ious = [
        1 if seen[i] == 0 else float(correct[i] / (seen[i] + positive[i] - correct[i]))
        for i in range(16)
    ]
    return np.array([math.nan, *ious]), np.mean(ious)


def _oracle_openoccupancy(pairs):  # fast_hist over gt != 255, cm_to_ious, sum / 16
    hist = np.zeros((17, 17), dtype=np.int64)
    for pred, gt, _ in pairs:
        m = gt != 255
        hist += np.bincount(17 * gt[m] + pred[m], minlength=289).reshape(17, 17)
    iou = [hist[i, i] / (hist[:, i].sum() + hist[i, :].sum() - hist[i, i]) for i in range(17)]
    return np.array(iou), sum(iou[1:]) / 16


def _oracle_nuplan(pairs):  # MonoScene SSCMetrics: tp / (tp + fp + fn + 1e-5)
    tps, fps, fns = np.zeros(9), np.zeros(9), np.zeros(9)
    for pred, gt, _ in pairs:
        m = gt != 255
        g, p = gt[m], pred[m]
        for j in range(9):
            tps[j] += ((g == j) & (p == j)).sum()
            fps[j] += ((g != j) & (p == j)).sum()
            fns[j] += ((g == j) & (p != j)).sum()
    iou = tps / (tps + fps + fns + 1e-5)
    return iou, np.mean(iou[1:])


ORACLES = {
    "occ3d-waymo": _oracle_waymo,
    "surroundocc": _oracle_surroundocc,
    "surroundocc-gf": _oracle_gf,
    "openoccupancy": _oracle_openoccupancy,
    "nuplan-occ": _oracle_nuplan,
}


SLOW_TREES = {"openoccupancy", "nuplan-occ"}  # 512x512x40 and 400x400x32 grids


@pytest.mark.parametrize(
    "name",
    [pytest.param(n, marks=pytest.mark.slow) if n in SLOW_TREES else n for n in sorted(ORACLES)],
)
def test_every_voxel_benchmark_matches_its_official_rules_to_the_bit(trees, name) -> None:
    tree = trees[name]
    report = dego.evaluate(tree.gt, tree.pred, benchmark=name, rayiou=False)
    [occupancy] = report.protocols.values()
    per_class, miou = ORACLES[name](_pairs(tree, name))
    ids = list(occupancy.evaluated_classes)
    assert occupancy.miou == float(miou)  # bit for bit
    np.testing.assert_array_equal(occupancy.per_class.numpy()[ids], per_class[ids])
    assert report.benchmark == name and report.rules[0].startswith(f"benchmark: {name}")


@pytest.mark.slow
def test_workers_give_the_same_counts(
    trees, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the workers' rendezvous folder in this test's own folder (another test watches the
    # system's temporary folder for stray ones)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    tree = trees["occ3d-waymo"]
    one = dego.evaluate(tree.gt, tree.pred, benchmark="occ3d-waymo", rayiou=False)
    two = dego.evaluate(tree.gt, tree.pred, benchmark="occ3d-waymo", rayiou=False, workers=2)
    for metric, parts in one.counts.items():
        for key, value in parts.items():
            assert np.array_equal(value.numpy(), two.counts[metric][key].numpy())


@pytest.mark.slow
def test_openocc_v2_rayiou_mave_and_occscore(tmp_path: Path) -> None:
    tree = write_benchmark_tree("openocc-v2", tmp_path / "o", frames=1)
    for variant in ("dataset", "server"):
        report = dego.evaluate(
            tree.gt, tree.pred, benchmark="openocc-v2", infos=tree.infos, mave=variant
        )
        assert report.rayiou is not None and report.flow is not None
        assert report.rayiou.class_names[0] == "car" and len(report.rayiou.class_ids) == 16
        mave = report.flow["mave"]
        assert mave >= 0 and report.flow["variant"] == variant
        expected = 0.9 * report.rayiou.rayiou + 0.1 * max(1 - mave, 0.0)
        assert report.flow["occ_score"] == expected


def test_occ3d_ids_scored_as_openocc_are_refused_with_the_map(tmp_path: Path) -> None:
    tree = write_benchmark_tree("openocc-v2", tmp_path / "o", frames=1)
    pred = next(Path(tree.pred).glob("*.npz"))
    occ3d = np.full((200, 200, 16), 17, dtype=np.uint8)
    np.savez(pred, pred=occ3d)
    with pytest.raises(EvaluationSetupError, match=r"openocc-v2.*occ3d_to_openocc"):
        dego.evaluate(tree.gt, tree.pred, benchmark="openocc-v2", infos=tree.infos)
    assert OCC3D_TO_OPENOCC[17] == 16 and OCC3D_TO_OPENOCC[4] == 0


@pytest.mark.slow
def test_a_tree_of_another_benchmark_is_a_setup_error(trees) -> None:
    surround = trees["surroundocc"]
    with pytest.raises(EvaluationSetupError, match="nuplan-occ"):
        dego.evaluate(surround.gt, surround.pred, benchmark="nuplan-occ", rayiou=False)
    waymo = trees["occ3d-waymo"]
    with pytest.raises(EvaluationSetupError, match=r"no occ3d-nuscenes|no ground truth"):
        dego.evaluate(waymo.gt, waymo.pred, rayiou=False)
    with pytest.raises(EvaluationSetupError, match="no benchmark 'kitti'"):
        dego.evaluate(waymo.gt, waymo.pred, benchmark="kitti")


@pytest.mark.slow
def test_a_prediction_on_the_wrong_grid_names_the_benchmark_and_shape(trees) -> None:
    tree = trees["nuplan-occ"]
    pred = sorted(Path(tree.pred).glob("*.npy"))[0]
    np.save(pred, np.zeros((200, 200, 16), dtype=np.uint8))
    with pytest.raises(EvaluationSetupError, match=r"nuplan-occ grid is \(200, 200, 32\)"):
        dego.evaluate(tree.gt, tree.pred, benchmark="nuplan-occ", rayiou=False)


def test_rows_outside_the_grid_are_refused(tmp_path: Path) -> None:
    spec = get_benchmark("surroundocc")
    rows = np.array([[0, 0, 0, 4], [250, 3, 2, 4]])
    np.save(tmp_path / "a.npy", rows)
    with pytest.raises(ValueError, match="outside the surroundocc grid"):
        layout_of(spec).read(tmp_path / "a.npy", spec)


@pytest.mark.slow
def test_openoccupancy_majority_vote_and_logits(tmp_path: Path) -> None:
    spec = get_benchmark("openoccupancy")
    rows = np.array([[1, 2, 3, 4], [1, 2, 3, 5], [1, 2, 3, 5], [0, 0, 0, 7], [0, 0, 0, 6]])
    np.save(tmp_path / "rows.npy", rows)
    dense = layout_of(spec).read(tmp_path / "rows.npy", spec).semantics
    assert int(dense[3, 2, 1]) == 5  # z, y, x rows; 2 votes beat 1
    assert int(dense[0, 0, 0]) == 6  # a tie goes to the smaller label
    logits = np.zeros((17, 8, 8, 2), dtype=np.float32)
    logits[4] = 1.0
    np.save(tmp_path / "logits.npy", logits)
    labels, _ = read_prediction(tmp_path / "logits.npy", spec)
    assert labels.shape == (512, 512, 40) and bool((labels == 4).all())


def test_duplicate_tokens_are_a_setup_error(tmp_path: Path) -> None:
    tree = write_benchmark_tree("occ3d-nuscenes", tmp_path / "t", frames=1)
    gts = Path(tree.gt) / "gts"
    [scene] = list(gts.iterdir())
    twin = gts / "scene-9999"
    twin.mkdir()
    for token in scene.iterdir():
        (twin / token.name).mkdir()
        (twin / token.name / "labels.npz").write_bytes((token / "labels.npz").read_bytes())
    with pytest.raises(EvaluationSetupError, match="appears twice"):
        dego.evaluate(tree.gt, tree.pred, rayiou=False, benchmark="openocc-v2")


@pytest.mark.slow
def test_cli_lists_benchmarks_and_writes_trees(tmp_path: Path) -> None:
    run = [sys.executable, "-m", "dego"]
    listed = subprocess.run([*run, "eval", "--benchmarks"], capture_output=True, text=True)
    assert listed.returncode == 0
    assert [line.split()[0] for line in listed.stdout.splitlines()] == list(BENCHMARKS)
    wrote = subprocess.run(
        [*run, "data", "write-tree", "--benchmark", "nuplan-occ", str(tmp_path / "n")],
        capture_output=True,
        text=True,
    )
    assert wrote.returncode == 0, wrote.stderr
    scored = subprocess.run(
        [
            *run,
            "eval",
            "--benchmark",
            "nuplan-occ",
            "--gt",
            str(tmp_path / "n/gt"),
            "--pred",
            str(tmp_path / "n/pred"),
            "--quiet",
        ],
        capture_output=True,
        text=True,
    )
    assert scored.returncode == 0, scored.stderr
    assert "benchmark: nuplan-occ" in scored.stdout and "epsilon" in scored.stdout
    bad = subprocess.run(
        [*run, "eval", "--benchmark", "nope", "--gt", ".", "--pred", "."],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2


def test_chunked_logit_upsampling_equals_one_interpolate_and_argmax() -> None:
    generator = torch.Generator().manual_seed(3)
    logits = torch.randn(9, 3, 4, 2, generator=generator)
    logits[:, 0, 0, 0] = 1.0  # a tie: the first maximum wins, as torch.argmax
    full = torch.nn.functional.interpolate(
        logits[None], size=(7, 9, 5), mode="trilinear", align_corners=False
    )[0].argmax(0)
    assert torch.equal(upsample_logits(logits, (7, 9, 5)), full)


def _rays(gt_cls, pred_cls, gt_dist, pred_dist, gt_flow, pred_flow):
    return {
        "gt_cls": torch.tensor(gt_cls),
        "pred_cls": torch.tensor(pred_cls),
        "gt_dist": torch.tensor(gt_dist, dtype=torch.float32),
        "pred_dist": torch.tensor(pred_dist, dtype=torch.float32),
        "gt_flow": torch.tensor(gt_flow, dtype=torch.float32),
        "pred_flow": torch.tensor(pred_flow, dtype=torch.float32),
    }


def test_the_two_mave_scripts_average_over_different_rays() -> None:
    """Two car rays (one a true positive with flow error 1, one 3 m off with error 3), one
    pedestrian ray missed (error 2), one free ray (dropped): the dataset script averages
    the true positive only (1), the server script every kept ray of the sample (2)."""
    spec = get_benchmark("openocc-v2")
    rays = _rays(
        [0, 0, 7, 16],
        [0, 0, 16, 16],
        [5.0, 5.0, 8.0, 9.0],
        [5.5, 8.0, 8.0, 9.0],
        [[0, 0], [0, 0], [0, 0], [0, 0]],
        [[1, 0], [3, 0], [0, 2], [0, 0]],
    )
    (gt_count, pred_count, tp), sums, numbers = ray_flow_counts(spec, rays, "dataset")
    assert gt_count[0] == 2 and gt_count[7] == 1 and int(gt_count.sum()) == 3
    assert tp[:, 0].tolist() == [1, 1, 2] and pred_count[16] == 1
    assert (sums[0], numbers[0]) == (1.0, 1) and numbers[7] == 0
    _, server_sums, server_numbers = ray_flow_counts(spec, rays, "server")
    assert (server_sums[0], server_numbers[0]) == (6.0, 3)
    ave, value = mave(spec, [(sums, numbers)])
    assert ave[0] == 1.0 and math.isnan(ave[7]) and value == 1.0
    assert mave(spec, [(server_sums, server_numbers)])[1] == 2.0
    assert occ_score(0.5, 2.0) == 0.45 and math.isnan(occ_score(0.5, math.nan))


def test_per_class_rules_are_the_official_arithmetic() -> None:
    confusion = torch.tensor([[5, 1, 0], [2, 3, 0], [0, 0, 0]])
    ratio = class_iou(confusion, "ratio", 3)
    assert ratio[1] == 3 / (3 + 1 + 2) and math.isnan(float(ratio[2]))
    assert class_iou(confusion, "absent-is-one-float32", 3)[2] == 1.0
    assert class_iou(confusion, "epsilon", 3)[1] == 3 / (3 + 1 + 2 + 1e-5)
    assert class_iou(confusion, "epsilon", 3)[2] == 0.0
    mean = class_iou(confusion, "sample-mean", 3)[1]
    assert mean == (3 / 3) / (5 / 3 + 4 / 3 - 3 / 3)
    with pytest.raises(ValueError, match="unknown per-class rule"):
        class_iou(confusion, "median", 1)


def test_every_benchmark_names_its_rules() -> None:
    for spec in BENCHMARKS.values():
        rules = "\n".join(spec.rules())
        assert spec.name in rules and "grid:" in rules and f"{spec.free_label} = free" in rules
        for protocol in spec.voxel:
            assert f"voxel protocol {protocol.name}" in rules and protocol.averaging in rules


def test_occ3d_labels_map_onto_openocc_ids() -> None:
    labels = torch.arange(18)
    mapped = occ3d_to_openocc(labels)
    names = get_benchmark("openocc-v2").class_names
    occ3d = get_benchmark("occ3d-nuscenes").class_names
    for occ3d_id in range(1, 18):
        assert names[int(mapped[occ3d_id])] == occ3d[occ3d_id]
    assert int(mapped[0]) == 16  # others: free (OpenOcc v2 has no such class)
    with pytest.raises(ValueError, match=r"0\.\.17"):
        occ3d_to_openocc(torch.tensor([18]))


@pytest.mark.slow
def test_openocc_workers_give_the_same_bits_and_the_submission_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    tree = write_benchmark_tree("openocc-v2", tmp_path / "o", frames=2)
    kwargs = {"benchmark": "openocc-v2", "infos": tree.infos}
    one = dego.evaluate(tree.gt, tree.pred, **kwargs)
    two = dego.evaluate(tree.gt, tree.pred, workers=2, **kwargs)
    assert repr(one.flow) == repr(two.flow)  # same bits (repr round-trips; NaN included)
    assert one.rayiou.rayiou == two.rayiou.rayiou
    out = write_openocc_submission(tree.pred, tree.infos, tmp_path / "submission.gz")
    with gzip.open(out, "rb") as file:
        submission = pickle.load(file)  # our own file
    assert set(submission) >= {"method", "team", "results"}
    result = next(iter(submission["results"].values()))
    assert result["pcd_cls"].dtype == np.uint8 and result["pcd_dist"].dtype == np.float16
    assert result["pcd_flow"].shape == (result["pcd_cls"].shape[0], 2)
    assert result["pcd_cls"].shape[0] % 14040 == 0


@pytest.mark.slow
def test_occ3d_nuscenes_rayiou_over_both_class_sets(tmp_path: Path) -> None:
    tree = write_benchmark_tree("occ3d-nuscenes", tmp_path / "n", frames=1)
    report = dego.evaluate(tree.gt, tree.pred, infos=tree.infos)
    seventeen, fifteen = report.rayiou_sets.values()
    assert len(seventeen.class_ids) == 17 and len(fifteen.class_ids) == 15
    weak = dego.evaluate(tree.gt, tree.pred, infos=tree.infos, classes=fifteen.class_ids)
    assert weak.rayiou.rayiou == fifteen.rayiou and report.rayiou is seventeen
    assert "15 classes (the weak set)" in report.tables()


def test_rerun_is_refused_for_other_benchmarks(tmp_path: Path) -> None:
    from dego.cli import main

    argv = ["eval", "--benchmark", "occ3d-waymo", "--gt", str(tmp_path), "--pred", str(tmp_path)]
    with pytest.raises(SystemExit) as stop:
        main([*argv, "--rerun", str(tmp_path / "eval.rrd")])
    assert stop.value.code == 2 and not (tmp_path / "eval.rrd").exists()


def _waymo_file(tmp_path: Path, **arrays: np.ndarray) -> Path:
    shape = (200, 200, 16)
    base = {
        "voxel_label": np.full(shape, 23, dtype=np.uint8),
        "origin_voxel_state": np.ones(shape, dtype=np.uint8),
        "final_voxel_state": np.ones(shape, dtype=np.uint8),
        "infov": np.ones(shape, dtype=np.uint8),
    }
    base.update(arrays)
    path = tmp_path / "000" / "001_04.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **{k: v for k, v in base.items() if v is not None})
    return path


@pytest.mark.parametrize(
    ("arrays", "message"),
    [
        ({"infov": None}, r"missing array\(s\) \['infov'\]"),
        ({"voxel_label": np.zeros((200, 200, 32), np.uint8)}, r"occ3d-waymo expects"),
        ({"voxel_label": np.full((200, 200, 16), 17, np.uint8)}, r"label\(s\) \[17\]"),
        ({"final_voxel_state": np.full((200, 200, 16), 2, np.uint8)}, "0/1 or bool mask"),
    ],
    ids=["missing key", "shape", "label", "mask"],
)
def test_waymo_files_of_another_kind_are_refused(tmp_path: Path, arrays, message) -> None:
    spec = get_benchmark("occ3d-waymo")
    path = _waymo_file(tmp_path, **arrays)
    with pytest.raises(ValueError, match=message):
        layout_of(spec).read(path, spec)
    assert layout_of(spec).read(_waymo_file(tmp_path / "ok"), spec).semantics.max() == 15


def test_a_free_id_where_the_benchmark_has_none_is_refused(tmp_path: Path) -> None:
    """23 is Waymo's stored free; in SurroundOcc rows it is not a label."""
    spec = get_benchmark("surroundocc")
    np.save(tmp_path / "a.npy", np.array([[1, 2, 3, 23]]))
    with pytest.raises(ValueError, match=r"row label\(s\) \[23\].*another benchmark"):
        layout_of(spec).read(tmp_path / "a.npy", spec)
    np.save(tmp_path / "b.npy", np.array([[1.5, 2, 3, 4]]))
    with pytest.raises(ValueError, match="whole numbers"):
        layout_of(spec).read(tmp_path / "b.npy", spec)


def test_openocc_ground_truth_without_flow_is_refused(tmp_path: Path) -> None:
    spec = get_benchmark("openocc-v2")
    path = tmp_path / "labels.npz"
    np.savez(path, semantics=np.full((200, 200, 16), 16, np.uint8))
    with pytest.raises(ValueError, match=r"missing array\(s\) \['flow'\]"):
        layout_of(spec).read(path, spec)


def test_a_scene_folder_linked_twice_is_a_setup_error(tmp_path: Path) -> None:
    """Issue 50 (1): ``ln -s scene-0 gts/scene-0-copy`` scored every sample twice."""
    tree = write_benchmark_tree("occ3d-nuscenes", tmp_path / "t", frames=1)
    gts = Path(tree.gt) / "gts"
    [scene] = list(gts.iterdir())
    (gts / f"{scene.name}-copy").symlink_to(scene, target_is_directory=True)
    with pytest.raises(EvaluationSetupError, match="appears twice"):
        dego.evaluate(tree.gt, tree.pred, rayiou=False)


def test_a_protocol_the_benchmark_lacks_is_named(trees) -> None:
    tree = trees["occ3d-waymo"]
    with pytest.raises(EvaluationSetupError, match=r"occ3d-waymo has no protocol 'weak'"):
        dego.evaluate(tree.gt, tree.pred, benchmark="occ3d-waymo", protocol="weak")


@pytest.mark.slow
def test_openocc_reports_carry_the_rules_and_the_flow(tmp_path: Path) -> None:
    tree = write_benchmark_tree("openocc-v2", tmp_path / "o", frames=1)
    report = dego.evaluate(tree.gt, tree.pred, benchmark="openocc-v2", infos=tree.infos)
    data = json.loads(report.to_json())
    assert data["benchmark"] == "openocc-v2" and data["rules"] == list(report.rules)
    assert data["flow"]["variant"] == "dataset"
    assert data["flow"]["occ_score"] == pytest.approx(100 * report.flow["occ_score"])
    markdown = report.to_markdown()
    assert "- benchmark: openocc-v2" in markdown and "## Flow (OpenOcc v2)" in markdown
    assert "mAVE (dataset script)" in report.tables()
