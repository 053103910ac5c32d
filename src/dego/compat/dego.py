"""The official DeGO code's layouts, computed by dego's core.

- :func:`render_temporal`: the training renders of every time step and camera in one call,
  laid out as the official rasteriser loop returns them, ``[B, T*V, H, W, X]``.
- :func:`occupancy_to_labels`: the official test-time post-processing of a voxelised grid
  (density floor, roof cut, free-space overlay), the labels its evaluation scores.

Official checkpoints of the deformation network load with
:meth:`dego.DecoupledDeformation.from_official_state_dict`.
"""

from __future__ import annotations

import math

from jaxtyping import Float, Int
from torch import Tensor

from dego._typing import typechecked
from dego.classes import FREE_LABEL
from dego.compat.gsplat import DEPTH_MODES, RenderMode, options_of_release
from dego.gaussians import GaussianSet
from dego.splatting import pipeline
from dego.splatting.types import ImageSize, SplatConfig
from dego.voxelizer import VoxelOutput

OFFICIAL_THRESHOLD = 0.05
"""Density below which a voxel is free (``eval_threshold_range=[.05]``)."""
OFFICIAL_MIN_DENSITY = 1e-3
"""Density below which the official post-processing zeroes a voxel first."""
OFFICIAL_MAX_Z_INDEX = 11
"""Voxels with z index >= 11 (z >= 3.4 m on the Occ3D grid) are free: the "roof" cut."""


@typechecked
def render_temporal(
    gaussians: GaussianSet,
    world_to_cam: Float[Tensor, "B T V 4 4"],
    intrinsics: Float[Tensor, "B T V 3 3"],
    image_size: ImageSize,
    *,
    features: Float[Tensor, "B N C"] | Float[Tensor, "B T N C"] | None = None,
    mode: RenderMode = "RGB+D",
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    gsplat_version: str = "1.4.0",
) -> Float[Tensor, "B TV H W X"]:
    """Render ``(B, T)`` Gaussians into each time step's ``V`` cameras, in one call.

    The official training loop renders every batch item and time step with its own gsplat
    call and concatenates the time steps' cameras; this is one :func:`dego.splat` over the
    flattened ``(B, T)`` batch, in the same layout and under the same rules (gsplat 1.4.0's
    radii, classic mode, no background).

    Args:
        gaussians: batch shape ``(B, T)``, e.g. ``DeformationOutput.gaussians`` or
            ``DeformationOutput.with_canonical(canonical).gaussians`` (the official 9 frames:
            8 deformed, the canonical set last).
        world_to_cam: ``(B, T, V, 4, 4)`` world (current ego) to camera of time step t.
        intrinsics: ``(B, T, V, 3, 3)`` pinhole intrinsics of the rendered images.
        image_size: ``(H, W)``, e.g. ``(256, 704)``.
        features: ``(B, N, C)`` shared by every time step (the official code copies the
            semantic logits unchanged), ``(B, T, N, C)`` per step, or ``None``: the
            Gaussians' own ``features`` (required unless ``mode`` is ``"D"`` / ``"ED"``).
        mode: gsplat's ``render_mode``: ``"RGB"``, ``"D"`` (accumulated depth),
            ``"ED"`` (expected depth), ``"RGB+D"`` (the official semantic render) or
            ``"RGB+ED"``; the depth is the last channel.
        near_plane: cull Gaussians whose camera z is below this.
        far_plane: cull Gaussians whose camera z is above this.
        eps2d: screen-space dilation of the 2D covariance (pixels^2).
        gsplat_version: the gsplat release whose radius rule and max alpha to follow (DeGO
            pins 1.4.0).

    Returns:
        ``[B, T*V, H, W, X]`` channels-last, time-major (index ``t * V + v``), ``X = C``,
        ``C + 1`` or 1 as gsplat's ``render_colors``.
    """
    if len(gaussians.batch_shape) != 2:
        raise ValueError(
            f"gaussians: expected batch shape (B, T), got {tuple(gaussians.batch_shape)}; "
            "a canonical (B,) set renders with dego.splat"
        )
    b, t = gaussians.batch_shape
    v = world_to_cam.shape[2]
    for name, cameras in [("world_to_cam", world_to_cam), ("intrinsics", intrinsics)]:
        if cameras.shape[:3] != (b, t, v):
            raise ValueError(
                f"{name}: expected (B, T, V) = ({b}, {t}, {v}) leading axes to match "
                f"gaussians and world_to_cam, got {tuple(cameras.shape[:3])}"
            )
    if mode not in DEPTH_MODES:
        raise ValueError(f"mode: expected one of {list(DEPTH_MODES)}, got {mode!r}")
    with_features = mode.startswith("RGB")
    if features is None and with_features:
        features = gaussians.features
        if features is None:
            raise ValueError(
                f"features: mode {mode!r} renders features, but none were given and the "
                "Gaussians carry none"
            )
    n = gaussians.num_gaussians
    flat = gaussians.reshape_batch(b * t)
    flat_features = None
    if with_features:
        assert features is not None
        if features.ndim == 4 and features.shape[:3] == (b, t, n):
            flat_features = features.reshape(b * t, n, -1)
        elif features.ndim == 3 and features.shape[:2] == (b, n):
            flat_features = features.repeat_interleave(t, dim=0)
        else:
            raise ValueError(
                f"features: expected (B, N, C) = ({b}, {n}, C) or (B, T, N, C) = "
                f"({b}, {t}, {n}, C), got {tuple(features.shape)}"
            )
    config = SplatConfig(
        near=near_plane,
        far=far_plane,
        eps2d=eps2d,
        depth_mode=DEPTH_MODES[mode],  # type: ignore[arg-type]
        **options_of_release(gsplat_version),
    )
    image = pipeline.render(
        flat,
        world_to_cam.reshape(b * t, v, 4, 4),
        intrinsics.reshape(b * t, v, 3, 3),
        image_size,
        flat_features,
        None,
        config,
        layout="channels_last",
    ).image
    return image.contiguous().reshape(b, t * v, *image.shape[2:])


