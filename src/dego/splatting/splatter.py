"""``splat`` and ``DifferentiableSplatter``: Gaussians -> feature, depth and alpha images."""

from __future__ import annotations

import dataclasses
import functools
import math
import operator
from collections.abc import Callable, Sequence
from typing import Any, Literal, SupportsIndex, TypeVar

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor, nn

from dego import _serialization
from dego._policy import (
    HALF_DTYPES,
    Check,
    check_dtype,
    check_memory,
    compute_dtype,
    finite_check,
    float32_under_autocast,
    run_checks,
)
from dego._typing import _is_compiling, typechecked
from dego.gaussians import GaussianSet
from dego.splatting import composite
from dego.splatting.composite import CompositeRules, composite_tiles
from dego.splatting.projection import (
    RADIUS_SIGMA,
    Projection,
    RadiusRule,
    RasterizeMode,
    project_gaussians,
)
from dego.splatting.tiles import TileLists, build_tile_lists, contributing_extents

F = TypeVar("F", bound=Callable[..., Any])
DepthMode = Literal["expected", "accumulated", "none"]
Backend = Literal["torch", "auto", "gsplat"]
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


@dataclasses.dataclass(frozen=True)
class SplatConfig:
    """Rendering settings shared by :func:`splat` and :class:`DifferentiableSplatter`."""

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
            ("backend", self.backend in ("torch", "auto", "gsplat"), "'torch', 'auto' or 'gsplat'"),
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
                raise ValueError(f"{name}: expected {expected}, got {getattr(self, name)!r}")
        for name in ("near", "far", "eps2d", "radius_sigma", "radius_clip"):
            value = getattr(self, name)
            if value is not None and math.isnan(value):
                raise ValueError(f"{name}: must not be NaN")


