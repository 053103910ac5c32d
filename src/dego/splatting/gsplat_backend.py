"""Optional dispatch to gsplat's CUDA rasteriser (``pip install -e ".[gsplat]"``).

gsplat compiles its compositing constants (max alpha, alpha threshold 1/255,
transmittance threshold 1e-4) and its radius rule into the kernels, so it is only used
when the requested settings equal those of the installed release (:func:`constants_of`):
max alpha is 0.999 in gsplat 1.4 and 1.5 and 0.99 from 1.6; gsplat 1.4.x uses the
``"gsplat<=1.4"`` radius rule and unbatched inputs (rendered one batch item at a time),
gsplat >= 1.5 the ``"gsplat>=1.5"`` rule and batched inputs. ``backend="auto"`` silently
keeps the torch path otherwise, ``backend="gsplat"`` raises with the reasons.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
from typing import Any

import torch
from torch import Tensor

from dego.gaussians import GaussianSet
from dego.splatting.projection import RADIUS_SIGMA, Projection
from dego.splatting.types import SplatConfig, SplatOutput

# Every gsplat version fact dego relies on, keyed by release (major, minor).
MIN_VERSION = (1, 4)
"""The oldest release the backend and the adapters support."""
RULE_CHANGE = (1, 5)
"""The release from which gsplat uses per-axis, opacity-aware radii (``"gsplat>=1.5"``;
one radius per Gaussian, ``"gsplat<=1.4"``, before) and returns ``meta["radii"]`` per axis."""
BATCHED_FROM = (1, 5)
"""The release from which ``rasterization`` takes batched inputs (1.4: one scene a call)."""
MAX_ALPHA_CHANGE = (1, 6)
"""The release from which gsplat caps alpha at 0.99 (0.999 before; its commit c5ff586b)."""


def constants_of(version: tuple[int, int]) -> dict[str, float]:
    """The compositing constants a gsplat release compiles in, under SplatConfig's names."""
    return {
        "max_alpha": 0.99 if version >= MAX_ALPHA_CHANGE else 0.999,
        "alpha_min": 1 / 255,
        "transmittance_min": 1e-4,
    }


def batched(version: tuple[int, int]) -> bool:
    """Whether a gsplat release's ``rasterization`` takes batched ``[B, ...]`` inputs."""
    return version >= BATCHED_FROM


def release_options(version: tuple[int, int]) -> dict[str, Any]:
    """The SplatConfig fields a gsplat release fixes: its radius rule and compositing constants."""
    return {"radius_rule": rule_of(version), **constants_of(version)}


def installed_version() -> tuple[int, int] | None:
    """``(major, minor)`` of the installed gsplat, or ``None`` when it is not installed."""
    if importlib.util.find_spec("gsplat") is None:
        return None
    try:
        text = importlib.metadata.version("gsplat")
    except importlib.metadata.PackageNotFoundError:
        import gsplat

        text = getattr(gsplat, "__version__", "0.0")
    parts = [*text.split("+")[0].split("."), "0"][:2]
    try:
        return int(parts[0]), int("".join(ch for ch in parts[1] if ch.isdigit()) or 0)
    except ValueError:
        return (0, 0)


def rule_of(version: tuple[int, int]) -> str:
    """The radius rule that a gsplat release compiles in."""
    return "gsplat>=1.5" if version >= RULE_CHANGE else "gsplat<=1.4"


