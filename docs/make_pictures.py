"""Draw the pictures of the module pages (docs/images/*.png) with dego itself.

    python docs/make_pictures.py                        # all of PICTURES
    python docs/make_pictures.py synthetic_bev.png ...  # only these

Deterministic (fixed seeds, matplotlib's Agg renderer, no pyplot); about 20 s on one
CPU core. Every picture in docs/images comes from a command in this repository:

=================================  =====================================================
picture                            command
=================================  =====================================================
foundation_gaussians.png,          ``python docs/make_pictures.py`` (this file)
voxelizer_bev.png,
deformation_mask.png,
teacher_targets.png,
metrics_bev.png, rayiou_rays.png,
synthetic_cameras.png,
synthetic_bev.png
w1_depth_semantics.png             ``python benchmarks/bench_splat.py --skip-w2
                                   --repeats 1 --png docs/images/w1_depth_semantics.png``
demo_bev_{static,rigid,            ``OMP_NUM_THREADS=1 dego demo --out /tmp/demo`` (seed 0,
decoupled,true-motion}.png,        full run), then copy ``bev_*.png``,
demo_camera_decoupled.png,         ``camera_decoupled.png`` and ``losses.png`` to
demo_losses.png                    ``docs/images/demo_*.png``
study.png                          ``OMP_NUM_THREADS=1 dego study --out /tmp/study``, copy
                                   ``study.png``
=================================  =====================================================
"""

from __future__ import annotations

import functools
import math
import sys
from pathlib import Path

import torch
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse

from dego import (
    CLASS_NAMES,
    FREE_LABEL,
    INSTANCE_CLASSES,
    PALETTE,
    DecoupledDeformation,
    DeformationLossWeights,
    GaussianSet,
    OccupancyMetrics,
    PositionalEncoding,
    RayIoU,
    SyntheticFrame,
    SyntheticScene,
    VoxelGrid,
    cast_rays,
    deformation_loss,
    generate_lidar_rays,
    lidar_origins,
    splat,
    viz,
    voxelize,
)
from dego import Occ3DLabel as L
from dego.teacher import (
    FactorizedSpatioTemporalTeacher,
    FactorizedTeacherFeatures,
    StudentProjector,
    distillation_loss,
)

IMAGES = Path(__file__).resolve().parent / "images"
DPI = 80
CROP = VoxelGrid(lower=(-16, -16, -1), upper=(16, 16, 5.4), voxel_size=0.4)
NEAR = (slice(60, 140), slice(60, 140))  # CROP's columns in the Occ3D grid


def new_figure(width: float, height: float) -> Figure:
    return Figure(figsize=(width, height), layout="constrained")


@functools.cache
def reference_frame() -> SyntheticFrame:
    return SyntheticScene(seed=0, image_size=(32, 88)).frame(0)


def surface_gaussians(
    frame: SyntheticFrame, grid: VoxelGrid, visible_only: bool = False
) -> GaussianSet:
    """One small Gaussian per occupied ground-truth voxel with a free neighbour, with
    one-hot logits of classes 0..16 as features."""
    gt = frame.occupancy.long()
    occupied = gt != FREE_LABEL
    padded = torch.nn.functional.pad(occupied[None, None].float(), (1,) * 6, value=1.0)[0, 0]
    padded[..., -1] = 0  # open sky above the grid: roofs cut by it are surface too
    inner = -torch.nn.functional.max_pool3d(-padded[None], 3, stride=1)[0]
    surface = occupied & (inner == 0)
    if visible_only:
        surface &= frame.mask_camera
    voxels = surface.nonzero()
    n = voxels.shape[0]
    g = torch.Generator().manual_seed(0)
    return GaussianSet(
        means=(grid.index_to_world(voxels) + 0.03 * torch.randn(n, 3, generator=g))[None],
        quats=torch.randn(1, n, 4, generator=g),
        scales=0.1 + 0.04 * torch.rand(1, n, 3, generator=g),
        opacities=torch.full((1, n), 0.9),
        features=torch.nn.functional.one_hot(gt[tuple(voxels.T)], 17).float()[None],
    )


