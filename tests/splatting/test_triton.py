"""backend="triton": the Triton kernels equal the torch path (forward to 1e-5 absolute,
gradients to 1e-4 of the largest), on CPU through Triton's interpreter (tests/conftest.py
sets TRITON_INTERPRET=1 where no GPU is present) and on CUDA when one is.

Scenes are small on purpose: the interpreter runs each program in Python."""

from __future__ import annotations

import warnings
from typing import Any

import pytest
import torch
from hypothesis import given, settings
from torch import Tensor

import dego
from dego.compat import gsplat as compat_gsplat
from dego.splatting import SplatConfig, triton_backend
from tests.helpers import triton
from tests.helpers.splatting import (
    Scene,
    gradients,
    make_cameras,
    make_scene_gaussians,
    render,
    scenes,
    small_scene,
    weighted_sum,
    with_grad,
)

pytestmark = pytest.mark.skipif(not triton.INSTALLED, reason=triton.NOT_INSTALLED)

DEVICES = [pytest.param(device, marks=triton.on(device)) for device in ("cpu", "cuda")]


def _relative(a: Tensor, b: Tensor) -> float:
    if a.numel() == 0:
        return 0.0
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-12))


SCREEN = ("means2d", "conics", "opacities", "depths")


def _screen_gradients(scene: Scene, **options: Any) -> dict[str, Tensor]:
    """The gradients the compositing kernels produce: of the projected means, conics,
    opacities and depths, and of the features."""
    scene, leaves = with_grad(scene)
    out = render(scene, **options)
    screen = {name: getattr(out.projection, name) for name in SCREEN}
    for tensor in screen.values():
        tensor.retain_grad()
    loss = weighted_sum(out)
    if not loss.requires_grad:
        return {}
    loss.backward()
    features = {k: v.grad for k, v in leaves.items() if k.startswith("features")}
    return {**{k: v.grad for k, v in screen.items()}, **features}


def assert_matches_torch(scene: Scene, *, leaves: bool = True, **options: Any) -> None:
    """Forward within 1e-5 absolute (depth: 1e-5 of its largest value, times alpha when
    expected, as alpha near 0 magnifies it) and radii equal; the gradients of what the
    kernels differentiate (projected means, conics, opacities, depths; features) and of
    the leaves within 1e-4 of the largest, or at worst twice as far from float64 as the
    float32 torch path is (float32's own noise can exceed 1e-4: the conics' sums over many
    pixels cancel, the projection's backward magnifies). Float64 is, for the kernels'
    gradients, the torch path compositing the float32 projection in float64, and for the
    leaves' the whole torch path in float64."""
    ours = render(scene, backend="triton", **options)
    theirs = render(scene, backend="torch", **options)
    torch.testing.assert_close(ours.features, theirs.features, rtol=0, atol=1e-5)
    torch.testing.assert_close(ours.alpha, theirs.alpha, rtol=0, atol=1e-5)
    assert torch.equal(ours.radii, theirs.radii)
    if theirs.depth is not None:
        assert ours.depth is not None
        scale = float(theirs.depth.abs().max().clamp_min(1.0))
        torch.testing.assert_close(
            ours.depth * ours.alpha, theirs.depth * theirs.alpha, rtol=0, atol=1e-5 * scale
        )
    screen_ours = _screen_gradients(scene, backend="triton", **options)
    screen_theirs = _screen_gradients(scene, backend="torch", **options)
    assert screen_ours.keys() == screen_theirs.keys()
    for name, grad in screen_theirs.items():
        if grad is None:
            assert screen_ours[name] is None, name
    screen = {k: v for k, v in screen_theirs.items() if v is not None}
    _assert_as_exact(
        screen_ours,
        screen,
        lambda: _screen_gradients(scene.to(torch.float64), backend="torch", **options),
        lambda: [_screen_gradients(s, backend="torch", **options) for s in _nudged(scene)],
    )
    if not leaves:
        return
    grads_ours = gradients(scene, render, backend="triton", **options)
    grads_theirs = gradients(scene, render, backend="torch", **options)
    _assert_as_exact(
        grads_ours,
        grads_theirs,
        lambda: gradients(scene.to(torch.float64), render, backend="torch", **options),
        lambda: [gradients(s, render, backend="torch", **options) for s in _nudged(scene)],
    )


