"""The splat options gsplat users need: radius rules, radius_clip, antialiasing, per-camera
features, absgrad, and the errors that replace silent porting mistakes."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from dego import DifferentiableSplatter, GaussianSet, splat
from dego.splatting import gsplat_backend
from dego.splatting.pipeline import render as pipeline_render
from dego.splatting.types import SplatConfig
from tests.helpers.splatting import (
    Scene,
    assert_outputs_close,
    gradients,
    make_cameras,
    make_scene_gaussians,
    render,
    render_reference,
    scenes,
    small_scene,
)

OPTIONS = st.fixed_dictionaries(
    {
        "radius_rule": st.sampled_from(["gsplat<=1.4", "gsplat>=1.5"]),
        "radius_clip": st.sampled_from([0.0, 2.0, 4.5]),
        "rasterize_mode": st.sampled_from(["classic", "antialiased"]),
    }
)


def per_camera(scene: Scene, seed: int) -> Scene:
    """The scene with different features for every camera ``(B, V, N, C)``."""
    b, v = scene.world_to_cam.shape[:2]
    n = scene.gaussians.num_gaussians
    g = torch.Generator().manual_seed(seed)
    channels = 2 if scene.background is None else scene.background.shape[-1]
    feats = torch.randn(b, v, n, channels, generator=g, dtype=torch.float64)
    return scene.replace(features=feats.to(scene.gaussians.dtype))


# ---------------------------------------------------------------------------------------
# agreement with the dense reference
# ---------------------------------------------------------------------------------------


@pytest.mark.slow
@settings(max_examples=25)
@given(scenes(), OPTIONS, st.booleans())
def test_options_match_dense_reference(scene: Scene, options: dict, cameras: bool) -> None:
    if cameras:
        scene = per_camera(scene, 7)
    scene = scene.replace(config={**scene.config, **options})
    out = render(scene)
    assert_outputs_close(out, render_reference(scene), rtol=1e-5, atol=1e-5)


@pytest.mark.slow
@settings(max_examples=12)
@given(scenes(max_n=12), OPTIONS, st.booleans())
def test_option_gradients_match_dense_reference(scene: Scene, options: dict, cameras: bool) -> None:
    if cameras:
        scene = per_camera(scene, 3)
    scene = scene.replace(config={**scene.config, **options})
    grads = gradients(scene, render)
    expected = gradients(scene, render_reference)
    for name in expected:
        torch.testing.assert_close(grads[name], expected[name], rtol=1e-4, atol=1e-4, msg=name)


def test_per_camera_features_equal_single_camera_renders() -> None:
    scene = per_camera(small_scene(channels=None, views=3), 1)
    out = render(scene)
    for v in range(3):
        one = render(
            scene.replace(
                world_to_cam=scene.world_to_cam[:, v : v + 1],
                intrinsics=scene.intrinsics[:, v : v + 1],
                features=scene.features[:, v],
            )
        )
        torch.testing.assert_close(out.features[:, v : v + 1], one.features, rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------------------
# closed forms
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("scale", [0.02, 0.1, 0.5])
def test_antialiased_compensation_of_an_isotropic_gaussian(
    dtype: torch.dtype, scale: float
) -> None:
    """On the optical axis the 2D covariance is v I with v = (f s / z)^2: the compensation is
    sqrt(v^2 / (v + eps)^2) = v / (v + eps), and the pixel under the mean gets o times it."""
    focal, depth, opacity, eps2d = 50.0, 4.0, 0.8, 0.3
    size = 33  # odd: the mean projects onto the centre of pixel 16
    gs = GaussianSet(
        means=torch.tensor([[[0.0, 0.0, depth]]], dtype=dtype),
        quats=torch.tensor([[[1.0, 0.0, 0.0, 0.0]]], dtype=dtype),
        scales=torch.full((1, 1, 3), scale, dtype=dtype),
        opacities=torch.tensor([[opacity]], dtype=dtype),
    )
    k = torch.tensor([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]], dtype=dtype)
    w2c, k = torch.eye(4, dtype=dtype)[None, None], k[None, None]
    variance = (focal * scale / depth) ** 2
    out = splat(gs, w2c, k, (size, size), rasterize_mode="antialiased", eps2d=eps2d)
    expected = opacity * variance / (variance + eps2d)
    assert float(out.projection.opacities) == pytest.approx(expected, rel=1e-6)
    assert float(out.alpha[0, 0, 16, 16]) == pytest.approx(expected, rel=1e-5)
    classic = splat(gs, w2c, k, (size, size), eps2d=eps2d)
    assert float(classic.alpha[0, 0, 16, 16]) == pytest.approx(opacity, rel=1e-5)


def test_radius_rules_follow_their_formulas() -> None:
    """Random scenes well inside the field of view (no Jacobian clamp): the 1.5 rule gives
    ceil(min(3.33, sqrt(2 ln(255 o))) sqrt(Sigma_ii)) per axis and culls o < 1/255; the 1.4
    rule gives ceil(3 sqrt(lambda_max)) with lambda_max floored as gsplat 1.4 does."""
    size = (64, 96)
    gs = make_scene_gaussians(
        2, 300, size, seed=5, spread=0.6, opacity_range=(0.0, 1.0), scale_range=(0.01, 0.6)
    )
    gs = gs.replace(opacities=torch.where(gs.opacities < 0.05, gs.opacities * 0.05, gs.opacities))
    w2c, k = make_cameras(2, 1, size, seed=5)
    w2c = torch.eye(4, dtype=w2c.dtype).expand_as(w2c)
    cam = gs.means  # identity cameras: camera coordinates are the world's
    x, y, z = cam.unbind(-1)
    fx, fy = k[:, :, 0, 0], k[:, :, 1, 1]
    zero = torch.zeros_like(z)
    jac = torch.stack([fx / z, zero, -fx * x / z**2, zero, fy / z, -fy * y / z**2], -1).unflatten(
        -1, (2, 3)
    )
    cov2d = jac @ gs.covariances() @ jac.transpose(-1, -2) + 0.3 * torch.eye(2, dtype=z.dtype)
    var_x, var_y, cov_xy = cov2d[..., 0, 0], cov2d[..., 1, 1], cov2d[..., 0, 1]

    new = splat(gs, w2c, k, size, radius_rule="gsplat>=1.5").projection
    o = gs.opacities
    extent = torch.clamp(torch.sqrt(2 * torch.log((o * 255).clamp_min(1))), max=3.33)
    expected = torch.stack(
        [torch.ceil(extent * var_x.sqrt()), torch.ceil(extent * var_y.sqrt())], -1
    )
    keep = new.visible[:, 0]
    assert bool(((o >= 1 / 255) == keep).all())  # all on screen and in front
    assert torch.equal(new.radii_xy[:, 0][keep].double(), expected[keep])
    assert bool((new.radii_xy[:, 0][~keep] == 0).all())

    old = splat(gs, w2c, k, size).projection
    mid = 0.5 * (var_x + var_y)
    lam = mid + torch.sqrt((mid**2 - (var_x * var_y - cov_xy**2)).clamp_min(0.01))
    assert torch.equal(old.radii[:, 0].double(), torch.ceil(3 * lam.sqrt()))
    assert torch.equal(old.radii_xy[..., 0], old.radii_xy[..., 1])


def test_radius_clip_culls_small_footprints() -> None:
    scene = small_scene()
    out = render(scene)
    clip = float(out.radii[out.radii > 0].double().median())
    clipped = render(scene, radius_clip=clip)
    assert bool(((clipped.radii > 0) == (out.radii > clip)).all())
    assert bool((clipped.radii[clipped.radii > 0] == out.radii[clipped.radii > 0]).all())
    nothing = render(scene, radius_clip=1e6)
    assert float(nothing.alpha.abs().max()) == 0.0


# ---------------------------------------------------------------------------------------
# absgrad: per-pixel screen-space gradients summed in absolute value
# ---------------------------------------------------------------------------------------


def _tiny_scene() -> tuple[GaussianSet, Tensor, Tensor, tuple[int, int]]:
    size = (10, 14)
    gs = make_scene_gaussians(1, 4, size, seed=11, feature_dim=2, spread=0.6)
    gs = gs.replace(scales=gs.scales * 0.6)
    w2c, k = make_cameras(1, 2, size, seed=11)
    return gs, w2c, k, size


def _pixel_losses(
    gs: GaussianSet, w2c: Tensor, k: Tensor, size: tuple[int, int], shift: Tensor, **kw: Any
) -> tuple[Tensor, Any]:
    """Per-pixel scalar losses ``(B, V, H, W)`` with the projected means moved by ``shift``."""
    out = pipeline_render(
        gs, w2c, k, size, None, None, SplatConfig(**kw), means2d_hook=lambda p: p.means2d + shift
    )
    g = torch.Generator().manual_seed(4)
    weights = torch.randn(out.features.shape, generator=g, dtype=torch.float64)
    alpha_weights = torch.randn(out.alpha.shape, generator=g, dtype=torch.float64)
    return (out.features * weights).sum(2) + out.alpha * alpha_weights, out


def test_absgrad_is_the_sum_of_absolute_per_pixel_gradients() -> None:
    """Float64 central differences of every pixel's loss w.r.t. every projected mean."""
    gs, w2c, k, size = _tiny_scene()
    shift = torch.zeros(1, 2, 4, 2, dtype=torch.float64)
    h = 1e-6
    jac = torch.zeros(*shift.shape, 1, 2, *size, dtype=torch.float64)  # (B,V,N,2,B,V,H,W)
    for index in np.ndindex(*shift.shape):
        step = torch.zeros_like(shift)
        step[index] = h
        plus = _pixel_losses(gs, w2c, k, size, step)[0]
        minus = _pixel_losses(gs, w2c, k, size, -step)[0]
        jac[index] = (plus - minus) / (2 * h)
    # a Gaussian of camera v only reaches camera v's pixels
    same_camera = torch.stack([jac[:, v, :, :, :, v] for v in range(2)], 1)
    expected_abs = same_camera.abs().sum((-1, -2, -3))
    expected_grad = same_camera.sum((-1, -2, -3))

    means = gs.means.detach().clone().requires_grad_(True)
    moved = gs.replace(means=means)
    losses, out = _pixel_losses(moved, w2c, k, size, torch.zeros_like(shift), absgrad=True)
    means2d = out.projection.means2d
    means2d.retain_grad()
    losses.sum().backward()
    torch.testing.assert_close(means2d.grad, expected_grad, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(means2d.absgrad, expected_abs, rtol=1e-5, atol=1e-7)
    assert float(expected_abs.max()) > 0
    # per pixel gradients of both signs: the absolute sum exceeds the plain one somewhere
    assert bool((means2d.absgrad > means2d.grad.abs() + 1e-6).any())


def test_without_absgrad_nothing_is_attached() -> None:
    gs, w2c, k, size = _tiny_scene()
    gs = gs.replace(means=gs.means.detach().clone().requires_grad_(True))
    out = splat(gs, w2c, k, size)
    out.alpha.sum().backward()
    assert not hasattr(out.projection.means2d, "absgrad")


# ---------------------------------------------------------------------------------------
# image_size forms and the errors that replace silent porting mistakes
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "size",
    [
        (20, 36),
        [20, 36],
        torch.Size([20, 36]),
        (np.int64(20), np.int32(36)),
        np.array([20, 36]),
    ],
    ids=["tuple", "list", "torch.Size", "numpy-ints", "numpy-array"],
)
def test_image_size_accepts_any_pair_of_ints(size: Any) -> None:
    scene = small_scene()
    expected = render(scene)
    out = render(scene.replace(image_size=size))
    assert torch.equal(out.features, expected.features)