def draw_ellipses(
    ax: Axes, means: torch.Tensor, covariances: torch.Tensor, colours: list, **style: object
) -> None:
    """2-sigma ellipses of the x-y marginals of (N, 3) means and (N, 3, 3) covariances."""
    values, vectors = torch.linalg.eigh(covariances[:, :2, :2].double())
    for i in range(means.shape[0]):
        angle = math.degrees(math.atan2(vectors[i, 1, 1], vectors[i, 0, 1]))
        minor, major = (4 * values[i].clamp_min(0).sqrt()).tolist()
        xy = means[i, :2].tolist()
        ax.add_patch(Ellipse(xy, major, minor, angle=angle, color=colours[i], **style))


def perturbed_prediction(gt: torch.Tensor) -> torch.Tensor:
    """Ground truth with known mistakes: objects 1.2 m too far forward, pedestrians
    missed, others / other_flat confused, 10% of the sidewalk as terrain."""
    instance = torch.isin(gt, torch.tensor(INSTANCE_CLASSES))
    pred = torch.where(instance, FREE_LABEL, gt)
    shifted = torch.roll(torch.where(instance, gt, FREE_LABEL), shifts=3, dims=0)
    pred = torch.where(shifted != FREE_LABEL, shifted, pred)
    pred[pred == L.PEDESTRIAN] = FREE_LABEL
    pred[gt == L.OTHERS] = L.MANMADE
    pred[gt == L.OTHER_FLAT] = L.DRIVEABLE_SURFACE
    noise = torch.rand(gt.shape, generator=torch.Generator().manual_seed(0))
    pred[(gt == L.SIDEWALK) & (noise < 0.1)] = L.TERRAIN
    return pred


# ------------------------------------------------------------------------------ pictures


def foundation() -> Figure:
    """Gaussians from their covariances, the positional encoding, the class palette."""
    g = torch.Generator().manual_seed(0)
    objects = [  # (label, centre, size, count); the road first, drawn underneath
        (L.DRIVEABLE_SURFACE, (4.0, 0.0), (14.0, 9.0, 0.2), 25),
        (L.CAR, (6.0, -2.0), (4.5, 1.9, 1.6), 12),
        (L.PEDESTRIAN, (2.0, 2.5), (0.6, 0.6, 1.8), 5),
    ]
    sets, colours = [], []
    for label, (x, y), size, count in objects:
        size = torch.tensor(size)
        offsets = (torch.rand(count, 3, generator=g) - 0.5) * size
        sets.append(
            GaussianSet(
                means=torch.tensor([x, y, 0.0]) + offsets,
                quats=torch.randn(count, 4, generator=g) * torch.tensor([1.0, 0.2, 0.2, 1.0]),
                scales=size / 8 * (0.5 + torch.rand(count, 3, generator=g)),
                opacities=torch.full((count,), 0.8),
            )
        )
        colours += [tuple(c / 255 for c in PALETTE[label])] * count
    scene = GaussianSet.cat(sets)

    fig = new_figure(12.0, 3.6)
    ax_g, ax_pe, ax_palette = fig.subplots(1, 3, width_ratios=[1.0, 1.2, 0.9])
    draw_ellipses(ax_g, scene.means, scene.covariances(), colours, fill=False, linewidth=1.2)
    ax_g.set(
        xlim=(-4, 12),
        ylim=(-6, 6),
        aspect="equal",
        xlabel="x [m]",
        ylabel="y [m]",
        title="GaussianSet: 2-sigma ellipses (x-y)",
    )

    x = torch.linspace(-math.pi, math.pi, 400)[:, None]
    encoded = PositionalEncoding(4)(x)  # (400, 9): x, then sin(2^k x), then cos(2^k x)
    encoded[:, 0] /= math.pi
    names = ["x / pi"] + [f"sin 2^{k}x" for k in range(4)] + [f"cos 2^{k}x" for k in range(4)]
    image = ax_pe.imshow(
        encoded.T,
        aspect="auto",
        cmap="coolwarm",
        vmin=-1,
        vmax=1,
        extent=(-math.pi, math.pi, 8.5, -0.5),
        interpolation="nearest",
    )
    ax_pe.set_yticks(range(9), names, fontsize="small")
    ax_pe.set(xlabel="input x", title="PositionalEncoding(4): 1 -> 9 channels")
    fig.colorbar(image, ax=ax_pe, shrink=0.8)

    ax_palette.axis("off")
    ax_palette.set_title("Occ3D-nuScenes classes")
    viz.add_class_legend(
        ax_palette,
        list(range(18)),
        loc="center",
        bbox_to_anchor=(0.5, 0.45),
        ncols=2,
        fontsize="small",
    )
    return fig


