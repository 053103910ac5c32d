"""``dego eval --rerun``: ground truth beside prediction for the first samples, for rerun.

Entities: ``world/occupancy/ground_truth`` and ``world/occupancy/prediction`` inside the
camera mask (where the occ3d protocol scores them), their bird's-eye views
``bev/ground_truth`` and ``bev/prediction``, and ``sample`` (the scene and token as
text), on the ``sample`` timeline (0, 1, ... in scoring order).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from dego.classes import FREE_LABEL
from dego.data.occ3d import LABELS_FILENAME, load_occ3d_labels
from dego.evaluation.predictions import load_prediction
from dego.evaluation.run import prepare
from dego.grid import VoxelGrid
from dego.viz import rerun as rerun_log

PathLike = str | os.PathLike[str]

DEFAULT_LIMIT = 20
"""Samples ``dego eval --rerun`` records without ``--limit``."""
MAX_RECORDED_SAMPLES = 1000
"""The most samples ``--limit`` allows (about 0.3 MB and 0.1 s a sample)."""


def grid_of(shape: tuple[int, int, int]) -> VoxelGrid:
    """The Occ3D-nuScenes grid for its shape ``(200, 200, 16)``; another shape gets 0.4 m
    voxels from the same lower corner (the labels carry no geometry of their own)."""
    occ3d = VoxelGrid.occ3d()
    if shape == occ3d.shape:
        return occ3d
    upper = [
        low + n * size for low, n, size in zip(occ3d.lower, shape, occ3d.voxel_size, strict=True)
    ]
    return VoxelGrid(occ3d.lower, tuple(upper), occ3d.voxel_size)


@dataclass(frozen=True)
class RecordedSamples:
    """What :func:`record_samples` wrote: the file, the samples recorded and those that
    could not be read (``token: reason``)."""

    path: Path
    recorded: int
    failed: dict[str, str]


def record_samples(
    path: PathLike,
    gt: PathLike,
    pred: PathLike,
    *,
    limit: int = DEFAULT_LIMIT,
    infos: PathLike | None = None,
    missing: str = "error",
) -> RecordedSamples:
    """Record the first ``limit`` samples that ``dego eval`` scores (same selection and
    order: ``--infos`` order when given, else the ground-truth tree's) to ``path``,
    atomically. A sample whose files cannot be read is left out and listed in ``failed``."""
    plan, _ = prepare(gt, pred, rayiou=False, infos=infos, missing=missing)
    rows = {"ground truth": "ground_truth", "prediction": "prediction"}
    layout = rerun_log.blueprint(
        tabs={name: [f"+ /world/occupancy/{entity}"] for name, entity in rows.items()},
        bev=[f"bev/{entity}" for entity in rows.values()],
    )
    rr = rerun_log.require_rerun()
    failed: dict[str, str] = {}
    recorded = 0
    with rerun_log.recording_file(path, application_id="dego eval", blueprint=layout) as rec:
        for sample in plan.samples[:limit]:
            gt_path = Path(plan.gt) / sample.scene / sample.token / LABELS_FILENAME
            try:
                labels = load_occ3d_labels(gt_path)
                if sample.prediction is None:  # --missing free
                    prediction = torch.full(labels.shape, FREE_LABEL, dtype=torch.uint8)
                else:
                    prediction = load_prediction(sample.prediction, expected_shape=labels.shape)
            except (OSError, ValueError, TypeError, KeyError) as error:
                failed[sample.token] = str(error)
                continue
            x, y, z = labels.semantics.shape
            grid = grid_of((x, y, z))
            rec.set_time(rerun_log.SAMPLE_TIMELINE, sequence=recorded)
            rec.log("sample", rr.TextDocument(f"scene {sample.scene}, sample {sample.token}"))
            for entity, grid_labels in (
                ("ground_truth", labels.semantics),
                ("prediction", prediction),
            ):
                rerun_log.log_occupancy(
                    f"world/occupancy/{entity}",
                    grid_labels,
                    grid,
                    mask=labels.mask_camera,
                    recording=rec,
                )
                rerun_log.log_bev(
                    f"bev/{entity}", grid_labels, mask=labels.mask_camera, recording=rec
                )
            recorded += 1
    return RecordedSamples(Path(path), recorded, failed)
