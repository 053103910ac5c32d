"""Tile-based Gaussian splatting: dense-reference agreement, closed forms, invariants, errors."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

import dego
from dego import GaussianSet
from dego.splatting import DifferentiableSplatter, SplatOutput, splat
from tests.helpers.splatting import (
    Scene,
    assert_outputs_close,
    axis_angle_matrix,
    gradients,
    make_cameras,
    make_scene_gaussians,
    render,
    render_reference,
    scenes,
    small_scene,
    weighted_sum,
    with_grad,
)

ALPHA_MIN = 1 / 255
EPS2D = 0.3

# ---------------------------------------------------------------------------------------
# scene helpers
# ---------------------------------------------------------------------------------------


def batch_item(gs: GaussianSet, b: int) -> GaussianSet:
    """Batch element ``b`` of a ``(B,)`` set, kept as a batch of one."""
    return GaussianSet(
        **{n: getattr(gs, n)[b : b + 1] for n in GaussianSet.FIELDS if getattr(gs, n) is not None}
    )


# ---------------------------------------------------------------------------------------
# agreement with the dense reference
# ---------------------------------------------------------------------------------------


@settings(max_examples=30)
@given(scenes())
def test_forward_matches_dense_reference(scene: Scene) -> None:
    out = render(scene)
    assert isinstance(out, SplatOutput)
    b, v = scene.world_to_cam.shape[:2]
    h, w = scene.image_size
    assert out.alpha.shape == (b, v, h, w)
    assert out.radii.shape == (b, v, scene.gaussians.num_gaussians)
    assert_outputs_close(out, render_reference(scene), rtol=1e-5, atol=1e-5)


@settings(max_examples=20)
@given(scenes(max_n=20))
def test_gradients_match_dense_reference(scene: Scene) -> None:
    grads = gradients(scene, render)
    expected = gradients(scene, render_reference)
    for name in expected:
        torch.testing.assert_close(grads[name], expected[name], rtol=1e-4, atol=1e-4, msg=name)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(3))
def test_dense_scene_with_termination_and_truncation_matches_reference(seed: int) -> None:
    image_size = (32, 48)
    gs = make_scene_gaussians(
        1,
        30,
        image_size,
        seed=seed,
        feature_dim=2,
        opacity_range=(0.6, 1.0),
        scale_range=(0.2, 1.0),
        spread=0.9,
    )
    w2c, intrinsics = make_cameras(1, 2, image_size, seed=seed)
    config = {
        "tile_size": 8,
        "radius_sigma": 2.0,
        "alpha_min": 1e-3,
        "transmittance_min": 1e-3,
        "chunk_size": 4,
    }
    scene = Scene(gs, w2c, intrinsics, image_size, config=config)
    expected = render_reference(scene)
    # Both rules must matter here: dropping either changes the reference image.
    assert not torch.equal(render_reference(scene, transmittance_min=0.0).alpha, expected.alpha)
    assert not torch.equal(render_reference(scene, tile_size=1024).alpha, expected.alpha)
    assert_outputs_close(render(scene), expected, rtol=1e-5, atol=1e-5)
    grads, expected_grads = gradients(scene, render), gradients(scene, render_reference)
    for name in expected_grads:
        torch.testing.assert_close(
            grads[name], expected_grads[name], rtol=1e-4, atol=1e-4, msg=name
        )


@pytest.mark.parametrize("seed", range(4))
def test_float32_matches_float64_reference(seed: int) -> None:
    image_size = (32, 48)
    gs = make_scene_gaussians(2, 25, image_size, seed=seed, feature_dim=3, culled=True)
    w2c, intrinsics = make_cameras(2, 2, image_size, seed=seed)
    background = torch.tensor([0.2, -0.1, 0.5], dtype=torch.float64)
    scene = Scene(gs, w2c, intrinsics, image_size, background=background, config={"tile_size": 8})
    out = render(scene.to(torch.float32))
    assert out.features.dtype == torch.float32 and out.alpha.dtype == torch.float32
    expected = render_reference(scene)
    torch.testing.assert_close(out.features.double(), expected.features, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(out.alpha.double(), expected.alpha, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(out.depth.double(), expected.depth, rtol=1e-4, atol=1e-4)
    assert torch.equal(out.radii.long(), expected.radii)


@pytest.mark.slow
@settings(max_examples=15)
@given(scenes(max_n=20), st.sampled_from([1, 3]), st.sampled_from([64, 300]))
def test_chunking_and_pair_limits_do_not_change_the_result(
    scene: Scene, chunk_size: int, max_pairs: int
) -> None:
    base = {"chunk_size": 64, "max_pairs": 2**22}
    small = {"chunk_size": chunk_size, "max_pairs": max_pairs}
    assert_outputs_close(render(scene, **small), render(scene, **base), rtol=1e-10, atol=1e-10)
    grads, expected = gradients(scene, render, **small), gradients(scene, render, **base)
    for name in expected:
        torch.testing.assert_close(grads[name], expected[name], rtol=1e-9, atol=1e-9, msg=name)


# ---------------------------------------------------------------------------------------
# closed forms
# ---------------------------------------------------------------------------------------


def on_axis_scene(
    depths: list[float],
    scales: list[float],
    opacities: list[float],
    *,
    focal: float,
    image_size: tuple[int, int] = (32, 32),
    features: Tensor | None = None,
    background: Tensor | None = None,
    **config: Any,
) -> Scene:
    """Isotropic Gaussians on the optical axis of an identity camera whose principal point
    is the centre of pixel (16, 16)."""
    n = len(depths)
    dtype = torch.float64
    means = torch.zeros(1, n, 3, dtype=dtype)
    means[0, :, 2] = torch.tensor(depths, dtype=dtype)
    quats = torch.zeros(1, n, 4, dtype=dtype)
    quats[..., 0] = 1
    gs = GaussianSet(
        means=means,
        quats=quats,
        scales=torch.tensor(scales, dtype=dtype)[None, :, None].expand(1, n, 3).clone(),
        opacities=torch.tensor([opacities], dtype=dtype),
    )
    w2c = torch.eye(4, dtype=dtype).expand(1, 1, 4, 4).clone()
    intrinsics = torch.tensor([[[[focal, 0, 16.5], [0, focal, 16.5], [0, 0, 1]]]], dtype=dtype)
    return Scene(gs, w2c, intrinsics, image_size, features, background, config)


def tile_range_mask(centre: float, radius: int, size: int, tile_size: int) -> Tensor:
    """1-D bool mask of the pixels whose tile lies in ``[floor((c-r)/ts), ceil((c+r)/ts))``."""
    tiles = math.ceil(size / tile_size)
    lo = min(max(math.floor((centre - radius) / tile_size), 0), tiles)
    hi = min(max(math.ceil((centre + radius) / tile_size), 0), tiles)
    tile = torch.arange(size) // tile_size
    return (tile >= lo) & (tile < hi)


@pytest.mark.parametrize(
    ("focal", "scale", "depth", "opacity", "tile_size", "size", "truncated"),
    [
        (20.0, 0.5, 4.0, 0.8, 16, 32, False),
        (30.0, 0.2, 3.0, 0.9, 4, 32, False),
        (25.0, 1e-3, 5.0, 0.5, 8, 32, False),  # footprint dominated by eps2d
        (40.0, 1.02, 4.0, 0.9, 16, 64, True),  # 3-sigma tile rectangle cuts visible alpha
    ],
)
def test_isotropic_gaussian_on_the_optical_axis(
    focal: float,
    scale: float,
    depth: float,
    opacity: float,
    tile_size: int,
    size: int,
    truncated: bool,
) -> None:
    colour = torch.tensor([[[1.0, -2.0]]], dtype=torch.float64)
    background = torch.tensor([0.5, 0.25], dtype=torch.float64)
    scene = on_axis_scene(
        [depth],
        [scale],
        [opacity],
        focal=focal,
        image_size=(size, size),
        features=colour,
        background=background,
        tile_size=tile_size,
    )
    out = render(scene)

    variance = (focal * scale / depth) ** 2 + EPS2D
    radius = math.ceil(3 * math.sqrt(variance))
    centres = torch.arange(size, dtype=torch.float64) + 0.5
    d2 = (centres[:, None] - 16.5) ** 2 + (centres[None, :] - 16.5) ** 2
    untruncated = opacity * torch.exp(-d2 / (2 * variance))
    untruncated = torch.where(untruncated >= ALPHA_MIN, untruncated, 0.0)
    mask = tile_range_mask(16.5, radius, size, tile_size)
    alpha = torch.where(mask[:, None] & mask[None, :], untruncated, 0.0)
    if truncated:  # the case is built so that the truncation drops visible alpha
        assert bool(((untruncated > 0) & (alpha == 0)).any())

    assert out.radii.flatten().tolist() == [radius]
    torch.testing.assert_close(out.alpha[0, 0], alpha, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(
        out.depth[0, 0], torch.where(alpha > 0, depth, torch.zeros_like(alpha))
    )
    expected = colour[0, 0, :, None, None] * alpha + background[:, None, None] * (1 - alpha)
    torch.testing.assert_close(out.features[0, 0], expected, rtol=1e-10, atol=1e-12)
    accumulated = render(scene, depth_mode="accumulated")
    torch.testing.assert_close(accumulated.depth[0, 0], depth * alpha, rtol=1e-10, atol=1e-12)


def test_world_to_cam_convention_on_a_moved_camera() -> None:
    # Camera centre c with rotation R: world_to_cam = [R | -R c]. An isotropic Gaussian at
    # c + d * R^T e_z sits on its optical axis at depth d, exactly like (0, 0, d) seen by the
    # identity camera.
    scene = on_axis_scene([4.0], [0.4], [0.7], focal=25.0, tile_size=8)
    rot = axis_angle_matrix(torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64), 2.0)
    centre = torch.tensor([1.0, -2.0, 3.0], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3], w2c[:3, 3] = rot, -rot @ centre
    means = (centre + 4.0 * rot.T[:, 2])[None, None]
    moved = scene.replace(
        gaussians=scene.gaussians.replace(means=means), world_to_cam=w2c[None, None]
    )
    assert_outputs_close(render(moved), render(scene), rtol=1e-9, atol=1e-9)
    assert float(render(moved).alpha.max()) == pytest.approx(0.7)


def test_two_gaussians_composite_front_to_back() -> None:
    # Listed back first: the renderer must sort by camera depth.
    features = torch.tensor([[[0.0, 1.0], [1.0, 0.0]]], dtype=torch.float64)
    background = torch.tensor([0.3, 0.7], dtype=torch.float64)
    scene = on_axis_scene(
        [6.0, 3.0], [1.0, 1.0], [0.5, 0.6], focal=20.0, features=features, background=background
    )
    out = render(scene)
    front, back = 0.6, 0.5
    centre = (0, 0, slice(None), 16, 16)
    expected = torch.tensor(
        [
            front + 0.3 * (1 - front) * (1 - back),
            back * (1 - front) + 0.7 * (1 - front) * (1 - back),
        ],
        dtype=torch.float64,
    )
    torch.testing.assert_close(out.features[centre], expected)
    alpha = 1 - (1 - front) * (1 - back)
    torch.testing.assert_close(out.alpha[0, 0, 16, 16], torch.tensor(alpha, dtype=torch.float64))
    depth = (3.0 * front + 6.0 * back * (1 - front)) / alpha
    torch.testing.assert_close(out.depth[0, 0, 16, 16], torch.tensor(depth, dtype=torch.float64))


@pytest.mark.parametrize(("transmittance_min", "contributing"), [(1e-4, 3), (1e-6, 4), (0.1, 0)])
def test_termination_drops_the_gaussian_that_crosses_the_threshold(
    transmittance_min: float, contributing: int
) -> None:
    # Five opaque Gaussians at the centre pixel, each alpha 0.95: T = 0.05, 0.0025,
    # 1.25e-4, 6.25e-6, 3.1e-7. The one whose T_next <= transmittance_min stops the pixel.
    opacity = 0.95
    features = torch.eye(5, dtype=torch.float64)[None]
    background = torch.full((5,), 10.0, dtype=torch.float64)
    scene = on_axis_scene(
        [5.0, 4.0, 3.0, 2.0, 1.0],
        [0.8, 0.6, 0.5, 0.3, 0.2],
        [opacity] * 5,
        focal=20.0,
        features=features,
        background=background,
        transmittance_min=transmittance_min,
    )
    out = render(scene)
    weights = [opacity * (1 - opacity) ** k if k < contributing else 0.0 for k in range(5)]
    final_t = (1 - opacity) ** contributing
    expected = torch.tensor(weights[::-1], dtype=torch.float64) + 10.0 * final_t
    torch.testing.assert_close(out.features[0, 0, :, 16, 16], expected)
    torch.testing.assert_close(
        out.alpha[0, 0, 16, 16], torch.tensor(1 - final_t, dtype=torch.float64)
    )
    torch.testing.assert_close(out.features, render_reference(scene).features)


# ---------------------------------------------------------------------------------------
# invariants
# ---------------------------------------------------------------------------------------


@settings(max_examples=15)
@given(scenes(), st.integers(0, 2**31 - 1))
def test_weights_form_a_partition_of_alpha(scene: Scene, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    b, n = scene.world_to_cam.shape[0], scene.gaussians.num_gaussians
    colour = torch.randn(2, generator=g, dtype=torch.float64)
    background = torch.randn(2, generator=g, dtype=torch.float64)
    scene = scene.replace(
        features=colour.expand(b, n, 2).clone(),
        background=background,
        config={**scene.config, "depth_mode": "expected"},
    )
    out = render(scene)
    tmin = scene.config.get("transmittance_min", 1e-4)
    assert bool((out.alpha >= 0).all()) and bool((out.alpha <= 1 - tmin + 1e-12).all())
    alpha = out.alpha.unsqueeze(2)
    torch.testing.assert_close(
        out.features, colour[:, None, None] * alpha + background[:, None, None] * (1 - alpha)
    )
    # Expected depth is a convex combination of the contributing Gaussians' camera depths.
    visible = out.alpha > 0
    assert bool((out.depth[~visible] == 0).all())
    cam = scene.world_to_cam[..., None, :3, :3] @ scene.gaussians.means[:, None, :, :, None]
    z = cam[..., 2, 0] + scene.world_to_cam[..., None, 2, 3]  # (B, V, N)
    z = torch.where(out.radii > 0, z, torch.nan)
    for b_, v_ in zip(*torch.nonzero(visible.flatten(2).any(-1), as_tuple=True), strict=True):
        depth = out.depth[b_, v_][visible[b_, v_]]
        assert float(depth.min()) >= float(z[b_, v_].nan_to_num(torch.inf).min()) - 1e-9
        assert float(depth.max()) <= float(z[b_, v_].nan_to_num(-torch.inf).max()) + 1e-9


@pytest.mark.slow
@settings(max_examples=15)
@given(scenes(), st.integers(0, 2**31 - 1))
def test_linear_in_features(scene: Scene, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    b, n = scene.world_to_cam.shape[0], scene.gaussians.num_gaussians
    f1 = torch.randn(b, n, 3, generator=g, dtype=torch.float64)
    f2 = torch.randn(b, n, 3, generator=g, dtype=torch.float64)
    scene = scene.replace(background=None)
    combined = render(scene.replace(features=f1 + 2 * f2)).features
    separate = (
        render(scene.replace(features=f1)).features
        + 2 * render(scene.replace(features=f2)).features
    )
    torch.testing.assert_close(combined, separate, rtol=1e-10, atol=1e-10)


@settings(max_examples=15)
@given(scenes(), st.integers(0, 2**31 - 1))
def test_order_of_the_gaussians_does_not_matter(scene: Scene, seed: int) -> None:
    n = scene.gaussians.num_gaussians
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    features = None if scene.features is None else scene.features[:, perm]
    permuted = scene.replace(gaussians=scene.gaussians.select(perm), features=features)
    out, expected = render(permuted), render(scene)
    torch.testing.assert_close(out.features, expected.features, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(out.alpha, expected.alpha, rtol=1e-10, atol=1e-10)
    if expected.depth is not None:
        torch.testing.assert_close(out.depth, expected.depth, rtol=1e-10, atol=1e-10)
    assert torch.equal(out.radii, expected.radii[..., perm])


@pytest.mark.slow
@settings(max_examples=12)
@given(scenes(max_n=15, culling=False), st.integers(0, 2**31 - 1))
def test_invisible_gaussians_change_nothing_and_get_no_gradient(scene: Scene, seed: int) -> None:
    b = scene.world_to_cam.shape[0]
    n = scene.gaussians.num_gaussians
    gs = scene.gaussians
    shape = scene.image_size
    kw = {"feature_dim": gs.feature_dim, "seed": seed}
    g = torch.Generator().manual_seed(seed)
    transparent = make_scene_gaussians(b, 4, shape, **kw)
    transparent = transparent.replace(opacities=torch.zeros_like(transparent.opacities))
    behind = make_scene_gaussians(b, 3, shape, depth_range=(-3.0, -0.5), **kw)
    beyond = make_scene_gaussians(b, 3, shape, depth_range=(20.0, 30.0), **kw)
    extra = GaussianSet.cat([transparent, behind, beyond])
    features = scene.features
    if features is not None:
        features = torch.cat(
            [features, torch.randn(b, 10, features.shape[-1], generator=g, dtype=torch.float64)],
            dim=1,
        )
    bigger = scene.replace(
        gaussians=GaussianSet.cat([gs, extra]),
        features=features,
        config={**scene.config, "near": 0.01, "far": 15.0},
    )
    out = render(bigger)
    expected = render(scene, near=0.01, far=15.0)
    torch.testing.assert_close(out.features, expected.features, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out.alpha, expected.alpha, rtol=1e-12, atol=1e-12)
    if expected.depth is not None:
        torch.testing.assert_close(out.depth, expected.depth, rtol=1e-12, atol=1e-12)
    assert torch.equal(out.radii[..., :n], expected.radii)
    assert bool((out.radii[..., n + 4 :] == 0).all())

    grads = gradients(bigger, render)
    for name, grad in grads.items():
        assert bool(torch.isfinite(grad).all()), name
        if name != "background_arg":  # every other leaf has a Gaussian axis at dim 1
            assert bool((grad[:, n:] == 0).all()), name


@settings(max_examples=10)
@given(scenes(max_views=3, max_batch=1))
def test_several_cameras_equal_single_camera_renders(scene: Scene) -> None:
    out = render(scene)
    views = scene.world_to_cam.shape[1]
    for v in range(views):
        background = scene.background
        if background is not None and background.ndim == 3:
            background = background[:, v : v + 1]
        single = scene.replace(
            world_to_cam=scene.world_to_cam[:, v : v + 1],
            intrinsics=scene.intrinsics[:, v : v + 1],
            background=background,
        )
        one = render(single)
        torch.testing.assert_close(out.features[:, v : v + 1], one.features, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(out.alpha[:, v : v + 1], one.alpha, rtol=1e-12, atol=1e-12)
        if one.depth is not None:
            torch.testing.assert_close(out.depth[:, v : v + 1], one.depth, rtol=1e-12, atol=1e-12)
        assert torch.equal(out.radii[:, v : v + 1], one.radii)


@pytest.mark.slow
@settings(max_examples=10)
@given(scenes(max_batch=3, max_views=1))
def test_batch_equals_single_renders(scene: Scene) -> None:
    out = render(scene)
    for b in range(scene.world_to_cam.shape[0]):
        background = scene.background
        if background is not None and background.ndim == 3:
            background = background[b : b + 1]
        single = scene.replace(
            gaussians=batch_item(scene.gaussians, b),
            world_to_cam=scene.world_to_cam[b : b + 1],
            intrinsics=scene.intrinsics[b : b + 1],
            features=None if scene.features is None else scene.features[b : b + 1],
            background=background,
        )
        one = render(single)
        torch.testing.assert_close(out.features[b : b + 1], one.features, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(out.alpha[b : b + 1], one.alpha, rtol=1e-12, atol=1e-12)
        if one.depth is not None:
            torch.testing.assert_close(out.depth[b : b + 1], one.depth, rtol=1e-12, atol=1e-12)
        assert torch.equal(out.radii[b : b + 1], one.radii)


@settings(max_examples=12)
@given(scenes(culling=False), st.sampled_from(["expected", "accumulated"]))
def test_scaling_the_whole_scene_scales_only_depth(scene: Scene, depth_mode: str) -> None:
    k = 2.0
    gs = scene.gaussians
    w2c = scene.world_to_cam.clone()
    w2c[..., :3, 3] *= k
    scaled = scene.replace(
        gaussians=gs.replace(means=gs.means * k, scales=gs.scales * k), world_to_cam=w2c
    )
    out = render(scaled, depth_mode=depth_mode)
    expected = render(scene, depth_mode=depth_mode)
    torch.testing.assert_close(out.features, expected.features, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(out.alpha, expected.alpha, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(out.depth, k * expected.depth, rtol=1e-9, atol=1e-10)
    assert torch.equal(out.radii, expected.radii)


# ---------------------------------------------------------------------------------------
# gradients: finiteness at the edges, gradcheck
# ---------------------------------------------------------------------------------------


EXTREME_CASES = {
    "at_the_near_plane": {"means": [0.0, 0.0, 0.01]},
    "just_past_the_near_plane": {"means": [0.002, -0.001, 0.0101]},
    "near_plane_off_axis": {"means": [0.5, 0.3, 0.02]},
    "just_before_the_near_plane": {"means": [0.0, 0.0, 0.0099]},
    "at_the_camera_centre": {"means": [0.0, 0.0, 0.0]},
    "behind_the_camera": {"means": [0.1, 0.2, -1.0]},
    "tiny_scale": {"scales": [1e-6, 1e-6, 1e-6]},
    "huge_scale": {"scales": [1e3, 1e3, 1e3]},
    "huge_scale_near": {"means": [0.0, 0.0, 0.05], "scales": [1e3, 1e3, 1e3]},
    "needle": {"scales": [1e-6, 1e-6, 1e3]},
    "unnormalised_small_quat": {"quats": [1e-3, 2e-3, -1e-3, 5e-4]},
    "unnormalised_large_quat": {"quats": [300.0, -200.0, 100.0, 50.0]},
    "opacity_zero": {"opacities": 0.0},
    "opacity_one": {"opacities": 1.0},
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(EXTREME_CASES))
def test_gradients_are_finite_in_extreme_cases(case: str, dtype: torch.dtype) -> None:
    image_size = (20, 36)
    gs = make_scene_gaussians(1, 6, image_size, seed=3, feature_dim=2)
    special = {
        "means": [0.1, -0.1, 4.0],
        "quats": [0.9, 0.1, -0.3, 0.2],
        "scales": [0.3, 0.1, 0.2],
        "opacities": 0.8,
        **EXTREME_CASES[case],
    }
    fields = {
        name: torch.cat([getattr(gs, name), torch.tensor([[special[name]]], dtype=gs.dtype)], 1)
        for name in ("means", "quats", "scales", "opacities")
    }
    fields["features"] = torch.cat([gs.features, torch.tensor([[[1.0, -1.0]]]).double()], 1)
    w2c, intrinsics = make_cameras(1, 2, image_size, seed=1)
    scene = Scene(GaussianSet(**fields), w2c, intrinsics, image_size, config={"tile_size": 8}).to(
        dtype
    )
    out = render(scene)
    for t in (out.features, out.alpha, out.depth):
        assert bool(torch.isfinite(t).all())
    grads = gradients(scene, render)
    for name, grad in grads.items():
        assert bool(torch.isfinite(grad).all()), name
    z = special["means"][2]
    if z < 0.01:  # culled by view 0; view 1 moves at most 0.3 m, so z <= -0.5 stays culled
        if z <= -0.5:
            assert bool((out.radii[..., -1] == 0).all())
            for name in ("means", "quats", "scales", "opacities", "features"):
                assert bool((grads[name][:, -1] == 0).all()), name
        else:
            assert int(out.radii[0, 0, -1]) == 0
    if dtype == torch.float64:
        expected = gradients(scene, render_reference)
        for name in expected:
            scale = max(1.0, float(expected[name].abs().max()))
            torch.testing.assert_close(
                grads[name], expected[name], rtol=1e-5, atol=1e-6 * scale, msg=name
            )


@pytest.mark.slow
def test_gradcheck_on_a_tiny_scene() -> None:
    dtype = torch.float64
    # Three large Gaussians well inside an 8x8 image: every pixel sees alpha >> alpha_min,
    # opacities stay below max_alpha and T never gets near transmittance_min, so the
    # rendered image is a smooth function of every input.
    means = torch.tensor([[[0.2, -0.1, 2.5], [-0.3, 0.2, 3.0], [0.1, 0.3, 4.0]]], dtype=dtype)
    quats = torch.tensor(
        [[[1.0, 0.2, -0.1, 0.3], [0.8, -0.3, 0.2, 0.1], [1.0, 0.0, 0.4, 0.0]]], dtype=dtype
    )
    scales = torch.tensor([[[3.0, 3.5, 3.2], [3.6, 3.1, 3.3], [4.0, 4.4, 4.2]]], dtype=dtype)
    opacities = torch.tensor([[0.5, 0.6, 0.4]], dtype=dtype)
    features = torch.tensor([[[1.0, 0.5], [-0.5, 2.0], [0.3, -1.0]]], dtype=dtype)
    background = torch.tensor([0.2, -0.3], dtype=dtype)
    w2c = torch.eye(4, dtype=dtype)[None, None]
    intrinsics = torch.tensor([[[[8.0, 0, 4.2], [0, 9.0, 3.9], [0, 0, 1]]]], dtype=dtype)

    def fn(
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        opacities: Tensor,
        features: Tensor,
        background: Tensor,
    ) -> Tensor:
        gs = GaussianSet(means=means, quats=quats, scales=scales, opacities=opacities)
        out = splat(
            gs, w2c, intrinsics, (8, 8), features=features, background=background, tile_size=4
        )
        return torch.cat([out.features.flatten(), out.depth.flatten(), out.alpha.flatten()])

    inputs = tuple(
        t.clone().requires_grad_(True)
        for t in (means, quats, scales, opacities, features, background)
    )
    out = splat(
        GaussianSet(means=means, quats=quats, scales=scales, opacities=opacities),
        w2c,
        intrinsics,
        (8, 8),
        tile_size=4,
    )
    assert float(out.alpha.min()) > 0.5 and bool((out.radii > 0).all())
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


# ---------------------------------------------------------------------------------------
# module, depth modes, radii
# ---------------------------------------------------------------------------------------


def test_module_equals_functional() -> None:
    scene = small_scene()
    config = {"tile_size": 8, "chunk_size": 4, "max_pairs": 256, "depth_mode": "accumulated"}
    config |= {"near": 0.05, "eps2d": 0.2, "alpha_min": 0.01, "radius_sigma": 2.5}
    module = DifferentiableSplatter(**config)
    assert isinstance(module, torch.nn.Module)
    background = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    out = module(
        scene.gaussians,
        scene.world_to_cam,
        scene.intrinsics,
        scene.image_size,
        background=background,
    )
    assert isinstance(out, SplatOutput)
    expected = render(scene.replace(background=background), **config)
    assert_outputs_close(out, expected, rtol=0, atol=0)
    assert_outputs_close(
        out, render_reference(scene.replace(background=background), **config), rtol=1e-5, atol=1e-5
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        out.alpha = out.alpha  # type: ignore[misc]


def test_exported_from_the_package() -> None:
    assert dego.splat is splat
    assert dego.DifferentiableSplatter is DifferentiableSplatter
    assert dego.SplatOutput is SplatOutput


def test_depth_modes() -> None:
    scene = small_scene()
    expected = render(scene, depth_mode="expected")
    accumulated = render(scene, depth_mode="accumulated")
    none = render(scene, depth_mode="none")
    assert none.depth is None
    for out in (accumulated, none):
        torch.testing.assert_close(out.features, expected.features, rtol=0, atol=0)
        torch.testing.assert_close(out.alpha, expected.alpha, rtol=0, atol=0)
    torch.testing.assert_close(accumulated.depth, expected.depth * expected.alpha)
    assert bool((expected.alpha > 0).any())


def test_radii_are_integers_and_zero_when_culled() -> None:
    scene = small_scene(views=1)
    gs = scene.gaussians
    means = gs.means.clone()
    means[:, 0] = torch.tensor([0.0, 0.0, -2.0])  # behind the camera
    means[:, 1] = torch.tensor([0.0, 0.0, 5.0])  # straight ahead
    means[:, 2] = torch.tensor([100.0, 0.0, 5.0])  # far outside the image
    means[:, 3] = torch.tensor([0.0, 0.0, 50.0])  # beyond far
    scene = scene.replace(gaussians=gs.replace(means=means))
    out = render(scene, far=20.0)
    assert not out.radii.dtype.is_floating_point and out.radii.dtype != torch.bool
    assert out.radii.shape == (2, 1, gs.num_gaussians)
    assert bool((out.radii[:, 0, [0, 2, 3]] == 0).all())
    assert bool((out.radii[:, 0, 1] > 0).all())
    assert bool((out.radii >= 0).all())


def test_no_gaussians_gives_the_background() -> None:
    scene = small_scene(n=0)
    background = torch.randn(2, 2, 3, dtype=torch.float64)
    out = render(scene.replace(background=background))
    assert out.features.shape == (2, 2, 3, 20, 36)
    torch.testing.assert_close(out.features, background[..., None, None].expand(2, 2, 3, 20, 36))
    assert bool((out.alpha == 0).all()) and bool((out.depth == 0).all())
    assert out.radii.shape == (2, 2, 0)


def test_outputs_stay_in_the_graph_when_everything_is_culled() -> None:
    # A batch where nothing is visible must not break ``loss.backward()``.
    image_size = (20, 36)
    gs = make_scene_gaussians(1, 3, image_size, feature_dim=2, depth_range=(-3.0, -1.0))
    w2c, intrinsics = make_cameras(1, 1, image_size)
    scene, leaves = with_grad(Scene(gs, w2c, intrinsics, image_size))
    out = render(scene)
    assert bool((out.radii == 0).all())
    assert out.features.requires_grad and out.alpha.requires_grad and out.depth.requires_grad
    weighted_sum(out).backward()
    for name, leaf in leaves.items():
        assert leaf.grad is None or bool((leaf.grad == 0).all()), name


def test_no_features_renders_depth_and_alpha_only() -> None:
    scene = small_scene(channels=None)
    out = render(scene)
    assert out.features.shape == (2, 2, 0, 20, 36)
    expected = render_reference(scene)
    torch.testing.assert_close(out.alpha, expected.alpha, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out.depth, expected.depth, rtol=1e-5, atol=1e-5)


# ---------------------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------------------


def _bad_intrinsics(value: float) -> Any:
    def change(scene: Scene) -> dict[str, Any]:
        k = scene.intrinsics.clone()
        k[0, 1, 0, 0] = value
        return {"intrinsics": k}

    return change


BAD_INPUTS = {
    "batch_mismatch": lambda s: {
        "world_to_cam": s.world_to_cam[:1],
        "intrinsics": s.intrinsics[:1],
    },
    "view_mismatch": lambda s: {"intrinsics": s.intrinsics[:, :1]},
    "extrinsics_3x4": lambda s: {"world_to_cam": s.world_to_cam[..., :3, :]},
    "extrinsics_3x3": lambda s: {"world_to_cam": s.world_to_cam[..., :3, :3]},
    "zero_height": lambda s: {"image_size": (0, 36)},
    "negative_width": lambda s: {"image_size": (20, -4)},
    "nan_intrinsics": _bad_intrinsics(float("nan")),
    "inf_intrinsics": _bad_intrinsics(float("inf")),
    "bad_depth_mode": lambda s: {"config": {"depth_mode": "median"}},
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_raises(case: str) -> None:
    scene = small_scene()
    bad = scene.replace(**BAD_INPUTS[case](scene))
    with pytest.raises((ValueError, TypeError)):
        render(bad)


def test_bad_depth_mode_in_the_module_raises() -> None:
    scene = small_scene()
    with pytest.raises((ValueError, TypeError)):
        module = DifferentiableSplatter(depth_mode="median")
        module(scene.gaussians, scene.world_to_cam, scene.intrinsics, scene.image_size)


# ---------------------------------------------------------------------------------------
# devices
# ---------------------------------------------------------------------------------------


def test_runs_on_device(device: torch.device) -> None:
    scene = small_scene().to(torch.float32)
    scene = scene.replace(
        gaussians=scene.gaussians.to(device),
        world_to_cam=scene.world_to_cam.to(device),
        intrinsics=scene.intrinsics.to(device),
    )
    out = render(scene, tile_size=8)
    for t in (out.features, out.depth, out.alpha, out.radii):
        assert t.device.type == device.type
    assert bool(torch.isfinite(out.features).all()) and bool((out.alpha > 0).any())
    grads = gradients(scene, render, tile_size=8)
    assert all(bool(torch.isfinite(g).all()) for g in grads.values())
    cpu = render(
        scene.replace(
            gaussians=scene.gaussians.to("cpu"),
            world_to_cam=scene.world_to_cam.cpu(),
            intrinsics=scene.intrinsics.cpu(),
        ),
        tile_size=8,
    )
    torch.testing.assert_close(out.features.cpu(), cpu.features, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(out.alpha.cpu(), cpu.alpha, rtol=1e-4, atol=1e-4)
