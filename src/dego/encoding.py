"""NeRF-style sinusoidal positional encoding, as used for positions and time in DeGO."""

from __future__ import annotations

from typing import Literal

import torch
from jaxtyping import Float
from torch import Tensor, nn

from dego._typing import typechecked

Layout = Literal["coord_major", "freq_interleaved"]


def _check_levels(num_levels: int, include_input: bool) -> None:
    if not isinstance(num_levels, int) or isinstance(num_levels, bool) or num_levels < 0:
        raise ValueError(f"num_levels: expected an int >= 0, got {num_levels!r}")
    if num_levels == 0 and not include_input:
        raise ValueError("num_levels: 0 levels without include_input would encode nothing")


@typechecked
def positional_encoding(
    x: Float[Tensor, "*batch dim"],
    num_levels: int,
    *,
    include_input: bool = True,
    layout: Layout = "coord_major",
) -> Float[Tensor, "*batch out_dim"]:
    """gamma(x) = [x, sin(2^k x), cos(2^k x)] for k = 0..L-1 (no factor pi).

    Args:
        x: ``(*, D)`` inputs, any leading shape.
        num_levels: L, the number of octaves.
        include_input: prepend ``x`` itself.
        layout: channel order of the sinusoids.

            ``"coord_major"`` (default; DeGO's official and 4DGaussians' layout):
            ``[x, sin(2^0 x_1) .. sin(2^{L-1} x_1), sin(2^0 x_2) .. , cos(...same...)]``, i.e.
            the input, then every sine, then every cosine, each block indexed
            ``d * L + k`` (coordinate d, level k). Required to load official weights.

            ``"freq_interleaved"`` (Deformable-3DGS / NeRF): ``[x, sin(2^0 x), cos(2^0 x),
            sin(2^1 x), cos(2^1 x), ...]`` with each term a D-vector.

    Returns:
        ``(*, D * (2L + 1))`` with ``include_input``, else ``(*, 2 D L)``.
    """
    _check_levels(num_levels, include_input)
    freqs = 2.0 ** torch.arange(num_levels, dtype=x.dtype, device=x.device)
    if layout == "coord_major":
        scaled = (x.unsqueeze(-1) * freqs).flatten(-2)  # (*, D * L), index d * L + k
        parts = [scaled.sin(), scaled.cos()]
    else:
        scaled = freqs.unsqueeze(-1) * x.unsqueeze(-2)  # (*, L, D)
        parts = [torch.stack([scaled.sin(), scaled.cos()], dim=-2).flatten(-3)]
    return torch.cat([x, *parts] if include_input else parts, dim=-1)


class PositionalEncoding(nn.Module):
    """Module form of :func:`positional_encoding`; stateless (no parameters or buffers).

    Example: ``PositionalEncoding(6)`` maps 3-D positions to 39 channels and
    ``PositionalEncoding(4)`` maps 1-D time to 9.
    """

    def __init__(
        self, num_levels: int, include_input: bool = True, *, layout: Layout = "coord_major"
    ) -> None:
        super().__init__()
        _check_levels(num_levels, include_input)
        if layout not in ("coord_major", "freq_interleaved"):
            raise ValueError(
                f"layout: expected 'coord_major' or 'freq_interleaved', got {layout!r}"
            )
        self.num_levels = num_levels
        self.include_input = include_input
        self.layout: Layout = layout

    def out_dim(self, in_dim: int) -> int:
        """Output channels for ``in_dim`` input channels: ``in_dim * (2L + [include_input])``."""
        if not isinstance(in_dim, int) or isinstance(in_dim, bool) or in_dim < 1:
            raise ValueError(f"in_dim: expected an int >= 1, got {in_dim!r}")
        return in_dim * (2 * self.num_levels + int(self.include_input))

    @typechecked
    def forward(self, x: Float[Tensor, "*batch dim"]) -> Float[Tensor, "*batch out_dim"]:
        """Encode ``(*, D)`` to ``(*, out_dim(D))``."""
        return positional_encoding(
            x, self.num_levels, include_input=self.include_input, layout=self.layout
        )

    def extra_repr(self) -> str:
        return (
            f"num_levels={self.num_levels}, include_input={self.include_input}, "
            f"layout={self.layout!r}"
        )


__all__ = ["PositionalEncoding", "positional_encoding"]