def _matrix_rows_ok(matrix: Tensor, expected_last_row: list[float]) -> Tensor:
    """Whether the last row of each ``(..., k, k)`` matrix is ``expected_last_row``."""
    expected = torch.tensor(expected_last_row, dtype=matrix.dtype, device=matrix.device)
    return ((matrix[..., -1, :] - expected).abs() <= 1e-6).all(-1)


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
    b, n = gaussians.batch_shape[0], gaussians.num_gaussians
    v = world_to_cam.shape[1]
    if world_to_cam.shape[0] != b:
        raise ValueError(f"world_to_cam: batch {world_to_cam.shape[0]} != gaussians' batch {b}")
    optional = (("features", features), ("background", background))
    tensors = [("world_to_cam", world_to_cam), ("intrinsics", intrinsics)]
    tensors += [(name, t) for name, t in optional if t is not None]
    for name, t in tensors:
        check_dtype(name, t, gaussians.dtype, "the gaussians")
        if t.device != gaussians.device:
            raise ValueError(f"{name}: on {t.device}, expected the gaussians' {gaussians.device}")
    if features is not None and features.shape[-2] != n:
        raise ValueError(
            f"features: expected shape (B, N, C) or (B, V, N, C) with N = {n}, "
            f"got {tuple(features.shape)}"
        )
    channels = 0 if features is None else features.shape[-1]
    if background is not None and background.shape not in ((channels,), (b, v, channels)):
        raise ValueError(
            f"background: expected shape ({channels},) or (B, V, {channels}), "
            f"got {tuple(background.shape)}"
        )
    height, width = image_size
    focal = torch.maximum(intrinsics[..., 0, 0].abs(), intrinsics[..., 1, 1].abs())
    cx, cy = intrinsics[..., 0, 2], intrinsics[..., 1, 2]
    outside = (cx < 0) | (cx > width) | (cy < 0) | (cy > height)
    transposed = outside & (cx >= 0) & (cx <= height) & (cy >= 0) & (cy <= width)
    opacities = gaussians.opacities
    out_of_range = (opacities < 0) | (opacities > 1)
    finite = [(f"gaussians.{name}", t) for name, t in gaussians.items() if name != "features"]
    finite += [(name, t) for name, t in optional if t is not None]
    pinhole = (
        "intrinsics: expected pinhole matrices [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] "
        "(zero skew, last row [0, 0, 1], tolerance 1e-6 relative). A resize, crop or "
        "translation of the image folds into K (dego.cameras.resize_crop_intrinsics, "
        "dego.cameras.apply_image_aug); an image rotation or flip does not: warp the "
        "image instead, or move a rotation about the optical axis into world_to_cam. "
        "To split a 3x4 lidar2img projection use dego.cameras.split_projection"
    )
    rigid = (
        "world_to_cam: expected 4x4 rigid transforms with last row [0, 0, 0, 1]; a "
        "projection matrix (K [R | t], lidar2img) splits with dego.cameras.split_projection"
    )
    transposed_message = (
        f"image_size: (H, W) = ({height}, {width}) looks transposed: a principal point "
        f"(cx, cy) lies outside a {width} x {height} (W x H) image but inside the "
        f"transposed one; pass image_size=(height, width)"
    )
    log_scales = (
        "gaussians.scales: every scale is negative, which looks like log-scales; "
        "use GaussianSet.from_tensors(..., scale_space='log') (or exp them)"
    )
    opacity_range = "gaussians.opacities: values lie outside [0, 1]"

    def bad_opacities() -> Exception:
        hint = (
            ", which looks like logits: use GaussianSet.from_tensors(..., "
            "opacity_space='logit') (or apply a sigmoid)"
            if bool(out_of_range.all())
            else "; if they are logits, use GaussianSet.from_tensors(..., "
            "opacity_space='logit'), else clamp them"
        )
        return ValueError(
            f"gaussians.opacities: {int(out_of_range.sum())} of {opacities.numel()} values lie "
            f"outside [0, 1]{hint}"
        )

    def fail(message: str) -> Callable[[], Exception]:
        return lambda: ValueError(message)

    def check(ok: Tensor, message: str) -> Check:
        return ok, message, fail(message)

    scales = gaussians.scales
    # One host sync for every value check (none under torch.compile).
    run_checks(
        [finite_check(name, t) for name, t in finite]
        + [
            check(torch.isfinite(world_to_cam).all(), "world_to_cam: contains non-finite values"),
            check(torch.isfinite(intrinsics).all(), "intrinsics: contains non-finite values"),
            check(
                ((intrinsics[..., 0, 0] > 0) & (intrinsics[..., 1, 1] > 0)).all(),
                "intrinsics: focal lengths fx, fy must be positive",
            ),
            check(
                ((intrinsics[..., 0, 1].abs() <= 1e-6 * focal) & (intrinsics[..., 1, 0] == 0)).all()
                & _matrix_rows_ok(intrinsics, [0.0, 0.0, 1.0]).all(),
                pinhole,
            ),
            check(_matrix_rows_ok(world_to_cam, [0.0, 0.0, 0.0, 1.0]).all(), rigid),
            check(~transposed.any(), transposed_message),
            check(~(scales < 0).all() | (scales.numel() == 0), log_scales),
            (~out_of_range.any(), opacity_range, bad_opacities),
        ]
    )


_GSPLAT_KEYWORDS = {
    "viewmats": "world_to_cam",
    "Ks": "intrinsics",
    "width": "image_size=(height, width)",
    "height": "image_size=(height, width)",
    "colors": "features",
    "near_plane": "near",
    "far_plane": "far",
    "backgrounds": "background",
    "render_mode": "depth_mode ('RGB+D' is 'accumulated', 'RGB+ED' is 'expected')",
}


def _image_size(value: object) -> tuple[int, int]:
    """``(H, W)`` as Python ints from any pair of ints (numpy ints, ``torch.Size``)."""
    try:
        height, width = (operator.index(v) for v in value)  # type: ignore[attr-defined]
        ok = not any(isinstance(v, bool) for v in value) and height > 0 and width > 0  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"image_size: expected (H, W), two positive ints, got {value!r}")
    return height, width


