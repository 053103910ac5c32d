"""One small training step that calls every public op, for the torch.compile and autocast
tests and benchmarks/bench_compile.py: splat, the gsplat adapter, voxelize, the deformation
network, the teacher, the distillation loss, ray casting and both metrics' updates."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import torch
from torch import Tensor
from torch.utils._pytree import tree_map

from dego import (
    DecoupledDeformation,
    DeformationOutput,
    FactorizedSpatioTemporalTeacher,
    FactorizedTeacherFeatures,
    GaussianSet,
    OccupancyMetrics,
    RayIoU,
    VoxelGrid,
    cast_rays,
    distillation_loss,
    splat,
    voxelize,
)
from dego.compat import gsplat as compat_gsplat

HEIGHT, WIDTH = 16, 32
GRID = VoxelGrid((-8.0, -8.0, -2.0), (8.0, 8.0, 2.0), 0.8)
CHANNELS = 4


def cameras(views: int = 2) -> tuple[Tensor, Tensor]:
    """``(1, V, 4, 4)`` world_to_cam and ``(1, V, 3, 3)`` K, yawed around z, 1 m up."""
    w2c, k = [], []
    for i in range(views):
        yaw = 2 * math.pi * i / views
        forward = torch.tensor([math.cos(yaw), math.sin(yaw), 0.0])
        right = torch.tensor([math.sin(yaw), -math.cos(yaw), 0.0])
        rotation = torch.stack([right, torch.tensor([0.0, 0.0, -1.0]), forward])
        m = torch.eye(4)
        m[:3, :3] = rotation
        m[:3, 3] = -rotation @ torch.tensor([0.0, 0.0, 1.0])
        w2c.append(m)
        k.append(torch.tensor([[24.0, 0, WIDTH / 2], [0, 24.0, HEIGHT / 2], [0, 0, 1]]))
    return torch.stack(w2c)[None], torch.stack(k)[None]


@dataclasses.dataclass
class StepInputs:
    """Leaves that require grad (``means``, ``features``) and the fixed inputs."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    features: Tensor
    world_to_cam: Tensor
    intrinsics: Tensor
    images: Tensor  # (1, T, V, 3, H, W) teacher input
    labels: Tensor  # (X, Y, Z) ground truth on GRID
    directions: Tensor  # (R, 3)
    backend: str = "torch"  # splat's backend (the adapter's too)


def make_inputs(
    seed: int = 0, n: int = 200, *, device: str = "cpu", backend: str = "torch"
) -> StepInputs:
    """The same values on every device (drawn on the CPU, then moved)."""
    g = torch.Generator().manual_seed(seed)
    w2c, k = cameras()
    means = (torch.rand(1, n, 3, generator=g) - 0.5) * torch.tensor([14.0, 14.0, 3.0])
    return StepInputs(
        means=means.to(device).requires_grad_(True),
        quats=torch.randn(1, n, 4, generator=g).to(device),
        scales=(0.2 + 0.5 * torch.rand(1, n, 3, generator=g)).to(device),
        opacities=(0.2 + 0.7 * torch.rand(1, n, generator=g)).to(device),
        features=torch.randn(1, n, CHANNELS, generator=g).to(device).requires_grad_(True),
        world_to_cam=w2c.to(device),
        intrinsics=k.to(device),
        images=torch.rand(1, 2, 2, 3, HEIGHT, WIDTH, generator=g).to(device),
        labels=torch.randint(0, 18, GRID.shape, generator=g).to(device),
        directions=torch.randn(40, 3, generator=g).to(device),
        backend=backend,
    )


@dataclasses.dataclass
class StepModules:
    deformation: DecoupledDeformation
    teacher: FactorizedSpatioTemporalTeacher
    targets: FactorizedTeacherFeatures
    occupancy: OccupancyMetrics
    rayiou: RayIoU


def make_modules(seed: int = 0, *, device: str = "cpu") -> StepModules:
    modules = _make_modules(seed)
    modules.deformation.to(device)
    modules.teacher.to(device)
    modules.targets.to(device)
    modules.occupancy.to(device)
    modules.rayiou.to(device)
    return modules


def _make_modules(seed: int) -> StepModules:
    torch.manual_seed(seed)
    deformation = DecoupledDeformation(CHANNELS, hidden_dim=32, head_hidden=32, depth=2)
    with torch.no_grad():  # non-zero heads: the zero-initialised identity would hide errors
        for head in deformation.heads.values():
            head[-1].weight.normal_(0, 0.05)
    teacher = FactorizedSpatioTemporalTeacher(embed_dim=32, depth=1, num_heads=2, patch_size=8)
    rays = torch.nn.functional.normalize(torch.randn(30, 3, generator=torch.Generator()), dim=-1)
    return StepModules(
        deformation=deformation,
        teacher=teacher,
        targets=FactorizedTeacherFeatures(64, CHANNELS),
        occupancy=OccupancyMetrics("occ3d"),
        rayiou=RayIoU(grid=GRID, rays=rays),
    )