def voxelizer() -> Figure:
    """Gaussians on a synthetic scene's surface, voxelised into the Occ3D grid."""
    frame = reference_frame()
    grid = VoxelGrid.occ3d()
    pred = voxelize(surface_gaussians(frame, grid), grid).labels(label_offset=0)[0]
    fig = viz.compare_bev(pred, frame.occupancy, titles=("voxelised Gaussians", "ground truth"))
    fig.set_size_inches(10.0, 6.2)  # room for the titles above a three-row legend
    return fig


def deformation() -> Figure:
    """DecoupledDeformation fitted to a toy clip: the rigidity mask it learns."""
    n, c = 64, 8
    g = torch.Generator().manual_seed(0)
    times = torch.linspace(-1.0, 1.0, 5)
    canonical = GaussianSet(
        means=torch.rand(1, n, 3, generator=g) * torch.tensor([16.0, 16.0, 2.0])
        - torch.tensor([8.0, 8.0, 0.0]),
        quats=torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(1, n, 4),
        scales=torch.full((1, n, 3), 0.3),
        opacities=torch.full((1, n), 0.8),
    )
    latents = torch.randn(1, n, c, generator=g)
    translating = torch.arange(n) < n // 2
    t = times[None, :, None, None]
    moving = translating[None, None, :, None]
    target_means = canonical.means[:, None] + torch.where(
        moving, torch.tensor([3.0, 1.0, 0.0]) * t, 0.0
    )
    stretch = torch.where(moving, 0.0, torch.tensor([1.0, -0.5, 0.0]) * t)
    target_scales = canonical.scales[:, None] * stretch.exp()
    half_angle = torch.where(moving, 0.0, 0.25 * t)
    zeros = torch.zeros_like(half_angle)
    target_quats = torch.cat([half_angle.cos(), zeros, zeros, half_angle.sin()], -1)

    torch.manual_seed(0)
    module = DecoupledDeformation(c, hidden_dim=64, head_hidden=64, depth=3, time_dim=16)
    optimizer = torch.optim.Adam(module.parameters(), lr=1e-2)
    weights = DeformationLossWeights(reg=1e-3, mask=1e-3)
    for _ in range(150):
        out = module(canonical, latents, times)
        deformed = out.gaussians
        dot = (torch.nn.functional.normalize(deformed.quats, dim=-1) * target_quats).sum(-1)
        error = (
            (deformed.means - target_means).square().sum(-1).mean()
            + (deformed.scales.log() - target_scales.log()).square().sum(-1).mean()
            + (1 - dot.square()).mean()
        )
        loss = error + deformation_loss(out, weights).total
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        out = module(canonical, latents, times)
    mask = out.rigid_mask[0]

    fig = new_figure(10.0, 3.6)
    ax_scene, ax_mask = fig.subplots(1, 2, width_ratios=[1.2, 1.0])
    colours = ["tab:blue" if moving else "tab:orange" for moving in translating.tolist()]
    final = out.at(-1)
    target_cov = GaussianSet(
        means=target_means[0, -1],
        quats=target_quats[0, -1],
        scales=target_scales[0, -1],
        opacities=canonical.opacities[0],
    ).covariances()
    draw_ellipses(ax_scene, target_means[0, -1], target_cov, colours, fill=False, linestyle="--")
    draw_ellipses(ax_scene, final.means[0], final.covariances()[0], colours, alpha=0.5)
    ax_scene.set(
        xlim=(-12, 12),
        ylim=(-10, 10),
        aspect="equal",
        xlabel="x [m]",
        ylabel="y [m]",
        title="t = +1: fitted (filled) and target (dashed)",
    )
    bins = torch.linspace(0, 1, 21)
    for group, colour, name in [
        (translating, "tab:blue", "translating only"),
        (~translating, "tab:orange", "rotating and stretching"),
    ]:
        ax_mask.hist(mask[group], bins=bins, color=colour, alpha=0.75, label=name)
    ax_mask.set(
        title="learned rigidity mask after 150 steps", xlabel="m (1 = nonrigid)", ylabel="Gaussians"
    )
    ax_mask.legend(loc="upper center")
    return fig