def _check_call(name: str, cameras_at: int) -> Callable[[F], F]:
    """Friendly errors for the mistakes ports from gsplat make, before the shape checks:
    gsplat's keyword names and cameras with extra leading axes (``(B, T, V, 4, 4)``)."""

    def decorate(fn: F) -> F:
        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            for key in kwargs:
                if key in _GSPLAT_KEYWORDS:
                    raise TypeError(
                        f"{name}() got gsplat's keyword {key!r}: dego calls it "
                        f"{_GSPLAT_KEYWORDS[key]}; or call dego.compat.gsplat.rasterization, "
                        "which takes gsplat's names and layout"
                    )
            cameras = list(args[cameras_at : cameras_at + 2])
            cameras += [kwargs.get(k) for k in ("world_to_cam", "intrinsics")[len(cameras) :]]
            for arg, (label, tail) in zip(
                cameras, (("world_to_cam", "4, 4"), ("intrinsics", "3, 3")), strict=True
            ):
                if isinstance(arg, Tensor) and arg.ndim != 4:
                    shape = tuple(arg.shape)
                    if arg.ndim > 4:
                        advice = (
                            "; flatten the leading axes into one batch axis, e.g. (B, T, V) "
                            "-> (B * T, V) with .flatten(0, 1), and the Gaussians likewise "
                            "(GaussianSet.flatten_batch())"
                        )
                    elif arg.ndim == 3:  # (V, ...): one batch
                        advice = f"; add the batch axis B, e.g. {label}[None]"
                    elif arg.ndim == 2:  # one matrix: one batch of one camera
                        advice = f"; add the batch and camera axes B, V, e.g. {label}[None, None]"
                    else:
                        advice = ""
                    raise ValueError(f"{label}: expected shape (B, V, {tail}), got {shape}{advice}")
            return fn(*args, **kwargs)

        return wrapper  # type: ignore[return-value]

    return decorate


