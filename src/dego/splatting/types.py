"""The splatter's types, written once: the option aliases, :class:`SplatConfig` (every
option's annotation, default and validation), :class:`SplatOptions` (the same options as a
``TypedDict``, for ``DifferentiableSplatter(**overrides)``) and :class:`SplatOutput`."""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Sequence
from typing import Literal, SupportsIndex, TypedDict

import numpy as np
from jaxtyping import Float, Int
from torch import Tensor

from dego import _serialization
from dego._typing import device_hint
from dego.splatting.projection import RADIUS_SIGMA, Projection, RadiusRule, RasterizeMode

DepthMode = Literal["expected", "accumulated", "none"]
Backend = Literal["torch", "auto", "gsplat", "triton"]
Layout = Literal["channels_first", "channels_last"]
ImageSize = tuple[SupportsIndex, SupportsIndex] | Sequence[SupportsIndex] | np.ndarray


@dataclasses.dataclass(frozen=True)
class SplatOutput(_serialization.DictForm):
    """Rendered images, channels first.

    Attributes:
        features: ``(B, V, C, H, W)`` composited features plus ``T_final * background``.
        depth: ``(B, V, H, W)`` camera z of the means, ``expected`` (normalised by alpha)
            or ``accumulated``; ``None`` with ``depth_mode="none"``.
        alpha: ``(B, V, H, W)`` accumulated opacity ``1 - T_final``.
        radii: ``(B, V, N)`` int32 screen radius of each Gaussian (the larger axis under
            ``radius_rule="gsplat>=1.5"``), 0 where culled.
        projection: the per (camera, Gaussian) screen-space quantities
            (:class:`~dego.splatting.Projection`): ``means2d`` ``(B, V, N, 2)`` (call
            ``retain_grad()`` on it for densification; ``.absgrad`` with ``absgrad=True``),
            ``conics``, ``depths``, per-axis ``radii_xy``, effective ``opacities``.
    """

    features: Float[Tensor, "B V C H W"]
    depth: Float[Tensor, "B V H W"] | None
    alpha: Float[Tensor, "B V H W"]
    radii: Int[Tensor, "B V N"]
    projection: Projection | None = None


# Pickles (torch.save, checkpoints) name a class by module and qualified name: SplatOutput
# keeps the name it has always been saved under, so that old files load. Its annotations
# are resolved here first, as typing.get_type_hints would look them up in __module__.
SplatOutput.__annotations__ = typing.get_type_hints(SplatOutput)
SplatOutput.__module__ = "dego.splatting.splatter"


@dataclasses.dataclass(frozen=True)
class ChannelsLastOutput:
    """Rendered images laid out as gsplat returns them (what the adapters serve).

    Attributes:
        image: ``(B, V, H, W, X)``: the features (plus ``T_final * background``), then the
            depth when ``depth_mode`` renders one (X = C or C + 1).
        alpha: ``(B, V, H, W)`` accumulated opacity ``1 - T_final``.
        projection: the per (camera, Gaussian) screen-space quantities.
    """

    image: Float[Tensor, "B V H W X"]
    alpha: Float[Tensor, "B V H W"]
    projection: Projection


@dataclasses.dataclass(frozen=True)
class SplatConfig:
    """Rendering settings shared by :func:`~dego.splatting.splat` and
    :class:`~dego.splatting.DifferentiableSplatter` (each option is documented in
    :func:`~dego.splatting.splat`); a bad value raises ``ValueError`` naming the option."""

    near: float = 0.01
    far: float = 1e10
    eps2d: float = 0.3
    max_alpha: float = 0.999
    alpha_min: float = 1 / 255
    transmittance_min: float = 1e-4
    radius_sigma: float | None = None
    tile_size: int = 16
    depth_mode: DepthMode = "expected"
    backend: Backend = "torch"
    chunk_size: int = 32
    max_pairs: int = 1 << 22
    radius_clip: float = 0.0
    rasterize_mode: RasterizeMode = "classic"
    radius_rule: RadiusRule | None = None
    absgrad: bool = False

    def __post_init__(self) -> None:
        checks = [
            ("near", self.near >= 0, ">= 0"),
            ("far", self.far > self.near, f"> near ({self.near})"),
            ("eps2d", self.eps2d >= 0, ">= 0"),
            ("max_alpha", 0 < self.max_alpha <= 1, "in (0, 1]"),
            ("alpha_min", 0 <= self.alpha_min < 1, "in [0, 1)"),
            ("transmittance_min", 0 <= self.transmittance_min < 1, "in [0, 1)"),
            ("radius_sigma", self.radius_sigma is None or self.radius_sigma > 0, "None or > 0"),
            ("tile_size", isinstance(self.tile_size, int) and self.tile_size > 0, "a positive int"),
            (
                "chunk_size",
                isinstance(self.chunk_size, int) and self.chunk_size > 0,
                "a positive int",
            ),
            ("max_pairs", isinstance(self.max_pairs, int) and self.max_pairs > 0, "a positive int"),
            ("radius_clip", self.radius_clip >= 0, ">= 0 (pixels)"),
            (
                "depth_mode",
                self.depth_mode in ("expected", "accumulated", "none"),
                "'expected', 'accumulated' or 'none'",
            ),
            (
                "backend",
                self.backend in ("torch", "auto", "gsplat", "triton"),
                "'torch', 'auto', 'gsplat' or 'triton'",
            ),
            (
                "rasterize_mode",
                self.rasterize_mode in ("classic", "antialiased"),
                "'classic' or 'antialiased'",
            ),
            (
                "radius_rule",
                self.radius_rule is None or self.radius_rule in RADIUS_SIGMA,
                "None, 'gsplat<=1.4' or 'gsplat>=1.5'",
            ),
            ("absgrad", isinstance(self.absgrad, bool), "a bool"),
        ]
        for name, ok, expected in checks:
            if not ok:
                value = getattr(self, name)
                raise ValueError(
                    f"{name}: expected {expected}, got {value!r}{device_hint(name, value)}"
                )
        for name in ("near", "far", "eps2d", "radius_sigma", "radius_clip"):
            value = getattr(self, name)
            if value is not None and math.isnan(value):
                raise ValueError(f"{name}: must not be NaN")


class SplatOptions(TypedDict, total=False):
    """The fields of :class:`SplatConfig` as keyword overrides of
    :class:`~dego.splatting.DifferentiableSplatter` (a test keeps the two identical)."""

    near: float
    far: float
    eps2d: float
    max_alpha: float
    alpha_min: float
    transmittance_min: float
    radius_sigma: float | None
    tile_size: int
    depth_mode: DepthMode
    backend: Backend
    chunk_size: int
    max_pairs: int
    radius_clip: float
    rasterize_mode: RasterizeMode
    radius_rule: RadiusRule | None
    absgrad: bool


__all__ = [
    "Backend",
    "ChannelsLastOutput",
    "DepthMode",
    "ImageSize",
    "Layout",
    "SplatConfig",
    "SplatOptions",
    "SplatOutput",
]
