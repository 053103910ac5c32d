"""A factorized spatio-temporal transformer teacher (DeGO section 4.2).

Every block attends across cameras first, then across time:

    spatial:   z~_{t,v} = Attn_sp(z_{t,v}, {z_{t,u}}_u)          tokens of all V cameras at t
    temporal:  z^_{t,v} = Attn_tmp(z~_{t,v}, {z~_{tau,v}}_tau)   tokens of camera v at all T

so, unlike the official feature cache (which stacks cameras and frames on the batch axis
and never mixes them), information really flows between cameras and between frames.
Patch positions use 2-D rotary embeddings, so any image size that is a multiple of the
patch size works without an image-size argument.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import cast

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from dego import _serialization
from dego._checks import check_int, check_positive
from dego._policy import check_dtype, check_memory
from dego._typing import check_tensor_fields, typechecked

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _rope_angles(positions: Tensor, dim: int, base: float) -> Tensor:
    """``(L, dim / 2)`` rotation angles of 1-D positions ``(L,)`` over ``dim`` channels."""
    inverse = base ** (-torch.arange(0, dim, 2, dtype=torch.float64, device=positions.device) / dim)
    return positions.double()[:, None] * inverse


@typechecked
def rotary_2d(x: Tensor, positions: Tensor, base: float = 100.0) -> Tensor:
    """Apply 2-D rotary position embedding to ``x (..., L, D)`` at ``positions (L, 2)``
    (row, column): the first half of D rotates with the row, the second with the column,
    each as consecutive channel pairs. D must be a multiple of 4; position (0, 0) is the
    identity."""
    half = x.shape[-1] // 2
    parts = []
    for axis, chunk in enumerate(x.split(half, dim=-1)):
        angles = _rope_angles(positions[:, axis], half, base).to(x.dtype)
        cos, sin = angles.cos(), angles.sin()
        even, odd = chunk[..., 0::2], chunk[..., 1::2]
        rotated = torch.stack([even * cos - odd * sin, even * sin + odd * cos], -1)
        parts.append(rotated.flatten(-2))
    return torch.cat(parts, -1)


class AttentionBlock(nn.Module):
    """Pre-norm transformer block: ``x + Attn(LN(x))``, then ``x + MLP(LN(x))``, with
    QK-norm and 2-D RoPE on queries and keys; attention by
    :func:`torch.nn.functional.scaled_dot_product_attention` over ``(batch, L, C)``."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, rope_base: float) -> None:
        super().__init__()
        self.num_heads, self.rope_base = num_heads, rope_base
        self.head_dim = head_dim = dim // num_heads
        self.norm1 = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.q_norm, self.k_norm = nn.LayerNorm(head_dim), nn.LayerNorm(head_dim)
        self.proj = nn.Linear(dim, dim)
        self.norm2 = nn.LayerNorm(dim)
        hidden = int(dim * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))

    @typechecked
    def forward(self, x: Tensor, positions: Tensor) -> Tensor:
        batch, length, dim = x.shape
        # Explicit sizes (no -1): a batch or length of 0 stays a valid, empty view.
        qkv = self.qkv(self.norm1(x)).view(batch, length, 3, self.num_heads, self.head_dim)
        q, k, v = qkv.permute(2, 0, 3, 1, 4).unbind(0)  # (batch, heads, L, head_dim)
        q = rotary_2d(self.q_norm(q), positions, self.rope_base)
        k = rotary_2d(self.k_norm(k), positions, self.rope_base)
        attended = F.scaled_dot_product_attention(q, k, v)
        x = x + self.proj(attended.transpose(1, 2).reshape(batch, length, dim))
        return x + self.mlp(self.norm2(x))


@dataclasses.dataclass(frozen=True)
class TeacherOutput(_serialization.DictForm):
    """Per-block outputs of :class:`FactorizedSpatioTemporalTeacher`.

    Attributes:
        spatial: one ``(B, T, V, P, C)`` tensor per block, after cross-camera attention.
        temporal: one ``(B, T, V, P, C)`` tensor per block, after cross-frame attention.
        patch_start_idx: special (camera + register) tokens at the start of each image's P.
        patch_grid: ``(H', W')``, so ``P = patch_start_idx + H' W'``.
    """

    def __post_init__(self) -> None:
        check_tensor_fields(self)

    spatial: list[Float[Tensor, "B T V P C"]]
    temporal: list[Float[Tensor, "B T V P C"]]
    patch_start_idx: int
    patch_grid: tuple[int, int]


