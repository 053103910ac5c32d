"""From a peer's tensors to a scored occupancy grid: DeGO, GaussianFlowOcc, GaussianFormer.

The worked example of the three porting guides (docs/from-dego.md,
docs/from-gaussianflowocc.md, docs/from-gaussianformer.md). A stand-in for each peer's
trained model is built from a synthetic frame's ground truth: Gaussians on occupied voxels
with confident logits, in the peer's own layout (opacity ``[B, N, 1]``, DeGO's time
indices, GaussianFormer's quaternion convention and 17 + empty channels). Each section then
does what a port does: convert, (deform and render,) voxelise, post-process, score.

    python examples/porting.py                  # all three
    python examples/porting.py --peer dego      # one of dego, gaussianflowocc, gaussianformer
"""

from __future__ import annotations

import argparse
import warnings

import torch

import dego
from dego import DecoupledDeformation, GaussianSet, OccupancyMetrics, VoxelGrid, voxelize
from dego.compat.dego import occupancy_to_labels, render_temporal
from dego.compat.gaussianflowocc import TemporalOffsetNetwork
from dego.compat.gaussianformer import aggregate_gf1, aggregate_gf2
from dego.compat.gsplat import rasterization

PEERS = ("dego", "gaussianflowocc", "gaussianformer")
OFFICIAL_CURRENT_INDEX = 8  # DeGO's time input: index into frame offsets -8..8
RENDER_SIZE = (64, 176)  # (H, W) of the synthetic cameras


def peer_heads(frame: dego.data.SyntheticFrame, n: int, seed: int) -> dict[str, torch.Tensor]:
    """A trained model's head outputs, DeGO / GaussianFlowOcc layout: Gaussians on (up to)
    ``n`` occupied, observed ground-truth voxels, 16 logits for the labels 1..16, opacity
    ``[1, N, 1]``."""
    g = torch.Generator().manual_seed(seed)
    grid = VoxelGrid.occ3d()
    # the occupied voxels that the cameras see (the ones the metric scores)
    occupied = ((frame.occupancy != dego.FREE_LABEL) & frame.mask_camera).nonzero()
    pick = occupied[torch.randperm(len(occupied), generator=g)[:n]]
    labels = frame.occupancy[pick[:, 0], pick[:, 1], pick[:, 2]].long()
    centres = grid.index_to_world(pick)
    logits = torch.randn(len(pick), 16, generator=g)
    logits[torch.arange(len(pick)), (labels - 1).clamp(0, 15)] += 6.0
    quats = torch.nn.functional.normalize(torch.randn(len(pick), 4, generator=g), dim=-1)
    return {
        "means": (centres + 0.05 * torch.randn(len(pick), 3, generator=g))[None],
        "rotations": quats[None],  # wxyz, normalised
        "scales": torch.full((1, len(pick), 3), 0.15),  # sigmoid: std in metres
        "opacity": torch.full((1, len(pick), 1), 0.9),  # [B, N, 1]
        "semantics": logits[None],  # [B, N, 16]
        "features": torch.randn(1, len(pick), 256, generator=g),  # the decoder's features
    }


def score(pred: torch.Tensor, frame: dego.data.SyntheticFrame, protocol: str) -> str:
    metrics = OccupancyMetrics(protocol)
    metrics.update(pred, frame.occupancy[None], frame.mask_camera[None])
    report = metrics.compute()
    return f"{protocol}: IoU {100 * report.iou:.1f}, mIoU {100 * report.miou:.1f}"


def from_dego(scene: dego.SyntheticScene, heads: dict[str, torch.Tensor]) -> None:
    print("== DeGO ==")
    # Gaussians: the heads' layout (opacity [B, N, 1]) goes in unchanged.
    canonical = GaussianSet.from_tensors(
        heads["means"], heads["rotations"], heads["scales"], heads["opacity"]
    )
    # The deformation network from a checkpoint: here one written by dego itself, in the
    # official key layout, under the detector's prefix (torch.load(path)["state_dict"]).
    prefix = "gaussian_decoder.deformation_module."
    trained = DecoupledDeformation(256, preset="official")
    checkpoint = {"state_dict": trained.to_official_state_dict(prefix=prefix)}
    deformation = DecoupledDeformation.from_official_state_dict(
        checkpoint["state_dict"], prefix=prefix
    )
    # Render frames as the official training loop does: the other frames deformed to
    # their time index, the canonical set appended last.
    others = [offset for offset in scene.offsets if offset != 0]
    times = torch.tensor([[OFFICIAL_CURRENT_INDEX + o for o in others]], dtype=torch.float32)
    with torch.no_grad():
        deformed = deformation(canonical, heads["features"], times)
        official = deformed.to_official_dict()
        print(f"deformation: {times.shape[1]} time steps, official layout", end="")
        print(f" means {tuple(official['means'].shape)} (B, N, T, 3)")
        frames = deformed.with_canonical(canonical)
        cameras = [scene.frame(o) for o in [*others, 0]]
        world_to_cam = torch.stack([f.world_to_cam for f in cameras])[None]  # (1, T+1, V, 4, 4)
        intrinsics = torch.stack([f.intrinsics for f in cameras])[None]
        images = render_temporal(
            frames.gaussians, world_to_cam, intrinsics, RENDER_SIZE, features=heads["semantics"]
        )
    semantic, depth = images[..., :-1], images[..., -1]  # rendered_outs["semantic" / "depth"]
    print(f"render_temporal: {tuple(images.shape)} = [B, (T+1)*V, H, W, 16 + 1], current last")
    print(f"  semantic {tuple(semantic.shape)}, accumulated depth {tuple(depth.shape)}")
    # Test time: the canonical set, the official cube (nbh = 5), the official
    # post-processing, the weak protocol.
    voxels = voxelize(
        canonical, VoxelGrid.occ3d(), features=heads["semantics"], neighborhood="cube", nbh=5
    )
    labels = occupancy_to_labels(voxels.density, voxels.features)
    print(score(labels, scene.frame(0), "weak"))
    # The trap: argmax + 1 without the free-space overlay gives every voxel a class.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        forgotten = score(voxels.features.argmax(-1) + 1, scene.frame(0), "weak")
    print(f"without the free overlay: {forgotten} (warned: {bool(caught)})")