@float32_under_autocast()
@_check_call("splat", cameras_at=1)
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
        backend: ``"torch"`` (this implementation, any device), ``"gsplat"`` (gsplat's CUDA
            rasteriser, needs ``pip install "dego-occupancy[gsplat]"`` and CUDA tensors) or
            ``"auto"`` (gsplat when it is usable and the settings match its compiled
            constants).
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

    Differentiable w.r.t. the Gaussians' means, quats, scales and opacities, the features
    and the background, and, through the projection, the cameras.
    """
    config = SplatConfig(
        near=near,
        far=far,
        eps2d=eps2d,
        max_alpha=max_alpha,
        alpha_min=alpha_min,
        transmittance_min=transmittance_min,
        radius_sigma=radius_sigma,
        tile_size=tile_size,
        depth_mode=depth_mode,
        backend=backend,
        chunk_size=chunk_size,
        max_pairs=max_pairs,
        radius_clip=radius_clip,
        rasterize_mode=rasterize_mode,
        radius_rule=radius_rule,
        absgrad=absgrad,
    )
    return _render(gaussians, world_to_cam, intrinsics, image_size, features, background, config)


@dataclasses.dataclass(frozen=True)
class _Composited:
    """What the compositing produced, before it is laid out as images."""

    tiles: Tensor  # (B*V*ty*tx, S, S, D): features, then depth when rendered
    transmittance: Tensor  # (B*V*ty*tx, S, S)
    lists: TileLists
    projection: Projection
    channels: int  # feature channels C (D = C + 1 with depth)


# Data-dependent by nature (the pair count, each tile's list length): run eagerly under
# torch.compile, as one graph break, rather than letting dynamo split it at each of its
# dynamic-shape operators. Its chunk kernels are compiled when the caller is.
@torch._dynamo.disable(recursive=True)
def _bin_and_composite(
    proj: Projection,
    extents: Tensor,
    max_sigma: Tensor,
    means2d: Tensor,
    opacities: Tensor,
    colors: Tensor,
    image_size: tuple[int, int],
    config: SplatConfig,
    absgrad_sink: Callable[[Tensor], None] | None,
    kernel_backend: str | None,
) -> tuple[Tensor, Tensor, TileLists]:
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
        means2d,
        proj.conics.reshape(-1, 3),
        opacities,
        colors,
        tile_size=config.tile_size,
        rules=CompositeRules(config.max_alpha, config.alpha_min, config.transmittance_min),
        chunk_size=config.chunk_size,
        max_pairs=config.max_pairs,
        absgrad_sink=absgrad_sink,
        kernel_backend=kernel_backend,
    )
    return tiles, transmittance, lists


def _composite(
    gaussians: GaussianSet,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    image_size: tuple[int, int],
    features: Tensor | None,
    config: SplatConfig,
    means2d_hook: Callable[[Projection], Tensor] | None,
    absgrad_sink: Callable[[Tensor], None] | None,
) -> _Composited:
    """Project, intersect with tiles and composite (the torch path)."""
    b, n = gaussians.batch_shape[0], gaussians.num_gaussians
    v = world_to_cam.shape[1]
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
        radius_rule=config.radius_rule or "gsplat<=1.4",
        radius_clip=config.radius_clip,
        opacities=gaussians.opacities,
        rasterize_mode=config.rasterize_mode,
    )
    columns = []
    if features is not None and channels:
        per_camera = features if features.ndim == 4 else features.unsqueeze(1)
        columns.append(per_camera.expand(b, v, n, channels))
    if config.depth_mode != "none":
        columns.append(proj.depths.unsqueeze(-1))
    dtype, device = gaussians.dtype, gaussians.device
    colors = (
        torch.cat(columns, -1) if columns else torch.zeros(b, v, n, 0, dtype=dtype, device=device)
    )

    opacities = proj.opacities
    assert opacities is not None
    extents, max_sigma = contributing_extents(
        proj.variances2d, proj.radii_xy, opacities, config.alpha_min
    )
    means2d = proj.means2d if means2d_hook is None else means2d_hook(proj)
    if config.absgrad and absgrad_sink is None:

        def absgrad_sink(total: Tensor) -> None:
            proj.means2d.absgrad = total.view_as(proj.means2d)  # type: ignore[attr-defined]

    tiles, transmittance, lists = _bin_and_composite(
        proj,
        extents,
        max_sigma,
        means2d.reshape(-1, 2),
        opacities.reshape(-1),
        colors.reshape(b * v * n, colors.shape[-1]),
        image_size,
        config,
        absgrad_sink if config.absgrad else None,
        composite.COMPILED_KERNELS if _is_compiling() else None,
    )
    return _Composited(tiles, transmittance, lists, proj, channels)


def _prepare(
    gaussians: GaussianSet,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    image_size: ImageSize,
    features: Tensor | None,
    background: Tensor | None,
    config: SplatConfig,
) -> tuple[tuple[int, int], GaussianSet, Tensor, Tensor, Tensor | None, Tensor | None]:
    """Check a call and return ``(H, W)`` and the tensors to render with: the features
    default to the Gaussians', and float16 / bfloat16 inputs are computed in float32."""
    size = _image_size(image_size)
    features = gaussians.features if features is None else features
    _check_inputs(gaussians, world_to_cam, intrinsics, size, features, background)
    _check_memory(gaussians, world_to_cam.shape[1], size, features, config)
    if gaussians.dtype in HALF_DTYPES:
        gaussians, world_to_cam, intrinsics = (
            t.to(torch.float32) for t in (gaussians, world_to_cam, intrinsics)
        )
        features, background = (
            None if t is None else t.to(torch.float32) for t in (features, background)
        )
    return size, gaussians, world_to_cam, intrinsics, features, background


def _check_memory(
    gaussians: GaussianSet,
    views: int,
    size: tuple[int, int],
    features: Tensor | None,
    config: SplatConfig,
) -> None:
    """Estimate the bytes of a render (per-pixel accumulators and their gradients, the
    per (camera, Gaussian) projection, the compositing's pair buffers) before allocating."""
    b, n = gaussians.batch_shape[0], gaussians.num_gaussians
    itemsize = torch.empty((), dtype=compute_dtype(gaussians.dtype)).element_size()
    channels = 0 if features is None else features.shape[-1]
    d = channels + (config.depth_mode != "none")
    ts = config.tile_size
    pixels = b * views * math.ceil(size[0] / ts) * ts * math.ceil(size[1] / ts) * ts
    nbytes = pixels * (3 * d + 4) * itemsize * 2
    nbytes += b * views * n * (40 + d) * itemsize
    nbytes += config.max_pairs * itemsize * 15
    sizes = (
        f"{b * views} images of {size[0]} x {size[1]} with {d} channels, "
        f"{n} Gaussians, {gaussians.dtype}"
    )
    check_memory("splat", nbytes, sizes)


