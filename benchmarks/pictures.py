"""Dependency-free PNG output for benchmark pictures (depth and semantic renders)."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import torch

from dego import PALETTE


def write_png(path: Path, rgb: torch.Tensor) -> None:
    """Write an ``(H, W, 3)`` uint8 tensor as an 8-bit RGB PNG."""
    height, width, _ = rgb.shape
    raw = b"".join(b"\x00" + bytes(row) for row in rgb.contiguous().numpy().reshape(height, -1))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw, 9))
        + chunk(b"IEND", b"")
    )


def save_depth_and_semantics(
    path: Path, depth: torch.Tensor, logits: torch.Tensor, alpha: torch.Tensor
) -> None:
    """Two rows of V camera images: inverse depth (grey) over semantic argmax (paper palette).

    ``depth`` ``(V, H, W)``, ``logits`` ``(V, C, H, W)`` with C <= 17 (label = argmax + 1),
    ``alpha`` ``(V, H, W)`` fades both to black where nothing was rendered.
    """
    inverse = (1.0 / depth.clamp_min(0.5)) * alpha
    grey = (inverse / inverse.max().clamp_min(1e-6) * 255).to(torch.uint8)
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
