"""``splat`` and ``DifferentiableSplatter``: Gaussians -> feature, depth and alpha images."""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import torch
from jaxtyping import Float, Int
from torch import Tensor, nn

from dego._typing import typechecked
from dego.gaussians import GaussianSet
from dego.splatting.composite import CompositeRules, composite_tiles
from dego.splatting.projection import project_gaussians
from dego.splatting.tiles import build_tile_lists, contributing_extents

DepthMode = Literal["expected", "accumulated", "none"]
Backend = Literal["torch", "auto", "gsplat"]


@dataclasses.dataclass(frozen=True)
class SplatOutput:
    """Rendered images, channels first.

    Attributes:
        features: ``(B, V, C, H, W)`` composited features plus ``T_final * background``.
        depth: ``(B, V, H, W)`` camera z of the means, ``expected`` (normalised by alpha)
            or ``accumulated``; ``None`` with ``depth_mode="none"``.
        alpha: ``(B, V, H, W)`` accumulated opacity ``1 - T_final``.
        radii: ``(B, V, N)`` int32 screen radius of each Gaussian, 0 where culled.
    """

    features: Float[Tensor, "B V C H W"]
    depth: Float[Tensor, "B V H W"] | None
    alpha: Float[Tensor, "B V H W"]
    radii: Int[Tensor, "B V N"]


@dataclasses.dataclass(frozen=True)
class SplatConfig:
    """Rendering settings shared by :func:`splat` and :class:`DifferentiableSplatter`."""

    near: float = 0.01
    far: float = 1e10
    eps2d: float = 0.3
    max_alpha: float = 0.999
    alpha_min: float = 1 / 255
    transmittance_min: float = 1e-4
    radius_sigma: float = 3.0
    tile_size: int = 16
    depth_mode: DepthMode = "expected"
    backend: Backend = "torch"
    chunk_size: int = 32
    max_pairs: int = 1 << 22

    def __post_init__(self) -> None:
        checks = [
            ("near", self.near >= 0, ">= 0"),
            ("far", self.far > self.near, f"> near ({self.near})"),
            ("eps2d", self.eps2d >= 0, ">= 0"),
            ("max_alpha", 0 < self.max_alpha <= 1, "in (0, 1]"),
            ("alpha_min", 0 <= self.alpha_min < 1, "in [0, 1)"),
            ("transmittance_min", 0 <= self.transmittance_min < 1, "in [0, 1)"),
            ("radius_sigma", self.radius_sigma > 0, "> 0"),
            ("tile_size", isinstance(self.tile_size, int) and self.tile_size > 0, "a positive int"),
            (
                "chunk_size",
                isinstance(self.chunk_size, int) and self.chunk_size > 0,
                "a positive int",
            ),
            ("max_pairs", isinstance(self.max_pairs, int) and self.max_pairs > 0, "a positive int"),
            (
                "depth_mode",
                self.depth_mode in ("expected", "accumulated", "none"),
                "'expected', 'accumulated' or 'none'",
            ),
            ("backend", self.backend in ("torch", "auto", "gsplat"), "'torch', 'auto' or 'gsplat'"),
        ]
        for name, ok, expected in checks:
            if not ok:
                raise ValueError(f"{name}: expected {expected}, got {getattr(self, name)!r}")
        for name in ("near", "far", "eps2d", "radius_sigma"):
            if math.isnan(getattr(self, name)):
                raise ValueError(f"{name}: must not be NaN")


def _check_inputs(
    gaussians: GaussianSet,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    image_size: tuple[int, int],
    features: Tensor | None,
    background: Tensor | None,
) -> None:
    if len(gaussians.batch_shape) != 1:
        raise ValueError(
            f"gaussians: expected batch shape (B,), got {tuple(gaussians.batch_shape)}; "
            "flatten extra axes with GaussianSet.flatten_batch()"
        )
    b = gaussians.batch_shape[0]
    if world_to_cam.shape[0] != b:
        raise ValueError(f"world_to_cam: batch {world_to_cam.shape[0]} != gaussians' batch {b}")
    for name, t in (("world_to_cam", world_to_cam), ("intrinsics", intrinsics)):
        if t.dtype != gaussians.dtype or t.device != gaussians.device:
            raise TypeError(
                f"{name}: {t.dtype} on {t.device}, expected the gaussians' "
                f"{gaussians.dtype} on {gaussians.device}"
            )
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"{name}: contains non-finite values")
    if len(image_size) != 2 or any(
        not isinstance(s, int) or isinstance(s, bool) or s <= 0 for s in image_size
    ):
        raise ValueError(f"image_size: expected (H, W) positive ints, got {image_size!r}")
    if bool((intrinsics[..., 0, 0] <= 0).any() | (intrinsics[..., 1, 1] <= 0).any()):
        raise ValueError("intrinsics: focal lengths fx, fy must be positive")
    if features is not None and features.shape[:2] != (b, gaussians.num_gaussians):
        raise ValueError(
            f"features: expected shape (B, N, C) = ({b}, {gaussians.num_gaussians}, C), "
            f"got {tuple(features.shape)}"
        )
    channels = 0 if features is None else features.shape[-1]
    if background is not None and background.shape not in (
        (channels,),
        (b, world_to_cam.shape[1], channels),
    ):
        raise ValueError(
            f"background: expected shape ({channels},) or (B, V, {channels}), "
            f"got {tuple(background.shape)}"
        )