class FactorizedSpatioTemporalTeacher(nn.Module):
    """Transformer over multi-camera clips ``(B, T, V, 3, H, W)`` with factorized attention.

    Each image is cut into ``patch_size`` patches (H and W must be multiples of it), embedded
    linearly, and prefixed with a learned camera token and ``num_register_tokens`` learned
    register tokens (``patch_start_idx = 1 + num_register_tokens``). Each of the ``depth``
    blocks applies cross-camera attention (all V cameras' tokens at one time step, batch
    ``B T``) and then cross-frame attention (one camera's tokens over all T steps, batch
    ``B V``). Positions are 2-D RoPE over the patch grid, (row + 1, col + 1) for patches and
    (0, 0) for special tokens, the same grid in every image (as in VGGT).

    Small defaults keep it cheap on a CPU; VGGT-like sizes are ``embed_dim=1024, depth=24,
    num_heads=16, patch_size=14``.

    Args:
        embed_dim: C, the token width.
        depth: number of (spatial, temporal) block pairs.
        num_heads: heads per attention (``embed_dim / num_heads`` must be a multiple of 4
            for 2-D RoPE).
        patch_size: square patch side in pixels.
        num_register_tokens: learned register tokens per image (VGGT: 4).
        mlp_ratio: MLP width / C.
        rope_base: RoPE base frequency (VGGT: 100).
        normalize: subtract the ImageNet mean and divide by its std (inputs in [0, 1]).
    """

    mean: Tensor  # buffers: ImageNet normalisation, (3, 1, 1)
    std: Tensor

    def __init__(
        self,
        embed_dim: int = 64,
        depth: int = 2,
        num_heads: int = 4,
        patch_size: int = 14,
        *,
        num_register_tokens: int = 4,
        mlp_ratio: float = 4.0,
        rope_base: float = 100.0,
        normalize: bool = True,
    ) -> None:
        super().__init__()
        for name, value, low in [
            ("embed_dim", embed_dim, 1),
            ("depth", depth, 1),
            ("num_heads", num_heads, 1),
            ("patch_size", patch_size, 1),
            ("num_register_tokens", num_register_tokens, 0),
        ]:
            check_int(name, value, low)
        if embed_dim % num_heads or (embed_dim // num_heads) % 4:
            raise ValueError(
                f"num_heads: embed_dim / num_heads must be a whole multiple of 4 for 2-D RoPE, "
                f"got embed_dim={embed_dim}, num_heads={num_heads}"
            )
        check_positive("mlp_ratio", mlp_ratio)
        check_positive("rope_base", rope_base)
        self.embed_dim, self.patch_size, self.normalize = embed_dim, patch_size, normalize
        self.patch_start_idx = 1 + num_register_tokens
        self.patch_embed = nn.Conv2d(3, embed_dim, patch_size, stride=patch_size)
        self.camera_token = nn.Parameter(torch.randn(1, 1, embed_dim) * 0.02)
        self.register_tokens = nn.Parameter(torch.randn(1, num_register_tokens, embed_dim) * 0.02)
        self.spatial_blocks = nn.ModuleList(
            AttentionBlock(embed_dim, num_heads, mlp_ratio, rope_base) for _ in range(depth)
        )
        self.temporal_blocks = nn.ModuleList(
            AttentionBlock(embed_dim, num_heads, mlp_ratio, rope_base) for _ in range(depth)
        )
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(3, 1, 1), persistent=False)

    def _positions(self, rows: int, cols: int, device: torch.device) -> Tensor:
        """``(P, 2)`` RoPE positions of one image's tokens."""
        r, c = torch.meshgrid(
            torch.arange(1, rows + 1, device=device),
            torch.arange(1, cols + 1, device=device),
            indexing="ij",
        )
        patches = torch.stack([r.flatten(), c.flatten()], -1)
        special = patches.new_zeros(self.patch_start_idx, 2)
        return torch.cat([special, patches])

    def _check_images(self, images: Tensor) -> None:
        h, w = images.shape[-2:]
        p = self.patch_size
        if h < p or w < p:
            raise ValueError(
                f"images: H and W must be at least patch_size={p} (one patch), got {h} x {w}"
            )
        if h % p or w % p:
            raise ValueError(
                f"images: H and W must be multiples of patch_size={p}, got {h} x {w}; resize "
                f"or crop (e.g. to {h // p * p} x {w // p * p})"
            )
        check_dtype("images", images, self.patch_embed.weight.dtype, "the teacher's parameters")
        if images.device != self.patch_embed.weight.device:
            raise ValueError(
                f"images: on device {images.device} but the teacher is on "
                f"{self.patch_embed.weight.device}"
            )

    def memory_estimate(self, images_shape: Sequence[int], itemsize: int = 4) -> tuple[int, str]:
        """``(bytes, description)``: an upper estimate of what :meth:`forward` allocates for
        images of ``images_shape = (B, T, V, 3, H, W)`` with ``itemsize``-byte floats.

        It counts the largest attention score matrix as if materialised (torch's math
        backend of ``scaled_dot_product_attention``: ``B T heads (V P)^2`` across cameras,
        ``B V heads (T P)^2`` across time), the MLP hidden activations, and the
        ``2 depth`` per-block outputs kept in :class:`TeacherOutput` plus a few
        working copies of the tokens.
        """
        b, t, v, _, h, w = (int(n) for n in images_shape)
        p = self.patch_start_idx + (h // self.patch_size) * (w // self.patch_size)
        c, depth = self.embed_dim, len(self.spatial_blocks)
        block = cast(AttentionBlock, self.spatial_blocks[0])
        heads, hidden = block.num_heads, cast(nn.Linear, block.mlp[0]).out_features
        scores = max(b * t * heads * (v * p) ** 2, b * v * heads * (t * p) ** 2)
        tokens = b * t * v * p
        nbytes = itemsize * (scores + tokens * (hidden + (2 * depth + 8) * c))
        sizes = (
            f"B*T*V = {b}*{t}*{v} images of P = {p} tokens x C = {c}, {heads} heads, attention "
            f"over V*P = {v * p} (cameras) and T*P = {t * p} (frames) tokens, "
            f"{itemsize}-byte floats"
        )
        return nbytes, sizes

    @typechecked
    def tokens(self, images: Float[Tensor, "B T V 3 H W"]) -> Tensor:
        """Initial tokens ``(B, T, V, P, C)``: camera, registers, then patches row-major."""
        self._check_images(images)
        b, t, v = images.shape[:3]
        x = images.flatten(0, 2)
        if self.normalize:
            x = (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)
        patches = self.patch_embed(x).flatten(2).transpose(1, 2)  # (B T V, H' W', C)
        special = torch.cat([self.camera_token, self.register_tokens], 1).to(patches.dtype)
        tokens = torch.cat([special.expand(patches.shape[0], -1, -1), patches], 1)
        return tokens.view(b, t, v, tokens.shape[1], self.embed_dim)

    @typechecked
    def forward(self, images: Float[Tensor, "B T V 3 H W"]) -> TeacherOutput:
        """Run every block on a clip ``(B, T, V, 3, H, W)``; ``images`` in [0, 1] (see
        ``normalize``), in the dtype and on the device of the teacher's parameters.

        Empty clips (B, T or V = 0) give empty ``(B, T, V, P, C)`` outputs. Before
        allocating, the memory estimate of :meth:`memory_estimate` goes through dego's
        memory guard (:func:`dego.set_memory_limit`).

        Raises:
            TypeError: ``images``' dtype differs from the parameters'.
            ValueError: H or W below ``patch_size`` or not a multiple of it, another
                device, or an estimate above the memory limit.
        """
        self._check_images(images)
        b, t, v, _, h, w = images.shape
        nbytes, sizes = self.memory_estimate(images.shape, images.element_size())
        check_memory("FactorizedSpatioTemporalTeacher", nbytes, sizes)
        grid = (h // self.patch_size, w // self.patch_size)
        z = self.tokens(images)
        p, c = z.shape[-2:]
        positions = self._positions(*grid, device=images.device)
        camera_positions, frame_positions = positions.repeat(v, 1), positions.repeat(t, 1)
        spatial, temporal = [], []
        for spatial_block, temporal_block in zip(
            self.spatial_blocks, self.temporal_blocks, strict=True
        ):
            z = spatial_block(z.reshape(b * t, v * p, c), camera_positions).view(b, t, v, p, c)
            spatial.append(z)
            across_time = z.transpose(1, 2).reshape(b * v, t * p, c)
            z = temporal_block(across_time, frame_positions).view(b, v, t, p, c).transpose(1, 2)
            temporal.append(z)
        return TeacherOutput(spatial, temporal, self.patch_start_idx, grid)

    def extra_repr(self) -> str:
        return (
            f"embed_dim={self.embed_dim}, depth={len(self.spatial_blocks)}, "
            f"patch_size={self.patch_size}, patch_start_idx={self.patch_start_idx}"
        )


__all__ = [
    "AttentionBlock",
    "FactorizedSpatioTemporalTeacher",
    "TeacherOutput",
    "rotary_2d",
]
