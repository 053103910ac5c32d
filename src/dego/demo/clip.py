"""A synthetic clip as the demo sees it: weak 2D supervision for fitting, a grid for scoring."""

from __future__ import annotations

import dataclasses
import inspect
import math

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from dego.data.synthetic import CAMERAS, LIDAR_ORIGIN, SyntheticScene
from dego.grid import VoxelGrid
from dego.metrics.rayiou import lidar_origins

DEMO_FRAME_DT = 0.2
"""Seconds between the demo's frames (5 Hz; nuScenes keyframes are 2 Hz). At 0.2 s an
agent moves less than its own size between neighbouring frames (a pedestrian about
0.3 m, a cyclist about 1 m), so its rendered and observed images overlap and the
rendering loss pulls the fitted agent towards its new position; at 0.5 s the cyclists
move 2-3 m and the fit loses them (measured on development seeds)."""

MAX_DEMO_FRAMES = 81
"""The longest clip ``dego demo`` and ``dego study`` render (``--frames``). The synthetic
ego drives 5 m/s, 1 m per frame at :data:`DEMO_FRAME_DT`, and the Occ3D grid reaches 40 m
ahead and behind it; the synthetic world's ground ends at +-80 m, so at 81 frames
(offsets -40 .. 40) the outermost frames' grids just reach its edge. A frame of the clip
holds about 13 MB (images, pseudo labels, three ground-truth grids): about 1 GB at 81
frames, rendered at about two seconds a frame on a CPU."""

CAMERA_PIXELS = len(CAMERAS) * math.prod(
    inspect.signature(SyntheticScene).parameters["image_size"].default
)
"""Camera pixels of one frame of the demo's clips (six cameras at
:class:`~dego.data.SyntheticScene`'s default image size)."""


def max_gaussians(num_frames: int) -> int:
    """The most canonical Gaussians a demo clip of ``num_frames`` frames can start from:
    :meth:`~dego.demo.GaussianSceneModel.from_clip` draws one per surface pixel without
    replacement, and a clip has fewer surface pixels than :data:`CAMERA_PIXELS` per frame
    (how many fewer depends on the scene: a count above what the clip holds is still
    refused by ``from_clip``)."""
    return num_frames * CAMERA_PIXELS


@dataclasses.dataclass(frozen=True)
class DemoClip:
    """Every frame of a :class:`~dego.data.SyntheticScene`, stacked over time.

    The world frame is the reference frame's ego frame (offset 0), so the ground-truth
    grid of the reference frame and canonical Gaussians live in the same coordinates;
    frame t's ground truth is in frame t's ego coordinates (``ego_poses[t]``: ego ->
    world).

    Attributes:
        times: ``(T,)`` frame offsets (integers stored as floats; 0 = reference).
        reference: index of offset 0 in ``times``.
        world_to_cam: ``(T, V, 4, 4)``. intrinsics: ``(T, V, 3, 3)``.
        ego_poses: ``(T, 4, 4)`` ego -> world of every frame.
        images: ``(T, V, 3, H, W)`` RGB, for pictures only.
        depth: ``(T, V, H, W)`` pseudo depth (0 = nothing hit). semantics: ``(T, V, H, W)``
            pseudo labels (17 = nothing hit).
        supervised: ``(T, V, H, W)`` pixels the losses use: sky, or a pseudo-depth point
            inside ``grid`` (surfaces beyond the grid have no Gaussians to explain them).
        occupancy, mask_camera, instances: every frame's ``(T, X, Y, Z)`` ground truth
            labels, camera mask and agent instance ids (0 = no agent), for scoring only.
        instance_pixels: ``(T, V, H, W)`` agent instance id of each pixel (0 = none),
            ground truth, for analysis only (never seen by the fit).
        agent_labels, agent_articulated, agent_moving: ``(A,)`` per agent (instance id
            ``a + 1``): Occ3D label, whether its shape changes over time (pedestrians,
            cyclists), whether it moves.
        ray_origins: ``(K, 3)`` RayIoU origins (reference ego frame).
        grid: the voxel grid of ``occupancy``.
    """

    times: Float[Tensor, " T"]
    reference: int
    world_to_cam: Float[Tensor, "T V 4 4"]
    intrinsics: Float[Tensor, "T V 3 3"]
    ego_poses: Float[Tensor, "T 4 4"]
    images: Float[Tensor, "T V 3 H W"]
    depth: Float[Tensor, "T V H W"]
    semantics: Int[Tensor, "T V H W"]
    supervised: Bool[Tensor, "T V H W"]
    occupancy: Int[Tensor, "T X Y Z"]
    mask_camera: Bool[Tensor, "T X Y Z"]
    instances: Int[Tensor, "T X Y Z"]
    instance_pixels: Int[Tensor, "T V H W"]
    agent_labels: Int[Tensor, " A"]
    agent_articulated: Bool[Tensor, " A"]
    agent_moving: Bool[Tensor, " A"]
    ray_origins: Float[Tensor, "K 3"]
    grid: VoxelGrid

    @classmethod
    def from_scene(cls, scene: SyntheticScene) -> DemoClip:
        """Render every frame of ``scene`` (about two seconds per frame on a CPU)."""
        frames = scene.frames()
        reference = scene.offsets.index(0)
        stack = {
            name: torch.stack([getattr(f, name) for f in frames])
            for name in (
                "world_to_cam",
                "intrinsics",
                "images",
                "depth",
                "semantics",
                "mask_camera",
                "instances",
                "instance_pixels",
            )
        }
        points = backproject(stack["depth"], stack["world_to_cam"], stack["intrinsics"])
        inside = scene.grid.contains(points) & (stack["depth"] > 0)
        lidar_to_ego = torch.eye(4, dtype=torch.float64).repeat(len(frames), 1, 1)
        lidar_to_ego[:, :3, 3] = torch.tensor(LIDAR_ORIGIN, dtype=torch.float64)
        ego_poses = torch.stack([f.ego_pose.double() for f in frames])
        agents = scene.agents
        return cls(
            times=torch.tensor([float(f.offset) for f in frames]),
            reference=reference,
            ego_poses=ego_poses.float(),
            supervised=inside | (stack["depth"] == 0),
            occupancy=torch.stack([f.occupancy.long() for f in frames]),
            agent_labels=torch.tensor([a.label for a in agents], dtype=torch.long),
            agent_articulated=torch.tensor([a.articulated for a in agents], dtype=torch.bool),
            agent_moving=torch.tensor([a.moving for a in agents], dtype=torch.bool),
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
