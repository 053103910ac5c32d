"""Real spherical harmonics of degree 0-4, in gsplat's basis, on any device.

:func:`spherical_harmonics` evaluates view-dependent colours (or any D-channel signal) from
per-Gaussian SH coefficients, as 3D Gaussian splatting stores them. The basis is the real
SH basis of Sloan's "Efficient Spherical Harmonic Evaluation" (JCGT 2013), the one gsplat
and the original 3DGS code use: band ``l`` occupies coefficients ``l^2 .. (l + 1)^2 - 1``,
ordered ``m = -l .. l``, with the Condon-Shortley phase, so that for a unit direction
``(x, y, z)``

- ``l = 0``: ``Y_0 = 1 / (2 sqrt(pi))``;
- ``l = 1``: ``(-y, z, -x) * sqrt(3 / (4 pi))``;
- ``l = 2``: ``sqrt(15 / (4 pi)) * (xy, -yz)``, ``sqrt(5 / (16 pi)) (3z^2 - 1)``,
  ``-sqrt(15 / (4 pi)) xz``, ``sqrt(15 / (16 pi)) (x^2 - y^2)``;
- ``l = 3, 4``: the analogous products of the Legendre factors in ``z`` with
  ``Re / Im (x + iy)^|m|`` (written out below).

Directions need not be unit: each is first divided by its largest absolute component and
then by its norm, so every finite non-zero direction gives its exact unit vector, however
large or small (a plain norm overflows above ~1.8e19 in float32 and a clamped one drops the
view-dependent bands below 1e-12). Zero and non-finite directions have no view direction:
they are a ``ValueError`` naming ``directions``. Coefficients beyond ``(degree + 1)^2`` are
ignored, so a degree-3 model can be evaluated at degree 1 (3DGS's progressive SH schedule).
"""

from __future__ import annotations

import math

import torch
from jaxtyping import Float
from torch import Tensor

from dego._policy import Check, finite_check, run_checks
from dego._typing import typechecked

MAX_DEGREE = 4
"""The highest SH degree evaluated (25 coefficients), as gsplat."""

# Normalisation constants of the real SH basis, sqrt((2l + 1) / (4 pi) (l - m)! / (l + m)!)
# times the polynomial factors below; derived, not copied.
_PI = math.pi
_C0 = 0.5 / math.sqrt(_PI)
_C1 = math.sqrt(3 / (4 * _PI))
_C2_XY = math.sqrt(15 / (4 * _PI))  # xy, yz, xz
_C2_Z = math.sqrt(5 / (16 * _PI))  # 3z^2 - 1
_C2_XX = math.sqrt(15 / (16 * _PI))  # x^2 - y^2
_C3_3 = math.sqrt(35 / (32 * _PI))  # Re/Im (x + iy)^3
_C3_2 = math.sqrt(105 / (4 * _PI))  # z Im (x + iy)^2 = 2xyz
_C3_2C = math.sqrt(105 / (16 * _PI))  # z Re (x + iy)^2
_C3_1 = math.sqrt(21 / (32 * _PI))  # (5z^2 - 1) (x, y)
_C3_0 = math.sqrt(7 / (16 * _PI))  # z (5z^2 - 3)
_C4_4 = 3 / 16 * math.sqrt(35 / _PI)  # Re/Im (x + iy)^4
_C4_3 = 3 / 4 * math.sqrt(35 / (2 * _PI))  # z Re/Im (x + iy)^3
_C4_2 = 3 / 8 * math.sqrt(5 / _PI)  # (7z^2 - 1) Re/Im (x + iy)^2
_C4_1 = 3 / 4 * math.sqrt(5 / (2 * _PI))  # z (7z^2 - 3) (x, y)
_C4_0 = 3 / 16 / math.sqrt(_PI)  # 35z^4 - 30z^2 + 3


