"""A procedural, seeded, dynamic driving scene: the embedded default data set.

A straight street along +x (the reference ego frame is the world frame: the ego starts
at the origin heading +x) with a crossing, sidewalks, terrain strips, buildings, trees,
barriers, traffic cones, parked and moving vehicles (rigid), walking pedestrians and
cyclists / motorcyclists with moving limbs (nonrigid), all built from analytic solids
(:mod:`dego.data.primitives`). Every frame gives six surround camera images, pseudo
depth and semantics ray-cast from the solids, the Occ3D-style ground truth grid in that
frame's ego coordinates with camera and LiDAR visibility masks, and the poses. Every
agent is an instance (:class:`SyntheticAgent`, :attr:`SyntheticScene.agents`): frames also
give per-voxel and per-pixel instance ids and the agents' poses.

Label conventions: Occ3D-nuScenes (17 = free). Riders carry the label of their bicycle
or motorcycle (as nuScenes boxes include the rider). Pixels that hit nothing (sky) have
depth 0 and semantics 17 (pseudo-label noise may break that pairing at sky boundaries,
as real pseudo labels do).
"""

from __future__ import annotations

import dataclasses
import math
import numbers

import torch
from torch import Tensor

from dego._checks import check_int, check_positive
from dego._policy import check_memory
from dego._typing import check_tensor_fields
from dego.classes import FREE_LABEL, PALETTE, Occ3DLabel
from dego.data.primitives import BOX, CYLINDER, ELLIPSOID, Primitives, axis_to_matrix, yaw_matrix
from dego.grid import VoxelGrid
from dego.raycast import generate_lidar_rays, observed_voxels

L = Occ3DLabel
LIDAR_ORIGIN = (0.9858, 0.0, 1.8402)
"""The nuScenes LiDAR's position in the ego frame (metres)."""

# (name, position x y z in the ego frame, yaw in degrees): a nuScenes-like surround rig
CAMERAS = (
    ("CAM_FRONT", (1.70, 0.00, 1.50), 0.0),
    ("CAM_FRONT_RIGHT", (1.55, -0.50, 1.50), -55.0),
    ("CAM_FRONT_LEFT", (1.55, 0.50, 1.50), 55.0),
    ("CAM_BACK", (0.00, 0.00, 1.55), 180.0),
    ("CAM_BACK_LEFT", (1.05, 0.50, 1.50), 110.0),
    ("CAM_BACK_RIGHT", (1.05, -0.50, 1.50), -110.0),
)
"""The six cameras of :class:`SyntheticScene`, in image order: ``(name, (x, y, z) in the ego
frame in metres, yaw in degrees)``, a nuScenes-like surround rig."""
# nuScenes intrinsics after DeGO's resize (0.44) and top crop (140 px) to 256 x 704
_BASE_SIZE, _BASE_FOCAL, _BASE_CENTRE = (256, 704), 557.0, (352.0, 58.0)
_SKY = (0.62, 0.78, 0.95)
_VEHICLE_LENGTHS = {
    "car": 4.5,
    "truck": 7.5,
    "bus": 11.5,
    "trailer": 8.9,
    "construction_vehicle": 6.0,
}
_VOXEL_MARGIN = 0.25  # a voxel is occupied when a solid comes within 0.25 voxel of its centre
# Memory per camera pixel: ~240 bytes measured at the peak of frame() (ray origins and
# directions, hits, labels, shading, images), 32 kept in each SyntheticFrame (images,
# depth, semantics, instance_pixels).
_PEAK_BYTES_PER_PIXEL = 256
_KEPT_BYTES_PER_PIXEL = 32


@dataclasses.dataclass(frozen=True)
class SyntheticFrame:
    """One frame of a :class:`SyntheticScene`.

    Attributes:
        time: seconds from the reference frame.
        offset: the frame offset (integer).
        images: ``(V, 3, H, W)`` float32 RGB in [0, 1] (per-class colours, shaded).
        depth: ``(V, H, W)`` float32 pseudo depth (camera z, metres; 0 where nothing is hit).
        semantics: ``(V, H, W)`` int64 pseudo labels (17 where nothing is hit).
        world_to_cam: ``(V, 4, 4)``: world (the reference ego frame) to OpenCV camera.
        intrinsics: ``(V, 3, 3)`` pinhole ``K``.
        ego_pose: ``(4, 4)`` ego -> world at this frame.
        lidar_origin: ``(3,)`` the LiDAR in this frame's ego coordinates.
        occupancy: ``(X, Y, Z)`` uint8 Occ3D labels in this frame's ego coordinates.
        mask_camera: ``(X, Y, Z)`` bool: voxels seen by camera rays, up to and including
            the first occupied voxel.
        mask_lidar: ``(X, Y, Z)`` bool: the same for the LiDAR rays.
        instances: ``(X, Y, Z)`` int64 agent instance ids (:attr:`SyntheticAgent.instance_id`)
            in this frame's ego grid: the id of the agent that owns the voxel's winning solid
            (the solid that gives ``occupancy`` its label), 0 where the voxel is free or
            taken by a static solid. Where it is k > 0, ``occupancy`` is
            ``scene.agents[k - 1].label``.
        instance_pixels: ``(V, H, W)`` int64 instance id of the first solid each pixel's ray
            hits (0 for static solids and sky), from the exact ray cast: ground truth, not
            affected by ``label_noise``.
        agent_poses: ``(A, 4, 4)`` float64 agent -> world poses of every agent of
            ``scene.agents`` at this frame's time (:meth:`SyntheticAgent.pose`).
    """

    def __post_init__(self) -> None:
        check_tensor_fields(self)

    time: float
    offset: int
    images: Tensor
    depth: Tensor
    semantics: Tensor
    world_to_cam: Tensor
    intrinsics: Tensor
    ego_pose: Tensor
    lidar_origin: Tensor
    occupancy: Tensor
    mask_camera: Tensor
    mask_lidar: Tensor
    instances: Tensor
    instance_pixels: Tensor
    agent_poses: Tensor


