"""``rasterization`` with gsplat's names, shapes and return layout, computed by :func:`dego.splat`.

Code written for gsplat (``from gsplat import rasterization``) runs unchanged with
``from dego.compat.gsplat import rasterization``, on CPU as well as CUDA. Both input
layouts are accepted: gsplat >= 1.5's batched ``means [..., N, 3]``, ``viewmats
[..., C, 4, 4]`` and gsplat <= 1.4's unbatched ``means [N, 3]``, ``viewmats [C, 4, 4]``.
``gsplat_version`` picks the radius rule (and ``meta["radii"]``'s shape) and the compositing
constants (max alpha 0.99 from 1.6, 0.999 before) of that release; left at ``None`` the
adapter follows :func:`dego.splat`'s defaults (the ``"gsplat<=1.4"`` radius rule, max alpha
0.999), so the same Gaussians give the same images through both entry points. With
``sh_degree``, ``colors`` are spherical-harmonics coefficients, evaluated per camera by
:func:`dego.spherical_harmonics` as gsplat does.
"""

from __future__ import annotations

import inspect
import math
import operator
from typing import Any, Literal

import torch
from torch import Tensor

from dego._compile import eager_only
from dego._policy import float32_under_autocast
from dego.gaussians import GaussianSet
from dego.spherical_harmonics import MAX_DEGREE, spherical_harmonics
from dego.splatting import gsplat_backend, pipeline
from dego.splatting.projection import Projection
from dego.splatting.tiles import tile_grid_shape
from dego.splatting.types import Backend, SplatConfig

RenderMode = Literal["RGB", "D", "ED", "RGB+D", "RGB+ED"]
DEPTH_MODES = {"RGB": "none", "D": "accumulated", "ED": "expected"}
DEPTH_MODES |= {"RGB+D": "accumulated", "RGB+ED": "expected"}

# gsplat options dego does not implement: their no-op value and what to do instead.
_UNSUPPORTED: dict[str, tuple[Any, str]] = {
    "camera_model": ("pinhole", "dego renders pinhole cameras only: undistort the images"),
    "covars": (None, "pass quats and scales (GaussianSet.from_tensors converts conventions)"),
    "distributed": (False, "render each rank's cameras on that rank and gather the images"),
    "with_ut": (False, "the unscented transform is not implemented: use pinhole cameras"),
    "with_eval3d": (False, "3D evaluation of the Gaussians is not implemented"),
    "radial_coeffs": (None, "lens distortion is not implemented: undistort the images"),
    "tangential_coeffs": (None, "lens distortion is not implemented: undistort the images"),
    "thin_prism_coeffs": (None, "lens distortion is not implemented: undistort the images"),
    "ftheta_coeffs": (None, "f-theta cameras are not implemented: undistort the images"),
    "rolling_shutter": ("GLOBAL", "rolling shutter is not implemented: use a global shutter"),
    "viewmats_rs": (None, "rolling shutter is not implemented: use a global shutter"),
}
# The radius rule dego.splat applies when SplatConfig.radius_rule is None (its default).
SPLAT_RADIUS_RULE = "gsplat<=1.4"
# Memory or speed knobs of gsplat's kernels: accepted, and the values are the same.
_LAYOUT_ONLY = ("channel_chunk", "segmented")


def _is_default(name: str, value: Any) -> bool:
    default = _UNSUPPORTED[name][0]
    if name == "rolling_shutter":  # gsplat's RollingShutterType enum, or its name / value
        return value is None or getattr(value, "name", value) in ("GLOBAL", "global", 0)
    if default is None:
        return value is None
    return bool(value == default)


def _release(gsplat_version: str) -> tuple[int, int]:
    """``(1, minor)`` of a gsplat 1.x release string such as ``"1.5.3"``."""
    parts = str(gsplat_version).split(".")
    try:
        major, minor = int(parts[0]), int(parts[1]) if len(parts) > 1 else 0
    except ValueError:
        major, minor = -1, -1
    if major != 1 or minor < 0:
        raise ValueError(
            f"gsplat_version: expected a gsplat 1.x release such as '1.4' or '1.5.3', "
            f"got {gsplat_version!r}"
        )
    return major, minor


def options_of_release(gsplat_version: str) -> dict[str, Any]:
    """The SplatConfig fields a gsplat release fixes: its radius rule and compositing constants."""
    return gsplat_backend.release_options(_release(gsplat_version))


