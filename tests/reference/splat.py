"""A dense, loop-based re-statement of the splatting rules, used only as a test oracle.

Written from the maths of the rasterizer's contract, not from its code: every image is
rendered on its own, every Gaussian is projected on its own (scalar tensors), and the
compositing loop walks the Gaussians front to back while working on all pixels at once.
Every Gaussian is evaluated on every pixel; the tile truncation of the contract (a
Gaussian only reaches the pixels of the tiles its ``radius`` rectangle overlaps) is
applied as an explicit mask. The result is differentiable by plain autograd.
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from dego import GaussianSet


@dataclasses.dataclass(frozen=True)
class ReferenceOutput:
    """Same fields and shapes as ``dego.splatting.SplatOutput``."""

    features: Tensor  # (B, V, C, H, W)
    depth: Tensor | None  # (B, V, H, W)
    alpha: Tensor  # (B, V, H, W)
    radii: Tensor  # (B, V, N), int64


@dataclasses.dataclass(frozen=True)
class Projected:
    """One Gaussian as seen by one camera."""

    mean2d: Tensor  # (2,) pixels
    conic: Tensor  # (3,) = (a, b, c) of the inverse 2D covariance [[a, b], [b, c]]
    depth: Tensor  # () camera z of the mean
    radius_xy: tuple[int, int]  # pixels per axis, > 0
    opacity: Tensor  # () opacity used by the compositing (antialiasing compensation applied)

    @property
    def radius(self) -> int:
        return max(self.radius_xy)


def project_gaussian(
    mean: Tensor,
    covariance: Tensor,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    height: int,
    width: int,
    *,
    near: float,
    far: float,
    eps2d: float,
    radius_sigma: float | None,
    opacity: Tensor,
    radius_rule: str = "gsplat<=1.4",
    radius_clip: float = 0.0,
    rasterize_mode: str = "classic",
) -> Projected | None:
    """Project a single Gaussian; ``None`` when it is culled (radius 0)."""
    rot, trans = world_to_cam[:3, :3], world_to_cam[:3, 3]
    x, y, z = rot @ mean + trans
    depth = float(z.detach())
    if depth < near or depth > far:
        return None
    cov_cam = rot @ covariance @ rot.T

    fx, fy = float(intrinsics[0, 0]), float(intrinsics[1, 1])
    cx, cy = float(intrinsics[0, 2]), float(intrinsics[1, 2])
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    tx = z * torch.clamp(x / z, -lim_x_neg, lim_x_pos)
    ty = z * torch.clamp(y / z, -lim_y_neg, lim_y_pos)
    zero = torch.zeros_like(z)
    jacobian = torch.stack(
        [
            torch.stack([fx / z, zero, -fx * tx / z**2]),
            torch.stack([zero, fy / z, -fy * ty / z**2]),
        ]
    )
    undilated = jacobian @ cov_cam @ jacobian.T
    cov2d = undilated + eps2d * torch.eye(2, dtype=z.dtype, device=z.device)

    det = cov2d[0, 0] * cov2d[1, 1] - cov2d[0, 1] ** 2
    if float(det.detach()) <= 0:
        return None
    conic = torch.stack([cov2d[1, 1] / det, -cov2d[0, 1] / det, cov2d[0, 0] / det])
    mean2d = torch.stack([fx * x / z + cx, fy * y / z + cy])
    if rasterize_mode == "antialiased":
        det_undilated = undilated[0, 0] * undilated[1, 1] - undilated[0, 1] ** 2
        opacity = opacity * torch.sqrt(torch.clamp(det_undilated / det, min=0.0))

    if radius_rule == "gsplat<=1.4":
        k = 3.0 if radius_sigma is None else radius_sigma
        mid = 0.5 * float((cov2d[0, 0] + cov2d[1, 1]).detach())
        lambda_max = mid + math.sqrt(max(mid * mid - float(det.detach()), 0.01))
        rx = ry = math.ceil(k * math.sqrt(lambda_max))
    else:  # gsplat 1.5's CUDA rule: per axis, opacity-aware, o < 1/255 culled
        o = float(opacity.detach())
        if o < 1 / 255:
            return None
        k = 3.33 if radius_sigma is None else radius_sigma
        extent = min(k, math.sqrt(2 * math.log(o * 255)))
        rx = math.ceil(extent * math.sqrt(float(cov2d[0, 0].detach())))
        ry = math.ceil(extent * math.sqrt(float(cov2d[1, 1].detach())))
    if rx <= radius_clip and ry <= radius_clip:
        return None
    mx, my = (float(c) for c in mean2d.detach())
    if mx + rx <= 0 or mx - rx >= width or my + ry <= 0 or my - ry >= height:
        return None
    return Projected(mean2d=mean2d, conic=conic, depth=z, radius_xy=(rx, ry), opacity=opacity)


def tile_mask(p: Projected, height: int, width: int, tile_size: int) -> Tensor:
    """``(H, W)`` bool: pixels whose tile lies in the Gaussian's tile rectangle."""
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    mx, my = (float(c) for c in p.mean2d.detach())
    rx, ry = p.radius_xy
    x0 = min(max(math.floor((mx - rx) / tile_size), 0), tiles_x)
    x1 = min(max(math.ceil((mx + rx) / tile_size), 0), tiles_x)
    y0 = min(max(math.floor((my - ry) / tile_size), 0), tiles_y)
    y1 = min(max(math.ceil((my + ry) / tile_size), 0), tiles_y)
    col_tile = torch.arange(width, device=p.mean2d.device) // tile_size
    row_tile = torch.arange(height, device=p.mean2d.device) // tile_size
    cols = (col_tile >= x0) & (col_tile < x1)
    rows = (row_tile >= y0) & (row_tile < y1)
    return rows[:, None] & cols[None, :]


