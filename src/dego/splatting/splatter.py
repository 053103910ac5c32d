"""``splat`` and ``DifferentiableSplatter``: Gaussians -> feature, depth and alpha images.

The options live in :class:`~dego.splatting.types.SplatConfig` (defaults and validation,
once); the checks in :mod:`dego.splatting.inputs`, the render in
:mod:`dego.splatting.pipeline`, the output layouts in :mod:`dego.splatting.layouts`.
``SplatOutput``, ``SplatConfig`` and the option aliases stay importable from here.
"""

from __future__ import annotations

import dataclasses

from jaxtyping import Float
from torch import Tensor, nn

try:
    from typing import Unpack
except ImportError:  # Python 3.10: typing_extensions, a dependency of torch
    from typing_extensions import Unpack

from dego._options import build_config, config_from
from dego._policy import float32_under_autocast
from dego._typing import typechecked
from dego.gaussians import GaussianSet
from dego.splatting import pipeline
from dego.splatting.inputs import GSPLAT_KEYWORDS, check_call
from dego.splatting.projection import RadiusRule, RasterizeMode
from dego.splatting.types import (
    Backend,
    DepthMode,
    ImageSize,
    SplatConfig,
    SplatOptions,
    SplatOutput,
)


@float32_under_autocast()
@check_call("splat", cameras_at=1, options=True)
@typechecked
def splat(
    gaussians: GaussianSet,
    world_to_cam: Float[Tensor, "B V 4 4"],
    intrinsics: Float[Tensor, "B V 3 3"],
    image_size: ImageSize,
    *,
    features: Float[Tensor, "B N C"] | Float[Tensor, "B V N C"] | None = None,
    background: Float[Tensor, " C"] | Float[Tensor, "B V C"] | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    max_alpha: float = 0.999,
    alpha_min: float = 1 / 255,
    transmittance_min: float = 1e-4,
    radius_sigma: float | None = None,
    tile_size: int = 16,
    depth_mode: DepthMode = "expected",
    backend: Backend = "torch",
    chunk_size: int = 32,
    max_pairs: int = 1 << 22,
    radius_clip: float = 0.0,
    rasterize_mode: RasterizeMode = "classic",
    radius_rule: RadiusRule | None = None,
    absgrad: bool = False,
) -> SplatOutput:
    """Render ``(B, N)`` Gaussians into ``(B, V)`` pinhole cameras, differentiably.

    Args:
        gaussians: batch shape ``(B,)``; opacities in [0, 1], scales standard deviations
            (see :meth:`GaussianSet.from_tensors` for logits, log-scales, xyzw quaternions).
        world_to_cam: ``(B, V, 4, 4)`` extrinsics, OpenCV axes (x right, y down, z forward),
            last row ``[0, 0, 0, 1]``. Flatten extra axes such as time into ``B``.
        intrinsics: ``(B, V, 3, 3)`` pinhole ``K``, zero skew, last row ``[0, 0, 1]``;
            pixel ``(u, v)`` is centred at ``(u+.5, v+.5)``.
        image_size: ``(H, W)``: height first (gsplat takes ``width, height``); any pair
            of Python or numpy ints (tuple, list, ``torch.Size``, numpy array).
        features: ``(B, N, C)`` per-Gaussian or ``(B, V, N, C)`` per-camera features;
            defaults to ``gaussians.features`` (none at all: C = 0, only depth and alpha
            are rendered).
        background: ``(C,)`` or ``(B, V, C)``, added as ``T_final * background`` (default 0).
        near: cull Gaussians whose camera z is below ``near``.
        far: cull Gaussians whose camera z is above ``far``.
        eps2d: screen-space dilation added to the 2D covariance (pixels^2).
        max_alpha: per-Gaussian alpha cap: alpha = min(max_alpha, o exp(-sigma)).
        alpha_min: a Gaussian with alpha < alpha_min (or sigma < 0) is skipped at a pixel.
        transmittance_min: a pixel stops before the Gaussian that would take its
            transmittance to transmittance_min or below.
        radius_sigma: standard deviations in the screen radius that decides which tiles
            a Gaussian touches; ``None``: the radius rule's own (3, or 3.33 for 1.5).
        tile_size: tile edge in pixels.
        depth_mode: ``"expected"`` sum(w z) / max(alpha, 1e-10) (gsplat's ``ED``),
            ``"accumulated"`` sum(w z) (gsplat's ``D``, what DeGO and GaussianFlowOcc
            train with), or ``"none"``; z is the camera z of the Gaussian's mean.
        backend: ``"torch"`` (this implementation, any device, any float dtype),
            ``"triton"`` (dego's Triton compositing kernels: CUDA tensors, float32 inside,
            no C++ build; needs ``pip install -e ".[triton]"``; float64 renders
            with the torch path), ``"gsplat"`` (gsplat's CUDA rasteriser, needs
            ``pip install -e ".[gsplat]"`` and CUDA tensors) or ``"auto"`` (in
            order: gsplat when it is usable and the settings match its compiled constants,
            Triton on CUDA when installed and its kernels compile there, else the torch
            path; never Triton on CPU).
        chunk_size: Gaussians composited per tile per step.
        max_pairs: bound on (Gaussian, pixel) pairs held at once; the compositing peak is
            about ``max_pairs * itemsize * 15`` bytes (backward), whatever N is. Smaller
            values use less memory and more, smaller steps.
        radius_clip: skip Gaussians whose screen radius is at most this many pixels on
            every axis (gsplat's ``radius_clip``).
        rasterize_mode: ``"classic"`` or ``"antialiased"``: opacities times gsplat's
            compensation ``sqrt(det(Sigma2d) / det(Sigma2d + eps2d I))`` (Mip-Splatting).
        radius_rule: ``"gsplat<=1.4"`` (one radius ``ceil(3 sqrt(lambda_max))``) or
            ``"gsplat>=1.5"`` (per-axis, opacity-aware radii); see
            :func:`~dego.splatting.project_gaussians`. Only the tiles a Gaussian reaches
            change, so images differ only at the edges of large, opaque Gaussians.
            ``None`` (default): ``"gsplat<=1.4"`` on the torch path, the installed
            gsplat's own rule on the gsplat backend.
        absgrad: after backward, ``out.projection.means2d.absgrad`` ``(B, V, N, 2)`` holds
            each Gaussian's per-pixel screen-space gradients summed in absolute value
            (AbsGS densification).

    Raises:
        TypeError: an unknown option (with the closest valid name) or gsplat's name for one.
        ValueError: a bad option value (naming the option), or a bad input (naming it).

    Differentiable w.r.t. the Gaussians' means, quats, scales and opacities, the features
    and the background, and, through the projection, the cameras.
    """
    config = config_from(SplatConfig, locals())
    return pipeline.render(
        gaussians, world_to_cam, intrinsics, image_size, features, background, config
    )