@pytest.mark.parametrize("size", [(20.0, 36), (True, 36), (20,), (20, 36, 3), "2036"])
def test_image_size_rejects_non_int_pairs(size: Any) -> None:
    with pytest.raises((ValueError, TypeError), match="image_size"):
        render(small_scene().replace(image_size=size))


def _one_camera(dtype: torch.dtype = torch.float64) -> tuple[GaussianSet, Tensor, Tensor]:
    gs = make_scene_gaussians(1, 6, (256, 704), seed=2).to(dtype)
    k = torch.tensor([[560.0, 0, 352], [0, 560.0, 128], [0, 0, 1]], dtype=dtype)[None, None]
    return gs, torch.eye(4, dtype=dtype)[None, None], k


def test_transposed_image_size_raises() -> None:
    gs, w2c, k = _one_camera()
    splat(gs, w2c, k, (256, 704))
    with pytest.raises(ValueError, match=r"image_size.*transposed"):
        splat(gs, w2c, k, (704, 256))


@pytest.mark.parametrize(
    ("entry", "value"),
    [((0, 1), 3.0), ((1, 0), 0.5), ((2, 0), 1e-3), ((2, 2), 2.0)],
    ids=["skew", "lower-left", "last-row", "homogeneous-scale"],
)
def test_non_pinhole_intrinsics_raise(entry: tuple[int, int], value: float) -> None:
    gs, w2c, k = _one_camera()
    k = k.clone()
    k[0, 0][entry] = value
    with pytest.raises(ValueError, match=r"intrinsics:.*skew.*warp the image"):
        splat(gs, w2c, k, (256, 704))