def _render(
    gaussians: GaussianSet,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    image_size: ImageSize,
    features: Tensor | None,
    background: Tensor | None,
    config: SplatConfig,
    *,
    means2d_hook: Callable[[Projection], Tensor] | None = None,
    absgrad_sink: Callable[[Tensor], None] | None = None,
) -> SplatOutput:
    """Render; ``means2d_hook`` gives, from the projection, the ``(B, V, N, 2)`` means the
    compositing reads (adapters use it to expose a packed layout), ``absgrad_sink``
    receives the absolute gradients (default: set as ``projection.means2d.absgrad``)."""
    dtype = gaussians.dtype
    size, gaussians, world_to_cam, intrinsics, features, background = _prepare(
        gaussians, world_to_cam, intrinsics, image_size, features, background, config
    )
    if config.backend != "torch":
        from dego.splatting import gsplat_backend

        if gsplat_backend.usable(gaussians, config, strict=config.backend == "gsplat"):
            out = gsplat_backend.render(
                gaussians, world_to_cam, intrinsics, size, features, background, config
            )
            return _in_dtype(out, dtype)
    done = _composite(
        gaussians, world_to_cam, intrinsics, size, features, config, means2d_hook, absgrad_sink
    )
    b, v = world_to_cam.shape[:2]
    height, width = size
    channels, lists = done.channels, done.lists
    ts, tx, ty = config.tile_size, lists.tiles_x, lists.tiles_y
    # (B*V*ty*tx, S, S, D) -> (B, V, D, ty*S, tx*S), cropped to (H, W)
    d = done.tiles.shape[-1]
    image = done.tiles.view(b, v, ty, tx, ts, ts, d).permute(0, 1, 6, 2, 4, 3, 5)
    image = image.reshape(b, v, d, ty * ts, tx * ts)[..., :height, :width]
    final_t = _untile(done.transmittance, b, v, lists, ts, size)
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
    proj = done.projection
    out = SplatOutput(
        features=rendered, depth=depth, alpha=alpha, radii=proj.radii, projection=proj
    )
    return _in_dtype(out, dtype)


def _in_dtype(out: SplatOutput, dtype: torch.dtype) -> SplatOutput:
    """The images in ``dtype`` (the input's: float16 / bfloat16 are computed in float32)."""
    if out.alpha.dtype == dtype:
        return out
    return dataclasses.replace(
        out,
        features=out.features.to(dtype),
        depth=None if out.depth is None else out.depth.to(dtype),
        alpha=out.alpha.to(dtype),
    )


def _untile(
    transmittance: Tensor, b: int, v: int, lists: TileLists, ts: int, size: tuple[int, int]
) -> Tensor:
    """Per-tile ``(B*V*ty*tx, S, S)`` values -> ``(B, V, H, W)`` images."""
    tx, ty = lists.tiles_x, lists.tiles_y
    image = transmittance.view(b, v, ty, tx, ts, ts).permute(0, 1, 2, 4, 3, 5)
    return image.reshape(b, v, ty * ts, tx * ts)[..., : size[0], : size[1]]


def render_channels_last(
    gaussians: GaussianSet,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    image_size: ImageSize,
    features: Tensor | None,
    background: Tensor | None,
    config: SplatConfig,
    *,
    means2d_hook: Callable[[Projection], Tensor] | None = None,
    absgrad_sink: Callable[[Tensor], None] | None = None,
) -> tuple[Tensor, Tensor, Projection]:
    """The torch path laid out as gsplat returns it, for adapters: ``(image (B, V, H, W, X),
    alpha (B, V, H, W), projection)`` with X the features (plus background) followed by
    the depth when ``config.depth_mode`` renders one. No transposition: the tiles are
    already channels-last, so this costs no more than :func:`splat`."""
    dtype = gaussians.dtype
    size, gaussians, world_to_cam, intrinsics, features, background = _prepare(
        gaussians, world_to_cam, intrinsics, image_size, features, background, config
    )
    done = _composite(
        gaussians, world_to_cam, intrinsics, size, features, config, means2d_hook, absgrad_sink
    )
    b, v = world_to_cam.shape[:2]
    channels, lists, ts = done.channels, done.lists, config.tile_size
    d = done.tiles.shape[-1]
    image = done.tiles.view(b, v, lists.tiles_y, lists.tiles_x, ts, ts, d)
    image = image.permute(0, 1, 2, 4, 3, 5, 6).reshape(b, v, lists.tiles_y * ts, -1, d)
    image = image[:, :, : size[0], : size[1]]
    final_t = _untile(done.transmittance, b, v, lists, ts, size)
    if background is not None and background.ndim == 1:
        background = background.expand(b, v, channels)
    expected = config.depth_mode == "expected"
    if background is not None or expected:
        image = _FinishChannelsLast.apply(image, final_t, background, channels, expected)
    return image.to(dtype), (1 - final_t).to(dtype), done.projection


