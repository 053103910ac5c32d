"""The splatter's input policy: non-finite values, extreme values, dtypes, empty axes,
the memory guard, and the exact alpha_min boundary."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

import dego
from dego import GaussianSet, splat
from dego.compat.gsplat import rasterization
from tests.helpers.splatting import make_cameras, make_scene_gaussians

SIZE = (20, 28)


def scene(
    dtype: torch.dtype = torch.float64, n: int = 12
) -> tuple[GaussianSet, Tensor, Tensor, Tensor, Tensor]:
    gs = make_scene_gaussians(2, n, SIZE, seed=3, spread=1.0).to(dtype)
    w2c, k = make_cameras(2, 2, SIZE, seed=3, dtype=dtype)
    features = torch.rand(2, n, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    return gs, w2c, k, features.to(dtype), torch.rand(3, dtype=torch.float64).to(dtype)


# ---------------------------------------------------------------------------------------
# non-finite inputs are rejected, naming the field
# ---------------------------------------------------------------------------------------


@settings(max_examples=30)
@given(
    field=st.sampled_from(["means", "quats", "scales", "opacities", "features", "background"]),
    value=st.sampled_from([math.nan, math.inf, -math.inf]),
    index=st.integers(0, 10_000),
)
def test_one_poisoned_value_is_rejected_naming_the_field(
    field: str, value: float, index: int
) -> None:
    gs, w2c, k, features, background = scene()
    tensors = {
        name: getattr(gs, name).clone() for name in ("means", "quats", "scales", "opacities")
    }
    tensors |= {"features": features.clone(), "background": background.clone()}
    flat = tensors[field].view(-1)
    flat[index % flat.numel()] = value
    gs = GaussianSet(**{name: tensors[name] for name in ("means", "quats", "scales", "opacities")})
    with pytest.raises(ValueError, match=rf"{field}: 1 of \d+ values are not finite"):
        splat(gs, w2c, k, SIZE, features=tensors["features"], background=tensors["background"])


def test_the_gsplat_adapter_rejects_them_too() -> None:
    gs, w2c, k, features, _ = scene()
    colors = features[0].clone()
    colors[3, 1] = math.nan
    with pytest.raises(ValueError, match="colors: 1 of"):
        rasterization(gs.means[0], gs.quats[0], gs.scales[0], gs.opacities[0], colors,
                      w2c[0], k[0], SIZE[1], SIZE[0])  # fmt: skip


# ---------------------------------------------------------------------------------------
# extreme but finite values: finite images and gradients
# ---------------------------------------------------------------------------------------


@pytest.mark.slow
@settings(max_examples=40)
@given(
    scale=st.sampled_from([1e-12, 1e-6, 1.0, 1e6, 1e15]),
    depth=st.sampled_from([-1e20, 0.0, 1e-3, 0.02, 5.0, 1e9, 1e20]),
    offset=st.sampled_from([0.0, 1e3, 1e12]),
    opacity=st.sampled_from([0.0, 1e-30, 0.5, 1.0]),
    quat_norm=st.sampled_from([0.0, 1e-20, 1.0, 1e20]),
    dtype=st.sampled_from([torch.float32, torch.float64]),
)
def test_extreme_finite_gaussians_give_finite_images_and_gradients(
    scale: float, depth: float, offset: float, opacity: float, quat_norm: float, dtype: torch.dtype
) -> None:
    gs, w2c, k, features, background = scene(dtype)
    means, scales = gs.means.clone(), gs.scales.clone()
    quats, opacities = gs.quats.clone(), gs.opacities.clone()
    means[:, 0] = torch.tensor([offset, -offset, depth], dtype=dtype)
    scales[:, 0] = scale
    quats[:, 0] = torch.tensor([0.6, 0.0, 0.8, 0.0], dtype=dtype) * quat_norm
    opacities[:, 0] = opacity
    leaves = [t.requires_grad_(True) for t in (means, quats, scales, opacities)]
    out = splat(GaussianSet(*leaves), w2c, k, SIZE, features=features, background=background)
    for name in ("features", "depth", "alpha"):
        assert bool(torch.isfinite(getattr(out, name)).all()), name
    (out.features.sum() + out.depth.sum() + out.alpha.sum()).backward()
    for leaf in leaves:
        assert bool(torch.isfinite(leaf.grad).all())


# ---------------------------------------------------------------------------------------
# dtypes: one floating dtype per call; float16 / bfloat16 computed in float32
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("argument", ["features", "background", "world_to_cam", "intrinsics"])
def test_mixed_dtypes_are_rejected_naming_the_argument(argument: str) -> None:
    gs, w2c, k, features, background = scene(torch.float32)
    args = {"features": features, "background": background, "world_to_cam": w2c, "intrinsics": k}
    args[argument] = args[argument].double()
    with pytest.raises(TypeError, match=rf"{argument}: dtype torch.float64 differs"):
        splat(gs, args["world_to_cam"], args["intrinsics"], SIZE,
              features=args["features"], background=args["background"])  # fmt: skip


@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
def test_half_precision_is_computed_in_float32(half: torch.dtype) -> None:
    gs, w2c, k, features, background = scene(torch.float32)
    reference = splat(gs, w2c, k, SIZE, features=features, background=background)
    leaves = [
        t.to(half).requires_grad_(True) for t in (gs.means, gs.quats, gs.scales, gs.opacities)
    ]
    out = splat(GaussianSet(*leaves), w2c.to(half), k.to(half), SIZE,
                features=features.to(half), background=background.to(half))  # fmt: skip
    assert out.features.dtype == out.depth.dtype == out.alpha.dtype == half
    # the inputs were rounded to `half`: compare at that precision, where the images are
    tolerance = 0.05 if half == torch.bfloat16 else 0.01
    torch.testing.assert_close(out.alpha.float(), reference.alpha, rtol=0, atol=tolerance)
    (out.features.float().sum() + out.alpha.float().sum()).backward()
    assert all(leaf.grad is not None and leaf.grad.dtype == half for leaf in leaves)
    assert all(bool(torch.isfinite(leaf.grad).all()) for leaf in leaves)


# ---------------------------------------------------------------------------------------
# empty axes and the memory guard
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(("b", "v", "n"), [(0, 2, 5), (1, 0, 5), (1, 2, 0), (0, 0, 0)])
def test_empty_axes_give_empty_results(b: int, v: int, n: int) -> None:
    gs = make_scene_gaussians(max(b, 1), n, SIZE, seed=1)
    gs = GaussianSet(*(getattr(gs, f)[:b] for f in ("means", "quats", "scales", "opacities")))
    w2c, k = make_cameras(max(b, 1), max(v, 1), SIZE, seed=1)
    out = splat(gs, w2c[:b, :v], k[:b, :v], SIZE, features=torch.zeros(b, n, 3, dtype=gs.dtype))
    assert out.features.shape == (b, v, 3, *SIZE)
    assert out.depth.shape == out.alpha.shape == (b, v, *SIZE)
    assert out.radii.shape == (b, v, n)
    if b and v:
        assert float(out.alpha.abs().max()) == 0.0


def test_the_memory_guard_trips_before_allocating() -> None:
    gs, w2c, k, features, _ = scene()
    with dego.memory_limit(10_000), pytest.raises(ValueError, match=r"splat: would need about"):
        splat(gs, w2c, k, SIZE, features=features)
    # 4 images of 1M x 1M pixels: refused at once under the default limit
    with pytest.raises(ValueError, match=r"4 images of 1000000 x 1000000.*memory limit"):
        splat(gs, w2c, k, (1_000_000, 1_000_000), features=features)
    assert dego.get_memory_limit() == 64 * 2**30
    previous = dego.set_memory_limit(None)
    try:
        assert dego.get_memory_limit() is None
    finally:
        dego.set_memory_limit(previous)
    with pytest.raises(ValueError, match="nbytes"):
        dego.set_memory_limit(0)


# ---------------------------------------------------------------------------------------
# the alpha_min boundary: alpha == alpha_min is kept (only alpha < alpha_min is skipped)
# ---------------------------------------------------------------------------------------


def test_alpha_exactly_alpha_min_is_kept() -> None:
    opacity = 0.5  # exp(log(0.5)) == 0.5 in float64, so the alpha under the mean is exact
    t = torch.tensor(opacity, dtype=torch.float64)
    assert float(torch.exp(torch.log(t))) == opacity
    gs = GaussianSet(
        means=torch.tensor([[[0.0, 0.0, 4.0]]], dtype=torch.float64),
        quats=torch.tensor([[[1.0, 0.0, 0.0, 0.0]]], dtype=torch.float64),
        scales=torch.full((1, 1, 3), 0.05, dtype=torch.float64),
        opacities=torch.tensor([[opacity]], dtype=torch.float64),
    )
    # principal point on the centre of pixel (16, 16): the mean projects exactly there
    k = torch.tensor([[40.0, 0, 16.5], [0, 40.0, 16.5], [0, 0, 1]], dtype=torch.float64)
    w2c, k = torch.eye(4, dtype=torch.float64)[None, None], k[None, None]
    kept = splat(gs, w2c, k, (33, 33), alpha_min=opacity)
    assert float(kept.alpha[0, 0, 16, 16]) == opacity
    assert int((kept.alpha > 0).sum()) == 1  # every other pixel is below alpha_min
    skipped = splat(gs, w2c, k, (33, 33), alpha_min=math.nextafter(opacity, 1.0))
    assert float(skipped.alpha.abs().max()) == 0.0
