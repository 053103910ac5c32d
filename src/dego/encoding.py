"""NeRF-style sinusoidal positional encoding, as used for positions and time in DeGO."""

from __future__ import annotations

import math
from typing import Literal

import torch
from jaxtyping import Float
from torch import Tensor, nn

from dego._policy import check_finite, compute_dtype
from dego._typing import _is_compiling, typechecked

Layout = Literal["coord_major", "freq_interleaved"]


def _check_levels(num_levels: int, include_input: bool) -> None:
    if not isinstance(num_levels, int) or isinstance(num_levels, bool) or num_levels < 0:
        raise ValueError(f"num_levels: expected an int >= 0, got {num_levels!r}")
    if num_levels == 0 and not include_input:
        raise ValueError("num_levels: 0 levels without include_input would encode nothing")


def _mantissa_bits(dtype: torch.dtype) -> int:
    """p, the significand precision: 24 for float32, 53 float64, 11 float16, 8 bfloat16."""
    return 1 - round(math.log2(torch.finfo(dtype).eps))


def _check_resolution(x: Tensor, num_levels: int) -> None:
    """ValueError unless the top octave ``2^(L-1) x`` is still resolved by ``x``'s dtype."""
    dtype = compute_dtype(x.dtype)
    exponent_limit = math.frexp(torch.finfo(dtype).max)[1]  # 2^(L-1) must be finite
    if num_levels > exponent_limit:
        raise ValueError(
            f"num_levels: {num_levels} levels need frequencies up to 2^{num_levels - 1}, "
            f"beyond {dtype}'s range; at most {exponent_limit}"
        )
    if num_levels == 0 or x.numel() == 0 or _is_compiling():
        return
    peak = float(x.detach().abs().amax())  # one reduction (and sync) per call
    if not math.isfinite(peak):
        check_finite("x", x)
    if peak == 0.0:
        return
    p = _mantissa_bits(x.dtype)
    # peak = m 2^e with m in [0.5, 1): 2^(L-1) peak < 2^p exactly when L - 1 <= p - e.
    allowed = p - math.frexp(peak)[1] + 1
    if num_levels > allowed:
        raise ValueError(
            f"num_levels: {num_levels} levels are too many for {x.dtype} x with |x| up to "
            f"{peak:.6g}: 2^{num_levels - 1} |x| reaches 2^{p}, where {x.dtype} cannot resolve "
            f"the phase of the top octave (its sinusoids would be rounding noise); use "
            f"num_levels <= {max(allowed, 0)} for this x, rescale x, or give x in float64"
        )


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
        x: ``(*, D)`` finite inputs, any leading shape (including empty ones).
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
        ``(*, D * (2L + 1))`` with ``include_input``, else ``(*, 2 D L)``, in ``x``'s
        dtype. float16 / bfloat16 inputs are computed in float32.

    Raises:
        ValueError: ``num_levels`` is too many for ``x``: the top frequency
            ``2^(L-1) max|x|`` must stay below ``2^p``, p the significand bits of ``x``'s
            dtype (24 float32, 53 float64, 11 float16, 8 bfloat16); beyond it the top
            octave's phase is below the input's resolution and its sinusoids are rounding
            noise (or NaN once ``2^(L-1)`` overflows). The message gives the largest
            ``num_levels`` allowed for this ``x``. Also raised for NaN or inf in ``x``.

    The limit is checked with one reduction over ``x`` per call (a host sync on CUDA),
    skipped for ``num_levels = 0`` and under ``torch.compile``.
    """
    _check_levels(num_levels, include_input)
    if layout not in ("coord_major", "freq_interleaved"):
        raise ValueError(f"layout: expected 'coord_major' or 'freq_interleaved', got {layout!r}")
    _check_resolution(x, num_levels)
    dtype = compute_dtype(x.dtype)
    inputs = x.to(dtype)
    # Exact powers of two (ldexp), so 2^k x is exact too.
    freqs = torch.ldexp(
        torch.ones(num_levels, dtype=dtype, device=x.device),
        torch.arange(num_levels, device=x.device),
    )
    if layout == "coord_major":
        scaled = (inputs.unsqueeze(-1) * freqs).flatten(-2)  # (*, D * L), index d * L + k
        parts = [scaled.sin(), scaled.cos()]
    else:
        scaled = freqs.unsqueeze(-1) * inputs.unsqueeze(-2)  # (*, L, D)
        parts = [torch.stack([scaled.sin(), scaled.cos()], dim=-2).flatten(-3)]
    out = torch.cat([inputs, *parts] if include_input else parts, dim=-1)
    return out.to(x.dtype)


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