def test_tiny_float_noise_in_the_intrinsics_is_tolerated() -> None:
    gs, w2c, k = _one_camera()
    k = k.clone()
    k[0, 0, 0, 1] = 1e-7 * 560  # relative 1e-7
    splat(gs, w2c, k, (256, 704))


def test_world_to_cam_with_a_projective_last_row_raises() -> None:
    gs, w2c, k = _one_camera()
    w2c = w2c.clone()
    w2c[0, 0, 3, 2] = 0.5
    with pytest.raises(ValueError, match=r"world_to_cam:.*\[0, 0, 0, 1\].*split_projection"):
        splat(gs, w2c, k, (256, 704))


def test_cameras_with_a_time_axis_say_flatten() -> None:
    gs, w2c, k = _one_camera()
    w2c5, k5 = w2c[:, None].expand(1, 3, 1, 4, 4), k[:, None].expand(1, 3, 1, 3, 3)
    with pytest.raises(ValueError, match=r"world_to_cam: expected shape \(B, V, 4, 4\).*flatten"):
        splat(gs, w2c5, k5, (256, 704))
    with pytest.raises(ValueError, match=r"intrinsics:.*flatten"):
        splat(gs, w2c, k5, (256, 704))
    with pytest.raises(ValueError, match=r"world_to_cam:.*add the batch axis"):
        splat(gs, w2c[0], k[0], (256, 704))
    module = DifferentiableSplatter()
    with pytest.raises(ValueError, match="flatten"):
        module(gs, w2c5, k5, (256, 704))
    with pytest.raises(ValueError, match="flatten"):
        module(gs, world_to_cam=w2c5, intrinsics=k5, image_size=(256, 704))


