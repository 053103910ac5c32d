"""Dependency-free PNG output for benchmark pictures (depth and semantic renders).

``python benchmarks/bench_splat.py --png docs/images/w1_depth_semantics.png`` draws the
splatting page's picture with :func:`save_depth_and_semantics`: half resolution, with
few enough colours for an indexed PNG (about 0.1 MB instead of 1.3 MB of RGB).
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import torch

from dego import PALETTE


def write_png(path: Path, rgb: torch.Tensor) -> None:
    """Write an ``(H, W, 3)`` uint8 tensor as a PNG: indexed when it has at most 256
    colours (much smaller), 8-bit RGB otherwise."""
    height, width, _ = rgb.shape
    colours, index = torch.unique(rgb.reshape(-1, 3), dim=0, return_inverse=True)
    if len(colours) <= 256:
        pixels = index.to(torch.uint8).reshape(height, width, 1)
        header = struct.pack(">IIBBBBB", width, height, 8, 3, 0, 0, 0)
        extra = [(b"PLTE", bytes(colours.flatten().tolist()))]
    else:
        pixels = rgb
        header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
        extra = []
    raw = b"".join(b"\x00" + bytes(row) for row in pixels.contiguous().numpy().reshape(height, -1))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + b"".join(chunk(kind, data) for kind, data in extra)
        + chunk(b"IDAT", zlib.compress(raw, 9))
        + chunk(b"IEND", b"")
    )


def save_depth_and_semantics(
    path: Path,
    depth: torch.Tensor,
    logits: torch.Tensor,
    alpha: torch.Tensor,
    *,
    downscale: int = 2,
    grey_levels: int = 48,
    alpha_levels: int = 12,
) -> None:
    """Two rows of V camera images: inverse depth (grey) over semantic argmax (paper palette).

    ``depth`` ``(V, H, W)``, ``logits`` ``(V, C, H, W)`` with C <= 17 (label = argmax + 1),
    ``alpha`` ``(V, H, W)`` fades both to black where nothing was rendered. The images
    are averaged over ``downscale`` x ``downscale`` pixels (labels: argmax of the mean
    logits), inverse depth is rounded to ``grey_levels`` and alpha to ``alpha_levels``
    steps, so that the picture has at most 256 colours and is written as an indexed PNG.
    """
    if downscale > 1:
        pool = torch.nn.functional.avg_pool2d
        weight = pool(alpha[:, None], downscale)[:, 0]
        depth = pool((depth * alpha)[:, None], downscale)[:, 0] / weight.clamp_min(1e-6)
        logits = pool(logits, downscale)
        alpha = weight
    alpha = (alpha.clamp(0, 1) * (alpha_levels - 1)).round() / (alpha_levels - 1)
    inverse = (1.0 / depth.clamp_min(0.5)) * alpha
    steps = grey_levels - 1
    inverse = (inverse / inverse.max().clamp_min(1e-6) * steps).round() / steps
    grey = (inverse * 255).to(torch.uint8)
    depth_rgb = grey.unsqueeze(-1).expand(*grey.shape, 3)
    palette = torch.tensor(PALETTE, dtype=torch.float32)
    labels = logits.argmax(1) + 1
    semantic_rgb = (palette[labels] * alpha.unsqueeze(-1)).to(torch.uint8)
    gap = torch.full((depth.shape[1], 4, 3), 255, dtype=torch.uint8)

    def row(images: torch.Tensor) -> torch.Tensor:
        parts = []
        for image in images:
            parts += [image, gap]
        return torch.cat(parts[:-1], dim=1)

    top, bottom = row(depth_rgb), row(semantic_rgb)
    write_png(
        path, torch.cat([top, torch.full((4, top.shape[1], 3), 255, dtype=torch.uint8), bottom], 0)
    )