def _boxes(
    centers: list, sizes: list, yaws: float | list, label: int, shade: float = 1.0
) -> Primitives:
    """Boxes from centres, full sizes and yaws (a single value or one per box)."""
    centre = torch.tensor(centers, dtype=torch.float32).reshape(-1, 3)
    yaw = torch.tensor(yaws, dtype=torch.float32).reshape(-1).expand(centre.shape[0])
    size = torch.tensor(sizes, dtype=torch.float32).reshape(-1, 3).expand(centre.shape[0], 3)
    return Primitives.make(BOX, centre, yaw_matrix(yaw), size / 2, label, shade)


def _segment_ellipsoids(a: Tensor, b: Tensor, radius: float, label: int) -> Primitives:
    """Limbs: ellipsoids along segments ``a -> b`` ``(P, 3)`` of the given thickness."""
    axis = b - a
    length = torch.linalg.vector_norm(axis, dim=-1)
    sizes = torch.stack(
        [torch.full_like(length, radius), torch.full_like(length, radius), length / 2 + radius], -1
    )
    return Primitives.make(ELLIPSOID, (a + b) / 2, axis_to_matrix(axis), sizes, label)


# the kinds of SyntheticAgent and their Occ3D labels; the articulated kinds' limbs move
_AGENT_LABELS = {
    "car": L.CAR,
    "truck": L.TRUCK,
    "bus": L.BUS,
    "trailer": L.TRAILER,
    "construction_vehicle": L.CONSTRUCTION_VEHICLE,
    "pedestrian": L.PEDESTRIAN,
    "bicycle": L.BICYCLE,
    "motorcycle": L.MOTORCYCLE,
}
_ARTICULATED = frozenset({"pedestrian", "bicycle", "motorcycle"})


@dataclasses.dataclass(frozen=True)
class SyntheticAgent:
    """A moving (or parked) agent of a :class:`SyntheticScene`: one instance.

    Attributes:
        instance_id: 1-based instance id (0 means "no agent" in the instance grids), the
            agent's position in :attr:`SyntheticScene.agents` plus one.
        kind: ``"car"``, ``"truck"``, ``"bus"``, ``"trailer"``, ``"construction_vehicle"``,
            ``"pedestrian"``, ``"bicycle"`` or ``"motorcycle"``.
        label: its Occ3D label.
        articulated: True for pedestrians, bicycles and motorcycles (their limbs move, so
            their shape changes over time); False for the rigid vehicles.
        position: ``(x, y)`` in metres in the world (the reference ego frame) at time 0.
        heading: yaw in radians (0 = +x).
        speed: metres per second along the heading (0: parked).
        phase: gait or crank angle at time 0 (radians; 0 for vehicles).
        shade: brightness factor of its solids in the images.
    """

    instance_id: int
    kind: str
    label: int
    articulated: bool
    position: tuple[float, float]
    heading: float
    speed: float
    phase: float
    shade: float

    def __post_init__(self) -> None:
        check_int("instance_id", self.instance_id, 1)
        if self.kind not in _AGENT_LABELS:
            raise ValueError(f"kind: expected one of {sorted(_AGENT_LABELS)}, got {self.kind!r}")

    @property
    def moving(self) -> bool:
        """Whether the agent moves (``speed > 0``)."""
        return self.speed > 0

    def pose(self, time: float) -> Tensor:
        """``(4, 4)`` float64 agent -> world (the reference ego frame) at ``time`` seconds:
        a yaw by ``heading`` and the translation ``(position + speed * time * forward, 0)``.
        """
        _check_time(time)
        distance = self.speed * float(time)
        pose = torch.eye(4, dtype=torch.float64)
        pose[:3, :3] = yaw_matrix(torch.tensor(self.heading, dtype=torch.float64))
        pose[0, 3] = self.position[0] + distance * math.cos(self.heading)
        pose[1, 3] = self.position[1] + distance * math.sin(self.heading)
        return pose


def _check_time(time: object) -> None:
    if isinstance(time, bool) or not isinstance(time, numbers.Real) or not math.isfinite(time):
        raise ValueError(f"time: expected a finite number of seconds, got {time!r}")