class _FinishChannelsLast(torch.autograd.Function):
    """Adds ``T_final * background`` to the feature channels and divides the depth channel
    (the last) by ``max(alpha, 1e-10)`` of a channels-last ``(B, V, H, W, X)`` image, as one
    autograd node: one new image forward, at most one backward (slicing the image into
    parts would allocate a zero-filled image per part in backward)."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: torch.autograd.function.FunctionCtx,
        image: Tensor,
        final_t: Tensor,
        background: Tensor | None,
        channels: int,
        expected: bool,
    ) -> Tensor:
        out = image.clone(memory_format=torch.contiguous_format)
        if background is not None:
            out[..., :channels] += final_t.unsqueeze(-1) * background[:, :, None, None]
        alpha = (1 - final_t).clamp_min(1e-10)
        if expected:
            out[..., channels] /= alpha
        ctx.save_for_backward(final_t, background, out[..., channels] if expected else None)
        ctx.channels, ctx.expected = channels, expected
        return out

    @staticmethod
    def backward(  # type: ignore[override]
        ctx: torch.autograd.function.FunctionCtx, grad: Tensor
    ) -> tuple[Tensor | None, ...]:
        final_t, background, depth = ctx.saved_tensors
        channels = ctx.channels
        grad_image, grad_t, grad_background = grad, None, None
        if background is not None:
            grad_features = grad[..., :channels]
            grad_t = torch.einsum("bvhwc,bvc->bvhw", grad_features, background)
            grad_background = torch.einsum("bvhwc,bvhw->bvc", grad_features, final_t)
        if ctx.expected:
            alpha = 1 - final_t
            grad_depth = grad[..., channels]
            grad_image = grad.clone(memory_format=torch.contiguous_format)
            grad_image[..., channels] /= alpha.clamp_min(1e-10)
            # depth = accumulated / alpha, alpha = 1 - T: d depth / dT = depth / alpha
            # (no gradient where the clamp is active, as with clamp_min)
            extra = torch.where(alpha > 1e-10, grad_depth * depth / alpha, 0.0)
            grad_t = extra if grad_t is None else grad_t + extra
        return grad_image, grad_t, grad_background, None, None


class DifferentiableSplatter(nn.Module):
    """Module form of :func:`splat`: holds the rendering settings (see :func:`splat` for
    their meaning); ``forward`` takes the per-call tensors."""

    def __init__(self, **config: object) -> None:
        super().__init__()
        for key in config:
            if key in _GSPLAT_KEYWORDS:
                raise TypeError(
                    f"DifferentiableSplatter() got gsplat's keyword {key!r}: dego calls it "
                    f"{_GSPLAT_KEYWORDS[key]}"
                )
        unknown = sorted(set(config) - {f.name for f in dataclasses.fields(SplatConfig)})
        if unknown:
            valid = ", ".join(f.name for f in dataclasses.fields(SplatConfig))
            raise TypeError(
                f"DifferentiableSplatter(): unknown setting(s) {unknown}; valid: {valid}"
            )
        self.config = SplatConfig(**config)  # type: ignore[arg-type]

    @_check_call("DifferentiableSplatter.forward", cameras_at=2)
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
        return _render(
            gaussians, world_to_cam, intrinsics, image_size, features, background, self.config
        )

    def extra_repr(self) -> str:
        return ", ".join(
            f"{f.name}={getattr(self.config, f.name)!r}" for f in dataclasses.fields(self.config)
        )


__all__ = ["DifferentiableSplatter", "SplatConfig", "SplatOutput", "splat"]