def _sh_basis(degree: int, directions: Tensor) -> Tensor:
    """The ``(degree + 1)^2`` real SH basis functions at unit ``directions [..., 3]``."""
    x, y, z = directions.unbind(-1)
    basis = [torch.full_like(x, _C0)]
    if degree >= 1:
        basis += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        zz = z * z
        # Re / Im of (x + iy)^m, the azimuthal factors of order m
        c1, s1 = x, y
        c2, s2 = x * x - y * y, 2 * x * y
        basis += [
            0.5 * _C2_XY * s2,
            -_C2_XY * y * z,
            _C2_Z * (3 * zz - 1),
            -_C2_XY * x * z,
            _C2_XX * c2,
        ]
    if degree >= 3:
        c3, s3 = x * c2 - y * s2, x * s2 + y * c2
        basis += [
            -_C3_3 * s3,
            0.5 * _C3_2 * z * s2,
            -_C3_1 * s1 * (5 * zz - 1),
            _C3_0 * z * (5 * zz - 3),
            -_C3_1 * c1 * (5 * zz - 1),
            _C3_2C * z * c2,
            -_C3_3 * c3,
        ]
    if degree >= 4:
        c4, s4 = x * c3 - y * s3, x * s3 + y * c3
        basis += [
            _C4_4 * s4,
            -_C4_3 * z * s3,
            _C4_2 * (7 * zz - 1) * s2,
            -_C4_1 * z * (7 * zz - 3) * s1,
            _C4_0 * (35 * zz * zz - 30 * zz + 3),
            -_C4_1 * z * (7 * zz - 3) * c1,
            _C4_2 * (7 * zz - 1) * c2,
            -_C4_3 * z * c3,
            _C4_4 * c4,
        ]
    return torch.stack(basis, dim=-1)


def _direction_checks(directions: Tensor) -> list[Check]:
    """Directions must be finite and non-zero."""
    zero = (directions == 0).all(dim=-1)

    def error() -> Exception:
        return ValueError(
            f"directions: {int(zero.sum())} of {zero.numel()} directions are zero "
            "(no view direction)"
        )

    return [
        finite_check("directions", directions),
        (~zero.any(), "directions: some directions are zero", error),
    ]


@typechecked
def spherical_harmonics(
    degree: int,
    directions: Float[Tensor, "*b 3"],
    coefficients: Float[Tensor, "*b K D"],
) -> Float[Tensor, "*b D"]:
    """Evaluate real spherical harmonics: ``sum_k Y_k(d / |d|) coefficients[..., k, :]``.

    gsplat's basis, constants, sign conventions and normalisation (module docstring);
    differentiable in ``directions`` and ``coefficients``; any float dtype and device.
    gsplat's ``rasterization`` adds 0.5 and clamps at 0 afterwards; this function does not
    (:func:`dego.compat.gsplat.rasterization` does, with ``sh_degree``).

    Args:
        degree: the SH degree to evaluate, 0 to 4; uses the first ``(degree + 1)^2``
            coefficients.
        directions: ``[..., 3]`` view directions (any norm; typically the Gaussian's mean
            minus the camera centre).
        coefficients: ``[..., K, D]`` SH coefficients with ``K >= (degree + 1)^2``; extra
            coefficients are ignored. ``D`` is 3 for RGB.

    Returns:
        ``[..., D]`` the evaluated signal.

    Raises:
        ValueError: ``degree`` outside 0-4; ``coefficients`` with fewer than
            ``(degree + 1)^2`` coefficients; ``directions`` and ``coefficients`` of
            different dtypes; a zero or non-finite direction.
    """
    if isinstance(degree, bool) or not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"degree: expected an int in 0..{MAX_DEGREE}, got {degree!r}")
    needed = (degree + 1) ** 2
    if coefficients.shape[-2] < needed:
        raise ValueError(
            f"coefficients: degree {degree} needs at least {needed} coefficients per "
            f"channel ([..., K >= {needed}, D]), got K = {coefficients.shape[-2]}"
        )
    if directions.dtype != coefficients.dtype:
        raise ValueError(
            f"directions, coefficients: expected one dtype, got {directions.dtype} and "
            f"{coefficients.dtype}"
        )
    run_checks(_direction_checks(directions))
    # divided by the largest component first (to within one rounding), so that the norm
    # neither overflows nor underflows
    largest = directions.abs().amax(dim=-1, keepdim=True)
    unit = torch.nn.functional.normalize(directions / largest, dim=-1)
    basis = _sh_basis(degree, unit)  # [..., needed]
    return (basis.unsqueeze(-1) * coefficients[..., :needed, :]).sum(dim=-2)


__all__ = ["MAX_DEGREE", "spherical_harmonics"]
