"""A synthetic clip as the demo sees it: weak 2D supervision for fitting, a grid for scoring."""

from __future__ import annotations

import dataclasses

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from dego.data.synthetic import LIDAR_ORIGIN, SyntheticScene
from dego.grid import VoxelGrid
from dego.metrics.rayiou import lidar_origins


@dataclasses.dataclass(frozen=True)
class DemoClip:
    """Every frame of a :class:`~dego.data.SyntheticScene`, stacked over time.

    The world frame is the reference frame's ego frame (offset 0), so the ground-truth
    grid of the reference frame and canonical Gaussians live in the same coordinates.

    Attributes:
        times: ``(T,)`` frame offsets (integers stored as floats; 0 = reference).
        reference: index of offset 0 in ``times``.
        world_to_cam: ``(T, V, 4, 4)``. intrinsics: ``(T, V, 3, 3)``.
        images: ``(T, V, 3, H, W)`` RGB, for pictures only.
        depth: ``(T, V, H, W)`` pseudo depth (0 = nothing hit). semantics: ``(T, V, H, W)``
            pseudo labels (17 = nothing hit).
        supervised: ``(T, V, H, W)`` pixels the losses use: sky, or a pseudo-depth point
            inside ``grid`` (surfaces beyond the grid have no Gaussians to explain them).
        occupancy, mask_camera: the reference frame's ``(X, Y, Z)`` ground truth, for
            scoring only. ray_origins: ``(K, 3)`` RayIoU origins (reference ego frame).
        grid: the voxel grid of ``occupancy``.
    """

    times: Float[Tensor, " T"]
    reference: int
    world_to_cam: Float[Tensor, "T V 4 4"]
    intrinsics: Float[Tensor, "T V 3 3"]
    images: Float[Tensor, "T V 3 H W"]
    depth: Float[Tensor, "T V H W"]
    semantics: Int[Tensor, "T V H W"]
    supervised: Bool[Tensor, "T V H W"]
    occupancy: Int[Tensor, "X Y Z"]
    mask_camera: Bool[Tensor, "X Y Z"]
    ray_origins: Float[Tensor, "K 3"]
    grid: VoxelGrid

    @classmethod
    def from_scene(cls, scene: SyntheticScene) -> DemoClip:
        """Render every frame of ``scene`` (about a second per frame on a CPU)."""
        frames = scene.frames()
        reference = scene.offsets.index(0)
        stack = {
            name: torch.stack([getattr(f, name) for f in frames])
            for name in ("world_to_cam", "intrinsics", "images", "depth", "semantics")
        }
        points = backproject(stack["depth"], stack["world_to_cam"], stack["intrinsics"])
        inside = scene.grid.contains(points) & (stack["depth"] > 0)
        lidar_to_ego = torch.eye(4, dtype=torch.float64).repeat(len(frames), 1, 1)
        lidar_to_ego[:, :3, 3] = torch.tensor(LIDAR_ORIGIN, dtype=torch.float64)
        ego_poses = torch.stack([f.ego_pose.double() for f in frames])
        return cls(
            times=torch.tensor([float(f.offset) for f in frames]),
            reference=reference,
            supervised=inside | (stack["depth"] == 0),
            occupancy=frames[reference].occupancy.long(),
            mask_camera=frames[reference].mask_camera,
            ray_origins=lidar_origins(ego_poses, lidar_to_ego, reference).float(),
            grid=scene.grid,
            **stack,
        )

    @property
    def num_frames(self) -> int:
        return self.times.shape[0]

    @property
    def image_size(self) -> tuple[int, int]:
        return (self.depth.shape[-2], self.depth.shape[-1])

    def to(self, device: torch.device | str) -> DemoClip:
        """The clip with every tensor on ``device``."""
        return dataclasses.replace(
            self,
            **{
                f.name: getattr(self, f.name).to(device)
                for f in dataclasses.fields(self)
                if isinstance(getattr(self, f.name), Tensor)
            },
        )


def backproject(
    depth: Float[Tensor, "*batch H W"],
    world_to_cam: Float[Tensor, "*batch 4 4"],
    intrinsics: Float[Tensor, "*batch 3 3"],
) -> Float[Tensor, "*batch H W 3"]:
    """World points of every pixel centre at its z-depth ``depth`` (OpenCV cameras)."""
    h, w = depth.shape[-2:]
    v, u = torch.meshgrid(
        torch.arange(h, dtype=depth.dtype, device=depth.device),
        torch.arange(w, dtype=depth.dtype, device=depth.device),
        indexing="ij",
    )
    pixels = torch.stack([u + 0.5, v + 0.5, torch.ones_like(u)], -1)  # (H, W, 3)
    rays = torch.einsum("...ij,hwj->...hwi", torch.linalg.inv(intrinsics), pixels)
    cam_points = rays * depth[..., None]
    cam_to_world = torch.linalg.inv(world_to_cam)
    rotation, translation = cam_to_world[..., None, None, :3, :3], cam_to_world[..., :3, 3]
    return (rotation @ cam_points[..., None]).squeeze(-1) + translation[..., None, None, :]
