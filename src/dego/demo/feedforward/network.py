"""A small feed-forward network: one frame of multi-view images in, a ``GaussianSet`` out.

Each camera's image goes through a small CNN (shared by the cameras); every cell of its
output map, one per ``block x block`` pixel block, predicts one Gaussian: a depth along the
ray through the block (a log-uniform range), a shift inside the block, three scales, a
rotation (in the camera frame, turned into the world frame), an opacity, class logits and a
latent feature for the deformation network. The means are the rays' points at that depth,
so the Gaussians start where the cameras look and the images only decide how far.

With ``anchor_depth`` (a depth map of the same frame, e.g. the t = 0 pseudo depth, which
inference has too: it comes from the same images), each Gaussian's distance along its ray is
that map's depth at the pixel it projects to, where the map has a surface; the network's
own depth is kept elsewhere (sky, pixels without a depth). Every other parameter stays
predicted. A depth-anchored predictor is our departure from the paper (see
docs/feedforward.md).
"""

from __future__ import annotations

import dataclasses
import math

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from dego._checks import check_int
from dego.classes import FREE_LABEL
from dego.gaussians import GaussianSet, quaternion_multiply, rotation_matrices_to_quaternions

SCALE_FLOOR = 0.1
"""The smallest scale :class:`GaussianPredictor` predicts by default, metres: a quarter of an
Occ3D voxel. Flatter Gaussians fall between the voxeliser's samples 0.4 m apart and vanish
from the occupancy grid while still rendering well."""

CLASSES = FREE_LABEL
"""Class logits per Gaussian: the 17 Occ3D classes other than free (free space is what the
Gaussians leave transparent)."""


@dataclasses.dataclass
class Prediction:
    """What :class:`GaussianPredictor` returns for a batch of ``B`` frames.

    Attributes:
        gaussians: ``(B, N)`` world-frame Gaussians, features = class probabilities
            ``(B, N, 17)``. logits: ``(B, N, 17)`` their class logits.
        latent: ``(B, N, L)`` latent features (the deformation network's input).
    """

    gaussians: GaussianSet
    logits: Float[Tensor, "B N K"]
    latent: Float[Tensor, "B N L"]


