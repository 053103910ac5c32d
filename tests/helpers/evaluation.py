"""Helpers of tests/evaluation/test_evaluation.py, also used by

- tests/evaluation/test_distributed.py
- tests/evaluation/test_sources.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import dego
from dego.cli import main as cli_main
from dego.data import LABELS_FILENAME, Occ3DLabels, save_occ3d_labels

SHAPE = (200, 200, 16)
SCENES = {"scene-a": ("tok-a0", "tok-a1", "tok-a2"), "scene-b": ("tok-b0", "tok-b1", "tok-b2")}
TOKENS = [t for tokens in SCENES.values() for t in tokens]
SCENE_OF = {t: s for s, tokens in SCENES.items() for t in tokens}
# how each sample's prediction is written (every accepted format once)
FORMATS = dict(
    zip(TOKENS, ("pred", "arr_0", "semantics", "npy", "gt_layout", "gts_layout"), strict=True)
)
LIDAR = (0.94, 0.0, 1.84)


def label_grid(seed: int) -> torch.Tensor:
    """A cheap random scene: ground plane (three surface classes) and a few boxes."""
    g = torch.Generator().manual_seed(seed)
    grid = torch.full(SHAPE, 17, dtype=torch.uint8)
    ground = torch.tensor([11, 13, 14], dtype=torch.uint8)[
        torch.randint(0, 3, (200, 1), generator=g)
    ]
    grid[:, :, 1] = ground.expand(200, 200)
    grid[:, :, 0] = 12
    for _ in range(8):
        x, y = (int(v) for v in torch.randint(20, 180, (2,), generator=g))
        w, h = (int(v) for v in torch.randint(2, 12, (2,), generator=g))
        z = int(torch.randint(3, 10, (1,), generator=g))
        label = int(torch.randint(0, 17, (1,), generator=g))
        grid[x : x + w, y : y + h, 2:z] = label
    return grid


def perturb(grid: torch.Tensor, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(1000 + seed)
    draw = torch.rand(SHAPE, generator=g)
    pred = grid.clone()
    pred[draw < 0.05] = 17
    swap = (draw > 0.97) & (grid != 17)
    pred[swap] = torch.randint(0, 17, SHAPE, generator=g, dtype=torch.uint8)[swap]
    return pred


def origins_of(i: int) -> np.ndarray:
    return np.array([LIDAR, (LIDAR[0] + 3.0 * i, 0.5, LIDAR[2])][: 1 + i % 2], dtype=np.float64)


def write_prediction(root: Path, scene: str, token: str, pred: np.ndarray, fmt: str) -> None:
    if fmt == "pred":
        np.savez_compressed(root / f"{token}.npz", pred=pred)
    elif fmt == "arr_0":
        np.savez(root / f"{token}.npz", pred)
    elif fmt == "semantics":
        np.savez(root / f"{token}.npz", semantics=pred.astype(np.int64))
    elif fmt == "npy":
        np.save(root / f"{token}.npy", pred.astype(np.int32))
    else:
        base = root / "gts" if fmt == "gts_layout" else root
        mask = torch.ones(SHAPE, dtype=torch.bool)
        save_occ3d_labels(
            base / scene / token / LABELS_FILENAME, Occ3DLabels(torch.from_numpy(pred), mask, mask)
        )


def make_tree(root: Path) -> dict[str, object]:
    """``root/gt`` (Occ3D layout), ``root/pred`` (every format), ``root/origins``."""
    gt, pred, origins = root / "gt", root / "pred", root / "origins"
    pred.mkdir(parents=True)
    origins.mkdir()
    arrays = {}
    for i, token in enumerate(TOKENS):
        scene = SCENE_OF[token]
        semantics = label_grid(i)
        g = torch.Generator().manual_seed(50 + i)
        mask = torch.rand(SHAPE, generator=g) < 0.8
        save_occ3d_labels(
            gt / "gts" / scene / token / LABELS_FILENAME, Occ3DLabels(semantics, mask, ~mask)
        )
        p = perturb(semantics, i).numpy()
        write_prediction(pred, scene, token, p, FORMATS[token])
        np.save(origins / f"{token}.npy", origins_of(i))
        arrays[token] = (p, semantics, mask, origins_of(i))
    return {"root": root, "gt": gt, "pred": pred, "origins": origins, "arrays": arrays}


def direct(tree: dict, tokens=None, *, rayiou=False, free=(), classes=None):
    """The metrics run directly on the same arrays: {name: metric}."""
    metrics = {"occ3d": dego.OccupancyMetrics("occ3d"), "weak": dego.OccupancyMetrics("weak")}
    if rayiou:
        metrics["rayiou"] = dego.RayIoU(class_ids=classes)
    for token in tokens or TOKENS:
        pred, gt, mask, origins = tree["arrays"][token]
        if token in free:
            pred = np.full(SHAPE, 17, dtype=np.uint8)
        metrics["occ3d"].update(pred, gt, mask)
        metrics["weak"].update(pred, gt, mask)
        if rayiou:
            metrics["rayiou"].update(pred, gt, torch.from_numpy(origins))
    return metrics


def assert_same_counts(report: dego.EvaluationReport, metrics: dict) -> None:
    assert set(report.counts) == set(metrics)
    for name, metric in metrics.items():
        for count in metric.COUNTS:
            assert torch.equal(report.counts[name][count], getattr(metric, count)), (name, count)


def run_cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = cli_main(["eval", *args])
    out, err = capsys.readouterr()
    return code, out, err