OPS: tuple[str, ...] = (
    "splat",
    "gsplat_adapter",
    "voxelize",
    "deformation",
    "teacher",
    "distillation_loss",
    "cast_rays",
    "occupancy_update",
    "rayiou_update",
)


def op_functions(inputs: StepInputs, modules: StepModules) -> dict[str, Callable[[], Tensor]]:
    """Each public op alone, as a function returning a scalar (for ``torch._dynamo.explain``)."""
    gaussians = gaussian_set(inputs)

    pred = (inputs.labels + 1) % 18
    with torch.no_grad():
        teacher = targets(inputs, modules)
    student = (teacher + 0.1 * torch.randn_like(teacher)).requires_grad_(True)

    def occupancy_update() -> Tensor:
        modules.occupancy.update(pred, inputs.labels, mask=None)
        return modules.occupancy.confusion.sum()

    def rayiou_update() -> Tensor:
        modules.rayiou.update(pred, inputs.labels, torch.zeros(1, 3))
        return modules.rayiou.true_positives.sum()

    return {
        "splat": lambda: render(gaussians, inputs).sum(),
        "gsplat_adapter": lambda: adapter(gaussians, inputs).sum(),
        "voxelize": lambda: voxelize(gaussians, GRID).density.sum(),
        "deformation": lambda: deform(gaussians, modules).gaussians.means.sum(),
        "teacher": lambda: targets(inputs, modules).sum(),
        "distillation_loss": lambda: distillation_loss(student, teacher),
        "cast_rays": lambda: cast_rays(inputs.labels, torch.zeros(1, 3), inputs.directions, GRID)[
            0
        ].sum(),
        "occupancy_update": occupancy_update,
        "rayiou_update": rayiou_update,
    }


def gaussian_set(inputs: StepInputs) -> GaussianSet:
    return GaussianSet(
        means=inputs.means,
        quats=inputs.quats,
        scales=inputs.scales,
        opacities=inputs.opacities,
        features=inputs.features,
    )


def render(gaussians: GaussianSet, inputs: StepInputs) -> Tensor:
    """``(1, V, C, H, W)`` rendered features."""
    out = splat(
        gaussians,
        inputs.world_to_cam,
        inputs.intrinsics,
        (HEIGHT, WIDTH),
        backend=inputs.backend,  # type: ignore[arg-type]
    )
    return out.features


def adapter(gaussians: GaussianSet, inputs: StepInputs) -> Tensor:
    colors, alphas, _ = compat_gsplat.rasterization(
        gaussians.means[0],
        gaussians.quats[0],
        gaussians.scales[0],
        gaussians.opacities[0],
        gaussians.features[0],
        inputs.world_to_cam[0],
        inputs.intrinsics[0],
        WIDTH,
        HEIGHT,
        render_mode="RGB+ED",
        backend=inputs.backend,  # type: ignore[arg-type]
    )
    return colors.sum() + alphas.sum()


def deform(gaussians: GaussianSet, modules: StepModules) -> DeformationOutput:
    times = torch.tensor([0.0, 1.0], dtype=gaussians.dtype, device=gaussians.device)
    return modules.deformation(gaussians, gaussians.features, times)


def targets(inputs: StepInputs, modules: StepModules) -> Tensor:
    return modules.targets(modules.teacher(inputs.images), (HEIGHT, WIDTH))


def training_step(inputs: StepInputs, modules: StepModules) -> tuple[Tensor, dict[str, Tensor]]:
    """Every op in one step: a scalar loss (differentiable w.r.t. the means and features)
    and the detached values each op produced."""
    gaussians = gaussian_set(inputs)
    deformed = deform(gaussians, modules)
    last = tree_map(lambda t: t[:, -1], deformed.gaussians)  # (B, T) -> the last time
    rendered = render(last, inputs)
    teacher = targets(inputs, modules)
    distill = distillation_loss(rendered, teacher.detach())
    voxels = voxelize(last, GRID)
    adapted = adapter(last, inputs)
    origins = torch.zeros(1, 3, device=inputs.labels.device)
    distance, hit = cast_rays(inputs.labels, origins, inputs.directions, GRID)
    pred = voxels.features.argmax(-1)[0] % 18
    modules.occupancy.update(pred, inputs.labels, mask=None)
    modules.rayiou.update(pred, inputs.labels, origins)
    loss = (
        distill
        + 1e-3 * rendered.square().mean()
        + 1e-3 * voxels.density.mean()
        + 1e-6 * adapted
        + 1e-2 * deformed.rigid_mask.mean()
    )
    values = {
        "rendered": rendered.detach(),
        "teacher": teacher.detach(),
        "density": voxels.density.detach(),
        "distance": distance,
        "hit": hit,
        "confusion": modules.occupancy.confusion.clone(),
        "ray_true_positives": modules.rayiou.true_positives.clone(),
    }
    return loss, values