class SyntheticScene:
    """A seeded street scene with rigid and nonrigid agents; frames on demand.

    Args:
        seed: everything random is drawn from it (same seed, same scene).
        grid: the ground-truth voxel grid (Occ3D by default).
        num_frames: frames of the clip; offsets ``-(n // 2) .. (n - 1) // 2``, 0 = reference.
        frame_dt: seconds between frames (nuScenes keyframes: 0.5).
        image_size: ``(H, W)`` of the six camera images. A frame needs about 256 bytes
            per pixel while it is built (about 0.28 GB at 256 x 704): sizes beyond the memory
            limit (:func:`dego.set_memory_limit`) raise ``ValueError`` here, and
            :meth:`frame` / :meth:`frames` check again under the limit of their call.
        num_vehicles: vehicles (parked or moving), >= 5: the first five are a car, a truck,
            a bus, a trailer and a construction vehicle, so every vehicle class occurs.
        num_pedestrians: walking pedestrians, >= 1.
        num_cyclists: riders, >= 2, alternately on a bicycle and on a motorcycle. They
            follow the ego (the k-th of each kind 6 + 12 k to 13 + 12 k metres behind it at
            time 0), bicycles right of the ego lane, motorcycles left of it, in sight of the
            back camera, so that every class of humans and cycles is seen in most frames.
        ego_speed: the ego's speed along +x (m/s).
        label_noise: pseudo-label noise: the probability that a pixel on a class boundary
            takes a neighbour's label. 0 (default) gives exact labels.
        depth_noise: pseudo-depth noise: the relative depth error at 10 m (it grows
            linearly with distance). 0 (default) gives exact depth.

    The solids of a frame are public: :attr:`static_primitives` then, for each agent of
    :attr:`agents`, ``agent_shape(agent, time)`` placed with ``frame.agent_poses`` (world
    coordinates, float32 as :meth:`Primitives.transformed` gives them), then moved into the
    frame's ego coordinates with ``inverse(frame.ego_pose)`` and rasterized with a margin of
    a quarter voxel: that is exactly ``frame.occupancy`` (and the winning solids' agents are
    ``frame.instances``).
    """

    def __init__(
        self,
        seed: int,
        *,
        grid: VoxelGrid | None = None,
        num_frames: int = 5,
        frame_dt: float = 0.5,
        image_size: tuple[int, int] = (64, 176),
        num_vehicles: int = 10,
        num_pedestrians: int = 8,
        num_cyclists: int = 3,
        ego_speed: float = 5.0,
        label_noise: float = 0.0,
        depth_noise: float = 0.0,
    ) -> None:
        check_int("seed", seed)
        for name, value, low in [
            ("num_frames", num_frames, 1),
            ("num_vehicles", num_vehicles, 5),
            ("num_pedestrians", num_pedestrians, 1),
            ("num_cyclists", num_cyclists, 2),
        ]:
            check_int(name, value, low)
        if len(image_size) != 2:
            raise ValueError(f"image_size: expected (H, W), got {image_size!r}")
        for value in image_size:
            check_int("image_size", value, 1)
        check_positive("frame_dt", frame_dt)
        if isinstance(ego_speed, bool) or not math.isfinite(ego_speed) or ego_speed < 0:
            raise ValueError(f"ego_speed: expected a finite number >= 0, got {ego_speed!r}")
        if not 0 <= label_noise <= 1:
            raise ValueError(f"label_noise: expected a probability in [0, 1], got {label_noise!r}")
        if not 0 <= depth_noise < 1:
            raise ValueError(f"depth_noise: expected a number in [0, 1), got {depth_noise!r}")
        if grid is not None and not isinstance(grid, VoxelGrid):
            raise ValueError(f"grid: expected a VoxelGrid, got {type(grid).__name__}")
        self.seed, self.grid = seed, VoxelGrid.occ3d() if grid is None else grid
        self.frame_dt, self.image_size, self.ego_speed = frame_dt, tuple(image_size), ego_speed
        self._check_memory()
        self.label_noise, self.depth_noise = label_noise, depth_noise
        self.offsets = tuple(range(-(num_frames // 2), (num_frames - 1) // 2 + 1))
        self._generator = torch.Generator().manual_seed(seed)
        self.crossing_x = self._uniform(12, 22)
        self._static = self._build_static()
        self._agents = self._build_agents(num_vehicles, num_pedestrians, num_cyclists)
        self._lidar_rays = generate_lidar_rays()

    # -- the world --------------------------------------------------------------------
    def _rand(self) -> float:
        """The next number in [0, 1) of the scene's generator."""
        return float(torch.rand((), generator=self._generator))

    def _uniform(self, low: float, high: float) -> float:
        return low + (high - low) * self._rand()

    def _build_static(self) -> Primitives:
        cx = self.crossing_x
        parts = [
            _boxes([0, 0, -0.5], [160, 160, 1.0], 0, L.TERRAIN),
            _boxes(
                [[0, 0.75, -0.5], [cx, 0, -0.5]],
                [[160, 10.5, 1.0], [8, 160, 1.0]],
                0,
                L.DRIVEABLE_SURFACE,
            ),
            # a flat parking area beside the crossing (other_flat)
            _boxes([cx + 13, -16, -0.45], [14, 10, 1.0], 0, L.OTHER_FLAT),
        ]
        for y in (-6.0, 7.5):  # raised sidewalks from x = -80 to 80, cut by the crossing
            west, east = (-80.0, cx - 4), (cx + 4, 80.0)
            parts.append(
                _boxes(
                    [[sum(west) / 2, y, -0.425], [sum(east) / 2, y, -0.425]],
                    [[west[1] - west[0], 3.0, 1.15], [east[1] - east[0], 3.0, 1.15]],
                    0,
                    L.SIDEWALK,
                )
            )
        for side in (-1, 1):  # buildings along both sides, with gaps
            x = -75.0
            while x < 75:
                length = self._uniform(10, 22)
                if abs(x + length / 2 - cx) > length / 2 + 6 and self._rand() < 0.85:
                    depth, height = self._uniform(8, 14), self._uniform(4, 14)
                    y = side * (11.5 + depth / 2) + (1.5 if side > 0 else 0)
                    parts.append(
                        _boxes(
                            [x + length / 2, y, height / 2 - 0.2],
                            [length, depth, height],
                            0,
                            L.MANMADE,
                            self._uniform(0.6, 1.0),
                        )
                    )
                x += length + self._uniform(1, 6)
        for side in (-1, 1):  # trees on the terrain strips: trunk and crown
            for x in torch.arange(-70.0, 70.0, 9.0).tolist():
                if abs(x - cx) < 7 or self._rand() < 0.3:
                    continue
                y = side * 9.0 + (0.75 if side > 0 else 0) + self._uniform(-0.4, 0.4)
                x = x + self._uniform(-2, 2)
                height = self._uniform(2.0, 3.5)
                parts.append(
                    Primitives.make(
                        CYLINDER,
                        torch.tensor([[x, y, height / 2]]),
                        torch.eye(3)[None],
                        torch.tensor([[0.2, 0.2, height / 2]]),
                        L.VEGETATION,
                        0.55,
                    )
                )
                radius = self._uniform(1.3, 2.4)
                parts.append(
                    Primitives.make(
                        ELLIPSOID,
                        torch.tensor([[x, y, height + radius * 0.8]]),
                        torch.eye(3)[None],
                        torch.tensor([[radius, radius, radius * 0.8]]),
                        L.VEGETATION,
                        self._uniform(0.7, 1.0),
                    )
                )
        # barriers along the crossing's corners, traffic cones by the parking lane
        parts.append(
            _boxes(
                [[cx - 6, 5.2, 0.45], [cx + 6, -3.9, 0.45]],
                [[2.0, 0.35, 0.9], [2.0, 0.35, 0.9]],
                [0.0, 0.0],
                L.BARRIER,
            )
        )
        cones = torch.tensor([[cx - 9 + 1.5 * i, -4.2, 0.35] for i in range(4)])
        parts.append(
            Primitives.make(
                CYLINDER,
                cones,
                torch.eye(3).expand(4, 3, 3),
                torch.tensor([[0.18, 0.18, 0.35]]).expand(4, 3),
                L.TRAFFIC_CONE,
            )
        )
        # "others": a few loose objects on the sidewalk
        parts.append(
            _boxes(
                [[cx - 20, -6.5, 0.55], [cx + 25, 7.8, 0.55]],
                [[0.9, 0.9, 0.8]] * 2,
                [0.3, -0.4],
                L.OTHERS,
            )
        )
        return Primitives.cat(parts)

    def _build_agents(
        self, vehicles: int, pedestrians: int, cyclists: int
    ) -> tuple[SyntheticAgent, ...]:
        agents: list[SyntheticAgent] = []

        def add(
            kind: str,
            position: tuple[float, float],
            heading: float,
            speed: float,
            phase: float,
            shade: float,
        ) -> None:
            agents.append(
                SyntheticAgent(
                    instance_id=len(agents) + 1,
                    kind=kind,
                    label=int(_AGENT_LABELS[kind]),
                    articulated=kind in _ARTICULATED,
                    position=(float(position[0]), float(position[1])),
                    heading=float(heading),
                    speed=float(speed),
                    phase=float(phase),
                    shade=float(shade),
                )
            )

        vehicle_types = ["car", "truck", "bus", "trailer", "construction_vehicle"]
        taken: dict[float, list[tuple[float, float]]] = {}  # parked intervals per lane
        for i in range(vehicles):
            kind = vehicle_types[i] if i < len(vehicle_types) else ("car", "truck")[i % 2]
            parked = kind in ("trailer", "construction_vehicle") or self._rand() < 0.4
            if parked:  # the parking lane on the right, or on the far side of the road
                y, heading, speed = (-3.4 if i % 2 else 4.6), 0.0, 0.0
            elif self._rand() < 0.5:
                y, heading, speed = 0.0, 0.0, self._uniform(4, 11)
            else:
                y, heading, speed = 3.5, math.pi, self._uniform(4, 11)
            x = self._uniform(-36, 36)
            if parked:
                x = self._parking_spot(y, _VEHICLE_LENGTHS[kind], taken)
            elif y == 0.0:  # the ego's lane: only pull away from the ego, never close in
                ahead = self._rand() < 0.7
                x = (1 if ahead else -1) * self._uniform(15, 36)
                low = min(self.ego_speed, max(self.ego_speed - 2, 3.0))
                speed = (
                    self._uniform(self.ego_speed, self.ego_speed + 6)
                    if ahead
                    else self._uniform(low, self.ego_speed)
                )
            add(kind, (x, y), heading, speed, 0.0, self._uniform(0.6, 1.0))
        for i in range(pedestrians):
            if i % 3 == 2:  # crossing the street on the crosswalk
                position = (self.crossing_x + self._uniform(-2, 2), self._uniform(-5, 5))
                heading = math.pi / 2 * (1 if self._rand() < 0.5 else -1)
            else:
                side = -6.0 if i % 2 else 7.5
                position = (self._uniform(-35, 35), side + self._uniform(-0.8, 0.8))
                heading = 0.0 if self._rand() < 0.5 else math.pi
            speed = self._uniform(1.1, 1.6)
            phase = self._uniform(0, 2 * math.pi)
            add("pedestrian", position, heading, speed, phase, self._uniform(0.6, 1.0))
        for i in range(cyclists):
            # riders follow the ego in its direction, the k-th of each kind 6 + 12 k to
            # 13 + 12 k m behind it, in plain sight of the back camera and never in the ego's
            # blind spots beside it: bicycles right of the ego lane, motorcycles left of it
            # (between the ego lane's vehicles, |y| <= 1.3, and the oncoming ones, y >= 2.2)
            motor, k = i % 2 == 1, i // 2
            x = -(6 + 12 * k + self._uniform(0, 7))
            if motor:  # about the ego's speed: it stays behind the ego over the clip
                low = max(self.ego_speed - 1.5, 0.0)
                speed = self._uniform(low, self.ego_speed + 1.5)
            else:
                speed = self._uniform(3.5, 6)
            phase = self._uniform(0, 2 * math.pi)
            kind, y = ("motorcycle", 1.75) if motor else ("bicycle", -1.6)
            add(kind, (x, y), 0.0, speed, phase, self._uniform(0.6, 1.0))
        return tuple(agents)

    def _parking_spot(
        self, lane: float, length: float, taken: dict[float, list[tuple[float, float]]]
    ) -> float:
        """A parking position in ``lane`` clear of the ego (|x| > 8 m), of the crossing and
        its cones and barriers, and of the vehicles already parked there."""
        cx, intervals = self.crossing_x, taken.setdefault(lane, [])
        for _ in range(200):
            x = self._uniform(-38, 38)
            low, high = x - length / 2 - 0.8, x + length / 2 + 0.8
            clear = high < cx - 12 or low > cx + 9
            clear &= high < -8 or low > 8
            if clear and all(high < a or low > b for a, b in intervals):
                intervals.append((low, high))
                return x
        return -60.0  # the street is full: park out of sight

    # -- agents at a time -------------------------------------------------------------
    @staticmethod
    def _vehicle(kind: str, label: int) -> Primitives:
        """A vehicle in its own frame (x forward, ground at z = 0)."""
        if kind == "car":
            return _boxes(
                [[0, 0, 0.75], [-0.3, 0, 1.5]], [[4.5, 1.9, 1.0], [2.4, 1.7, 0.6]], [0, 0], label
            )
        if kind == "truck":
            return _boxes(
                [[2.6, 0, 1.5], [-1.2, 0, 1.8]], [[1.9, 2.4, 2.6], [5.6, 2.5, 3.2]], [0, 0], label
            )
        if kind == "bus":
            return _boxes([0, 0, 1.75], [11.5, 2.6, 3.1], 0, label)
        if kind == "trailer":
            return _boxes(
                [[0, 0, 2.0], [4.4, 0, 0.9]], [[8.0, 2.5, 3.0], [1.0, 0.3, 0.3]], [0, 0], label
            )
        # construction vehicle: body, cabin and a raised arm
        arm = Primitives.make(
            BOX,
            torch.tensor([[2.8, 0.0, 3.1]]),
            axis_to_matrix(torch.tensor([[0.8, 0.0, 0.6]])),
            torch.tensor([[0.25, 0.25, 1.8]]),
            label,
        )
        return Primitives.cat(
            [
                _boxes(
                    [[0, 0, 1.1], [-0.8, 0, 2.7]], [[5.0, 2.5, 1.8], [2.0, 2.0, 1.4]], [0, 0], label
                ),
                arm,
            ]
        )

    @staticmethod
    def _person(phase: float, label: int, riding: bool = False) -> Primitives:
        """An articulated person in its own frame (facing +x, feet on z = 0); ``phase`` is
        the gait (or pedalling) angle, so limbs move with time."""
        parts = []
        lift = 0.35 if riding else 0.0  # riders sit: hips higher above their feet
        hip_z, shoulder_z = 0.95 + lift, 1.45 + lift
        lean = 0.35 if riding else 0.0
        torso_centre = torch.tensor([[0.1 * lean, 0.0, (hip_z + shoulder_z) / 2]])
        parts.append(
            Primitives.make(
                ELLIPSOID,
                torso_centre,
                axis_to_matrix(torch.tensor([[lean, 0.0, 1.0]])),
                torch.tensor([[0.2, 0.13, 0.3]]),
                label,
            )
        )
        parts.append(
            Primitives.make(
                ELLIPSOID,
                torch.tensor([[0.25 * lean, 0.0, shoulder_z + 0.22]]),
                torch.eye(3)[None],
                torch.tensor([[0.1, 0.1, 0.12]]),
                label,
            )
        )
        for side in (-1.0, 1.0):
            angle = phase + (0.0 if side > 0 else math.pi)
            hip = torch.tensor([0.0, 0.1 * side, hip_z])
            if riding:  # pedalling: the foot circles around the crank
                foot = torch.tensor(
                    [0.35 + 0.17 * math.cos(angle), 0.15 * side, 0.35 + 0.17 * math.sin(angle)]
                )
                knee = (hip + foot) / 2 + torch.tensor([0.28, 0.0, 0.12])
            else:  # walking: thigh swings, knee bends on the back swing
                thigh = 0.45 * math.sin(angle)
                shin = thigh - 0.6 * max(0.0, -math.cos(angle))
                knee = hip + 0.45 * torch.tensor([math.sin(thigh), 0.0, -math.cos(thigh)])
                foot = knee + 0.45 * torch.tensor([math.sin(shin), 0.0, -math.cos(shin)])
            parts.append(_segment_ellipsoids(hip[None], knee[None], 0.075, label))
            parts.append(_segment_ellipsoids(knee[None], foot[None], 0.06, label))
            swing = -0.35 * math.sin(angle) if not riding else 0.9
            shoulder = torch.tensor([0.1 * lean, 0.24 * side, shoulder_z - 0.05])
            elbow = shoulder + 0.3 * torch.tensor([math.sin(swing), 0.0, -math.cos(swing)])
            hand = elbow + 0.28 * torch.tensor([math.sin(swing + 0.3), 0.0, -math.cos(swing + 0.3)])
            parts.append(_segment_ellipsoids(shoulder[None], elbow[None], 0.05, label))
            parts.append(_segment_ellipsoids(elbow[None], hand[None], 0.045, label))
        return Primitives.cat(parts)

    @classmethod
    def _cycle(cls, motor: bool, phase: float, label: int) -> Primitives:
        wheel = 0.33 if motor else 0.35
        wheels = Primitives.make(
            CYLINDER,
            torch.tensor([[0.55, 0.0, wheel], [-0.55, 0.0, wheel]]),
            axis_to_matrix(torch.tensor([[0.0, 1.0, 0.0]])).expand(2, 3, 3),
            torch.tensor([[wheel, wheel, 0.05 if not motor else 0.09]]).expand(2, 3),
            label,
        )
        frame = _boxes(
            [0, 0, 0.62], [1.0, 0.12 if not motor else 0.45, 0.25 if not motor else 0.45], 0, label
        )
        rider = cls._person(phase, label, riding=True).transformed(
            torch.eye(3), torch.tensor([-0.2, 0.0, 0.0])
        )
        return Primitives.cat([wheels, frame, rider])

    @property
    def agents(self) -> tuple[SyntheticAgent, ...]:
        """Every agent, in instance order: ``agents[i].instance_id == i + 1``."""
        return self._agents

    @property
    def static_primitives(self) -> Primitives:
        """The static solids (ground, buildings, vegetation, barriers, cones, others) in
        world coordinates; the first solids of :meth:`primitives` at any time."""
        return self._static

    def agent_shape(self, agent: SyntheticAgent, time: float) -> Primitives:
        """The solids of ``agent`` in its own frame (x forward, ground at z = 0) at ``time``
        seconds, shaded by ``agent.shade``: vehicles do not depend on the time, pedestrians
        and riders have the limbs of that time's gait or crank phase. Placed with
        ``pose = agent.pose(time)`` (``shape.transformed(pose[:3, :3], pose[:3, 3])``) they
        are the agent's solids in :meth:`primitives`."""
        if not isinstance(agent, SyntheticAgent):
            raise ValueError(f"agent: expected a SyntheticAgent, got {type(agent).__name__}")
        _check_time(time)
        if agent.kind == "pedestrian":
            cadence = 2 * math.pi * 0.9 * agent.speed / 1.3  # steps per second ~ speed
            shape = self._person(agent.phase + cadence * time, agent.label)
        elif agent.kind in ("bicycle", "motorcycle"):
            crank = agent.phase + 2 * math.pi * agent.speed / 2.0 * time
            shape = self._cycle(agent.kind == "motorcycle", crank, agent.label)
        else:
            shape = self._vehicle(agent.kind, agent.label)
        return dataclasses.replace(shape, shades=shape.shades * agent.shade)

    def _solids_at(self, time: float) -> tuple[Primitives, Tensor]:
        """Every solid at ``time`` in world coordinates (static scene first, then the agents
        in instance order) and its ``(P,)`` int64 instance id (0 for static solids)."""
        parts = [self._static]
        ids = [torch.zeros(len(self._static), dtype=torch.long)]
        for agent in self._agents:
            pose = agent.pose(time)
            shape = self.agent_shape(agent, time)
            parts.append(shape.transformed(pose[:3, :3], pose[:3, 3]))
            ids.append(torch.full((len(shape),), agent.instance_id, dtype=torch.long))
        return Primitives.cat(parts), torch.cat(ids)

    # -- poses and cameras ------------------------------------------------------------
    def ego_pose(self, time: float) -> Tensor:
        """``(4, 4)`` float64 ego -> world (the reference ego frame) at ``time`` seconds."""
        pose = torch.eye(4, dtype=torch.float64)
        pose[0, 3] = self.ego_speed * time
        return pose

    def camera_to_ego(self) -> Tensor:
        """``(V, 4, 4)`` float64 OpenCV camera -> ego transforms of the rig."""
        poses = []
        for _, position, yaw in CAMERAS:
            psi = math.radians(yaw)
            forward = [math.cos(psi), math.sin(psi), 0.0]
            right = [math.sin(psi), -math.cos(psi), 0.0]
            pose = torch.eye(4, dtype=torch.float64)
            pose[:3, :3] = torch.tensor([right, [0.0, 0.0, -1.0], forward], dtype=torch.float64).T
            pose[:3, 3] = torch.tensor(position, dtype=torch.float64)
            poses.append(pose)
        return torch.stack(poses)

    def intrinsics(self) -> Tensor:
        """``(V, 3, 3)`` float64 pinhole intrinsics for ``image_size``."""
        h, w = self.image_size
        sx, sy = w / _BASE_SIZE[1], h / _BASE_SIZE[0]
        k = torch.tensor(
            [
                [_BASE_FOCAL * sx, 0, _BASE_CENTRE[0] * sx],
                [0, _BASE_FOCAL * sy, _BASE_CENTRE[1] * sy],
                [0, 0, 1],
            ],
            dtype=torch.float64,
        )
        return k.expand(len(CAMERAS), 3, 3).clone()

    def primitives(self, time: float) -> Primitives:
        """Every solid at ``time`` seconds, in world coordinates (static scene first)."""
        _check_time(time)
        return self._solids_at(time)[0]

    # -- frames -----------------------------------------------------------------------
    def _check_offset(self, offset: object) -> float:
        """The time of frame ``offset`` (one of ``self.offsets``)."""
        if isinstance(offset, bool) or not isinstance(offset, int) or offset not in self.offsets:
            raise ValueError(f"offset: expected one of {self.offsets}, got {offset!r}")
        return offset * self.frame_dt

    def _check_memory(self, kept: int = 0) -> None:
        """The memory guard (:func:`dego._policy.check_memory`) for building a frame while
        ``kept`` frames are held (:meth:`frames` keeps them all)."""
        h, w = self.image_size
        pixels = len(CAMERAS) * h * w
        nbytes = pixels * (_PEAK_BYTES_PER_PIXEL + _KEPT_BYTES_PER_PIXEL * kept)
        held = f", {kept} frames of {_KEPT_BYTES_PER_PIXEL} bytes each kept" if kept else ""
        check_memory(
            "SyntheticScene",
            nbytes,
            f"image_size={self.image_size}: {len(CAMERAS)} cameras x {h} x {w} pixels, about "
            f"{_PEAK_BYTES_PER_PIXEL} bytes each while a frame is built{held}",
        )

    def _ego_solids(self, time: float) -> tuple[Primitives, Tensor]:
        """Every solid at ``time`` in that time's ego coordinates, and its instance id."""
        world_to_ego = torch.linalg.inv(self.ego_pose(time))
        solids, ids = self._solids_at(time)
        return solids.transformed(world_to_ego[:3, :3], world_to_ego[:3, 3]), ids

    def _camera_rays(self) -> tuple[Tensor, Tensor]:
        """``(V * H * W, 3)`` ego-frame origins (float64) and directions (float32) of the
        pixel centres' rays, with camera z = 1 (the ray parameter is the z-depth)."""
        cam_to_ego, k = self.camera_to_ego(), self.intrinsics()
        h, w = self.image_size
        v_idx, u_idx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        pixels = torch.stack([u_idx + 0.5, v_idx + 0.5, torch.ones(h, w)], -1).double()
        rays_cam = pixels.reshape(-1, 3) @ torch.linalg.inv(k[0]).T
        directions = torch.einsum("vij,rj->vri", cam_to_ego[:, :3, :3], rays_cam)
        origins = cam_to_ego[:, None, :3, 3].expand_as(directions)
        return origins.reshape(-1, 3), directions.reshape(-1, 3).float()

    @staticmethod
    def _pixel_instances(index: Tensor, ids: Tensor, shape: tuple[int, ...]) -> Tensor:
        return torch.where(index >= 0, ids[index.clamp_min(0)], 0).view(shape)

    def instance_pixels(self, offset: int) -> Tensor:
        """``(V, H, W)`` int64 instance id of the first solid each pixel's ray hits in frame
        ``offset`` (0 for static solids and sky): :attr:`SyntheticFrame.instance_pixels`
        without building the rest of the frame (only the camera ray cast)."""
        time = self._check_offset(offset)
        self._check_memory()
        solids, ids = self._ego_solids(time)
        origins, directions = self._camera_rays()
        _, index = solids.intersect(origins.float(), directions)
        return self._pixel_instances(index, ids, (len(CAMERAS), *self.image_size))

    def frame(self, offset: int) -> SyntheticFrame:
        """The frame at integer ``offset`` (one of ``self.offsets``)."""
        time = self._check_offset(offset)
        self._check_memory()
        ego_pose = self.ego_pose(time)
        solids, ids = self._ego_solids(time)
        winner = solids.rasterize_index(self.grid, _VOXEL_MARGIN * min(self.grid.voxel_size))
        occupied = winner >= 0
        # the labels and instances of the winning solids (Primitives.rasterize's rule)
        occupancy = torch.where(occupied, solids.labels[winner.clamp_min(0)], FREE_LABEL)
        occupancy = occupancy.to(torch.uint8)
        instances = torch.where(occupied, ids[winner.clamp_min(0)], 0)

        h, w = self.image_size
        shape = (len(CAMERAS), h, w)
        origins, directions = self._camera_rays()
        t, index = solids.intersect(origins.float(), directions)
        hit = index >= 0
        depth = torch.where(hit, t, 0.0).view(shape)
        semantics = torch.where(hit, solids.labels[index.clamp_min(0)], FREE_LABEL).view(shape)
        instance_pixels = self._pixel_instances(index, ids, shape)
        images = self._shade(
            semantics, depth, torch.where(hit, solids.shades[index.clamp_min(0)], 1.0)
        )
        depth, semantics = self._pseudo_label_noise(depth, semantics, offset)

        labels = occupancy.long()
        mask_camera = observed_voxels(labels, origins, directions, self.grid)
        lidar = torch.tensor(LIDAR_ORIGIN, dtype=torch.float64)
        mask_lidar = observed_voxels(
            labels, lidar.expand_as(self._lidar_rays), self._lidar_rays, self.grid
        )
        world_to_cam = torch.linalg.inv(ego_pose @ self.camera_to_ego())
        agent_poses = torch.stack([agent.pose(time) for agent in self._agents])
        return SyntheticFrame(
            time=time,
            offset=offset,
            images=images,
            depth=depth.float(),
            semantics=semantics,
            world_to_cam=world_to_cam.float(),
            intrinsics=self.intrinsics().float(),
            ego_pose=ego_pose.float(),
            lidar_origin=lidar.float(),
            occupancy=occupancy,
            mask_camera=mask_camera,
            mask_lidar=mask_lidar,
            instances=instances,
            instance_pixels=instance_pixels,
            agent_poses=agent_poses,
        )

    def frames(self) -> list[SyntheticFrame]:
        """Every frame of the clip, in offset order."""
        self._check_memory(kept=len(self.offsets))
        return [self.frame(offset) for offset in self.offsets]

    @staticmethod
    def _shade(semantics: Tensor, depth: Tensor, shades: Tensor) -> Tensor:
        palette = torch.tensor(PALETTE, dtype=torch.float32) / 255
        colours = palette[semantics]  # (V, H, W, 3)
        falloff = 0.55 + 0.45 * torch.exp(-depth / 45)
        lit = colours * (shades.view_as(depth) * falloff).unsqueeze(-1)
        sky = torch.tensor(_SKY).expand_as(lit)
        images = torch.where((semantics == FREE_LABEL).unsqueeze(-1), sky, lit)
        return images.permute(0, 3, 1, 2).contiguous().clamp(0, 1)

    def _pseudo_label_noise(
        self, depth: Tensor, semantics: Tensor, offset: int
    ) -> tuple[Tensor, Tensor]:
        """Metric3D / Grounded-SAM-like noise: relative depth noise growing with distance,
        boundary pixels taking a neighbour's label."""
        if self.depth_noise == 0 and self.label_noise == 0:
            return depth, semantics
        g = torch.Generator().manual_seed(self.seed * 1000 + offset + 500)
        noise = torch.randn(depth.shape, generator=g)
        depth = torch.where(
            depth > 0, depth * (1 + self.depth_noise * depth / 10 * noise).clamp_min(0.05), depth
        )
        padded = torch.nn.functional.pad(semantics.float()[:, None], (1, 1, 1, 1), mode="replicate")
        right, down = padded[:, 0, 1:-1, 2:].long(), padded[:, 0, 2:, 1:-1].long()
        boundary = (right != semantics) | (down != semantics)
        swap = boundary & (torch.rand(semantics.shape, generator=g) < self.label_noise)
        use_right = torch.rand(semantics.shape, generator=g) < 0.5
        neighbour = torch.where(use_right & (right != semantics), right, down)
        return depth, torch.where(swap, neighbour, semantics)


__all__ = [
    "CAMERAS",
    "LIDAR_ORIGIN",
    "SyntheticAgent",
    "SyntheticFrame",
    "SyntheticScene",
]