def _assert_as_exact(
    ours: dict[str, Tensor], theirs: dict[str, Tensor], float64: Any, nudged: Any
) -> None:
    """Each gradient within 1e-4 of the largest of the torch path's, or, where float32
    itself is not that exact, no further from the float64 torch path than twice float32's
    own error: the float32 torch path's distance from float64, at the scene and at the
    scene's inputs moved by one rounding (``nudged``). One float32 evaluation alone can
    land lucky: where a gradient's terms cancel over many pixels (an expected depth at
    faint pixels, divided by ``1 - T`` of a float32 ``T``), a different order of the same
    sums, or inputs one rounding away, move it by several times that."""
    oracle, others = None, None
    for name, grad in theirs.items():
        if _relative(ours[name], grad) <= 1e-4:
            continue
        if oracle is None:
            oracle, others = float64(), nudged()
        exact = oracle[name].to(grad)
        own = max(_relative(g[name], exact) for g in (theirs, *others))
        assert _relative(ours[name], exact) <= 2 * own, name


def _nudged(scene: Scene, draws: int = 2) -> list[Scene]:
    """``scene`` with every float32 input of the Gaussians moved by one rounding (a relative
    2**-23, of random sign per element), ``draws`` times."""
    g = torch.Generator().manual_seed(0)

    def nudge(t: Tensor | None) -> Tensor | None:
        if t is None or not t.is_floating_point():
            return t
        sign = torch.randint(0, 2, t.shape, generator=g).to(t) * 2 - 1
        return t * (1 + sign * 2.0**-23)

    gs = scene.gaussians
    return [
        scene.replace(
            gaussians=gs.replace(**{f: nudge(getattr(gs, f)) for f in gs.FIELDS}),
            features=nudge(scene.features),
        )
        for _ in range(draws)
    ]


def _scene(
    device: str, *, batch: int = 2, n: int = 16, channels: int = 3, size=(20, 36), **kw: Any
) -> Scene:
    gs = make_scene_gaussians(
        batch, n, size, seed=3, feature_dim=channels or None, dtype=torch.float32, **kw
    )
    w2c, k = make_cameras(batch, 2, size, seed=3, dtype=torch.float32)
    return Scene(gs, w2c, k, size).to(device)


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(
    "options",
    [
        {},
        {"depth_mode": "accumulated"},
        {"depth_mode": "none"},
        {"rasterize_mode": "antialiased"},
        {"radius_rule": "gsplat>=1.5"},
        {"max_alpha": 0.99, "radius_clip": 0.5},
        {"max_alpha": 1.0, "transmittance_min": 1e-2},
        {"tile_size": 8},
        {"tile_size": 5},
    ],
    ids=lambda o: ",".join(f"{k}={v}" for k, v in o.items()) or "defaults",
)
def test_render_modes_and_rules_match_the_torch_path(device: str, options: dict) -> None:
    # (20, 36): partial tiles at 16, 8 and 5 px; culled and near-plane Gaussians included
    scene = _scene(device, culled=True, near_plane=True)
    assert_matches_torch(scene, **options)


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("channels", [1, 17, 40, 128])
def test_channel_counts_match_the_torch_path(device: str, channels: int) -> None:
    # 17 and 40 cross the kernel's 32-channel blocks; 128 + depth is 5 blocks
    assert_matches_torch(_scene(device, batch=1, n=10, channels=channels))


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
def test_per_camera_features_and_backgrounds_match(device: str) -> None:
    scene = _scene(device, channels=0)
    g = torch.Generator().manual_seed(0)
    features = torch.randn(2, 2, 16, 4, generator=g).to(device)
    background = torch.randn(2, 2, 4, generator=g).to(device)
    assert_matches_torch(scene.replace(features=features, background=background))
    assert_matches_torch(scene.replace(features=features[:, 0], background=background[0, 0]))


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
def test_early_termination_empty_tiles_and_a_gaussian_over_every_tile(device: str) -> None:
    size = (24, 40)
    w2c, k = make_cameras(1, 1, size, seed=1, dtype=torch.float32)
    g = torch.Generator().manual_seed(1)
    # 20 opaque Gaussians stacked on one pixel column (T falls below 1e-4 there), small ones
    # in one corner (other tiles empty) and one wide Gaussian that reaches every tile
    stacked = torch.cat([torch.full((20, 2), 0.0), torch.linspace(2, 6, 20)[:, None]], 1)
    corner = torch.tensor([[-1.0, -0.6, 3.0], [-1.1, -0.7, 3.5]])
    wide = torch.tensor([[0.0, 0.0, 8.0]])
    means = torch.cat([stacked, corner, wide])[None]
    n = means.shape[1]
    # anisotropic: an isotropic Gaussian's quaternion gradient is zero up to rounding
    sizes = torch.cat([torch.full((20, 1), 0.3), torch.full((2, 1), 0.02), torch.full((1, 1), 6.0)])
    scales = sizes * (0.5 + torch.rand(n, 3, generator=g))
    opacities = torch.cat([torch.full((20,), 0.99), torch.full((2,), 0.8), torch.full((1,), 0.3)])
    gs = dego.GaussianSet(
        means=means,
        quats=torch.randn(1, n, 4, generator=g),
        scales=scales[None],
        opacities=opacities[None],
        features=torch.rand(1, n, 3, generator=g),
    )
    scene = Scene(gs, w2c, k, size).to(device)
    out = render(scene, backend="triton")
    assert float(out.alpha.max()) > 1 - 1.1e-4  # some pixels stopped
    assert_matches_torch(scene)
    assert_matches_torch(scene.replace(gaussians=gs.select(slice(20, 22)).to(device)))