def render_image(
    means: Tensor,
    covariances: Tensor,
    opacities: Tensor,
    features: Tensor,
    background: Tensor,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    height: int,
    width: int,
    *,
    near: float,
    far: float,
    eps2d: float,
    max_alpha: float,
    alpha_min: float,
    transmittance_min: float,
    radius_sigma: float | None,
    tile_size: int,
    **rules: object,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One camera: ``(features (C,H,W), accumulated depth (H,W), alpha (H,W), radii (N,))``.

    ``features`` ``(N, C)``; ``rules``: ``radius_rule``, ``radius_clip``, ``rasterize_mode``.
    """
    n = means.shape[0]
    dtype, device = means.dtype, means.device
    radii = torch.zeros(n, dtype=torch.int64, device=device)
    projected: dict[int, Projected] = {}
    for i in range(n):
        p = project_gaussian(
            means[i],
            covariances[i],
            world_to_cam,
            intrinsics,
            height,
            width,
            near=near,
            far=far,
            eps2d=eps2d,
            radius_sigma=radius_sigma,
            opacity=opacities[i],
            **rules,  # type: ignore[arg-type]
        )
        if p is not None:
            projected[i] = p
            radii[i] = p.radius

    px = torch.arange(width, dtype=dtype, device=device)[None, :] + 0.5
    py = torch.arange(height, dtype=dtype, device=device)[:, None] + 0.5
    transmittance = torch.ones(height, width, dtype=dtype, device=device)
    active = torch.ones(height, width, dtype=torch.bool, device=device)
    out = torch.zeros(features.shape[-1], height, width, dtype=dtype, device=device)
    depth = torch.zeros(height, width, dtype=dtype, device=device)
    zero = torch.zeros_like(transmittance)

    for i in sorted(projected, key=lambda j: float(projected[j].depth.detach())):
        p = projected[i]
        dx, dy = p.mean2d[0] - px, p.mean2d[1] - py
        a, b, c = p.conic
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        # clamp_min keeps exp finite where sigma < 0 (those pixels are skipped anyway).
        alpha = torch.clamp(p.opacity * torch.exp(-sigma.clamp_min(0)), max=max_alpha)
        hit = active & tile_mask(p, height, width, tile_size) & (sigma >= 0)
        hit = hit & (alpha >= alpha_min)
        next_transmittance = transmittance * (1 - alpha)
        stop = hit & (next_transmittance <= transmittance_min)
        active = active & ~stop
        hit = hit & ~stop
        weight = torch.where(hit, alpha * transmittance, zero)
        out = out + features[i][:, None, None] * weight
        depth = depth + p.depth * weight
        transmittance = torch.where(hit, next_transmittance, transmittance)

    out = out + transmittance * background[:, None, None]
    return out, depth, 1 - transmittance, radii


def reference_splat(
    gaussians: GaussianSet,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    image_size: tuple[int, int],
    *,
    features: Tensor | None = None,
    background: Tensor | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    max_alpha: float = 0.999,
    alpha_min: float = 1 / 255,
    transmittance_min: float = 1e-4,
    radius_sigma: float | None = None,
    tile_size: int = 16,
    depth_mode: str = "expected",
    **rules: object,
) -> ReferenceOutput:
    """Render ``gaussians`` (batch ``(B,)``) into ``B x V`` images, one at a time.

    ``features`` ``(B, N, C)`` or per camera ``(B, V, N, C)``; ``rules``: ``radius_rule``,
    ``radius_clip``, ``rasterize_mode`` (as ``dego.splat``).
    """
    height, width = image_size
    num_batch, num_views = world_to_cam.shape[:2]
    n = gaussians.num_gaussians
    dtype, device = gaussians.dtype, gaussians.device
    if features is None:
        features = gaussians.features
    if features is None:
        features = torch.zeros(num_batch, n, 0, dtype=dtype, device=device)
    channels = features.shape[-1]
    if features.ndim == 3:
        features = features.unsqueeze(1).expand(num_batch, num_views, n, channels)
    if background is None:
        background = torch.zeros(channels, dtype=dtype, device=device)
    if background.ndim == 1:
        background = background.expand(num_batch, num_views, channels)
    covariances = gaussians.covariances()

    images, depths, alphas, radii = [], [], [], []
    for b in range(num_batch):
        for v in range(num_views):
            image, depth, alpha, rad = render_image(
                gaussians.means[b],
                covariances[b],
                gaussians.opacities[b],
                features[b, v],
                background[b, v],
                world_to_cam[b, v],
                intrinsics[b, v],
                height,
                width,
                near=near,
                far=far,
                eps2d=eps2d,
                max_alpha=max_alpha,
                alpha_min=alpha_min,
                transmittance_min=transmittance_min,
                radius_sigma=radius_sigma,
                tile_size=tile_size,
                **rules,
            )
            if depth_mode == "expected":
                depth = depth / alpha.clamp_min(1e-10)
            images.append(image)
            depths.append(depth)
            alphas.append(alpha)
            radii.append(rad)

    def stack(tensors: list[Tensor]) -> Tensor:
        return torch.stack(tensors).unflatten(0, (num_batch, num_views))

    return ReferenceOutput(
        features=stack(images),
        depth=None if depth_mode == "none" else stack(depths),
        alpha=stack(alphas),
        radii=stack(radii),
    )


__all__ = ["Projected", "ReferenceOutput", "project_gaussian", "reference_splat", "render_image"]