def usable(gaussians: GaussianSet, config: SplatConfig, *, strict: bool) -> bool:
    """Whether gsplat can render this call; with ``strict`` a reason is raised instead of False."""
    reasons = []
    version = installed_version()
    if version is None:
        reasons.append("gsplat is not installed (pip install -e '.[gsplat]' in your dego clone)")
    elif version < MIN_VERSION:
        reasons.append(
            f"gsplat {version[0]}.{version[1]} is older than {MIN_VERSION[0]}.{MIN_VERSION[1]} "
            "(pip install -U gsplat)"
        )
    else:
        rule = rule_of(version)
        if config.radius_rule not in (None, rule):
            reasons.append(
                f"radius_rule={config.radius_rule!r} differs from the installed gsplat "
                f"{version[0]}.{version[1]}'s {rule!r}"
            )
        if config.radius_sigma not in (None, RADIUS_SIGMA[rule]):
            reasons.append(
                f"radius_sigma={config.radius_sigma} differs from gsplat's fixed "
                f"{RADIUS_SIGMA[rule]}"
            )
        if not batched(version) and config.absgrad and gaussians.batch_shape[0] > 1:
            reasons.append("absgrad with gsplat 1.4 needs a batch of one (1.4 is unbatched)")
        for name, value in constants_of(version).items():
            if getattr(config, name) != value:
                reasons.append(
                    f"{name}={getattr(config, name)} differs from the installed gsplat "
                    f"{version[0]}.{version[1]}'s fixed {value}"
                )
    if gaussians.device.type != "cuda":
        reasons.append(f"gsplat needs CUDA tensors, got {gaussians.device}")
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

    b, n = gaussians.batch_shape[0], gaussians.num_gaussians
    v = world_to_cam.shape[1]
    height, width = image_size
    channels = 0 if features is None else features.shape[-1]
    depth_mode = {"expected": "ED", "accumulated": "D", "none": ""}[config.depth_mode]
    colors = (
        features
        if features is not None and channels
        else torch.zeros(b, n, 1, dtype=gaussians.dtype, device=gaussians.device)
    )
    mode = ("RGB+" + depth_mode) if depth_mode else "RGB"
    backgrounds = None
    if background is not None and channels:
        backgrounds = background.expand(b, v, channels)
        if depth_mode:
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(b, v, 1)], -1)
    options: dict[str, Any] = {
        "near_plane": config.near,
        "far_plane": config.far,
        "eps2d": config.eps2d,
        "tile_size": config.tile_size,
        "render_mode": mode,
        "packed": False,
        "radius_clip": config.radius_clip,
        "rasterize_mode": config.rasterize_mode,
        "absgrad": config.absgrad,
    }
    tensors = (gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities)
    version = installed_version()
    if version is not None and batched(version):
        images, alphas, meta = rasterization(
            *tensors,
            colors,
            world_to_cam,
            intrinsics,
            width,
            height,
            backgrounds=backgrounds,
            **options,
        )
        metas = [meta]
    else:  # gsplat 1.4 takes one scene (means [N, 3], viewmats [C, 4, 4]) per call
        calls = [
            rasterization(
                *(t[i] for t in tensors),
                colors[i],
                world_to_cam[i],
                intrinsics[i],
                width,
                height,
                backgrounds=None if backgrounds is None else backgrounds[i],
                **options,
            )
            for i in range(b)
        ]
        images = torch.stack([c[0] for c in calls])
        alphas = torch.stack([c[1] for c in calls])
        metas = [c[2] for c in calls]
    projection = _projection(metas, gaussians.opacities, b, v, n)
    images = images.permute(0, 1, 4, 2, 3)  # (B, V, D, H, W)
    return SplatOutput(
        features=images[:, :, :channels],
        depth=images[:, :, -1] if depth_mode else None,
        alpha=alphas[..., 0],
        radii=projection.radii,
        projection=projection,
    )


def _projection(
    metas: list[dict[str, Any]], opacities: Tensor, b: int, v: int, n: int
) -> Projection:
    """dego's :class:`Projection` from gsplat's dense ``meta`` (one per call)."""

    def gather(key: str) -> Tensor:
        # gsplat >= 1.5: one batched meta (B, V, N, ...); 1.4: one (V, N, ...) per item
        if len(metas) == 1 and metas[0][key].ndim >= 3 and metas[0][key].shape[:2] == (b, v):
            return metas[0][key]
        return torch.stack([m[key] for m in metas])

    radii = gather("radii").to(torch.int32)
    radii_xy = radii if radii.ndim == 4 else radii.unsqueeze(-1).expand(b, v, n, 2)
    conics = gather("conics")
    a, bb, c = conics.unbind(-1)
    det = (a * c - bb * bb).clamp_min(1e-30)
    variances2d = torch.stack([c / det, a / det], -1).detach()
    effective = gather("opacities") if "opacities" in metas[0] else None
    if effective is None:
        effective = opacities.unsqueeze(1).expand(b, v, n)
    return Projection(
        means2d=gather("means2d"),
        conics=conics,
        variances2d=variances2d,
        depths=gather("depths"),
        radii=radii_xy.amax(-1),
        visible=radii_xy.amax(-1) > 0,
        radii_xy=radii_xy,
        opacities=effective.reshape(b, v, n),
    )
