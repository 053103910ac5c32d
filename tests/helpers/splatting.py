"""Helpers of tests/splatting/test_splatting.py, also used by

- tests/compat/test_dego.py
- tests/compat/test_gsplat.py
- tests/splatting/test_options.py
- tests/splatting/test_policy.py
- tests/splatting/test_options_parity.py
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch
from hypothesis import strategies as st
from torch import Tensor

import dego
from dego import GaussianSet
from dego.splatting import SplatOutput, splat
from tests.helpers.strategies import random_quaternions
from tests.reference.splat import reference_splat

REFERENCE_KEYS = (
    "near",
    "far",
    "eps2d",
    "max_alpha",
    "alpha_min",
    "transmittance_min",
    "radius_sigma",
    "tile_size",
    "depth_mode",
    "radius_rule",
    "radius_clip",
    "rasterize_mode",
)

# ---------------------------------------------------------------------------------------
# scene helpers
# ---------------------------------------------------------------------------------------


def axis_angle_matrix(axis: Tensor, angle: float) -> Tensor:
    """Rotation matrix ``(3, 3)`` about ``axis`` (any non-zero length) by ``angle`` radians."""
    axis = axis / torch.linalg.vector_norm(axis)
    quat = torch.cat(
        [torch.tensor([math.cos(angle / 2)], dtype=axis.dtype), axis * math.sin(angle / 2)]
    )
    return dego.quaternions_to_rotation_matrices(quat)


def make_cameras(
    batch: int,
    views: int,
    image_size: tuple[int, int],
    *,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
) -> tuple[Tensor, Tensor]:
    """``(world_to_cam (B,V,4,4), K (B,V,3,3))``: view 0 is the identity camera at the origin
    looking along +z, later views are slightly rotated (<= 0.15 rad) and translated (<= 0.3 m).
    Intrinsics vary per image (fx != fy, principal point off-centre)."""
    height, width = image_size
    g = torch.Generator().manual_seed(seed)
    w2c = torch.eye(4, dtype=torch.float64).repeat(batch, views, 1, 1)
    intrinsics = torch.zeros(batch, views, 3, 3, dtype=torch.float64)
    for b in range(batch):
        for v in range(views):
            if v > 0:
                angle = 0.15 * (2 * torch.rand((), generator=g, dtype=torch.float64).item() - 1)
                axis = torch.randn(3, generator=g, dtype=torch.float64)
                w2c[b, v, :3, :3] = axis_angle_matrix(axis, angle)
                w2c[b, v, :3, 3] = 0.3 * (2 * torch.rand(3, generator=g, dtype=torch.float64) - 1)
            r = torch.rand(4, generator=g, dtype=torch.float64)
            fx = 0.8 * width * (0.9 + 0.2 * r[0])
            fy = fx * (0.9 + 0.2 * r[1])
            cx = width * (0.4 + 0.2 * r[2])
            cy = height * (0.4 + 0.2 * r[3])
            intrinsics[b, v] = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return w2c.to(device=device, dtype=dtype), intrinsics.to(device=device, dtype=dtype)


def make_scene_gaussians(
    batch: int,
    n: int,
    image_size: tuple[int, int],
    *,
    seed: int = 0,
    feature_dim: int | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
    culled: bool = False,
    near_plane: bool = False,
    opacity_range: tuple[float, float] = (0.05, 0.95),
    scale_range: tuple[float, float] = (0.05, 0.5),
    depth_range: tuple[float, float] = (2.0, 10.0),
    spread: float = 2.0,
) -> GaussianSet:
    """Random Gaussians in front of the identity camera: z in ``depth_range``, projections
    spread over ``spread`` times the image extent around its centre (with the default 2, some
    fall outside the image and beyond the Jacobian's clamp). ``culled`` moves about a quarter
    behind the camera (z < 0.01) or to z in [11, 14]; ``near_plane`` moves about a sixth to
    z in [0.02, 0.5] (footprints larger than the image)."""
    height, width = image_size
    g = torch.Generator().manual_seed(seed)

    def rand(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=g, dtype=torch.float64)

    focal = 0.8 * width
    z = depth_range[0] + (depth_range[1] - depth_range[0]) * rand(batch, n)
    u = (spread * (rand(batch, n) - 0.5) + 0.5) * width
    v = (spread * (rand(batch, n) - 0.5) + 0.5) * height
    kind = rand(batch, n)
    if culled:
        z = torch.where(kind < 0.125, -3 + 3.005 * rand(batch, n), z)
        z = torch.where((kind >= 0.125) & (kind < 0.25), 11 + 3 * rand(batch, n), z)
    if near_plane:
        z = torch.where(kind > 5 / 6, 0.02 + 0.48 * rand(batch, n), z)
    means = torch.stack([(u - width / 2) * z / focal, (v - height / 2) * z / focal, z], dim=-1)
    lo, hi = math.log(scale_range[0]), math.log(scale_range[1])
    scales = torch.exp(lo + (hi - lo) * rand(batch, n, 3))
    opacities = opacity_range[0] + (opacity_range[1] - opacity_range[0]) * rand(batch, n)
    features = None
    if feature_dim is not None:
        features = torch.randn(batch, n, feature_dim, generator=g, dtype=torch.float64)
    gs = GaussianSet(
        means=means,
        quats=random_quaternions((batch, n), g, torch.float64),
        scales=scales,
        opacities=opacities,
        features=features,
    )
    return gs.to(device=device, dtype=dtype)


@dataclasses.dataclass(frozen=True)
class Scene:
    """Everything one ``splat`` call needs."""

    gaussians: GaussianSet
    world_to_cam: Tensor
    intrinsics: Tensor
    image_size: tuple[int, int]
    features: Tensor | None = None
    background: Tensor | None = None
    config: dict[str, Any] = dataclasses.field(default_factory=dict)

    def replace(self, **changes: Any) -> Scene:
        return dataclasses.replace(self, **changes)

    def to(self, target: torch.dtype | torch.device | str) -> Scene:
        """Every tensor in another dtype or on another device."""

        def cast(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.to(target)

        return self.replace(
            gaussians=self.gaussians.to(target),
            world_to_cam=self.world_to_cam.to(target),
            intrinsics=self.intrinsics.to(target),
            features=cast(self.features),
            background=cast(self.background),
        )


def render(scene: Scene, **overrides: Any) -> SplatOutput:
    """The implementation under test."""
    return splat(
        scene.gaussians,
        scene.world_to_cam,
        scene.intrinsics,
        scene.image_size,
        features=scene.features,
        background=scene.background,
        **{**scene.config, **overrides},
    )


def render_reference(scene: Scene, **overrides: Any) -> Any:
    """The dense oracle of ``tests/reference/splat.py``."""
    config = {k: v for k, v in {**scene.config, **overrides}.items() if k in REFERENCE_KEYS}
    return reference_splat(
        scene.gaussians,
        scene.world_to_cam,
        scene.intrinsics,
        scene.image_size,
        features=scene.features,
        background=scene.background,
        **config,
    )


def with_grad(scene: Scene) -> tuple[Scene, dict[str, Tensor]]:
    """A copy of ``scene`` whose Gaussian fields, features and background are fresh leaves."""
    gs = scene.gaussians
    leaves = {
        name: getattr(gs, name).detach().clone().requires_grad_(True)
        for name in GaussianSet.FIELDS
        if getattr(gs, name) is not None
    }
    changes: dict[str, Any] = {"gaussians": GaussianSet(**leaves)}
    for name in ("features", "background"):
        if getattr(scene, name) is not None:
            leaves[f"{name}_arg"] = getattr(scene, name).detach().clone().requires_grad_(True)
            changes[name] = leaves[f"{name}_arg"]
    return scene.replace(**changes), leaves


def weighted_sum(out: Any, seed: int = 0) -> Tensor:
    """A scalar that depends on every output pixel through random weights."""
    g = torch.Generator().manual_seed(seed)

    def weights(t: Tensor) -> Tensor:
        return torch.randn(t.shape, generator=g, dtype=torch.float64).to(t)

    total = (out.features * weights(out.features)).sum() + (out.alpha * weights(out.alpha)).sum()
    if out.depth is not None:
        total = total + (out.depth * weights(out.depth)).sum()
    return total


def gradients(scene: Scene, renderer: Any, seed: int = 0, **overrides: Any) -> dict[str, Tensor]:
    """Gradients of :func:`weighted_sum` w.r.t. every input leaf (zeros where unused)."""
    scene, leaves = with_grad(scene)
    loss = weighted_sum(renderer(scene, **overrides), seed)
    if not loss.requires_grad:  # the reference detaches when every Gaussian is culled
        return {name: torch.zeros_like(leaf) for name, leaf in leaves.items()}
    grads = torch.autograd.grad(loss, list(leaves.values()), allow_unused=True)
    return {
        name: torch.zeros_like(leaf) if grad is None else grad
        for (name, leaf), grad in zip(leaves.items(), grads, strict=True)
    }


def assert_outputs_close(out: Any, expected: Any, *, rtol: float, atol: float) -> None:
    assert out.features.shape == expected.features.shape
    torch.testing.assert_close(out.features, expected.features, rtol=rtol, atol=atol)
    torch.testing.assert_close(out.alpha, expected.alpha, rtol=rtol, atol=atol)
    if expected.depth is None:
        assert out.depth is None
    else:
        torch.testing.assert_close(out.depth, expected.depth, rtol=rtol, atol=atol)
    assert torch.equal(out.radii.long(), expected.radii.long())


RULES = [
    {},
    # tight 2-sigma tile rectangles: the tile truncation often drops visible alpha
    {"radius_sigma": 2.0, "alpha_min": 1e-3},
    # early termination, a lower alpha cap and less blur
    {"transmittance_min": 1e-2, "max_alpha": 0.99, "eps2d": 0.1},
]
IMAGE_SIZES = [(20, 36), (32, 48), (17, 23)]


@st.composite
def scenes(
    draw: st.DrawFn,
    *,
    max_n: int = 30,
    max_batch: int = 2,
    max_views: int = 2,
    culling: bool = True,
    dtype: torch.dtype = torch.float64,
) -> Scene:
    """Random scenes: batch, views, N (0 included), image size, tiles, features, background,
    near/far, chunking and depth mode are all drawn."""
    batch = draw(st.integers(1, max_batch))
    views = draw(st.integers(1, max_views))
    n = draw(st.integers(0, max_n))
    image_size = draw(st.sampled_from(IMAGE_SIZES))
    channels = draw(st.integers(0, 3))
    feature_source = draw(st.sampled_from(["gaussians", "argument", "override"]))
    background_kind = draw(st.sampled_from(["none", "shared", "per_view"]))
    seed = draw(st.integers(0, 2**31 - 1))
    culled = culling and draw(st.booleans())
    near_plane = culling and draw(st.booleans())
    # "clustered": large, opaque Gaussians packed into the image so that pixels terminate
    # (T <= transmittance_min) and 3-sigma tile rectangles cut off visible alpha.
    clustered = draw(st.booleans())
    g = torch.Generator().manual_seed(seed + 1)

    gs = make_scene_gaussians(
        batch,
        n,
        image_size,
        seed=seed,
        feature_dim=channels if feature_source == "gaussians" and channels else None,
        culled=culled,
        near_plane=near_plane,
        opacity_range=(0.6, 1.0) if clustered else (0.05, 0.95),
        scale_range=(0.3, 2.0) if clustered else (0.05, 0.5),
        spread=0.8 if clustered else 2.0,
    )
    features = None
    if feature_source != "gaussians" and channels:
        features = torch.randn(batch, n, channels, generator=g, dtype=torch.float64)
        if feature_source == "override":
            other = torch.randn(batch, n, channels + 1, generator=g, dtype=torch.float64)
            gs = gs.replace(features=other)
    background = None
    if background_kind == "shared":
        background = torch.randn(channels, generator=g, dtype=torch.float64)
    elif background_kind == "per_view":
        background = torch.randn(batch, views, channels, generator=g, dtype=torch.float64)
    w2c, intrinsics = make_cameras(batch, views, image_size, seed=seed)
    config = {
        "tile_size": draw(st.sampled_from([8, 16])),
        "near": draw(st.sampled_from([0.01, 2.5])) if culling else 0.01,
        "far": draw(st.sampled_from([1e10, 10.5])) if culling else 1e10,
        "depth_mode": draw(st.sampled_from(["expected", "accumulated", "none"])),
        "chunk_size": draw(st.sampled_from([1, 4, 32])),
        "max_pairs": draw(st.sampled_from([256, 2**22])),
        **draw(st.sampled_from(RULES)),
    }
    scene = Scene(gs, w2c, intrinsics, image_size, features, background, config)
    return scene.to(dtype)


def small_scene(
    *, seed: int = 0, batch: int = 2, views: int = 2, n: int = 12, channels: int | None = 3
) -> Scene:
    image_size = (20, 36)
    gs = make_scene_gaussians(batch, n, image_size, seed=seed, feature_dim=channels, culled=True)
    w2c, intrinsics = make_cameras(batch, views, image_size, seed=seed)
    return Scene(gs, w2c, intrinsics, image_size)