def _options(gsplat_version: str | None) -> dict[str, Any]:
    """``options_of_release``, or with ``None`` the values ``dego.splat`` uses by default."""
    if gsplat_version is not None:
        return options_of_release(gsplat_version)
    defaults = SplatConfig()
    return {
        "radius_rule": defaults.radius_rule or SPLAT_RADIUS_RULE,
        "max_alpha": defaults.max_alpha,
        "alpha_min": defaults.alpha_min,
        "transmittance_min": defaults.transmittance_min,
    }


def _colors_layout(
    colors: Any, batch: tuple[int, ...], cameras: int, n: int, sh_degree: int | None
) -> bool:
    """Check ``colors`` against the layouts gsplat accepts; return whether it is per camera."""
    if not isinstance(colors, Tensor) or not colors.is_floating_point():
        raise TypeError(f"colors: expected a floating-point tensor, got {type(colors).__name__}")
    lead = "".join(f"{b}, " for b in batch)
    raw = f"[{lead}{n}, D] or [{lead}{cameras}, {n}, D] (post-activation colours, sh_degree=None)"
    sh = f"[{lead}{n}, K, 3] or [{lead}{cameras}, {n}, K, 3] (SH coefficients, with sh_degree)"
    shape = tuple(colors.shape)
    trailing = 1 if sh_degree is None else 2
    prefix = shape[: len(shape) - trailing]
    per_camera = prefix == (*batch, cameras, n)
    ok = per_camera or prefix == (*batch, n)
    if sh_degree is not None:
        ok = ok and shape[-1] == 3
    if not ok:
        accepted = f"{raw}, or {sh}" if sh_degree is None else f"{sh}, or {raw}"
        raise ValueError(f"colors: expected shape {accepted}; got {list(shape)}")
    return per_camera


def _evaluate_sh(
    sh_degree: int, coefficients: Tensor, means: Tensor, viewmats: Tensor, per_camera: bool
) -> Tensor:
    """gsplat's SH colours ``[..., C, N, 3]``: evaluated along camera centre -> mean, + 0.5,
    clamped at 0."""
    rotation, translation = viewmats[..., :3, :3], viewmats[..., :3, 3]
    centres = -(rotation.transpose(-1, -2) @ translation.unsqueeze(-1)).squeeze(-1)  # [..., C, 3]
    directions = means.unsqueeze(-3) - centres.unsqueeze(-2)  # [..., C, N, 3]
    directions = directions.to(coefficients.dtype)
    # a Gaussian at a camera's centre has no view direction; it lies behind the near plane,
    # so its colour is never drawn: any direction serves (spherical_harmonics refuses zero)
    at_centre = (directions == 0).all(-1, keepdim=True)
    directions = torch.where(at_centre, torch.ones_like(directions), directions)
    if not per_camera:  # [..., N, K, 3] -> [..., C, N, K, 3]
        coefficients = coefficients.unsqueeze(-4).expand(
            *directions.shape[:-1], *coefficients.shape[-2:]
        )
    return torch.clamp_min(spherical_harmonics(sh_degree, directions, coefficients) + 0.5, 0.0)


def _check_shape(name: str, tensor: Any, expected: tuple[int | str, ...]) -> None:
    """``tensor`` must be a floating tensor of shape ``expected`` (ints fixed, str free)."""
    if not isinstance(tensor, Tensor) or not tensor.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got {type(tensor).__name__}")
    shape = tuple(tensor.shape)
    ok = len(shape) == len(expected) and all(
        isinstance(e, str) or s == e for s, e in zip(shape, expected, strict=True)
    )
    if not ok:
        described = ", ".join(str(e) for e in expected)
        raise ValueError(f"{name}: expected shape [{described}], got {list(shape)}")


