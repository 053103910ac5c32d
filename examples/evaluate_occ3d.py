"""Score a folder of occupancy predictions against Occ3D-nuScenes labels with ``dego.evaluate``.

This is the library call behind ``dego eval`` (same options; see ``dego eval --help``):
voxel IoU / mIoU under both protocols (``occ3d``: camera mask, 17 classes; ``weak``: DeGO /
GaussianFlowOcc, 15 classes) and SparseOcc's RayIoU, with its ray origins from an mmdet3d
infos file, the nuScenes tables or a folder of ``<token>.npy``.

    python examples/evaluate_occ3d.py       # self-contained demo on synthetic scenes
    python examples/evaluate_occ3d.py --gt data/occ3d-nus --pred preds \\
        --infos data/nuscenes_infos_val.pkl --out report.json
    dego eval --gt data/occ3d-nus --pred preds --infos data/nuscenes_infos_val.pkl  # the same

With no ``--gt`` / ``--pred`` the script builds a small data set from ``dego.SyntheticScene``
in a temporary folder: ground truth (``gts/<scene>/<token>/labels.npz``), perturbed
predictions (``<token>.npz``, array ``pred`` as SparseOcc writes them), an infos file in
the mmdet3d 0.x layout (plain dicts, what ``dego.data.load_infos`` reads without running
any code) and per-sample origins (``<token>.npy``), and evaluates that. With ``--demo-dir
DIR`` the data set stays in ``DIR`` and the script prints the ``dego eval`` command that
scores it the same way.
"""

from __future__ import annotations

import argparse
import pickle
import shlex
import tempfile
from pathlib import Path

import numpy as np
import torch

import dego
from dego import Occ3DLabels, SyntheticScene, lidar_origins, save_occ3d_labels
from dego.classes import FREE_LABEL
from dego.data import LABELS_FILENAME, LIDAR_ORIGIN
from dego.gaussians import rotation_matrices_to_quaternions


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


def _pose_fields(prefix: str, matrix: torch.Tensor) -> dict[str, list[float]]:
    """``<prefix>_translation`` and ``<prefix>_rotation`` (wxyz), as nuScenes infos hold them."""
    quaternion = rotation_matrices_to_quaternions(matrix[:3, :3])
    return {
        f"{prefix}_translation": matrix[:3, 3].tolist(),
        f"{prefix}_rotation": quaternion.tolist(),
    }


def make_demo_data(
    root: Path, *, scenes: int, frames: int, image_size: tuple[int, int], seed: int
) -> tuple[Path, Path, Path, Path]:
    """Write ``root/gt`` (Occ3D layout), ``root/pred``, ``root/origins`` and
    ``root/nuscenes_infos_val.pkl`` (mmdet3d 0.x: ``{"infos": [...], "metadata": ...}``)."""
    gt_root, pred_root, origins_root = root / "gt", root / "pred", root / "origins"
    pred_root.mkdir(parents=True, exist_ok=True)
    origins_root.mkdir(parents=True, exist_ok=True)
    generator = torch.Generator().manual_seed(seed)
    lidar2ego = torch.eye(4, dtype=torch.float64)
    lidar2ego[:3, 3] = torch.tensor(LIDAR_ORIGIN, dtype=torch.float64)
    infos = []
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
            pred = perturb(frame.occupancy, generator).numpy()
            np.savez_compressed(pred_root / f"{token}.npz", pred=pred)
            origins = lidar_origins(
                ego2global, lidar2ego.expand(len(scene.offsets), 4, 4), reference_index=index
            )
            np.save(origins_root / f"{token}.npy", origins.numpy())
            infos.append(
                {
                    "token": token,
                    "scene_name": scene_name,
                    "timestamp": int(1_500_000_000_000_000 + offset * scene.frame_dt * 1e6),
                    **_pose_fields("lidar2ego", lidar2ego),
                    **_pose_fields("ego2global", ego2global[index]),
                }
            )
            print(f"  wrote {scene_name}/{token} ({origins.shape[0]} RayIoU origins)")
    infos_path = root / "nuscenes_infos_val.pkl"
    with infos_path.open("wb") as file:  # plain dicts, lists and numbers only
        pickle.dump({"infos": infos, "metadata": {"version": "v1.0-trainval"}}, file)
    return gt_root, pred_root, origins_root, infos_path


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--gt", type=Path, help="Occ3D root holding gts/<scene>/<token>/")
    parser.add_argument("--pred", type=Path, help="predictions: <token>.npz or <token>.npy")
    parser.add_argument("--infos", type=Path, help="mmdet3d nuscenes_infos_val.pkl (origins)")
    parser.add_argument("--origins", type=Path, help="per-sample RayIoU origins <token>.npy")
    parser.add_argument(
        "--rayiou", action=argparse.BooleanOptionalAction, default=True, help="RayIoU too"
    )
    parser.add_argument("--workers", type=int, default=1, help="local processes (gloo)")
    parser.add_argument("--out", type=Path, help="write the JSON report here")
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


def _has_infos_reader() -> bool:
    return hasattr(dego.data, "load_infos") and hasattr(dego.data, "SceneOrigins")


def eval_command(
    gt_root: Path, pred_root: Path, *, infos: Path | None, origins: Path | None, rayiou: bool
) -> str:
    """The ``dego eval`` command line that scores ``pred_root`` as this script does."""
    words = ["dego", "eval", "--gt", str(gt_root), "--pred", str(pred_root)]
    if infos is not None:
        words += ["--infos", str(infos)]
    if origins is not None:
        words += ["--origins", str(origins)]
    if not rayiou:
        words.append("--no-rayiou")
    return shlex.join(words)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="dego-eval-") as scratch:
        infos, origins = args.infos, args.origins
        if args.gt is None:
            root = args.demo_dir if args.demo_dir is not None else Path(scratch)
            print(f"demo: {args.scenes} synthetic scenes x {args.frames} frames in {root}")
            gt_root, pred_root, origins_dir, infos_path = make_demo_data(
                root,
                scenes=args.scenes,
                frames=args.frames,
                image_size=tuple(args.image_size),
                seed=args.seed,
            )
            # the infos file when this dego reads them, else the origins written beside it
            infos, origins = (infos_path, None) if _has_infos_reader() else (None, origins_dir)
        else:
            gt_root, pred_root = args.gt, args.pred
        print(f"evaluating {pred_root} against {gt_root}")
        try:
            report = dego.evaluate(
                gt_root,
                pred_root,
                rayiou=args.rayiou,
                infos=infos,
                origins=origins,
                workers=args.workers,
                progress=True,
            )
        except ValueError as error:  # a setup error: missing files, no origins, ...
            raise SystemExit(f"error: {error}") from None
        print(report.tables())
        if args.out is not None:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(report.to_json())
            print(f"\nwrote {args.out}")
        if args.gt is None and args.demo_dir is not None:  # the data set outlives the script
            command = eval_command(
                gt_root, pred_root, infos=infos, origins=origins, rayiou=args.rayiou
            )
            print(f"\nthe same from the command line: {command}")
    return 0 if report.complete else 1


if __name__ == "__main__":
    raise SystemExit(main())
