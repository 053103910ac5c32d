"""The render pipeline behind :func:`dego.splat`, :class:`dego.DifferentiableSplatter` and
the adapters (:mod:`dego.compat.gsplat`, :mod:`dego.compat.dego`): check and prepare the
call, project, bin into tiles, composite, then lay the tiles out as images
(:mod:`dego.splatting.layouts`), channels first or channels last.

    out = render(gaussians, world_to_cam, intrinsics, (H, W), None, None, SplatConfig())
    last = render(..., layout="channels_last")  # (B, V, H, W, X), as gsplat returns it
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Literal, overload

import torch
from jaxtyping import Float
from torch import Tensor

from dego._compile import eager_only
from dego._policy import HALF_DTYPES
from dego._typing import _is_compiling, typechecked
from dego.gaussians import GaussianSet
from dego.splatting import composite, inputs, layouts
from dego.splatting.composite import CompositeRules, composite_tiles
from dego.splatting.projection import Projection, project_gaussians
from dego.splatting.tiles import build_tile_lists, contributing_extents
from dego.splatting.types import ChannelsLastOutput, ImageSize, Layout, SplatConfig, SplatOutput

Means2dHook = Callable[[Projection], Tensor]
AbsgradSink = Callable[[Tensor], None]


@overload
def render(
    gaussians: GaussianSet,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    image_size: ImageSize,
    features: Tensor | None,
    background: Tensor | None,
    config: SplatConfig,
    *,
    layout: Literal["channels_first"] = "channels_first",
    means2d_hook: Means2dHook | None = None,
    absgrad_sink: AbsgradSink | None = None,
) -> SplatOutput: ...


@overload
def render(
    gaussians: GaussianSet,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    image_size: ImageSize,
    features: Tensor | None,
    background: Tensor | None,
    config: SplatConfig,
    *,
    layout: Literal["channels_last"],
    means2d_hook: Means2dHook | None = None,
    absgrad_sink: AbsgradSink | None = None,
) -> ChannelsLastOutput: ...


@typechecked
def render(
    gaussians: GaussianSet,
    world_to_cam: Float[Tensor, "B V 4 4"],
    intrinsics: Float[Tensor, "B V 3 3"],
    image_size: ImageSize,
    features: Float[Tensor, "B N C"] | Float[Tensor, "B V N C"] | None,
    background: Float[Tensor, " C"] | Float[Tensor, "B V C"] | None,
    config: SplatConfig,
    *,
    layout: Layout = "channels_first",
    means2d_hook: Means2dHook | None = None,
    absgrad_sink: AbsgradSink | None = None,
) -> SplatOutput | ChannelsLastOutput:
    """Render ``(B, N)`` Gaussians into ``(B, V)`` cameras (see :func:`dego.splat` for the
    arguments; ``features=None`` takes the Gaussians').

    Args:
        layout: ``"channels_first"``: a :class:`SplatOutput`; ``"channels_last"``: a
            :class:`ChannelsLastOutput`, the image laid out as gsplat returns it,
            ``(B, V, H, W, X)`` with the features (plus background) then the depth when
            ``config.depth_mode`` renders one. Either costs one image copy forward and one
            backward. The channels-last layout always renders with the torch path
            (``backend="auto"`` keeps it; ``"gsplat"`` is refused).
        means2d_hook: from the projection, the ``(B, V, N, 2)`` means the compositing reads
            (the adapters use it to expose gsplat's packed layout).
        absgrad_sink: receives backward's summed absolute means2d gradients
            ``(B * V * N, 2)`` with ``config.absgrad`` (default: set as
            ``projection.means2d.absgrad``).
    """
    if layout not in ("channels_first", "channels_last"):
        raise ValueError(f"layout: expected 'channels_first' or 'channels_last', got {layout!r}")
    if layout == "channels_last" and config.backend == "gsplat":
        raise ValueError(
            "backend: 'gsplat' renders the channels_first layout only; use backend='torch', "
            "'triton' or 'auto' with layout='channels_last'"
        )
    dtype = gaussians.dtype
    size, gaussians, world_to_cam, intrinsics, features, background = _prepare(
        gaussians, world_to_cam, intrinsics, image_size, features, background, config
    )
    # backend="auto" tries, in order: gsplat (channels first, CUDA, its compiled constants
    # equal to the config's), the Triton kernels (CUDA), the torch path.
    if layout == "channels_first" and config.backend in ("auto", "gsplat"):
        from dego.splatting import gsplat_backend

        if gsplat_backend.usable(gaussians, config, strict=config.backend == "gsplat"):
            out = gsplat_backend.render(
                gaussians, world_to_cam, intrinsics, size, features, background, config
            )
            return _in_dtype(out, dtype)
    triton = False
    if config.backend in ("auto", "triton"):
        from dego.splatting import triton_backend

        triton = triton_backend.usable(gaussians, config, strict=config.backend == "triton")
    done = _composite(
        gaussians,
        world_to_cam,
        intrinsics,
        size,
        features,
        config,
        means2d_hook,
        absgrad_sink,
        triton=triton,
    )
    b, v = world_to_cam.shape[:2]
    grid = layouts.TileGrid.of(b, v, config.tile_size, size)
    final_t = layouts.untile(done.transmittance, grid)
    alpha = 1 - final_t
    proj = done.projection
    if layout == "channels_last":
        image = layouts.channels_last(
            done.tiles, final_t, background, done.channels, config.depth_mode, grid
        )
        return ChannelsLastOutput(image=image.to(dtype), alpha=alpha.to(dtype), projection=proj)
    rendered, depth = layouts.channels_first(
        done.tiles, final_t, background, done.channels, config.depth_mode, grid
    )
    out = SplatOutput(
        features=rendered, depth=depth, alpha=alpha, radii=proj.radii, projection=proj
    )
    return _in_dtype(out, dtype)


def _prepare(
    gaussians: GaussianSet,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    size: ImageSize,
    features: Tensor | None,
    background: Tensor | None,
    config: SplatConfig,
) -> tuple[tuple[int, int], GaussianSet, Tensor, Tensor, Tensor | None, Tensor | None]:
    """Check a call and return ``(H, W)`` and the tensors to render with: the features
    default to the Gaussians', and float16 / bfloat16 inputs are computed in float32."""
    hw = inputs.image_size(size)
    features = gaussians.features if features is None else features
    inputs.check_inputs(gaussians, world_to_cam, intrinsics, hw, features, background)
    inputs.check_splat_memory(gaussians, world_to_cam.shape[1], hw, features, config)
    if gaussians.dtype in HALF_DTYPES:
        gaussians = gaussians.to(torch.float32)
        world_to_cam, intrinsics = world_to_cam.float(), intrinsics.float()
        features, background = (
            None if t is None else t.to(torch.float32) for t in (features, background)
        )
    return hw, gaussians, world_to_cam, intrinsics, features, background


@dataclasses.dataclass(frozen=True)
class _Composited:
    """What the compositing produced, before it is laid out as images."""

    tiles: Tensor  # (B*V*ty*tx, S, S, D): features, then depth when rendered
    transmittance: Tensor  # (B*V*ty*tx, S, S)
    projection: Projection
    channels: int  # feature channels C (D = C + 1 with depth)


# Data-dependent by nature (the pair count, each tile's list length): run eagerly under
# torch.compile, as one graph break, rather than letting dynamo split it at each of its
# dynamic-shape operators. Its chunk kernels are compiled when the caller is.
@eager_only
def _bin_and_composite(
    proj: Projection,
    extents: Tensor,
    max_sigma: Tensor,
    means2d: Tensor,
    opacities: Tensor,
    colors: Tensor,
    size: tuple[int, int],
    config: SplatConfig,
    absgrad_sink: AbsgradSink | None,
    kernel_backend: str | None,
) -> tuple[Tensor, Tensor]:
    lists = build_tile_lists(
        proj.means2d.flatten(0, 1),
        extents.flatten(0, 1),
        proj.depths.flatten(0, 1),
        size,
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
    return tiles, transmittance


def _composite(
    gaussians: GaussianSet,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    size: tuple[int, int],
    features: Tensor | None,
    config: SplatConfig,
    means2d_hook: Means2dHook | None,
    absgrad_sink: AbsgradSink | None,
    *,
    triton: bool = False,
) -> _Composited:
    """Project, intersect with tiles and composite (the torch path; with ``triton``, the
    binning and compositing of :mod:`dego.splatting.triton_backend`)."""
    b, n = gaussians.batch_shape[0], gaussians.num_gaussians
    v = world_to_cam.shape[1]
    channels = 0 if features is None else features.shape[-1]
    proj = project_gaussians(
        gaussians.means,
        gaussians.quats,
        gaussians.scales,
        world_to_cam,
        intrinsics,
        size,
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

    if triton:
        from dego.splatting import triton_backend

        tiles, transmittance = triton_backend.bin_and_composite(
            proj.means2d.flatten(0, 1),
            extents.flatten(0, 1),
            proj.depths.flatten(0, 1),
            proj.conics.flatten(0, 1),
            max_sigma.flatten(0, 1),
            opacities.reshape(-1),
            colors.reshape(b * v * n, colors.shape[-1]),
            size,
            config,
            absgrad_sink if config.absgrad else None,
            means2d.reshape(-1, 2),
        )
        return _Composited(tiles, transmittance, proj, channels)
    tiles, transmittance = _bin_and_composite(
        proj,
        extents,
        max_sigma,
        means2d.reshape(-1, 2),
        opacities.reshape(-1),
        colors.reshape(b * v * n, colors.shape[-1]),
        size,
        config,
        absgrad_sink if config.absgrad else None,
        composite.COMPILED_KERNELS if _is_compiling() else None,
    )
    return _Composited(tiles, transmittance, proj, channels)


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


__all__ = ["AbsgradSink", "Means2dHook", "render"]
