"""Quick start: compose the foundation pieces of dego on a small synthetic scene.

Builds a GaussianSet for a few objects (a car, a pedestrian, a road patch), checks it,
computes covariances / precisions, finds which Occ3D voxels the Gaussians' centres
fall in, evaluates each Gaussian's density at the centre of its own voxel, and encodes
positions and time with the DeGO positional encodings.

    python examples/quickstart.py
"""

from __future__ import annotations

import torch

import dego
from dego import CLASS_NAMES, GaussianSet, Occ3DLabel, PositionalEncoding, VoxelGrid


def object_gaussians(
    label: Occ3DLabel,
    center: tuple[float, float, float],
    size: tuple[float, float, float],
    count: int,
    generator: torch.Generator,
) -> GaussianSet:
    """``count`` Gaussians spread inside a box of ``size`` metres around ``center``."""
    offsets = (torch.rand(count, 3, generator=generator) - 0.5) * torch.tensor(size)
    return GaussianSet(
        means=torch.tensor(center) + offsets,
        quats=torch.randn(count, 4, generator=generator),
        scales=torch.tensor(size) / 6 * (0.5 + torch.rand(count, 3, generator=generator)),
        opacities=torch.full((count,), 0.8),
        features=torch.nn.functional.one_hot(
            torch.full((count,), int(label)), len(CLASS_NAMES)
        ).float(),
    )


def main() -> None:
    g = torch.Generator().manual_seed(0)
    scene = GaussianSet.cat(
        [
            object_gaussians(Occ3DLabel.CAR, (10.0, -2.0, 0.0), (4.5, 1.9, 1.6), 40, g),
            object_gaussians(Occ3DLabel.PEDESTRIAN, (6.0, 4.0, 0.1), (0.6, 0.6, 1.8), 12, g),
            object_gaussians(
                Occ3DLabel.DRIVEABLE_SURFACE, (0.0, 0.0, -0.9), (30.0, 8.0, 0.1), 60, g
            ),
        ]
    ).check_values()
    print(f"dego {dego.__version__}: {scene}")

    grid = VoxelGrid.occ3d()
    index = grid.world_to_index(scene.means)
    inside = grid.contains(scene.means)
    centres = grid.index_to_world(index)
    # Mahalanobis distance of each Gaussian's own voxel centre, with the closed-form precision.
    d = (centres - scene.means).unsqueeze(-1)
    density = torch.exp(-0.5 * (d.transpose(-1, -2) @ scene.precisions() @ d).squeeze((-1, -2)))
    volume = torch.linalg.det(scene.covariances()).sqrt()  # proportional to the 1-sigma volume

    labels = scene.features.argmax(-1)
    print(
        f"grid {grid.shape}, voxel {grid.voxel_size[0]} m; "
        f"{int(inside.sum())}/{scene.num_gaussians} centres inside"
    )
    print(
        f"{'class':<20}{'gaussians':>10}{'voxels':>8}"
        f"{'mean sqrt|Sigma|':>18}{'g(voxel centre)':>17}"
    )
    for label in labels.unique().tolist():
        sel = labels == label
        voxels = index[sel & inside].unique(dim=0).shape[0]
        print(
            f"{CLASS_NAMES[label]:<20}{int(sel.sum()):>10}{voxels:>8}"
            f"{volume[sel].mean():>18.4f}{density[sel].mean():>17.3f}"
        )

    position_pe, time_pe = PositionalEncoding(6), PositionalEncoding(4)
    times = torch.linspace(-1, 1, 5).unsqueeze(-1)
    print(
        f"PE(mu): {tuple(scene.means.shape)} -> {tuple(position_pe(scene.means).shape)}; "
        f"PE(t): {tuple(times.shape)} -> {tuple(time_pe(times).shape)}"
    )


if __name__ == "__main__":
    main()
