"""Score a folder of occupancy predictions against Occ3D-nuScenes labels.

Reports voxel IoU / mIoU under both protocols of ``dego.OccupancyMetrics`` (``occ3d``:
inside the camera mask, 17 classes; ``weak``: the DeGO / GaussianFlowOcc protocol, 15
classes) and SparseOcc's RayIoU (``dego.RayIoU``), prints the tables and optionally writes
a JSON report.

    python examples/evaluate_occ3d.py       # self-contained demo on synthetic scenes
    python examples/evaluate_occ3d.py --gt data/occ3d-nus --pred preds --out report.json

Layout of the inputs:

- ``--gt ROOT``: the Occ3D-nuScenes release, ``ROOT/gts/<scene>/<token>/labels.npz``
  (``semantics``, ``mask_camera``, ``mask_lidar``); every sample found there is scored.
- ``--pred DIR``: one file per sample, ``DIR/<token>.npz`` (flat, as the usual submission
  writers produce) or ``DIR/<scene>/<token>/labels.npz`` (the GT's layout). The archive
  holds a ``(200, 200, 16)`` integer array ``semantics`` (17 = free); an archive with a
  single array under another name (``numpy.savez(path, pred)`` calls it ``arr_0``) is
  accepted too. A sample without a prediction file is an error.
- ``--origins DIR`` (optional): RayIoU ray origins per sample, ``DIR/<token>.npy`` with
  shape ``(K, 3)`` in that sample's ego frame, as SparseOcc builds them from the LiDAR
  positions of the scene's keyframes (``dego.lidar_origins(ego2global, lidar2ego,
  reference_index)``, see docs/rayiou.md). Without it every sample is scored from one
  origin, the nuScenes LiDAR position in the ego frame (``--lidar-origin``): that is
  fewer rays from a single viewpoint, so the numbers are *not* comparable with published
  RayIoU (which uses up to 8 origins per sample); the report says which was used.

Files are read with ``allow_pickle=False``. With no ``--gt`` / ``--pred`` the script
builds a small data set from ``dego.SyntheticScene`` in a temporary folder (ground truth
written with ``dego.save_occ3d_labels``, perturbed predictions, per-sample origins) and
evaluates that.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from dego import (
    Occ3DDataset,
    Occ3DLabels,
    OccupancyMetrics,
    OccupancyReport,
    RayIoU,
    RayIoUReport,
    SyntheticScene,
    lidar_origins,
    save_occ3d_labels,
)
from dego.classes import FREE_LABEL
from dego.data import LABELS_FILENAME, LIDAR_ORIGIN

# ----------------------------------------------------------------------------------------
# Reading predictions and origins
# ----------------------------------------------------------------------------------------


def prediction_path(pred_root: Path, scene: str, token: str) -> Path:
    """The prediction file of one sample: ``<token>.npz`` or ``<scene>/<token>/labels.npz``."""
    candidates = [pred_root / f"{token}.npz", pred_root / scene / token / LABELS_FILENAME]
    for path in candidates:
        if path.is_file():
            return path
    raise FileNotFoundError(
        f"no prediction for sample (scene {scene!r}, token {token!r}); looked for "
        + " and ".join(str(p) for p in candidates)
    )


def load_prediction(path: Path) -> np.ndarray:
    """The ``semantics`` array of a prediction archive (or its only array)."""
    with np.load(path, allow_pickle=False) as archive:
        if "semantics" in archive.files:
            return archive["semantics"]
        if len(archive.files) == 1:
            return archive[archive.files[0]]
        raise ValueError(f"{path}: expected an array 'semantics', found {archive.files}")


def load_origins(origins_root: Path, token: str) -> np.ndarray:
    """``(K, 3)`` RayIoU origins of one sample from ``<origins_root>/<token>.npy``."""
    path = origins_root / f"{token}.npy"
    if not path.is_file():
        raise FileNotFoundError(f"no RayIoU origins for token {token!r}: missing {path}")
    origins = np.load(path, allow_pickle=False)
    if origins.ndim != 2 or origins.shape[1] != 3:
        raise ValueError(f"{path}: expected origins of shape (K, 3), got {origins.shape}")
    return origins


# ----------------------------------------------------------------------------------------
# Evaluation
# ----------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """The scores of one folder of predictions."""

    samples: int
    occ3d: OccupancyReport
    weak: OccupancyReport
    rayiou: RayIoUReport | None
    origins: str  # how the RayIoU origins were chosen
    seconds: float


def evaluate(
    gt_root: Path,
    pred_root: Path,
    *,
    origins_root: Path | None,
    lidar_origin: tuple[float, float, float],
    with_rayiou: bool,
    device: torch.device,
) -> Evaluation:
    """Score every sample under ``gt_root/gts`` against its file in ``pred_root``."""
    start = time.perf_counter()
    dataset = Occ3DDataset.from_directory(gt_root)
    occ3d = OccupancyMetrics("occ3d", device=device)
    weak = OccupancyMetrics("weak", device=device)
    rayiou = RayIoU(device=device) if with_rayiou else None
    default_origins = torch.tensor([lidar_origin], dtype=torch.float64)
    every = max(1, len(dataset) // 10)
    for i, sample in enumerate(dataset):
        gt = sample.labels.to(device)
        pred = torch.from_numpy(
            load_prediction(prediction_path(pred_root, sample.scene_name, sample.token))
        ).to(device)
        if pred.shape != gt.semantics.shape:
            raise ValueError(
                f"prediction for token {sample.token!r}: shape {tuple(pred.shape)}, "
                f"ground truth {tuple(gt.semantics.shape)}"
            )
        occ3d.update(pred, gt.semantics, gt.mask_camera)
        weak.update(pred, gt.semantics, gt.mask_camera)
        if rayiou is not None:
            origins = (
                default_origins
                if origins_root is None
                else torch.from_numpy(load_origins(origins_root, sample.token))
            )
            rayiou.update(pred, gt.semantics, origins)  # RayIoU uses no visibility mask
        if (i + 1) % every == 0 or i + 1 == len(dataset):
            print(f"  [{i + 1}/{len(dataset)}] {sample.scene_name}/{sample.token}")
    if origins_root is not None:
        origins_note = f"per-sample origins from {origins_root}"
    else:
        origins_note = (
            f"one origin per sample at the LiDAR position {lidar_origin} "
            "(not SparseOcc's multi-origin protocol)"
        )
    return Evaluation(
        samples=len(dataset),
        occ3d=occ3d.compute(),
        weak=weak.compute(),
        rayiou=rayiou.compute() if rayiou is not None else None,
        origins=origins_note if with_rayiou else "RayIoU skipped",
        seconds=time.perf_counter() - start,
    )


def _finite_or_none(value: float) -> float | None:
    return None if math.isnan(value) else value  # JSON has no NaN


def report_json(evaluation: Evaluation, gt_root: Path, pred_root: Path) -> dict[str, object]:
    """The JSON report: fractions in [0, 1], null for classes absent from GT and predictions."""
    report: dict[str, object] = {
        "gt": str(gt_root),
        "pred": str(pred_root),
        "samples": evaluation.samples,
        "rayiou_origins": evaluation.origins,
        "occ3d": {k: _finite_or_none(v) for k, v in evaluation.occ3d.as_dict().items()},
        "weak": {k: _finite_or_none(v) for k, v in evaluation.weak.as_dict().items()},
    }
    if evaluation.rayiou is not None:
        report["rayiou"] = {k: _finite_or_none(v) for k, v in evaluation.rayiou.as_dict().items()}
    return report


# ----------------------------------------------------------------------------------------
# The demo data set
# ----------------------------------------------------------------------------------------


def perturb(semantics: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """A plausible imperfect prediction: missed voxels, confused classes, thick surfaces."""
    occupied = semantics != FREE_LABEL
    draw = torch.rand((3, *semantics.shape), generator=generator)
    pred = semantics.clone()
    # 10% of the occupied voxels are missed (predicted free)
    pred[occupied & (draw[0] < 0.10)] = FREE_LABEL
    # 5% take a random occupied class
    confused = occupied & (draw[1] < 0.05)
    random_labels = torch.randint(0, FREE_LABEL, semantics.shape, generator=generator)
    pred[confused] = random_labels[confused].to(pred.dtype)
    # 20% of the free voxels right above a surface copy its label (surfaces one voxel thick)
    below = pred[:, :, :-1]
    grow = (pred[:, :, 1:] == FREE_LABEL) & (below != FREE_LABEL) & (draw[2, :, :, 1:] < 0.2)
    pred[:, :, 1:] = torch.where(grow, below, pred[:, :, 1:])
    return pred


def make_demo_data(
    root: Path, *, scenes: int, frames: int, image_size: tuple[int, int], seed: int
) -> tuple[Path, Path, Path]:
    """Write ``root/gt`` (Occ3D layout), ``root/pred`` and ``root/origins`` (synthetic scenes)."""
    gt_root, pred_root, origins_root = root / "gt", root / "pred", root / "origins"
    pred_root.mkdir(parents=True, exist_ok=True)
    origins_root.mkdir(parents=True, exist_ok=True)
    generator = torch.Generator().manual_seed(seed)
    lidar2ego = torch.eye(4, dtype=torch.float64)
    lidar2ego[:3, 3] = torch.tensor(LIDAR_ORIGIN, dtype=torch.float64)
    for scene_seed in range(seed, seed + scenes):
        scene = SyntheticScene(scene_seed, num_frames=frames, image_size=image_size)
        scene_name = f"synthetic-{scene_seed:04d}"
        # every keyframe's pose, as SparseOcc takes them from the nuScenes infos
        ego2global = torch.stack([scene.ego_pose(o * scene.frame_dt) for o in scene.offsets])
        for index, offset in enumerate(scene.offsets):
            frame = scene.frame(offset)
            token = f"{scene_name}-frame{index}"
            labels = Occ3DLabels(frame.occupancy, frame.mask_camera, frame.mask_lidar)
            save_occ3d_labels(gt_root / "gts" / scene_name / token / LABELS_FILENAME, labels)
            pred = perturb(frame.occupancy, generator)
            np.savez_compressed(pred_root / f"{token}.npz", semantics=pred.numpy())
            origins = lidar_origins(
                ego2global, lidar2ego.expand(len(scene.offsets), 4, 4), reference_index=index
            )
            np.save(origins_root / f"{token}.npy", origins.numpy())
            print(f"  wrote {scene_name}/{token} ({origins.shape[0]} RayIoU origins)")
    return gt_root, pred_root, origins_root


# ----------------------------------------------------------------------------------------
# Command line
# ----------------------------------------------------------------------------------------


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--gt", type=Path, help="Occ3D root holding gts/<scene>/<token>/")
    parser.add_argument("--pred", type=Path, help="predictions: <token>.npz with 'semantics'")
    parser.add_argument("--origins", type=Path, help="per-sample RayIoU origins <token>.npy")
    parser.add_argument(
        "--lidar-origin",
        type=float,
        nargs=3,
        default=LIDAR_ORIGIN,
        metavar=("X", "Y", "Z"),
        help="the single RayIoU origin used without --origins (nuScenes LiDAR in the ego frame)",
    )
    parser.add_argument(
        "--rayiou",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also compute RayIoU (about 0.05 s per origin and sample on a CPU core)",
    )
    parser.add_argument("--out", type=Path, help="write the JSON report here")
    parser.add_argument("--device", default="cpu", help="where the metrics run (cpu, cuda)")
    demo = parser.add_argument_group("demo (used when --gt and --pred are not given)")
    demo.add_argument("--scenes", type=int, default=2, help="synthetic scenes")
    demo.add_argument("--frames", type=int, default=2, help="frames (samples) per scene")
    demo.add_argument("--image-size", type=int, nargs=2, default=(32, 88), metavar=("H", "W"))
    demo.add_argument("--seed", type=int, default=0, help="seed of the first scene")
    demo.add_argument("--demo-dir", type=Path, help="keep the demo data here (default: a temp dir)")
    args = parser.parse_args(argv)
    if (args.gt is None) != (args.pred is None):
        parser.error("--gt and --pred go together (give neither for the demo)")
    return args


def print_evaluation(evaluation: Evaluation) -> None:
    print(f"\n{evaluation.samples} samples scored in {evaluation.seconds:.1f} s\n")
    print("== Occ3D protocol (camera mask) ==")
    print(evaluation.occ3d.table())
    print("\n== weak protocol (DeGO / GaussianFlowOcc) ==")
    print(evaluation.weak.table())
    if evaluation.rayiou is not None:
        print(f"\n== RayIoU ({evaluation.origins}) ==")
        print(evaluation.rayiou.table())


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    device = torch.device(args.device)
    with tempfile.TemporaryDirectory(prefix="dego-eval-") as scratch:
        if args.gt is None:
            root = args.demo_dir if args.demo_dir is not None else Path(scratch)
            print(f"demo: {args.scenes} synthetic scenes x {args.frames} frames in {root}")
            gt_root, pred_root, origins_root = make_demo_data(
                root,
                scenes=args.scenes,
                frames=args.frames,
                image_size=tuple(args.image_size),
                seed=args.seed,
            )
        else:
            gt_root, pred_root, origins_root = args.gt, args.pred, args.origins
        print(f"evaluating {pred_root} against {gt_root}")
        try:
            evaluation = evaluate(
                gt_root,
                pred_root,
                origins_root=origins_root,
                lidar_origin=tuple(args.lidar_origin),
                with_rayiou=args.rayiou,
                device=device,
            )
        except FileNotFoundError as error:  # a missing folder or file: no traceback needed
            raise SystemExit(f"error: {error}") from None
        print_evaluation(evaluation)
        if args.out is not None:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            report = report_json(evaluation, gt_root, pred_root)
            args.out.write_text(json.dumps(report, indent=2) + "\n")
            print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
