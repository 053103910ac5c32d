"""EWA projection of 3D Gaussians into pinhole cameras (gsplat's maths, batched in torch)."""

from __future__ import annotations

import dataclasses
from typing import Literal

import torch
from jaxtyping import Float
from torch import Tensor

from dego._geometry import scaled_rotation_gram
from dego._policy import check_dtype
from dego._typing import typechecked

_MAX_RADIUS = 1 << 24  # pixels; keeps the integer conversion finite for degenerate inputs

RadiusRule = Literal["gsplat<=1.4", "gsplat>=1.5"]
RasterizeMode = Literal["classic", "antialiased"]
RADIUS_SIGMA = {"gsplat<=1.4": 3.0, "gsplat>=1.5": 3.33}
"""Each radius rule's default number of standard deviations."""
ALPHA_THRESHOLD = 1 / 255
"""gsplat's compiled alpha threshold, used by the ``gsplat>=1.5`` rule's opacity-aware extent."""


@dataclasses.dataclass(frozen=True)
class Projection:
    """Per (image, Gaussian) screen-space quantities, all shaped ``(B, V, N, ...)``.

    ``means2d`` pixels (x right, y down); when it comes from :func:`dego.splat` it is the
    tensor the compositing reads, so ``means2d.retain_grad()`` before backward gives the
    screen-space gradients 3DGS densification uses (and ``means2d.absgrad`` with
    ``absgrad=True``). ``conics`` the inverse dilated 2D covariance as ``(a, b, c)`` =
    ``[[a, b], [b, c]]``, ``variances2d`` its diagonal (pixels^2, no gradient),
    ``depths`` camera z of the mean, ``radii_xy`` integer pixel radius per axis ``(..., 2)``
    (0 where culled), ``radii`` their maximum, ``visible`` the complement of culling,
    ``opacities`` the opacities the compositing uses (times the antialiasing
    compensation in ``"antialiased"`` mode; ``None`` when no opacities were given).
    """

    means2d: Tensor
    conics: Tensor
    variances2d: Tensor
    depths: Tensor
    radii: Tensor
    visible: Tensor
    radii_xy: Tensor
    opacities: Tensor | None = None


@typechecked
def project_gaussians(
    means: Float[Tensor, "B N 3"],
    quats: Float[Tensor, "B N 4"],
    scales: Float[Tensor, "B N 3"],
    world_to_cam: Float[Tensor, "B V 4 4"],
    intrinsics: Float[Tensor, "B V 3 3"],
    image_size: tuple[int, int],
    *,
    near: float,
    far: float,
    eps2d: float,
    radius_sigma: float | None = None,
    radius_rule: RadiusRule = "gsplat<=1.4",
    radius_clip: float = 0.0,
    opacities: Float[Tensor, "B N"] | None = None,
    rasterize_mode: RasterizeMode = "classic",
) -> Projection:
    """Project ``(B, N)`` Gaussians into ``(B, V)`` cameras; differentiable in the Gaussians.

    Radius rules (``k = radius_sigma``, default 3 and 3.33 respectively):

    - ``"gsplat<=1.4"``: one radius ``ceil(k sqrt(lambda_max))`` with
      ``lambda_max = m + sqrt(max(0.01, m^2 - det))``, ``m`` the mean of the dilated 2D
      covariance's diagonal, as gsplat 1.0-1.4.
    - ``"gsplat>=1.5"``: per-axis radii ``ceil(e sqrt(Sigma_xx))``, ``ceil(e sqrt(Sigma_yy))``
      with the opacity-aware ``e = min(k, sqrt(2 log(255 o)))``; Gaussians with
      ``o < 1/255`` are culled (``o`` the effective opacity; needs ``opacities``).

    ``rasterize_mode="antialiased"`` multiplies the opacities by gsplat's compensation
    ``sqrt(max(0, det(Sigma2d) / det(Sigma2d + eps2d I)))`` (differentiable). Culled
    Gaussians (z outside [near, far], degenerate 2D covariance, radius at most
    ``radius_clip`` on every axis, footprint fully off-image) get radius 0 and finite,
    gradient-free placeholder values. Values are not checked here (NaN passes through);
    :func:`~dego.splat` checks them.

    Raises:
        TypeError: naming a tensor whose dtype differs from ``means``'.
    """
    tensors: dict[str, Tensor | None] = {"quats": quats, "scales": scales}
    tensors |= {"world_to_cam": world_to_cam}
    tensors |= {"intrinsics": intrinsics, "opacities": opacities}
    for name, tensor in tensors.items():
        if tensor is not None:
            check_dtype(name, tensor, means.dtype, "means")
    if radius_sigma is None:
        radius_sigma = RADIUS_SIGMA[radius_rule]
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
    cov3d = scaled_rotation_gram(quats, scales).unsqueeze(1)  # (B, 1, N, 3, 3)
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
    effective = None
    if opacities is not None:
        effective = opacities.unsqueeze(1).expand_as(z)
        if rasterize_mode == "antialiased":
            undilated = cov2d[..., 0, 0] * cov2d[..., 1, 1] - b * b
            effective = effective * torch.sqrt((undilated / det_safe).clamp_min(0))

    with torch.no_grad():
        if radius_rule == "gsplat<=1.4":
            mid = 0.5 * (a + c)
            lambda_max = mid + torch.sqrt((mid * mid - det).clamp_min(0.01))
            radius = torch.ceil(radius_sigma * torch.sqrt(lambda_max.clamp_min(0)))
            radius = radius.unsqueeze(-1).expand(*radius.shape, 2)
            opaque_enough = torch.ones_like(ok_det)
        else:
            extent = torch.full_like(z, radius_sigma)
            opaque_enough = torch.ones_like(ok_det)
            if effective is not None:
                o = effective.detach()
                opaque_enough = o >= ALPHA_THRESHOLD
                aware = torch.sqrt(2 * torch.log(o.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD))
                extent = torch.minimum(extent, aware)
            radius = torch.ceil(extent.unsqueeze(-1) * torch.stack([a, c], -1).clamp_min(0).sqrt())
        radius = radius.nan_to_num(0.0).clamp(0, _MAX_RADIUS)
        rx, ry = radius.unbind(-1)
        mx, my = means2d.unbind(-1)
        on_image = (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height)
        big_enough = (rx > radius_clip) | (ry > radius_clip)
        visible = in_depth & ok_det & opaque_enough & on_image & big_enough
        radii_xy = torch.where(visible.unsqueeze(-1), radius, 0.0).to(torch.int32)
    variances2d = torch.stack([a, c], dim=-1).detach()
    return Projection(
        means2d,
        conics,
        variances2d,
        torch.where(in_depth, z, zero),
        radii_xy.amax(-1),
        visible,
        radii_xy,
        effective,
    )
