"""OpenOcc v2 helpers: the Occ3D-nuScenes -> OpenOcc v2 id map (for models trained on
Occ3D labels) and the challenge's submission file (per token: the class, distance and
flow each ray of SparseOcc's pattern reads from the predicted grid).

The submission is the dict of OccNet's README, written as a gzip pickle as their
``tools/ray_iou/ray_casting.py`` writes it (dego never loads pickles it did not write):
``{"method", "team", "authors", "e-mail", "institution / company", "country / region",
"results": {token: {"pcd_cls": uint8 (N,), "pcd_dist": float16 (N,), "pcd_flow": float16
(N, 2)}}}``, N = K origins x 14,040 rays, every ray (the scorer drops the free ones).
"""

from __future__ import annotations

import gzip
import os
import pickle
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Integer
from torch import Tensor

from dego._atomic import temporary_name
from dego._typing import typechecked
from dego.evaluation.benchmarks import OCC3D_TO_OPENOCC, get_benchmark
from dego.evaluation.errors import EvaluationSetupError
from dego.evaluation.origins import OriginSource, load_keyframes, open_origins
from dego.evaluation.predictions import find_prediction, read_prediction
from dego.evaluation.scoring import cast_with_flow
from dego.raycast import generate_lidar_rays

PathLike = str | os.PathLike[str]


@typechecked
def occ3d_to_openocc(labels: Integer[Tensor, "*shape"]) -> Integer[Tensor, "*shape"]:
    """Occ3D-nuScenes labels (0 others .. 16 vegetation, 17 free) as OpenOcc v2 ids (0 car
    .. 15 vegetation, 16 free): :data:`~dego.evaluation.benchmarks.OCC3D_TO_OPENOCC`.
    ``others`` (0), which OpenOcc v2 lacks, becomes free.

    Raises:
        ValueError: a label outside 0..17.
    """
    if labels.numel() and (int(labels.min()) < 0 or int(labels.max()) > 17):
        raise ValueError(
            f"labels: Occ3D-nuScenes labels lie in 0..17, got {int(labels.min())}.."
            f"{int(labels.max())}"
        )
    table = torch.tensor(OCC3D_TO_OPENOCC, dtype=labels.dtype, device=labels.device)
    return table[labels.long()]


DEFAULT_FIELDS = {
    "method": "",
    "team": "",
    "authors": [""],
    "e-mail": "",
    "institution / company": "",
    "country / region": "",
}


@typechecked
def write_openocc_submission(
    pred: PathLike,
    infos: PathLike,
    out: PathLike,
    *,
    fields: Mapping[str, object] | None = None,
) -> Path:
    """Cast SparseOcc's rays from every sample's origins (the infos' poses) through the
    OpenOcc v2 predictions in ``pred`` (``<token>.npz`` with labels and optionally
    ``flow``, else zero flow) and write the challenge's submission to ``out``.

    Args:
        pred: the predictions folder (as ``dego eval --benchmark openocc-v2`` reads it).
        infos: the mmdet3d infos file of the split: its tokens, in order, are the samples.
        out: the ``.gz`` / ``.pkl`` file to write (atomically).
        fields: the README's header fields (``method``, ``team``, ...).

    Returns:
        ``out``.

    Raises:
        EvaluationSetupError: no infos, a sample without prediction, bad origins.
        ValueError: a prediction that is not OpenOcc v2 (shape, ids: convert Occ3D labels
            with :func:`occ3d_to_openocc`).
    """
    spec = get_benchmark("openocc-v2")
    source = OriginSource("infos", str(infos))
    keyframes = load_keyframes(source)
    tokens = [str(k.token) for k in keyframes]
    scene_of = {str(k.token): str(k.scene) for k in keyframes}
    origins_fn = open_origins(source, scene_of, tokens, keyframes)
    rays = generate_lidar_rays()
    results = {}
    for token in tokens:
        path = find_prediction(Path(pred), scene_of[token], token)
        if path is None:
            raise EvaluationSetupError(f"--pred: no prediction for sample {token!r} in {pred}")
        labels, flow = read_prediction(path, spec)
        if flow is None:  # no predicted flow: zero, as OccNet's ray_casting.py sets it
            flow = torch.zeros((*labels.shape, 2))
        free = torch.full_like(labels, spec.free_label)
        cast = cast_with_flow(
            spec, labels, free, flow, flow, origins_fn(token), rays, missed="every"
        )
        results[token] = {
            "pcd_cls": cast["pred_cls"].numpy().astype(np.uint8),
            "pcd_dist": cast["pred_dist"].numpy().astype(np.float16),
            "pcd_flow": cast["pred_flow"].numpy().astype(np.float16),
        }
    submission = {**DEFAULT_FIELDS, **(fields or {}), "results": results}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(out)
    with gzip.GzipFile(tmp, "wb", compresslevel=9) as file:
        pickle.dump(submission, file, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(tmp, out)
    return out


__all__ = ["occ3d_to_openocc", "write_openocc_submission"]
