"""The splatter's checks of a call, before anything is allocated: argument names (gsplat's
and misspelt ones), camera layouts, shapes, dtypes and devices, values (one host sync) and
the memory estimate."""

from __future__ import annotations

import functools
import inspect
import math
import operator
from collections.abc import Callable
from typing import Any, TypeVar

import torch
from torch import Tensor

from dego._options import check_option_names
from dego._policy import (
    Check,
    check_dtype,
    check_memory,
    compute_dtype,
    finite_check,
    gaussian_value_checks,
    run_checks,
)
from dego.gaussians import GaussianSet
from dego.splatting.types import SplatConfig

F = TypeVar("F", bound=Callable[..., Any])

_TO_COMPAT = "; or call dego.compat.gsplat.rasterization, which takes gsplat's names and layout"
GSPLAT_KEYWORDS = {
    name: hint + _TO_COMPAT
    for name, hint in {
        "viewmats": "world_to_cam",
        "Ks": "intrinsics",
        "width": "image_size=(height, width)",
        "height": "image_size=(height, width)",
        "colors": "features",
        "near_plane": "near",
        "far_plane": "far",
        "backgrounds": "background",
        "render_mode": "depth_mode ('RGB+D' is 'accumulated', 'RGB+ED' is 'expected')",
    }.items()
}
"""gsplat's keyword names -> what dego calls them (the ``foreign`` hints of the options)."""


def image_size(value: object) -> tuple[int, int]:
    """``(H, W)`` as Python ints from any pair of ints (numpy ints, ``torch.Size``)."""
    try:
        height, width = (operator.index(v) for v in value)  # type: ignore[attr-defined]
        ok = not any(isinstance(v, bool) for v in value) and height > 0 and width > 0  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"image_size: expected (H, W), two positive ints, got {value!r}")
    return height, width


def check_call(name: str, cameras_at: int, *, options: bool) -> Callable[[F], F]:
    """Friendly errors for the mistakes ports from gsplat make, before the shape checks:
    gsplat's keyword names, unknown option names (with the closest valid one, when
    ``options``: the function takes :class:`SplatConfig`'s options as keywords) and cameras
    with extra leading axes (``(B, T, V, 4, 4)``)."""

    def decorate(fn: F) -> F:
        arguments = set(inspect.signature(fn).parameters)

        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            names = [key for key in kwargs if key not in arguments]
            if options:
                check_option_names(f"{name}()", names, SplatConfig, foreign=GSPLAT_KEYWORDS)
            else:
                foreign = [key for key in names if key in GSPLAT_KEYWORDS]
                check_option_names(f"{name}()", foreign, SplatConfig, foreign=GSPLAT_KEYWORDS)
            cameras = list(args[cameras_at : cameras_at + 2])
            cameras += [kwargs.get(k) for k in ("world_to_cam", "intrinsics")[len(cameras) :]]
            for arg, (label, tail) in zip(
                cameras, (("world_to_cam", (4, 4)), ("intrinsics", (3, 3))), strict=True
            ):
                if not isinstance(arg, Tensor):
                    continue
                if arg.ndim != 4 or tuple(arg.shape[-2:]) != tail:
                    raise ValueError(
                        f"{label}: expected shape (B, V, {tail[0]}, {tail[1]}), got "
                        f"{tuple(arg.shape)}"
                        + (_camera_advice(label, arg.ndim) or _matrix_advice(label, arg.shape))
                    )
            size = args[cameras_at + 2] if len(args) > cameras_at + 2 else kwargs.get("image_size")
            if size is not None:
                image_size(size)  # one line in the caller's words, before the type checks
            return fn(*args, **kwargs)

        return wrapper  # type: ignore[return-value]

    return decorate


def _camera_advice(label: str, ndim: int) -> str:
    if ndim > 4:
        return (
            "; flatten the leading axes into one batch axis, e.g. (B, T, V) "
            "-> (B * T, V) with .flatten(0, 1), and the Gaussians likewise "
            "(GaussianSet.flatten_batch())"
        )
    if ndim == 3:  # (V, ...): one batch
        return f"; add the batch axis B, e.g. {label}[None]"
    if ndim == 2:  # one matrix: one batch of one camera
        return f"; add the batch and camera axes B, V, e.g. {label}[None, None]"
    return ""