@typechecked
def splat(
    gaussians: GaussianSet,
    world_to_cam: Float[Tensor, "B V 4 4"],
    intrinsics: Float[Tensor, "B V 3 3"],
    image_size: tuple[int, int],
    *,
    features: Float[Tensor, "B N C"] | None = None,
    background: Float[Tensor, " C"] | Float[Tensor, "B V C"] | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    max_alpha: float = 0.999,
    alpha_min: float = 1 / 255,
    transmittance_min: float = 1e-4,
    radius_sigma: float = 3.0,
    tile_size: int = 16,
    depth_mode: DepthMode = "expected",
    backend: Backend = "torch",
    chunk_size: int = 32,
    max_pairs: int = 1 << 22,
) -> SplatOutput:
    """Render ``(B, N)`` Gaussians into ``(B, V)`` pinhole cameras, differentiably.

    Args:
        gaussians: batch shape ``(B,)``.
        world_to_cam: ``(B, V, 4, 4)`` extrinsics, OpenCV axes (x right, y down, z forward).
        intrinsics: ``(B, V, 3, 3)`` pinhole ``K``; pixel ``(u, v)`` is centred at ``(u+.5, v+.5)``.
        image_size: ``(H, W)``.
        features: ``(B, N, C)`` per-Gaussian features; defaults to ``gaussians.features``
            (none at all: C = 0, only depth and alpha are rendered).
        background: ``(C,)`` or ``(B, V, C)``, added as ``T_final * background`` (default 0).
        near: cull Gaussians whose camera z is below ``near``.
        far: cull Gaussians whose camera z is above ``far``.
        eps2d: screen-space dilation added to the 2D covariance (pixels^2).
        max_alpha: per-Gaussian alpha cap: alpha = min(max_alpha, o exp(-sigma)).
        alpha_min: a Gaussian with alpha < alpha_min (or sigma < 0) is skipped at a pixel.
        transmittance_min: a pixel stops before the Gaussian that would take its
            transmittance to transmittance_min or below.
        radius_sigma: screen radius ``ceil(radius_sigma * sqrt(lambda_max))`` that decides
            which tiles a Gaussian touches.
        tile_size: tile edge in pixels.
        depth_mode: ``"expected"`` sum(w z) / max(alpha, 1e-10), ``"accumulated"`` sum(w z),
            or ``"none"``; z is the camera z of the Gaussian's mean.
        backend: ``"torch"`` (this implementation, any device), ``"gsplat"`` (gsplat's CUDA
            rasteriser, needs ``pip install dego[gsplat]`` and CUDA tensors) or ``"auto"``
            (gsplat when it is usable and the settings match its compiled constants).
        chunk_size: Gaussians composited per tile per step.
        max_pairs: bound on (Gaussian, pixel) pairs held at once; the compositing peak is
            about ``max_pairs * itemsize * 15`` bytes (backward), whatever N is. Smaller
            values use less memory and more, smaller steps.

    Differentiable w.r.t. the Gaussians' means, quats, scales and opacities, the features
    and the background (not the cameras' intrinsics).
    """
    config = SplatConfig(
        near,
        far,
        eps2d,
        max_alpha,
        alpha_min,
        transmittance_min,
        radius_sigma,
        tile_size,
        depth_mode,
        backend,
        chunk_size,
        max_pairs,
    )
    return _render(gaussians, world_to_cam, intrinsics, image_size, features, background, config)