class DifferentiableSplatter(nn.Module):
    """Module form of :func:`splat`: holds a :class:`SplatConfig`; ``forward`` takes the
    per-call tensors.

    Args:
        config: the settings (default: the defaults of :func:`splat`).
        **overrides: keyword options of :func:`splat` (:class:`SplatOptions`: ``near``,
            ``far``, ``eps2d``, ``max_alpha``, ``alpha_min``, ``transmittance_min``,
            ``radius_sigma``, ``tile_size``, ``depth_mode``, ``backend``, ``chunk_size``,
            ``max_pairs``, ``radius_clip``, ``rasterize_mode``, ``radius_rule``,
            ``absgrad``) applied on top of ``config``, e.g. ``depth_mode="accumulated"``.

    Raises:
        TypeError: ``config`` is not a :class:`SplatConfig`, an unknown option (with the
            closest valid name) or gsplat's name for one.
        ValueError: a bad option value, naming the option.
    """

    def __init__(
        self, config: SplatConfig | None = None, **overrides: Unpack[SplatOptions]
    ) -> None:
        super().__init__()
        self.config = build_config(
            "DifferentiableSplatter()", SplatConfig, config, overrides, foreign=GSPLAT_KEYWORDS
        )

    @check_call("DifferentiableSplatter.forward", cameras_at=2, options=False)
    @typechecked
    def forward(
        self,
        gaussians: GaussianSet,
        world_to_cam: Float[Tensor, "B V 4 4"],
        intrinsics: Float[Tensor, "B V 3 3"],
        image_size: ImageSize,
        features: Float[Tensor, "B N C"] | Float[Tensor, "B V N C"] | None = None,
        background: Float[Tensor, " C"] | Float[Tensor, "B V C"] | None = None,
    ) -> SplatOutput:
        return pipeline.render(
            gaussians, world_to_cam, intrinsics, image_size, features, background, self.config
        )

    def extra_repr(self) -> str:
        return ", ".join(
            f"{f.name}={getattr(self.config, f.name)!r}" for f in dataclasses.fields(self.config)
        )


__all__ = [
    "Backend",
    "DepthMode",
    "DifferentiableSplatter",
    "ImageSize",
    "SplatConfig",
    "SplatOptions",
    "SplatOutput",
    "splat",
]