def _deep_stack(device: str, n: int = 70, seed: int = 5) -> Scene:
    """``n`` Gaussians stacked over the middle of a (24, 24) image, opacities 0.3-0.7, so
    tile 0's pixels stop (T <= 1e-4) anywhere from list position ~20 to never, and the
    tiles' lists are no multiple of 16 or 32."""
    size = (24, 24)
    w2c, k = make_cameras(1, 1, size, seed=seed, dtype=torch.float32)
    g = torch.Generator().manual_seed(seed)
    depth = torch.linspace(2.0, 6.0, n)[:, None]
    lateral = 0.3 * torch.randn(n, 2, generator=g) * depth / 4
    means = torch.cat([lateral, depth], 1)
    scales = 0.5 * depth * (0.5 + torch.rand(n, 3, generator=g)) / 4
    gs = dego.GaussianSet(
        means=means[None],
        quats=torch.randn(1, n, 4, generator=g),
        scales=scales[None],
        opacities=(0.3 + 0.4 * torch.rand(n, generator=g))[None],
        features=torch.rand(1, n, 5, generator=g),
    )
    return Scene(gs, w2c, k, size).to(device)


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(
    ("bucket", "pixels", "tile_size"),
    [(16, 16, 16), (32, 32, 16), (32, 64, 16), (32, 256, 16), (16, 16, 5), (64, 32, 8)],
    ids=lambda v: str(v),
)
def test_buckets_straddle_early_termination_and_partial_lists(
    device: str, bucket: int, pixels: int, tile_size: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every bucket size against the torch path where pixels stop inside buckets, a bucket
    starts after some of its tile's pixels stopped and before others do, lists end
    partway through a bucket, and (5 px tiles) a block of pixels is partly outside the
    tile."""
    from dego.splatting import triton_configs, triton_kernels

    if device == "cpu":
        config = triton_configs.LaunchConfig(bucket=bucket, pixels=pixels)
        monkeypatch.setitem(triton_configs.TABLE, "cpu", config)
    seen: list[tuple[Tensor, Tensor]] = []
    forward = triton_kernels.forward

    def watched(*args: Any) -> Any:
        result = forward(*args)
        seen.append((result[2].flatten(1), args[4].counts))
        return result

    monkeypatch.setattr(triton_kernels, "forward", watched)
    scene = _deep_stack(device)
    assert_matches_torch(scene, tile_size=tile_size)
    stop, counts = max(seen, key=lambda s: int(s[1].sum()))  # not the probe's
    size = triton_configs.config_for(torch.device(device)).bucket
    # inside a bucket, and tiles whose pixels stop in different buckets
    assert bool((stop % size != 0).any())
    assert bool(((stop // size).amax(1) > (stop // size).amin(1)).any())
    assert bool((counts % size != 0).any())
    assert bool((stop < counts[:, None]).any())  # early termination happened


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
def test_no_gaussians_and_batches(device: str) -> None:
    empty = _scene(device, batch=2, n=0)
    out = render(empty, backend="triton")
    assert torch.equal(out.alpha, torch.zeros_like(out.alpha))
    assert_matches_torch(empty)
    assert_matches_torch(_scene(device, batch=3, n=8))
    # nothing to composite but alpha: no features and no depth (D = 0)
    assert_matches_torch(_scene(device, batch=1, n=8, channels=0), depth_mode="none")


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
@settings(max_examples=10, deadline=None)
@given(scene=scenes(max_n=10, max_batch=1, dtype=torch.float32))
def test_random_scenes_match_the_torch_path(device: str, scene: Scene) -> None:
    # the interpreter runs every tile in Python: small scenes, and the kernels' own
    # gradients (the leaves' are the projection's, checked on the fixed scenes above)
    assert_matches_torch(scene.to(device), leaves=False)


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
def test_absgrad_and_means2d_grad_match(device: str) -> None:
    results = []
    for backend in ("triton", "torch"):
        scene, _ = with_grad(_scene(device))
        out = render(scene, backend=backend, absgrad=True)
        out.projection.means2d.retain_grad()
        (out.features.square().sum() + out.alpha.sum()).backward()
        results.append((out.projection.means2d.grad, out.projection.means2d.absgrad))
    for ours, theirs in zip(*results, strict=True):
        assert _relative(ours, theirs) <= 1e-4


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("packed", [True, False])
def test_the_gsplat_adapter_on_triton(device: str, packed: bool) -> None:
    scene = _scene(device, batch=1)
    gs = scene.gaussians
    leaves = [t[0].detach().clone() for t in (gs.means, gs.quats, gs.scales, gs.opacities)]
    leaves.append(gs.features[0].detach().clone())
    results = []
    for backend in ("triton", "torch"):
        args = [t.clone().requires_grad_(True) for t in leaves]
        colors, alphas, meta = compat_gsplat.rasterization(
            *args,
            scene.world_to_cam[0],
            scene.intrinsics[0],
            36,
            20,
            render_mode="RGB+ED",
            packed=packed,
            absgrad=True,
            backend=backend,
        )
        meta["means2d"].retain_grad()
        (colors[..., :3].square().sum() + alphas.sum()).backward()
        results.append((colors, alphas, meta["means2d"].grad, meta["means2d"].absgrad, args))
    ours, theirs = results
    torch.testing.assert_close(ours[0][..., :3], theirs[0][..., :3], rtol=0, atol=1e-5)
    torch.testing.assert_close(ours[1], theirs[1], rtol=0, atol=1e-5)
    for a, b in [(ours[2], theirs[2]), (ours[3], theirs[3])]:
        assert _relative(a, b) <= 1e-4
    for a, b in zip(ours[4], theirs[4], strict=True):
        assert _relative(a.grad, b.grad) <= 1e-4


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
def test_bf16_autocast_computes_in_float32(device: str) -> None:
    scene = _scene(device)
    features = scene.gaussians.features
    kind = "cuda" if device == "cuda" else "cpu"
    with torch.autocast(kind, dtype=torch.bfloat16):
        half = features.to(torch.bfloat16)
        ours = render(scene.replace(features=half), backend="triton")
        theirs = render(scene.replace(features=half), backend="torch")
    assert ours.features.dtype == theirs.features.dtype
    torch.testing.assert_close(ours.features, theirs.features, rtol=0, atol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
def test_the_module_and_the_pipeline_take_the_backend(device: str) -> None:
    from dego.splatting import pipeline

    scene = _scene(device, batch=1, n=8)
    args = (scene.gaussians, scene.world_to_cam, scene.intrinsics, scene.image_size)
    expected = render(scene, backend="triton")
    module = dego.DifferentiableSplatter(backend="triton")(*args)
    config = SplatConfig(backend="triton")
    last = pipeline.render(*args, None, None, config, layout="channels_last")
    assert torch.equal(module.features, expected.features)
    image = torch.cat([expected.features, expected.depth.unsqueeze(2)], 2).permute(0, 1, 3, 4, 2)
    torch.testing.assert_close(last.image, image, rtol=0, atol=1e-6)


def test_float64_renders_with_the_torch_path() -> None:
    scene = small_scene().to(torch.float64)
    ours, theirs = render(scene, backend="triton"), render(scene)
    assert torch.equal(ours.features, theirs.features)


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
def test_compiled_step_has_no_graph_break_and_equals_eager(device: str) -> None:
    scene = _scene(device, batch=1)

    def step(means: Tensor, features: Tensor) -> Tensor:
        gs = scene.gaussians.replace(means=means, features=features)
        out = dego.splat(gs, scene.world_to_cam, scene.intrinsics, (20, 36), backend="triton")
        return out.features.square().sum() + out.depth.sum() + out.alpha.sum()

    torch._dynamo.reset()
    try:
        leaves = [scene.gaussians.means, scene.gaussians.features]
        step(*leaves)  # the eager first call probes the kernels
        explanation = torch._dynamo.explain(step)(*leaves)
        assert explanation.graph_break_count == 0, explanation.break_reasons
        results = []
        for fn in (step, torch.compile(step, backend="aot_eager")):
            args = [t.detach().clone().requires_grad_(True) for t in leaves]
            loss = fn(*args)
            loss.backward()
            results.append((loss.detach(), *(a.grad for a in args)))
        for ours, theirs in zip(*results, strict=True):
            assert _relative(ours, theirs) <= 1e-5
    finally:
        torch._dynamo.reset()


# -- selection and errors --------------------------------------------------------------


def test_backend_triton_without_triton_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(triton_backend, "installed", lambda: False)
    scene = small_scene()
    with pytest.raises(ImportError, match=r"pip install -e \"\.\[triton\]\""):
        render(scene.to(torch.float32), backend="triton")
    auto = render(scene.to(torch.float32), backend="auto")
    assert torch.equal(auto.features, render(scene.to(torch.float32)).features)


def test_backend_triton_needs_torch_custom_ops(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(triton_backend, "CUSTOM_OPS", False)  # torch < 2.4
    scene = small_scene().to(torch.float32)
    with pytest.raises(ImportError, match=r"backend: 'triton' needs torch >= 2.4"):
        render(scene, backend="triton")
    assert torch.equal(render(scene, backend="auto").features, render(scene).features)


def test_backend_triton_on_cpu_without_the_interpreter_says_cuda(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(triton_backend, "interpreting", lambda: False)
    with pytest.raises(ValueError, match=r"backend: 'triton' needs CUDA tensors, got cpu"):
        render(small_scene().to(torch.float32), backend="triton")


def test_auto_on_cpu_keeps_the_torch_path_even_when_interpreting() -> None:
    scene = small_scene().to(torch.float32)
    assert torch.equal(render(scene, backend="auto").features, render(scene).features)


def test_a_kernel_failure_warns_once_under_auto_and_raises_under_triton(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from dego.splatting import triton_kernels

    def broken(*args: Any, **kwargs: Any) -> Any:
        raise RuntimeError("PassManager::run failed\nmore lines")

    monkeypatch.setattr(triton_kernels, "forward", broken)
    monkeypatch.setattr(triton_backend, "_PROBED", {})
    # let "auto" consider the CPU, as it does a GPU
    monkeypatch.setattr(triton_backend, "_runs_on", lambda device, strict: True)
    scene = small_scene().to(torch.float32)
    with pytest.warns(RuntimeWarning, match=r"Triton kernels failed on cpu .*PassManager"):
        auto = render(scene, backend="auto")
    assert torch.equal(auto.features, render(scene).features)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        render(scene, backend="auto")  # warned once
    with pytest.raises(RuntimeError, match=r"backend: 'triton' cannot run on cpu: .*PassManager"):
        render(scene, backend="triton")


@pytest.mark.slow
@pytest.mark.parametrize("mode", [torch.no_grad, torch.inference_mode])
def test_the_first_call_may_come_without_gradients(
    mode: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The one-time probe runs forward and backward: a first call under ``no_grad`` or
    ``inference_mode`` (an evaluation loop) must not mistake that for a broken GPU."""
    monkeypatch.setattr(triton_backend, "_PROBED", {})
    scene = small_scene().to(torch.float32)
    with mode():
        out = render(scene, backend="triton")
    assert triton_backend._PROBED == {"cpu": None}
    torch.testing.assert_close(out.features, render(scene).features, rtol=0, atol=1e-5)


def test_bad_backend_names_the_choices() -> None:
    with pytest.raises(
        ValueError, match=r"backend: expected 'torch', 'auto', 'gsplat' or 'triton'"
    ):
        SplatConfig(backend="cuda")  # type: ignore[arg-type]