def test_wrong_size_camera_matrices_and_int_image_size_are_one_line_errors() -> None:
    """Issue 41 (6): in the caller's words, one line, not a type-check dump."""
    gs, w2c, k = _one_camera()
    k4 = torch.eye(4, dtype=k.dtype)[None, None]
    k4[..., :3, :3] = k
    module = DifferentiableSplatter()
    for call in (splat, module):
        cases = [
            ((gs, w2c, k4, (256, 704)), r"intrinsics: .*\(1, 1, 4, 4\); pass .*\[\.\.\., :3, :3\]"),
            ((gs, w2c, k4[..., :3, :], (256, 704)), r"intrinsics: .*split_projection"),
            (
                (gs, w2c[..., :3, :], k, (256, 704)),
                r"world_to_cam: .*append the row \[0, 0, 0, 1\]",
            ),
            ((gs, w2c, k, 256), r"image_size: expected \(H, W\), two positive ints, got 256"),
        ]
        for args, message in cases:
            with pytest.raises(ValueError, match=message) as caught:
                call(*args)
            assert len(str(caught.value).splitlines()) == 1
    with pytest.raises(ValueError, match="image_size"):
        splat(gs, w2c, k, image_size=256)
    # the 3 x 3 part is what the message says to pass, and renders
    splat(gs, w2c, k4[..., :3, :3], (256, 704))