def _matrix_advice(label: str, shape: torch.Size) -> str:
    """What to pass instead of a matrix of the wrong size."""
    rows, cols = tuple(shape[-2:])
    if label == "intrinsics" and (rows, cols) == (4, 4):
        return "; pass the 3 x 3 part, intrinsics[..., :3, :3]"
    if label == "intrinsics" and (rows, cols) == (3, 4):
        return (
            "; a 3 x 4 projection matrix holds intrinsics and pose: split it with "
            "dego.split_projection"
        )
    if label == "world_to_cam" and (rows, cols) == (3, 4):
        return "; append the row [0, 0, 0, 1] to make the 4 x 4 matrix"
    return ""


def _matrix_rows_ok(matrix: Tensor, expected_last_row: list[float]) -> Tensor:
    """Whether the last row of each ``(..., k, k)`` matrix is ``expected_last_row``."""
    expected = torch.tensor(expected_last_row, dtype=matrix.dtype, device=matrix.device)
    return ((matrix[..., -1, :] - expected).abs() <= 1e-6).all(-1)


def _fail(message: str) -> Callable[[], Exception]:
    return lambda: ValueError(message)


def _check(ok: Tensor, message: str) -> Check:
    return ok, message, _fail(message)


def check_inputs(
    gaussians: GaussianSet,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    size: tuple[int, int],
    features: Tensor | None,
    background: Tensor | None,
) -> None:
    """Shapes, dtypes and devices of a call, then every value check in one host sync
    (none under torch.compile)."""
    if len(gaussians.batch_shape) != 1:
        raise ValueError(
            f"gaussians: expected batch shape (B,), got {tuple(gaussians.batch_shape)}; "
            "flatten extra axes with GaussianSet.flatten_batch()"
        )
    b, n = gaussians.batch_shape[0], gaussians.num_gaussians
    v = world_to_cam.shape[1]
    if world_to_cam.shape[0] != b:
        raise ValueError(f"world_to_cam: batch {world_to_cam.shape[0]} != gaussians' batch {b}")
    given = (("features", features), ("background", background))
    optional: list[tuple[str, Tensor]] = [(name, t) for name, t in given if t is not None]
    for name, t in [("world_to_cam", world_to_cam), ("intrinsics", intrinsics), *optional]:
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
    finite = [(f"gaussians.{name}", t) for name, t in gaussians.items() if name != "features"]
    run_checks(
        [finite_check(name, t) for name, t in finite + optional]
        + _camera_checks(world_to_cam, intrinsics, size)
        + gaussian_value_checks(
            "gaussians.",
            scales=gaussians.scales,
            opacities=gaussians.opacities,
            positive_scales=False,
        )
    )


def _camera_checks(world_to_cam: Tensor, intrinsics: Tensor, size: tuple[int, int]) -> list[Check]:
    height, width = size
    focal = torch.maximum(intrinsics[..., 0, 0].abs(), intrinsics[..., 1, 1].abs())
    cx, cy = intrinsics[..., 0, 2], intrinsics[..., 1, 2]
    outside = (cx < 0) | (cx > width) | (cy < 0) | (cy > height)
    transposed = outside & (cx >= 0) & (cx <= height) & (cy >= 0) & (cy <= width)
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
    return [
        _check(torch.isfinite(world_to_cam).all(), "world_to_cam: contains non-finite values"),
        _check(torch.isfinite(intrinsics).all(), "intrinsics: contains non-finite values"),
        _check(
            ((intrinsics[..., 0, 0] > 0) & (intrinsics[..., 1, 1] > 0)).all(),
            "intrinsics: focal lengths fx, fy must be positive",
        ),
        _check(
            ((intrinsics[..., 0, 1].abs() <= 1e-6 * focal) & (intrinsics[..., 1, 0] == 0)).all()
            & _matrix_rows_ok(intrinsics, [0.0, 0.0, 1.0]).all(),
            pinhole,
        ),
        _check(_matrix_rows_ok(world_to_cam, [0.0, 0.0, 0.0, 1.0]).all(), rigid),
        _check(~transposed.any(), transposed_message),
    ]


def check_splat_memory(
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


__all__ = [
    "GSPLAT_KEYWORDS",
    "check_call",
    "check_inputs",
    "check_splat_memory",
    "image_size",
]