@typechecked
def occupancy_to_labels(
    density: Float[Tensor, "*B X Y Z"],
    semantics: Float[Tensor, "*B X Y Z C"],
    *,
    threshold: float = OFFICIAL_THRESHOLD,
    min_density: float | None = OFFICIAL_MIN_DENSITY,
    max_z_index: int | None = OFFICIAL_MAX_Z_INDEX,
    free_label: int = FREE_LABEL,
    label_offset: int = 1,
) -> Int[Tensor, "*B X Y Z"]:
    """The official post-processing: voxelised density and semantics -> label grid.

    ``label = argmax(semantics) + label_offset``, then the free-space overlay: density
    below ``min_density`` is zeroed, voxels with density < ``threshold`` or z index >=
    ``max_z_index`` get ``free_label``. The result is what the official evaluation scores,
    ready for ``OccupancyMetrics("weak").update(labels, gt, mask)``. Without the overlay
    every voxel carries a class and geometric IoU collapses.

    Args:
        density: ``(..., X, Y, Z)`` occupancy, e.g. ``VoxelOutput.density``.
        semantics: ``(..., X, Y, Z, C)`` per-class scores (``VoxelOutput.features``; the
            official C = 16 logits of the labels 1..16).
        threshold: free below it (official 0.05).
        min_density: zero density below it first (official 1e-3; ``None`` skips).
        max_z_index: voxels with z index >= it are free (official 11; ``None`` skips).
        free_label: the free label (Occ3D 17).
        label_offset: the label of channel 0 (official 1: channel c is class c + 1).

    Returns:
        int64 labels, the shape of ``density``.
    """
    channels = semantics.shape[-1]
    if channels == 0:
        raise ValueError("semantics: expected at least one class channel, got C = 0")
    top = label_offset + channels - 1
    if label_offset <= free_label <= top:
        raise ValueError(
            f"semantics: {channels} channels with label_offset={label_offset} give labels "
            f"{label_offset}..{top}, which include free_label={free_label}; pass the scores "
            "of the occupied classes only (the official C = 16 logits for labels 1..16)"
        )
    if not (isinstance(threshold, int | float) and math.isfinite(threshold)):
        raise ValueError(f"threshold: expected a finite number, got {threshold!r}")
    if min_density is not None and not (
        isinstance(min_density, int | float) and math.isfinite(min_density)
    ):
        raise ValueError(f"min_density: expected a finite number or None, got {min_density!r}")
    if max_z_index is not None and (isinstance(max_z_index, bool) or max_z_index < 0):
        raise ValueError(f"max_z_index: expected an int >= 0 or None, got {max_z_index!r}")
    lead = density.shape[:-3]
    grid = density.shape[-3:]
    voxels = VoxelOutput(
        density=density.reshape(-1, *grid), features=semantics.reshape(-1, *grid, channels)
    )
    labels = voxels.labels(
        threshold=threshold,
        free_label=free_label,
        label_offset=label_offset,
        min_density=min_density,
        max_z_index=max_z_index,
    )
    return labels.reshape(*lead, *grid)


__all__ = [
    "OFFICIAL_MAX_Z_INDEX",
    "OFFICIAL_MIN_DENSITY",
    "OFFICIAL_THRESHOLD",
    "occupancy_to_labels",
    "render_temporal",
]
