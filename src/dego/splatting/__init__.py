"""Differentiable Gaussian splatting into pinhole cameras, vectorised and tile-based."""

from dego.splatting.projection import Projection, project_gaussians
from dego.splatting.splatter import DifferentiableSplatter, SplatConfig, SplatOutput, splat
from dego.splatting.tiles import TileLists, build_tile_lists

__all__ = [
    "DifferentiableSplatter",
    "Projection",
    "SplatConfig",
    "SplatOutput",
    "TileLists",
    "build_tile_lists",
    "project_gaussians",
    "splat",
]