def _render(
    gaussians: GaussianSet,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    image_size: tuple[int, int],
    features: Tensor | None,
    background: Tensor | None,
    config: SplatConfig,
) -> SplatOutput:
    features = gaussians.features if features is None else features
    _check_inputs(gaussians, world_to_cam, intrinsics, tuple(image_size), features, background)
    if config.backend != "torch":
        from dego.splatting import gsplat_backend

        if gsplat_backend.usable(gaussians, config, strict=config.backend == "gsplat"):
            return gsplat_backend.render(
                gaussians, world_to_cam, intrinsics, image_size, features, background, config
            )
    b, n = gaussians.batch_shape[0], gaussians.num_gaussians
    v = world_to_cam.shape[1]
    height, width = image_size
    channels = 0 if features is None else features.shape[-1]

    proj = project_gaussians(
        gaussians.means,
        gaussians.quats,
        gaussians.scales,
        world_to_cam,
        intrinsics,
        image_size,
        near=config.near,
        far=config.far,
        eps2d=config.eps2d,
        radius_sigma=config.radius_sigma,
    )
    columns = []
    if channels:
        columns.append(features.unsqueeze(1).expand(b, v, n, channels))
    if config.depth_mode != "none":
        columns.append(proj.depths.unsqueeze(-1))
    dtype, device = gaussians.dtype, gaussians.device
    colors = (
        torch.cat(columns, -1) if columns else torch.zeros(b, v, n, 0, dtype=dtype, device=device)
    )

    opacities = gaussians.opacities.unsqueeze(1).expand(b, v, n)
    extents, max_sigma = contributing_extents(
        proj.variances2d, proj.radii, opacities, config.alpha_min
    )
    lists = build_tile_lists(
        proj.means2d.flatten(0, 1),
        extents.flatten(0, 1),
        proj.depths.flatten(0, 1),
        image_size,
        config.tile_size,
        conics=proj.conics.flatten(0, 1),
        max_sigma=max_sigma.flatten(0, 1),
    )
    tiles, transmittance = composite_tiles(
        lists,
        proj.means2d.reshape(-1, 2),
        proj.conics.reshape(-1, 3),
        opacities.reshape(-1),
        colors.reshape(b * v * n, colors.shape[-1]),
        tile_size=config.tile_size,
        rules=CompositeRules(config.max_alpha, config.alpha_min, config.transmittance_min),
        chunk_size=config.chunk_size,
        max_pairs=config.max_pairs,
    )
    ts, tx, ty = config.tile_size, lists.tiles_x, lists.tiles_y
    # (B*V*ty*tx, S, S, D) -> (B, V, D, ty*S, tx*S), cropped to (H, W)
    d = tiles.shape[-1]
    image = tiles.view(b, v, ty, tx, ts, ts, d).permute(0, 1, 6, 2, 4, 3, 5)
    image = image.reshape(b, v, d, ty * ts, tx * ts)[..., :height, :width]
    final_t = transmittance.view(b, v, ty, tx, ts, ts).permute(0, 1, 2, 4, 3, 5)
    final_t = final_t.reshape(b, v, ty * ts, tx * ts)[..., :height, :width]
    alpha = 1 - final_t

    rendered = image[:, :, :channels]
    if background is not None:
        bg = background if background.ndim == 3 else background.expand(b, v, channels)
        rendered = rendered + final_t.unsqueeze(2) * bg[..., None, None]
    depth = None
    if config.depth_mode != "none":
        depth = image[:, :, channels]
        if config.depth_mode == "expected":
            depth = depth / alpha.clamp_min(1e-10)
    return SplatOutput(features=rendered, depth=depth, alpha=alpha, radii=proj.radii)


class DifferentiableSplatter(nn.Module):
    """Module form of :func:`splat`: holds the rendering settings (see :func:`splat` for
    their meaning); ``forward`` takes the per-call tensors."""

    def __init__(self, **config: object) -> None:
        super().__init__()
        self.config = SplatConfig(**config)  # type: ignore[arg-type]

    @typechecked
    def forward(
        self,
        gaussians: GaussianSet,
        world_to_cam: Float[Tensor, "B V 4 4"],
        intrinsics: Float[Tensor, "B V 3 3"],
        image_size: tuple[int, int],
        features: Float[Tensor, "B N C"] | None = None,
        background: Float[Tensor, " C"] | Float[Tensor, "B V C"] | None = None,
    ) -> SplatOutput:
        return _render(
            gaussians, world_to_cam, intrinsics, image_size, features, background, self.config
        )

    def extra_repr(self) -> str:
        return ", ".join(
            f"{f.name}={getattr(self.config, f.name)!r}" for f in dataclasses.fields(self.config)
        )


__all__ = ["DifferentiableSplatter", "SplatConfig", "SplatOutput", "splat"]