def teacher() -> Figure:
    """Camera images, teacher target maps and a briefly distilled student render."""
    scene = SyntheticScene(seed=0, num_frames=3, image_size=(56, 154))
    frames = scene.frames()
    reference = scene.offsets.index(0)
    clip = torch.stack([frame.images for frame in frames])[None]
    torch.manual_seed(0)
    model = FactorizedSpatioTemporalTeacher(embed_dim=64, depth=2, num_heads=4, patch_size=14)
    with torch.no_grad():
        tokens = model.eval()(clip)
    targets = FactorizedTeacherFeatures(128, 32, reference_time=reference)(
        tokens, output_size=scene.image_size
    )

    frame = frames[reference]
    surface = surface_gaussians(frame, scene.grid, visible_only=True)
    gaussians = surface.replace(scales=surface.scales * 1.5, features=None)  # no holes
    latents = torch.nn.Parameter(0.1 * torch.randn(1, gaussians.num_gaussians, 64))
    projector = StudentProjector(64, 32)
    optimizer = torch.optim.Adam([latents, *projector.parameters()], lr=0.05)
    cameras = (frame.world_to_cam[None], frame.intrinsics[None], scene.image_size)
    for _ in range(8):
        rendered = splat(gaussians, *cameras, features=projector(latents), depth_mode="none")
        loss = distillation_loss(rendered.features, targets, mask=rendered.alpha > 0.5)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        rendered = splat(gaussians, *cameras, features=projector(latents), depth_mode="none")

    pixels = targets[0].movedim(1, -1).reshape(-1, 32)
    mean, basis = pixels.mean(0), torch.pca_lowrank(pixels, q=3, center=True)[2]

    def to_rgb(maps: torch.Tensor) -> torch.Tensor:  # (V, 32, H, W) -> (V, H, W, 3)
        rgb = (maps.movedim(1, -1) - mean) @ basis
        low, high = rgb.flatten(0, 2).amin(0), rgb.flatten(0, 2).amax(0)
        return ((rgb - low) / (high - low)).clamp(0, 1)

    rows = {
        "camera image": frame.images.movedim(1, -1),
        "teacher targets": to_rgb(targets[0]),
        "student render": to_rgb(rendered.features[0]) * (rendered.alpha[0, ..., None] > 0.5),
    }
    fig = new_figure(12.0, 3.0)
    axes = fig.subplots(3, 6)
    for row, (name, images) in enumerate(rows.items()):
        for v in range(6):
            axes[row, v].imshow(images[v].numpy(), interpolation="nearest")
            axes[row, v].set(xticks=[], yticks=[])
        axes[row, 0].set_ylabel(name.replace(" ", "\n"), fontsize="small")
    return fig


def metrics() -> Figure:
    """A prediction with known mistakes vs the ground truth, and the per-class IoU."""
    frame = reference_frame()
    gt = frame.occupancy.long()
    pred = perturbed_prediction(gt)
    fig = new_figure(13.0, 4.4)
    ax_pred, ax_gt, ax_bars = fig.subplots(1, 3, width_ratios=[1.0, 1.0, 1.5])
    viz.plot_bev(viz.bev_labels(pred)[NEAR], grid=CROP, ax=ax_pred, title="prediction")
    viz.plot_bev(viz.bev_labels(gt)[NEAR], grid=CROP, ax=ax_gt, title="ground truth")
    for shift, protocol in zip((0.2, -0.2), ("occ3d", "weak"), strict=True):
        metric = OccupancyMetrics(protocol=protocol)
        metric.update(pred, gt, frame.mask_camera)
        report = metric.compute()
        values = report.per_class[:17].nan_to_num(-1.0)  # not evaluated: off the axis
        ax_bars.barh(
            torch.arange(17) + shift,
            values,
            height=0.4,
            label=f"{protocol}: mIoU {report.miou:.1%}",
        )
    ax_bars.set_yticks(range(17), CLASS_NAMES[:17], fontsize="small")
    ax_bars.set(xlim=(0, 1), xlabel="IoU inside the camera mask", title="per-class IoU")
    ax_bars.invert_yaxis()
    ax_bars.legend(loc="upper right", fontsize="small")
    return fig


