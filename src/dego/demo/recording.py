"""``dego demo --rerun``: the clip, its ground truth and every variant over time, for rerun.

Entities (world = the reference frame's ego frame, metres):

- ``world/ego``: each frame's ego pose; below it, ``occupancy/<row>`` the ground truth and
  every table row's voxelised prediction, inside the camera mask (where they are scored);
- ``world/gaussians/<variant>``: each fitted variant's Gaussians at the frame (class colours);
  ``world/rigidity/<variant>``: the same coloured by the learned rigidity mask m;
- ``world/cameras/<camera>``: the six cameras, their images and pseudo labels;
- ``bev/<row>``: bird's-eye views of the ground truth and the pictured variants.

The ``frame`` timeline counts the clip's frame offsets (0 = the reference frame).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from torch import Tensor

from dego.data.synthetic import CAMERAS
from dego.demo.clip import DemoClip
from dego.demo.fit import FitResult, gaussians_at, rigidity_mask
from dego.viz import rerun as rerun_log

GROUND_TRUTH = "ground truth"


def entity_name(row: str) -> str:
    """A table row's name as one entity path part (``"free offsets"`` -> ``"free-offsets"``)."""
    return re.sub(r"[^a-z0-9_]+", "-", row.lower()).strip("-")


@torch.no_grad()
def record_demo(
    path: Path,
    clip: DemoClip,
    labels: Mapping[str, Tensor],
    results: Sequence[FitResult],
    *,
    row_names: Mapping[str, str],
    pictured: Sequence[str],
    learns_mask: Sequence[str],
) -> Path:
    """Write the demo's recording to ``path`` atomically and return it.

    Args:
        labels: table row -> ``(T, X, Y, Z)`` predicted labels at every frame.
        results: the fitted variants.
        row_names: variant -> its table row.
        pictured: the variants whose BEV is shown beside the ground truth's.
        learns_mask: the variants whose rigidity mask is learned (logged as colours).
    """
    rows = {GROUND_TRUTH: clip.occupancy, **labels}
    camera_names = [name for name, *_ in CAMERAS]
    bev = [GROUND_TRUTH, *(row_names[v] for v in pictured if row_names.get(v) in labels)]
    tabs: dict[str, list[str]] = {}
    for row in rows:
        tabs[row] = [f"+ /world/ego/occupancy/{entity_name(row)}", "+ /world/cameras/**"]
        tabs[row] += [
            f"+ /world/gaussians/{r.variant}" for r in results if row_names[r.variant] == row
        ]
    for variant in learns_mask:
        tabs[f"{row_names[variant]}: mask m"] = [f"+ /world/rigidity/{variant}"]
    layout = rerun_log.blueprint(
        tabs=tabs,
        bev=[f"bev/{entity_name(row)}" for row in bev],
        cameras=[f"world/cameras/{name}" for name in camera_names],
    )
    masks = {r.variant: rigidity_mask(r) for r in results if r.variant in learns_mask}
    with rerun_log.recording_file(path, application_id="dego demo", blueprint=layout) as rec:
        for index in range(clip.num_frames):
            frame = int(clip.times[index])
            rerun_log.log_pose("world/ego", clip.ego_poses[index], frame=frame, recording=rec)
            for row, grids in rows.items():
                rerun_log.log_occupancy(
                    f"world/ego/occupancy/{entity_name(row)}",
                    grids[index],
                    clip.grid,
                    mask=clip.mask_camera[index],
                    recording=rec,
                )
                if row in bev:
                    rerun_log.log_bev(
                        f"bev/{entity_name(row)}",
                        grids[index],
                        mask=clip.mask_camera[index],
                        recording=rec,
                    )
            for result in results:
                gaussians, _ = gaussians_at(result.model, result.deformation, clip, index)
                rerun_log.log_gaussians(
                    f"world/gaussians/{result.variant}", gaussians, recording=rec
                )
                if result.variant in masks:
                    rerun_log.log_gaussians(
                        f"world/rigidity/{result.variant}",
                        gaussians,
                        colors=rerun_log.mask_colors(masks[result.variant]),
                        recording=rec,
                    )
            rerun_log.log_cameras(
                "world/cameras",
                clip.world_to_cam[index],
                clip.intrinsics[index],
                clip.image_size,
                names=camera_names,
                images=clip.images[index],
                semantics=clip.semantics[index],
                recording=rec,
            )
    return path
