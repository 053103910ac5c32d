"""``dego.spherical_harmonics``: gsplat's real SH basis (degrees 0-4), from the maths."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from jaxtyping import TypeCheckError

from dego import spherical_harmonics

PI = math.pi


def closed_forms(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> list[torch.Tensor]:
    """The 25 real SH of a unit direction as plain polynomials (Condon-Shortley phase,
    ``m = -l .. l`` per band), each ``N_lm P_lm(z) Re/Im (x + iy)^|m|`` multiplied out."""
    one = torch.ones_like(x)
    return [
        0.5 / math.sqrt(PI) * one,
        -math.sqrt(3 / (4 * PI)) * y,
        math.sqrt(3 / (4 * PI)) * z,
        -math.sqrt(3 / (4 * PI)) * x,
        0.5 * math.sqrt(15 / PI) * x * y,
        -0.5 * math.sqrt(15 / PI) * y * z,
        0.25 * math.sqrt(5 / PI) * (3 * z**2 - 1),
        -0.5 * math.sqrt(15 / PI) * x * z,
        0.25 * math.sqrt(15 / PI) * (x**2 - y**2),
        -0.25 * math.sqrt(35 / (2 * PI)) * y * (3 * x**2 - y**2),
        0.5 * math.sqrt(105 / PI) * x * y * z,
        -0.25 * math.sqrt(21 / (2 * PI)) * y * (5 * z**2 - 1),
        0.25 * math.sqrt(7 / PI) * z * (5 * z**2 - 3),
        -0.25 * math.sqrt(21 / (2 * PI)) * x * (5 * z**2 - 1),
        0.25 * math.sqrt(105 / PI) * z * (x**2 - y**2),
        -0.25 * math.sqrt(35 / (2 * PI)) * x * (x**2 - 3 * y**2),
        0.75 * math.sqrt(35 / PI) * x * y * (x**2 - y**2),
        -0.75 * math.sqrt(35 / (2 * PI)) * y * z * (3 * x**2 - y**2),
        0.75 * math.sqrt(5 / PI) * x * y * (7 * z**2 - 1),
        -0.75 * math.sqrt(5 / (2 * PI)) * y * z * (7 * z**2 - 3),
        3 / 16 * math.sqrt(1 / PI) * (35 * z**4 - 30 * z**2 + 3),
        -0.75 * math.sqrt(5 / (2 * PI)) * x * z * (7 * z**2 - 3),
        3 / 8 * math.sqrt(5 / PI) * (x**2 - y**2) * (7 * z**2 - 1),
        -0.75 * math.sqrt(35 / (2 * PI)) * x * z * (x**2 - 3 * y**2),
        3 / 16 * math.sqrt(35 / PI) * (x**4 - 6 * x**2 * y**2 + y**4),
    ]


def basis(degree: int, directions: torch.Tensor) -> torch.Tensor:
    """The evaluator's basis: one-hot coefficients pick out each function ``[..., K]``."""
    k = (degree + 1) ** 2
    eye = torch.eye(k, dtype=directions.dtype)
    coefficients = eye.expand(*directions.shape[:-1], k, k)
    return spherical_harmonics(degree, directions, coefficients)


def random_directions(n: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, 3, generator=g, dtype=dtype)


def test_degree_zero_is_c0_times_the_coefficient() -> None:
    d = random_directions(20)
    c = torch.randn(20, 1, 3, dtype=torch.float64)
    expected = c[:, 0] / (2 * math.sqrt(PI))
    torch.testing.assert_close(spherical_harmonics(0, d, c), expected, rtol=1e-15, atol=0)


@pytest.mark.parametrize(
    ("direction", "values"),
    [
        ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
        ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0)),
        ((0.0, 1.0, 0.0), (-1.0, 0.0, 0.0)),
        ((0.0, 0.0, -2.5), (0.0, -1.0, 0.0)),
    ],
)
def test_degree_one_at_axis_directions(
    direction: tuple[float, ...], values: tuple[float, ...]
) -> None:
    got = basis(1, torch.tensor([direction], dtype=torch.float64))[0]
    c1 = math.sqrt(3 / (4 * PI))
    expected = torch.tensor([0.5 / math.sqrt(PI), *(c1 * v for v in values)], dtype=torch.float64)
    torch.testing.assert_close(got, expected, rtol=1e-15, atol=1e-15)


def test_every_basis_function_equals_its_closed_form() -> None:
    d = random_directions(200, seed=1)
    unit = d / d.norm(dim=-1, keepdim=True)
    expected = torch.stack(closed_forms(*unit.unbind(-1)), -1)
    torch.testing.assert_close(basis(4, d), expected, rtol=1e-12, atol=1e-12)


def test_the_basis_is_orthonormal_on_the_sphere() -> None:
    """Gauss-Legendre in z times uniform azimuths integrates these polynomials exactly."""
    nodes, weights = (torch.from_numpy(a) for a in np.polynomial.legendre.leggauss(12))
    phi = torch.arange(24, dtype=torch.float64) * (2 * PI / 24)
    z, p = torch.meshgrid(nodes, phi, indexing="ij")
    r = (1 - z**2).sqrt()
    d = torch.stack([r * p.cos(), r * p.sin(), z], -1).reshape(-1, 3)
    w = (weights[:, None] * (2 * PI / 24)).expand(-1, 24).reshape(-1)
    y = basis(4, d)  # [P, 25]
    gram = y.T @ (w[:, None] * y)
    torch.testing.assert_close(gram, torch.eye(25, dtype=torch.float64), rtol=0, atol=1e-12)