def from_gaussianflowocc(scene: dego.SyntheticScene, heads: dict[str, torch.Tensor]) -> None:
    print("== GaussianFlowOcc ==")
    canonical = GaussianSet.from_tensors(
        heads["means"], heads["rotations"], heads["scales"], heads["opacity"]
    )
    frame = scene.frame(0)
    # Its renderer's gsplat 1.2.0 call, unchanged, on any device.
    colors, alphas, _ = rasterization(
        canonical.means[0],
        canonical.quats[0],
        canonical.scales[0],
        canonical.opacities[0],
        heads["semantics"][0],
        frame.world_to_cam,
        frame.intrinsics,
        RENDER_SIZE[1],
        RENDER_SIZE[0],
        render_mode="RGB+D",
        gsplat_version="1.2.0",
    )
    print(
        f"rasterization (gsplat 1.2.0 rules): colors {tuple(colors.shape)} (depth last), "
        f"alphas {tuple(alphas.shape)}"
    )
    # Its temporal module (a checkpoint would load with load_state_dict after removing
    # "temporal_module."): one offset per Gaussian and frame, dynamic classes only.
    temporal = TemporalOffsetNetwork(256, num_timesteps=13, num_layers=3)
    others = [offset for offset in scene.offsets if offset != 0]
    time_indices = torch.tensor([offset + 6 for offset in others])  # offsets -6..6 -> 0..12
    with torch.no_grad():
        moved = temporal(canonical, heads["features"], time_indices, heads["semantics"])
        frames = moved.with_canonical(canonical)  # the current frame last
        cameras = [scene.frame(o) for o in [*others, 0]]
        images = render_temporal(
            frames.gaussians,
            torch.stack([f.world_to_cam for f in cameras])[None],
            torch.stack([f.intrinsics for f in cameras])[None],
            RENDER_SIZE,
            features=heads["semantics"],
            gsplat_version="1.2.0",
        )
    still = (moved.deltas.means.abs().sum((1, 3)) == 0).float().mean()
    print(f"temporal module: {len(others)} frames, {still:.0%} of the Gaussians static")
    print(f"render_temporal: {tuple(images.shape)}, the same layout as its rasteriser loop")
    voxels = voxelize(
        canonical, VoxelGrid.occ3d(), features=heads["semantics"], neighborhood="cube", nbh=4
    )
    print(score(occupancy_to_labels(voxels.density, voxels.features), frame, "weak"))


def from_gaussianformer(scene: dego.SyntheticScene, heads: dict[str, torch.Tensor]) -> None:
    print("== GaussianFormer ==")
    frame = scene.frame(0)
    # GaussianFormer's tensors: wxyz quaternions entering Sigma = R^T S^2 R (the conjugate of
    # dego's), 17 semantic channels for the labels 0..16. (GaussianFormer works on
    # SurroundOcc's 0.5 m LiDAR-frame grid; this example keeps the Occ3D frame's grid.)
    w, xyz = heads["rotations"][..., :1], heads["rotations"][..., 1:]
    gf_rotations = torch.cat([w, -xyz], -1)
    others = torch.full_like(heads["semantics"][..., :1], -10.0)
    gf_semantics = torch.cat([others, heads["semantics"]], -1)  # [B, N, 17]
    grid = VoxelGrid.occ3d()
    # GaussianFormer-1's "solid" configuration: 17 class scores per Gaussian (softplus),
    # plus its empty Gaussian with the learned empty-class logit (initialised to 10).
    gf1 = aggregate_gf1(
        heads["means"],
        heads["scales"],
        gf_rotations,
        heads["opacity"],
        torch.nn.functional.softplus(gf_semantics) * 4,
        grid=grid,
        empty_logit=10.0,
    )
    gf2 = aggregate_gf2(
        heads["means"], heads["scales"], gf_rotations, heads["opacity"], gf_semantics, grid=grid
    )
    for name, logits in (("GaussianFormer-1", gf1), ("GaussianFormer-2", gf2)):
        labels = logits.argmax(1).reshape(1, *grid.shape)  # [B, 18, X*Y*Z] -> (B, X, Y, Z)
        print(f"{name}: {tuple(logits.shape)} -> {score(labels, frame, 'occ3d')}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--peer", choices=PEERS, action="append", help="default: all three")
    parser.add_argument("--gaussians", type=int, default=8000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    scene = dego.SyntheticScene(args.seed, num_frames=3, image_size=RENDER_SIZE)
    heads = peer_heads(scene.frame(0), args.gaussians, args.seed)
    steps = {"dego": from_dego, "gaussianflowocc": from_gaussianflowocc}
    steps["gaussianformer"] = from_gaussianformer
    for peer in args.peer or PEERS:
        steps[peer](scene, heads)


if __name__ == "__main__":
    main()
