"""Optional dispatch to gsplat's CUDA rasteriser (``pip install dego[gsplat]``).

gsplat compiles its compositing constants (max alpha 0.999, alpha threshold 1/255,
transmittance threshold 1e-4) and its radius rule into the kernels, so it is only used
when the requested settings equal those; ``backend="auto"`` silently keeps the torch
path otherwise, ``backend="gsplat"`` raises.
"""

from __future__ import annotations

import importlib.util
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from dego.gaussians import GaussianSet

if TYPE_CHECKING:
    from dego.splatting.splatter import SplatConfig, SplatOutput

_GSPLAT_CONSTANTS = {
    "max_alpha": 0.999,
    "alpha_min": 1 / 255,
    "transmittance_min": 1e-4,
    "radius_sigma": 3.0,
}


def usable(gaussians: GaussianSet, config: SplatConfig, *, strict: bool) -> bool:
    """Whether gsplat can render this call; with ``strict`` a reason is raised instead of False."""
    reasons = []
    if importlib.util.find_spec("gsplat") is None:
        reasons.append("gsplat is not installed (pip install dego[gsplat])")
    if gaussians.device.type != "cuda":
        reasons.append(f"gsplat needs CUDA tensors, got {gaussians.device}")
    for name, value in _GSPLAT_CONSTANTS.items():
        if getattr(config, name) != value:
            reasons.append(f"{name}={getattr(config, name)} differs from gsplat's fixed {value}")
    if reasons and strict:
        raise ValueError("backend: cannot use 'gsplat': " + "; ".join(reasons))
    return not reasons


def render(
    gaussians: GaussianSet,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    image_size: tuple[int, int],
    features: Tensor | None,
    background: Tensor | None,
    config: SplatConfig,
) -> SplatOutput:
    """Render with ``gsplat.rasterization`` and convert to :class:`SplatOutput` layout."""
    from gsplat import rasterization

    from dego.splatting.splatter import SplatOutput

    b, n = gaussians.batch_shape[0], gaussians.num_gaussians
    v = world_to_cam.shape[1]
    height, width = image_size
    channels = 0 if features is None else features.shape[-1]
    depth_mode = {"expected": "ED", "accumulated": "D", "none": ""}[config.depth_mode]
    colors = (
        features
        if channels
        else torch.zeros(b, n, 1, dtype=gaussians.dtype, device=gaussians.device)
    )
    mode = ("RGB+" + depth_mode) if depth_mode else "RGB"
    backgrounds = None
    if background is not None and channels:
        backgrounds = background.expand(b, v, channels)
        if depth_mode:
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(b, v, 1)], -1)
    images, alphas, meta = rasterization(
        gaussians.means,
        gaussians.quats,
        gaussians.scales,
        gaussians.opacities,
        colors,
        world_to_cam,
        intrinsics,
        width,
        height,
        near_plane=config.near,
        far_plane=config.far,
        eps2d=config.eps2d,
        tile_size=config.tile_size,
        backgrounds=backgrounds,
        render_mode=mode,
        packed=False,
    )
    images = images.permute(0, 1, 4, 2, 3)  # (B, V, D, H, W)
    radii = meta["radii"]
    if radii.ndim == 4:  # gsplat >= 1.5 returns per-axis radii
        radii = radii.amax(-1)
    return SplatOutput(
        features=images[:, :, :channels],
        depth=images[:, :, -1] if depth_mode else None,
        alpha=alphas[..., 0],
        radii=radii.to(torch.int32),
    )