# Under torch.compile the adapter runs eagerly, as one graph break: its gsplat-layout
# bookkeeping (``retain_grad`` on ``meta["means2d"]``, the packed layout's data-dependent
# ``nonzero``) cannot be traced. ``dego.splat`` is the compile-friendly entry point.
@eager_only
@float32_under_autocast()
def rasterization(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,  # noqa: N803 - gsplat's name
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    packed: bool = True,
    tile_size: int = 16,
    backgrounds: Tensor | None = None,
    render_mode: RenderMode = "RGB",
    sparse_grad: bool = False,
    absgrad: bool = False,
    rasterize_mode: Literal["classic", "antialiased"] = "classic",
    camera_model: str = "pinhole",
    *,
    gsplat_version: str | None = None,
    backend: Backend = "torch",
    **rest: Any,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """gsplat's ``rasterization``, computed by :func:`dego.splat` (any device).

    Args:
        means: ``[..., N, 3]`` (or ``[N, 3]``, gsplat <= 1.4).
        quats: ``[..., N, 4]`` wxyz, any norm.
        scales: ``[..., N, 3]`` standard deviations (not log-scales).
        opacities: ``[..., N]`` in [0, 1] (not logits).
        colors: post-activation ``[..., N, D]`` or per camera ``[..., C, N, D]``; with
            ``sh_degree``, SH coefficients ``[..., N, K, 3]`` or ``[..., C, N, K, 3]``.
        viewmats: ``[..., C, 4, 4]`` world-to-camera, OpenCV axes.
        Ks: ``[..., C, 3, 3]`` pinhole intrinsics.
        width: image width in pixels (gsplat passes width before height).
        height: image height in pixels.
        near_plane: cull Gaussians whose camera z is below this.
        far_plane: cull Gaussians whose camera z is above this.
        radius_clip: skip Gaussians whose pixel radius is at most this on every axis.
        eps2d: screen-space dilation of the 2D covariance (pixels^2).
        sh_degree: None (``colors`` are colours), or the SH degree (0-4, with
            ``(sh_degree + 1)^2 <= K``) at which to evaluate the coefficients ``colors``
            along each camera centre -> mean direction, as gsplat: the colour is
            ``max(SH + 0.5, 0)`` (:func:`dego.spherical_harmonics`).
        packed: the layout of ``meta``: packed ``[nnz, ...]`` entries with
            ``camera_ids`` / ``gaussian_ids`` (and ``batch_ids``), as gsplat, or dense
            ``[..., C, N, ...]``; the images are the same.
        tile_size: tile edge in pixels.
        backgrounds: ``[..., C, D]``; depth channels get no background, as gsplat.
        sparse_grad: gsplat's sparse-gradient layout; accepted, the gradients are dense.
        render_mode: ``"RGB"``, ``"D"`` (accumulated depth), ``"ED"`` (expected depth),
            ``"RGB+D"`` or ``"RGB+ED"`` (depth appended as the last channel).
        absgrad: after backward, ``meta["means2d"].absgrad`` holds the summed absolute
            per-pixel screen-space gradients (AbsGS), as gsplat.
        rasterize_mode: ``"classic"`` or ``"antialiased"``.
        camera_model: must be ``"pinhole"``.
        gsplat_version: the gsplat release whose rules to follow: below 1.5 one radius
            per Gaussian (``meta["radii"]`` ``[..., C, N]``), from 1.5 per-axis,
            opacity-aware radii (``[..., C, N, 2]``); from 1.6 alpha is capped at 0.99
            (0.999 before). Default ``None``: :func:`dego.splat`'s defaults, i.e. the
            ``"gsplat<=1.4"`` radius rule (``meta["radii"]`` ``[..., C, N]``) and max alpha
            0.999, so both entry points give the same images; pass ``"1.5"`` for gsplat
            1.5's radii.
        backend: dego's compositing: ``"torch"`` (any device), ``"triton"`` (the Triton
            kernels, CUDA; ``pip install -e ".[triton]"``) or ``"auto"`` (Triton
            when usable, else torch); see :func:`dego.splat`. gsplat's own kernels are not
            offered here: this adapter is for code that runs without gsplat.
        **rest: gsplat's other keywords: ``channel_chunk`` and ``segmented`` are accepted
            (no effect on the values); distortion, rolling-shutter, unscented-transform,
            ``covars`` and ``distributed`` raise ``NotImplementedError`` unless left at
            their defaults; anything else raises ``TypeError``.

    Returns:
        ``(render_colors [..., C, H, W, X], render_alphas [..., C, H, W, 1], meta)`` with
        ``X = D``, ``D + 1`` (depth last) or 1 (depth alone); ``meta`` holds ``radii``,
        ``means2d`` (in the graph: ``retain_grad()`` works), ``depths``, ``conics``,
        ``opacities``, ``camera_ids``, ``gaussian_ids``, ``batch_ids``, ``width``,
        ``height``, ``tile_size``, ``tile_width``, ``tile_height``, ``n_cameras``,
        ``n_batches``. gsplat's tile-intersection buffers (``isect_ids``, ...) are not
        produced.
    """
    for name, value in rest.items():
        if name in _UNSUPPORTED:
            if not _is_default(name, value):
                raise NotImplementedError(f"{name}={_describe(value)}: {_UNSUPPORTED[name][1]}")
        elif name not in _LAYOUT_ONLY:
            named = [p for p in inspect.signature(rasterization).parameters if p != "rest"]
            accepted = sorted({*named, *_UNSUPPORTED, *_LAYOUT_ONLY})
            raise TypeError(
                f"rasterization() got an unexpected keyword {name!r}; accepted: "
                + ", ".join(accepted)
            )
    if not _is_default("camera_model", camera_model):
        raise NotImplementedError(
            f"camera_model={camera_model!r}: {_UNSUPPORTED['camera_model'][1]}"
        )
    if sh_degree is not None and (
        isinstance(sh_degree, bool)
        or not isinstance(sh_degree, int)
        or not 0 <= sh_degree <= MAX_DEGREE
    ):
        raise ValueError(
            f"sh_degree: expected None or an int in 0..{MAX_DEGREE}, got {sh_degree!r}"
        )
    if render_mode not in DEPTH_MODES:
        raise ValueError(f"render_mode: expected one of {list(DEPTH_MODES)}, got {render_mode!r}")
    release_options = _options(gsplat_version)
    radius_rule = release_options["radius_rule"]
    try:
        width, height = operator.index(width), operator.index(height)
    except TypeError as err:
        raise TypeError(f"width, height: expected ints, got {width!r}, {height!r}") from err

    if not isinstance(means, Tensor) or means.ndim < 2:
        raise ValueError("means: expected a tensor of shape [..., N, 3]")
    batch, n = tuple(means.shape[:-2]), means.shape[-2]
    _check_shape("means", means, (*batch, n, 3))
    _check_shape("quats", quats, (*batch, n, 4))
    _check_shape("scales", scales, (*batch, n, 3))
    if isinstance(opacities, Tensor) and opacities.shape == (*batch, n, 1):
        raise ValueError(
            f"opacities: expected shape [..., N], got {list(opacities.shape)}; "
            "squeeze the trailing axis (opacities.squeeze(-1))"
        )
    _check_shape("opacities", opacities, (*batch, n))
    if not isinstance(viewmats, Tensor) or viewmats.ndim != len(batch) + 3:
        raise ValueError(
            f"viewmats: expected shape [..., C, 4, 4] with the means' batch {list(batch)}, "
            f"got {list(getattr(viewmats, 'shape', []))}"
        )
    cameras = viewmats.shape[-3]
    _check_shape("viewmats", viewmats, (*batch, cameras, 4, 4))
    _check_shape("Ks", Ks, (*batch, cameras, 3, 3))
    per_camera = _colors_layout(colors, batch, cameras, n, sh_degree)
    if sh_degree is not None:
        if (sh_degree + 1) ** 2 > colors.shape[-2]:
            raise ValueError(
                f"sh_degree: degree {sh_degree} needs (sh_degree + 1)^2 = {(sh_degree + 1) ** 2} "
                f"coefficients, but colors has K = {colors.shape[-2]} ([..., N, K, 3])"
            )
        colors = _evaluate_sh(sh_degree, colors, means, viewmats, per_camera)  # [..., C, N, 3]
        per_camera = True
    channels = colors.shape[-1]
    if backgrounds is not None:
        _check_shape("backgrounds", backgrounds, (*batch, cameras, channels))

    flat = math.prod(batch)
    gaussians = GaussianSet(
        means=means.reshape(flat, n, 3),
        quats=quats.reshape(flat, n, 4),
        scales=scales.reshape(flat, n, 3),
        opacities=opacities.reshape(flat, n),
    )
    depth_mode = DEPTH_MODES[render_mode]
    with_colors = render_mode.startswith("RGB")
    features = None
    if with_colors:
        shape = (flat, cameras, n, channels) if per_camera else (flat, n, channels)
        features = colors.reshape(shape)
    background = None
    if with_colors and backgrounds is not None:
        background = backgrounds.reshape(flat, cameras, channels)
    config = SplatConfig(
        near=near_plane,
        far=far_plane,
        eps2d=eps2d,
        tile_size=tile_size,
        depth_mode=depth_mode,  # type: ignore[arg-type]
        radius_clip=radius_clip,
        rasterize_mode=rasterize_mode,
        absgrad=absgrad,
        backend=backend,
        **release_options,
    )
    layout = _MetaLayout(batch, cameras, n, packed)
    try:
        out = pipeline.render(
            gaussians,
            viewmats.reshape(flat, cameras, 4, 4),
            Ks.reshape(flat, cameras, 3, 3),
            (height, width),
            features,
            background,
            config,
            layout="channels_last",
            means2d_hook=layout.means2d_for_compositing,
            absgrad_sink=layout.receive_absgrad,
        )
    except (ValueError, TypeError) as error:
        raise type(error)(_in_gsplat_words(str(error))) from None
    # a crop to a size that is not a multiple of the tile leaves a strided view
    render_colors = out.image.contiguous().reshape(*batch, cameras, height, width, -1)
    render_alphas = out.alpha.reshape(*batch, cameras, height, width, 1)
    meta = layout.meta(out.projection, radius_rule)
    tiles_y, tiles_x = tile_grid_shape((height, width), tile_size)
    meta |= {"width": width, "height": height, "tile_size": tile_size}
    meta |= {"tile_width": tiles_x, "tile_height": tiles_y}
    meta |= {"n_cameras": cameras, "n_batches": flat}
    return render_colors, render_alphas, meta


_GSPLAT_NAMES = {
    "gaussians.means": "means",
    "gaussians.quats": "quats",
    "gaussians.scales": "scales",
    "gaussians.opacities": "opacities",
    "world_to_cam": "viewmats",
    "intrinsics": "Ks",
    "features": "colors",
    "background": "backgrounds",
}
"""The names dego's splatter reports -> the arguments a gsplat caller passed."""


def _in_gsplat_words(message: str) -> str:
    """A splatter error as a caller of gsplat's ``rasterization`` wrote the call: its
    argument names, and for opacities outside [0, 1] the sigmoid that gsplat expects."""
    name, colon, rest = message.partition(":")
    if colon and name in _GSPLAT_NAMES:
        message = _GSPLAT_NAMES[name] + colon + rest
    message = message.replace("the gaussians' ", "means' ")
    if message.startswith("opacities:") and "outside [0, 1]" in message:
        message = message.split("; ")[0] + (  # dego's own hint names GaussianSet.from_tensors
            "; rasterization() takes opacities in [0, 1], as gsplat does: pass "
            "torch.sigmoid(logits) for logits"
        )
    return message


def _describe(value: object) -> str:
    """A short description of an argument for an error message (never a whole tensor)."""
    if isinstance(value, Tensor):
        return f"<tensor of shape {list(value.shape)}>"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


class _MetaLayout:
    """Puts the per (camera, Gaussian) projection into gsplat's ``meta`` layout, dense
    ``[..., C, N, ...]`` or packed ``[nnz, ...]``, such that ``meta["means2d"]`` is the
    tensor the compositing reads (so its ``.grad`` and ``.absgrad`` are gsplat's)."""

    def __init__(self, batch: tuple[int, ...], cameras: int, n: int, packed: bool) -> None:
        self.batch, self.cameras, self.n, self.packed = batch, cameras, n, packed
        self.means2d: Tensor | None = None
        self.ids: tuple[Tensor, ...] | None = None

    def means2d_for_compositing(self, projection: Projection) -> Tensor:
        """The projected means ``(B, C, N, 2)``, read through ``meta``'s tensor."""
        dense = projection.means2d
        if not self.packed:
            self.means2d = dense.reshape(*self.batch, self.cameras, self.n, 2)
            if self.means2d.requires_grad:
                self.means2d.retain_grad()
            return self.means2d.reshape(dense.shape)
        self.ids = projection.visible.nonzero(as_tuple=True)
        self.means2d = dense[self.ids]
        if self.means2d.requires_grad:
            self.means2d.retain_grad()
        # Culled entries are never composited, so zeros may stand in for them.
        return torch.zeros_like(dense.detach()).index_put(self.ids, self.means2d)

    def receive_absgrad(self, total: Tensor) -> None:
        """Backward's summed absolute gradients ``(B * C * N, 2)`` -> ``means2d.absgrad``."""
        assert self.means2d is not None
        flat = total.view(-1, self.cameras, self.n, 2)
        self.means2d.absgrad = (  # type: ignore[attr-defined]
            flat[self.ids] if self.packed else flat.view_as(self.means2d)
        )

    def meta(self, projection: Projection, radius_rule: str) -> dict[str, Any]:
        radii = projection.radii_xy if radius_rule == "gsplat>=1.5" else projection.radii
        assert projection.opacities is not None  # the adapter always passes opacities
        fields: dict[str, Tensor] = {
            "radii": radii,
            "depths": projection.depths,
            "conics": projection.conics,
            "opacities": projection.opacities,
        }
        ids: dict[str, Tensor | None] = {"batch_ids": None, "camera_ids": None}
        ids["gaussian_ids"] = None
        if self.packed:
            assert self.ids is not None
            b, c, g = self.ids
            fields = {name: value[b, c, g] for name, value in fields.items()}
            ids = {"batch_ids": b, "camera_ids": c, "gaussian_ids": g}
        else:
            shape = (*self.batch, self.cameras, self.n)
            fields = {
                name: value.reshape(*shape, *value.shape[3:]) for name, value in fields.items()
            }
        return {**ids, **fields, "means2d": self.means2d}


__all__ = ["rasterization"]