def test_direction_scale_is_ignored_and_bands_are_rotation_invariant() -> None:
    d = random_directions(50, seed=2)
    c = torch.randn(50, 25, 3, dtype=torch.float64)
    scale = torch.rand(50, 1, dtype=torch.float64) * 100 + 1e-3
    torch.testing.assert_close(
        spherical_harmonics(4, d * scale, c), spherical_harmonics(4, d, c), rtol=1e-12, atol=1e-12
    )
    # addition theorem: sum_m Y_lm(d)^2 = (2l + 1) / (4 pi) for every direction
    y = basis(4, d)
    for band in range(5):
        power = y[:, band**2 : (band + 1) ** 2].square().sum(-1)
        expected = torch.full_like(power, (2 * band + 1) / (4 * PI))
        torch.testing.assert_close(power, expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("scale", [1e30, 3e19, 1e-13, 1e-30, 1e-37])
def test_every_finite_nonzero_direction_is_exact_at_any_magnitude(scale: float) -> None:
    """Issue 38 (10): in float32 a norm above ~1.8e19 overflowed and one below 1e-12 was
    clamped, and both silently left only the degree-0 term (an error of ~1.1). (Subnormal
    inputs, below 1.2e-38, carry fewer digits themselves.)"""
    d = random_directions(20, seed=5).float()
    c = torch.randn(20, 25, 3)
    expected = spherical_harmonics(4, d, c)
    got = spherical_harmonics(4, d * scale, c)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (0.0, r"directions: 1 of 4 directions are zero"),
        (float("nan"), "directions: 3 of 12 values are not finite"),
    ],
    ids=["zero", "nan"],
)
def test_zero_and_non_finite_directions_are_refused(value: float, message: str) -> None:
    d = random_directions(4, seed=1)
    d[2] = value
    with pytest.raises(ValueError, match=message):
        spherical_harmonics(2, d, torch.randn(4, 9, 3, dtype=torch.float64))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_coefficients_beyond_the_degree_are_ignored(degree: int) -> None:
    d = random_directions(30, seed=3)
    c = torch.randn(30, 25, 3, dtype=torch.float64)
    k = (degree + 1) ** 2
    full = spherical_harmonics(degree, d, c)
    assert torch.equal(full, spherical_harmonics(degree, d, c[:, :k]))
    changed = c.clone()
    changed[:, k:] = 1e6
    assert torch.equal(full, spherical_harmonics(degree, d, changed))


@pytest.mark.slow
@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_gradcheck_in_coefficients_and_directions(degree: int) -> None:
    d = random_directions(4, seed=degree).requires_grad_(True)
    c = torch.randn(4, (degree + 1) ** 2, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda d, c: spherical_harmonics(degree, d, c), (d, c))
    assert torch.autograd.gradgradcheck(lambda d, c: spherical_harmonics(degree, d, c), (d, c))


@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("channels", [1, 3, 8])
def test_shapes_and_dtypes(batch: tuple[int, ...], dtype: torch.dtype, channels: int) -> None:
    d = torch.randn(*batch, 3, dtype=dtype)
    c = torch.randn(*batch, 16, channels, dtype=dtype)
    out = spherical_harmonics(3, d, c)
    assert out.shape == (*batch, channels) and out.dtype == dtype
    reference = spherical_harmonics(3, d.double(), c.double())
    torch.testing.assert_close(out.double(), reference, rtol=1e-5, atol=1e-5)


def test_runs_on_device(device: torch.device) -> None:
    d = random_directions(64, seed=4, dtype=torch.float32)
    c = torch.randn(64, 25, 3)
    got = spherical_harmonics(4, d.to(device), c.to(device))
    assert got.device.type == device.type
    torch.testing.assert_close(got.cpu(), spherical_harmonics(4, d, c), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("degree", [-1, 5, True])
def test_bad_degree_names_it(degree: int) -> None:
    with pytest.raises(ValueError, match=r"^degree"):
        spherical_harmonics(degree, torch.randn(2, 3), torch.randn(2, 36, 3))


def test_too_few_coefficients_name_them() -> None:
    with pytest.raises(ValueError, match=r"^coefficients: degree 2 needs at least 9"):
        spherical_harmonics(2, torch.randn(2, 3), torch.randn(2, 4, 3))


def test_bad_shapes_and_dtypes_name_the_argument() -> None:
    with pytest.raises(TypeCheckError, match="directions"):
        spherical_harmonics(1, torch.randn(2, 4), torch.randn(2, 4, 3))
    with pytest.raises(TypeCheckError, match="coefficients"):
        spherical_harmonics(1, torch.randn(2, 3), torch.randn(3, 4, 3))
    with pytest.raises(TypeCheckError, match="directions"):
        spherical_harmonics(1, torch.zeros(2, 3, dtype=torch.int64), torch.randn(2, 4, 3))
    with pytest.raises(ValueError, match="directions, coefficients"):
        spherical_harmonics(1, torch.randn(2, 3), torch.randn(2, 4, 3, dtype=torch.float64))


@pytest.mark.slow
def test_a_zero_direction_under_compile_names_directions() -> None:
    """Issue 38 (10): the compiled path checks as the other ops do (an in-graph assertion)."""
    import torch._dynamo

    torch._dynamo.reset()
    d = random_directions(4, seed=2)
    d[1] = 0.0
    compiled = torch.compile(spherical_harmonics, backend="aot_eager")
    try:
        with pytest.raises(RuntimeError, match="directions: some directions are zero"):
            compiled(2, d, torch.randn(4, 9, 3, dtype=torch.float64))
    finally:
        torch._dynamo.reset()