class GaussianPredictor(nn.Module):
    """Images of ``V`` cameras -> ``V * h * w`` Gaussians (one per output cell).

    Args:
        block: pixels per output cell along each axis, a power of two (8: a 64 x 176
            image gives 8 x 22 Gaussians per camera).
        width: channels of the first stage (doubled once, at the second).
        latent_dim: latent channels per Gaussian.
        depth_range: ``(near, far)`` metres of the predicted depth (log-uniform).
        scale_range: ``(smallest, largest)`` scale in metres (the floor:
            :data:`SCALE_FLOOR`).
    """

    def __init__(
        self,
        *,
        block: int = 8,
        width: int = 32,
        latent_dim: int = 16,
        depth_range: tuple[float, float] = (1.0, 60.0),
        scale_range: tuple[float, float] = (SCALE_FLOOR, 1.0),
    ) -> None:
        super().__init__()
        check_int("block", block, 2)
        if block & (block - 1):
            raise ValueError(f"block: expected a power of two, got {block}")
        check_int("width", width, 1)
        check_int("latent_dim", latent_dim, 0)
        for name, (low, high) in (("depth_range", depth_range), ("scale_range", scale_range)):
            if not 0 < low < high < math.inf:
                raise ValueError(f"{name}: expected 0 < low < high, got {(low, high)!r}")
        self.block, self.latent_dim = block, latent_dim
        self.depth_range, self.scale_range = depth_range, scale_range
        layers: list[nn.Module] = [nn.Conv2d(5, width, 3, padding=1), nn.ReLU()]
        channels = width
        for stage in range(int(math.log2(block))):
            out = width * (2 if stage else 1)
            layers += [
                nn.Conv2d(channels, out, 3, stride=2, padding=1),
                nn.ReLU(),
                nn.Conv2d(out, out, 3, padding=2, dilation=2),
                nn.ReLU(),
            ]
            channels = out
        self.encoder = nn.Sequential(*layers)
        context: list[nn.Module] = []
        for _ in range(2):  # two more halvings, upsampled back: a wide receptive field
            context += [
                nn.Conv2d(channels, channels, 3, stride=2, padding=1),
                nn.ReLU(),
                nn.Conv2d(channels, channels, 3, padding=2, dilation=2),
                nn.ReLU(),
            ]
        self.context = nn.Sequential(*context)
        self.outputs = 1 + 2 + 3 + 4 + 1 + CLASSES + latent_dim
        last = nn.Conv2d(channels, self.outputs, 1)
        with torch.no_grad():  # start near identity rotations in the camera frame, with
            assert last.bias is not None  # scales near 0.2 m (a voxel is 0.4 m)
            last.bias[6] = 3.0
            low, high = scale_range
            last.bias[3:6] = math.log((0.2 - low) / (high - 0.2)) if low < 0.2 < high else 0.0
        self.head = nn.Sequential(nn.Conv2d(2 * channels, channels, 1), nn.ReLU(), last)

    def forward(
        self,
        images: Float[Tensor, "B V 3 H W"],
        world_to_cam: Float[Tensor, "B V 4 4"],
        intrinsics: Float[Tensor, "B V 3 3"],
        anchor_depth: Float[Tensor, "B V H W"] | None = None,
    ) -> Prediction:
        """Predict the Gaussians of each of ``B`` frames from its ``V`` images.

        ``anchor_depth``: ``(B, V, H, W)`` z-depth of each image (0: no surface); where it
        is > 0 at a Gaussian's pixel, that depth replaces the predicted one (see the
        module docstring). ``None``: every depth is predicted.
        """
        if images.ndim != 5 or images.shape[2] != 3:
            raise ValueError(f"images: expected (B, V, 3, H, W), got {tuple(images.shape)}")
        b, v, _, h, w = images.shape
        if world_to_cam.shape != (b, v, 4, 4) or intrinsics.shape != (b, v, 3, 3):
            raise ValueError(
                f"world_to_cam, intrinsics: expected ({b}, {v}, 4, 4) and ({b}, {v}, 3, 3) "
                f"for images {tuple(images.shape)}, got {tuple(world_to_cam.shape)} and "
                f"{tuple(intrinsics.shape)}"
            )
        if anchor_depth is not None and anchor_depth.shape != (b, v, h, w):
            raise ValueError(
                f"anchor_depth: expected ({b}, {v}, {h}, {w}) like images, got "
                f"{tuple(anchor_depth.shape)}"
            )
        flat = images.reshape(b * v, 3, h, w)
        rows = torch.linspace(-1, 1, h, device=images.device, dtype=images.dtype)
        cols = torch.linspace(-1, 1, w, device=images.device, dtype=images.dtype)
        coords = torch.stack(torch.meshgrid(rows, cols, indexing="ij")).expand(b * v, 2, h, w)
        local = self.encoder(torch.cat([flat - 0.5, coords], 1))  # (BV, C, h', w')
        wide = F.interpolate(
            self.context(local), size=local.shape[-2:], mode="bilinear", align_corners=False
        )
        raw = self.head(torch.cat([local, wide], 1))
        hh, ww = raw.shape[-2:]
        raw = raw.permute(0, 2, 3, 1).reshape(b, v, hh, ww, self.outputs)
        depth_raw, shift, scale_raw, quat, opacity_raw, rest = raw.split(
            [1, 2, 3, 4, 1, CLASSES + self.latent_dim], -1
        )
        logits, latent = rest.split([CLASSES, self.latent_dim], -1)

        near, far = self.depth_range
        depth = near * (far / near) ** torch.sigmoid(depth_raw)  # (B, V, h', w', 1)
        cell = torch.tensor([w / ww, h / hh], dtype=raw.dtype, device=raw.device)
        v_index, u_index = torch.meshgrid(
            torch.arange(hh, device=raw.device, dtype=raw.dtype),
            torch.arange(ww, device=raw.device, dtype=raw.dtype),
            indexing="ij",
        )
        centres = (torch.stack([u_index, v_index], -1) + 0.5) * cell  # (h', w', 2) pixels
        pixels = centres + torch.tanh(shift) * cell / 2
        if anchor_depth is not None:
            depth = _anchored(depth, anchor_depth.to(depth.dtype), pixels.detach())
        homogeneous = torch.cat([pixels, torch.ones_like(pixels[..., :1])], -1)
        rays = torch.einsum("bvij,bvhwj->bvhwi", torch.linalg.inv(intrinsics), homogeneous)
        cam_to_world = torch.linalg.inv(world_to_cam)
        points = rays * depth  # z-depth along the ray
        means = torch.einsum("bvij,bvhwj->bvhwi", cam_to_world[..., :3, :3], points)
        means = means + cam_to_world[:, :, None, None, :3, 3]

        low, high = self.scale_range
        scales = low + (high - low) * torch.sigmoid(scale_raw)
        camera_rotation = rotation_matrices_to_quaternions(cam_to_world[..., :3, :3])
        quats = quaternion_multiply(camera_rotation[:, :, None, None], F.normalize(quat, dim=-1))
        n = v * hh * ww
        logits = logits.reshape(b, n, CLASSES)
        gaussians = GaussianSet(
            means=means.reshape(b, n, 3),
            quats=quats.reshape(b, n, 4),
            scales=scales.reshape(b, n, 3),
            opacities=torch.sigmoid(opacity_raw).reshape(b, n),
            features=torch.softmax(logits, -1),
        )
        return Prediction(gaussians, logits, latent.reshape(b, n, self.latent_dim))


def _anchored(
    depth: Float[Tensor, "B V h w 1"], anchor: Float[Tensor, "B V H W"], pixels: Tensor
) -> Float[Tensor, "B V h w 1"]:
    """``depth`` with ``anchor``'s value at each cell's pixel ``(u, v)`` where it is > 0."""
    b, v, height, width = anchor.shape
    cols = pixels[..., 0].floor().long().clamp(0, width - 1)
    rows = pixels[..., 1].floor().long().clamp(0, height - 1)
    index = (rows * width + cols).reshape(b, v, -1)
    found = anchor.reshape(b, v, -1).gather(-1, index).reshape(depth.shape)
    return torch.where(found > 0, found, depth)