def rayiou() -> Figure:
    """Where LiDAR-like rays end on the objects, and RayIoU per class at 1, 2 and 4 m."""
    scene = SyntheticScene(seed=0, image_size=(32, 88))
    frame = reference_frame()
    gt = frame.occupancy.long()
    pred = perturbed_prediction(gt)
    ego2global = torch.stack([scene.ego_pose(o * scene.frame_dt) for o in scene.offsets])
    lidar2ego = torch.eye(4, dtype=torch.float64).repeat(len(scene.offsets), 1, 1)
    lidar2ego[:, :3, 3] = frame.lidar_origin.double()
    origins = lidar_origins(ego2global, lidar2ego, reference_index=scene.offsets.index(0))
    metric = RayIoU()
    metric.update(pred, gt, origins)
    report = metric.compute()

    rays = generate_lidar_rays().double()
    origin = frame.lidar_origin.double()[None]
    gt_distance, gt_label = cast_rays(gt, origin, rays, scene.grid)
    pred_distance, pred_label = cast_rays(pred, origin, rays, scene.grid)
    on_object = torch.isin(gt_label, torch.tensor(INSTANCE_CLASSES))
    same, close = pred_label == gt_label, (pred_distance - gt_distance).abs() < 1.0
    points = origin + gt_distance[:, None].double() * rays

    fig = new_figure(12.0, 4.6)
    ax_rays, ax_bars = fig.subplots(1, 2, width_ratios=[1.0, 1.4])
    viz.plot_bev(gt[NEAR], grid=CROP, ax=ax_rays, title="rays from the LiDAR that hit objects")
    for label, selected, colour in [
        ("same class, depth within 1 m", same & close, "tab:green"),
        ("same class, depth off by more", same & ~close, "tab:orange"),
        ("another class", ~same, "tab:red"),
    ]:
        keep = on_object & selected & (points[:, :2].abs() < 16).all(-1)
        ax_rays.scatter(points[keep, 1], points[keep, 0], s=6, color=colour, label=label)
    ax_rays.scatter(origins[:, 1], origins[:, 0], s=20, marker="x", color="0.2", label="origins")
    ax_rays.legend(loc="upper left", fontsize="x-small", framealpha=0.9)
    for i, (threshold, shift) in enumerate(zip(report.thresholds, (-0.27, 0.0, 0.27), strict=True)):
        ax_bars.bar(
            torch.arange(17) + shift,
            report.per_class[i, :17].nan_to_num(0.0),
            width=0.27,
            label=f"@{threshold:g} m: {report.at[i]:.1%}",
        )
    ax_bars.set_xticks(range(17), CLASS_NAMES[:17], rotation=50, ha="right", fontsize="small")
    ax_bars.set(ylim=(0, 1), ylabel="IoU", title=f"RayIoU {report.rayiou:.1%} per class")
    ax_bars.legend(loc="upper left", fontsize="small")
    return fig


def synthetic_cameras() -> Figure:
    """The data page's six cameras of ``SyntheticScene(0)``'s reference frame."""
    frame = SyntheticScene(seed=0).frame(0)
    return viz.camera_panels(frame.images, frame.depth, frame.semantics, panel_width=2.0)


def synthetic_bev() -> Figure:
    """The same frame's ground truth from above."""
    ax = viz.plot_bev(SyntheticScene(seed=0).frame(0).occupancy)
    return ax.figure


PICTURES = {
    "foundation_gaussians.png": foundation,
    "voxelizer_bev.png": voxelizer,
    "deformation_mask.png": deformation,
    "teacher_targets.png": teacher,
    "metrics_bev.png": metrics,
    "rayiou_rays.png": rayiou,
    "synthetic_cameras.png": synthetic_cameras,
    "synthetic_bev.png": synthetic_bev,
}


def main() -> None:
    names = sys.argv[1:] or list(PICTURES)
    unknown = sorted(set(names) - set(PICTURES))
    if unknown:
        raise SystemExit(f"unknown pictures {unknown}; choose from {sorted(PICTURES)}")
    for name in names:
        draw = PICTURES[name]
        path = viz.save_figure(draw(), IMAGES / name, dpi=DPI)
        print(f"{path.name}: {path.stat().st_size / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
