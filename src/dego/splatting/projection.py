"""EWA projection of 3D Gaussians into pinhole cameras (gsplat's maths, batched in torch)."""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from dego.gaussians import _gram_of_scaled_rotation

_MAX_RADIUS = 1 << 24  # pixels; keeps the integer conversion finite for degenerate inputs


@dataclasses.dataclass(frozen=True)
class Projection:
    """Per (image, Gaussian) screen-space quantities, all shaped ``(B, V, N, ...)``.

    ``means2d`` pixels (x right, y down), ``conics`` the inverse dilated 2D covariance
    as ``(a, b, c)`` = ``[[a, b], [b, c]]``, ``variances2d`` its diagonal (pixels^2, no
    gradient), ``depths`` camera z of the mean, ``radii`` integer pixel radius (0 where
    culled), ``visible`` the complement of culling.
    """

    means2d: Tensor
    conics: Tensor
    variances2d: Tensor
    depths: Tensor
    radii: Tensor
    visible: Tensor


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    image_size: tuple[int, int],
    *,
    near: float,
    far: float,
    eps2d: float,
    radius_sigma: float,
) -> Projection:
    """Project ``(B, N)`` Gaussians into ``(B, V)`` cameras; differentiable in the Gaussians.

    Culled Gaussians (z outside [near, far], degenerate 2D covariance, footprint fully
    off-image) get radius 0 and finite, gradient-free placeholder values.
    """
    height, width = image_size
    rotation = world_to_cam[..., :3, :3].unsqueeze(2)  # (B, V, 1, 3, 3)
    translation = world_to_cam[..., :3, 3].unsqueeze(2)  # (B, V, 1, 3)
    cam = (rotation @ means.unsqueeze(1).unsqueeze(-1)).squeeze(-1) + translation  # (B,V,N,3)
    x, y, z = cam.unbind(-1)
    in_depth = (z >= near) & (z <= far)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))  # no inf/NaN reaches autograd

    fx, fy = intrinsics[..., 0, 0, None], intrinsics[..., 1, 1, None]  # (B, V, 1)
    cx, cy = intrinsics[..., 0, 2, None], intrinsics[..., 1, 2, None]
    # The Jacobian uses x/z, y/z clamped to 1.3x the field of view (as gsplat), the mean does not.
    margin_x, margin_y = 0.3 * 0.5 * width / fx, 0.3 * 0.5 * height / fy
    tx = z_safe * torch.minimum(
        torch.maximum(x / z_safe, -(cx / fx + margin_x)), (width - cx) / fx + margin_x
    )
    ty = z_safe * torch.minimum(
        torch.maximum(y / z_safe, -(cy / fy + margin_y)), (height - cy) / fy + margin_y
    )
    zero = torch.zeros_like(z_safe)
    jacobian = torch.stack(
        [fx / z_safe, zero, -fx * tx / z_safe**2, zero, fy / z_safe, -fy * ty / z_safe**2], dim=-1
    ).unflatten(-1, (2, 3))
    # cov2d = (J R) Sigma (J R)^T, with Sigma = R_g diag(s^2) R_g^T shared by every camera.
    cov3d = _gram_of_scaled_rotation(quats, scales).unsqueeze(1)  # (B, 1, N, 3, 3)
    jr = jacobian @ rotation  # (B, V, N, 2, 3)
    cov2d = jr @ cov3d @ jr.transpose(-1, -2)
    a = cov2d[..., 0, 0] + eps2d
    b = cov2d[..., 0, 1]
    c = cov2d[..., 1, 1] + eps2d
    det = a * c - b * b
    ok_det = det > 0
    det_safe = torch.where(ok_det, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)
    means2d = torch.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], dim=-1)

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lambda_max = mid + torch.sqrt((mid * mid - det).clamp_min(0))
        radius = torch.ceil(radius_sigma * torch.sqrt(lambda_max.clamp_min(0)))
        radius = radius.nan_to_num(0.0).clamp(0, _MAX_RADIUS)
        mx, my = means2d.unbind(-1)
        on_image = (
            (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        )
        visible = in_depth & ok_det & on_image & (radius > 0)
        radii = torch.where(visible, radius, torch.zeros_like(radius)).to(torch.int32)
    variances2d = torch.stack([a, c], dim=-1).detach()
    return Projection(means2d, conics, variances2d, torch.where(in_depth, z, zero), radii, visible)