@pytest.mark.parametrize(
    ("keyword", "dego_name"),
    [
        ("viewmats", "world_to_cam"),
        ("Ks", "intrinsics"),
        ("width", "image_size"),
        ("near_plane", "near"),
        ("far_plane", "far"),
        ("backgrounds", "background"),
        ("render_mode", "depth_mode"),
        ("colors", "features"),
    ],
)
def test_gsplat_keywords_name_the_dego_argument(keyword: str, dego_name: str) -> None:
    gs, w2c, k = _one_camera()
    with pytest.raises(TypeError, match=rf"{keyword}.*{dego_name}.*compat\.gsplat"):
        splat(gs, w2c, k, (256, 704), **{keyword: 1})
    with pytest.raises(TypeError, match=rf"{keyword}.*{dego_name}"):
        DifferentiableSplatter(**{keyword: 1})


def test_unknown_module_setting_lists_the_valid_ones() -> None:
    with pytest.raises(
        TypeError, match=r"unknown option 'radius_rul' \(did you mean 'radius_rule'"
    ):
        DifferentiableSplatter(radius_rul="gsplat>=1.5")


def test_logit_opacities_raise_with_a_hint() -> None:
    gs, w2c, k = _one_camera()
    logits = torch.logit(gs.opacities) - 8  # every value negative: clearly not probabilities
    with pytest.raises(ValueError, match=r'opacities.*logits.*opacity_space="logit"'):
        splat(gs.replace(opacities=logits), w2c, k, (256, 704))
    some = gs.opacities.clone()
    some[0, 0] = 1.5
    with pytest.raises(ValueError, match=r"opacities: 1 of 6 values lie outside \[0, 1\]") as info:
        splat(gs.replace(opacities=some), w2c, k, (256, 704))
    assert "logit" not in str(info.value)  # the hint only when every value is outside


def test_log_scales_raise_with_a_hint() -> None:
    gs, w2c, k = _one_camera()
    with pytest.raises(ValueError, match=r'scales.*log-scales.*scale_space="log"'):
        splat(gs.replace(scales=gs.scales.log()), w2c, k, (256, 704))


@pytest.mark.parametrize(
    "bad",
    [
        {"radius_clip": -1.0},
        {"radius_clip": float("nan")},
        {"rasterize_mode": "mip"},
        {"radius_rule": "gsplat==1.5"},
        {"radius_sigma": 0.0},
        {"absgrad": 1},
    ],
)
def test_bad_option_values_raise(bad: dict) -> None:
    with pytest.raises((ValueError, TypeError), match=next(iter(bad))):
        render(small_scene(), **bad)


# ---------------------------------------------------------------------------------------
# the gsplat backend's version rules (no gsplat needed: the version is patched)
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("version", "rule", "message"),
    [
        ((1, 4), "gsplat>=1.5", r"radius_rule='gsplat>=1\.5' differs .* 1\.4's 'gsplat<=1\.4'"),
        ((1, 5), "gsplat<=1.4", r"radius_rule='gsplat<=1\.4' differs .* 1\.5's 'gsplat>=1\.5'"),
        ((1, 3), "gsplat<=1.4", r"gsplat 1\.3 is older than 1\.4"),
    ],
)
def test_gsplat_backend_checks_the_installed_version(
    monkeypatch: pytest.MonkeyPatch, version: tuple[int, int], rule: str, message: str
) -> None:
    monkeypatch.setattr(gsplat_backend, "installed_version", lambda: version)
    gs, w2c, k = _one_camera(torch.float32)
    with pytest.raises(ValueError, match=message):
        splat(gs, w2c, k, (256, 704), backend="gsplat", radius_rule=rule)
    out = splat(gs, w2c, k, (256, 704), backend="auto", radius_rule=rule)
    assert out.projection is not None  # fell back to the torch path


def test_gsplat_rule_of_each_release() -> None:
    assert gsplat_backend.rule_of((1, 4)) == "gsplat<=1.4"
    assert gsplat_backend.rule_of((1, 5)) == "gsplat>=1.5"
    assert gsplat_backend.rule_of((1, 6)) == "gsplat>=1.5"
