"""The demo's motion pieces: class gating, frame offsets (free / true motion), the single-frame
reference, segment latents and the new FitConfig options."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dego import DecoupledDeformation, SyntheticScene
from dego.demo import (
    EXTENSION_VARIANTS,
    MOVABLE_CLASSES,
    REFERENCE_VARIANTS,
    VARIANTS,
    DemoClip,
    FitConfig,
    FrameOffsets,
    FrameVelocities,
    GaussianSceneModel,
    agent_under,
    build_deformation,
    deformable,
    fit_scene,
    free_offsets,
    free_velocities,
    gaussians_at,
    true_motion,
)
from dego.demo.model import segment_ids
from dego.gaussians import GaussianSet


@pytest.fixture(scope="module")
def scene() -> SyntheticScene:
    return SyntheticScene(0, num_frames=3, frame_dt=0.2, image_size=(32, 88))


@pytest.fixture(scope="module")
def clip(scene: SyntheticScene) -> DemoClip:
    return DemoClip.from_scene(scene)


def canonical(n: int, seed: int = 0) -> GaussianSet:
    g = torch.Generator().manual_seed(seed)
    quats = torch.zeros(1, n, 4)
    quats[..., 0] = 1
    return GaussianSet(
        means=torch.randn(1, n, 3, generator=g),
        quats=quats,
        scales=torch.full((1, n, 3), 0.2),
        opacities=torch.full((1, n), 0.5),
        features=torch.rand(1, n, 2, generator=g),
    )


# -- FrameOffsets ------------------------------------------------------------------------


def test_frame_offsets_look_up_each_frame() -> None:
    times = torch.tensor([-1.0, 0.0, 2.0])
    offsets = torch.randn(3, 4, 3)
    module = FrameOffsets(times, offsets)
    gaussians = canonical(4)
    out = module(gaussians, torch.zeros(1, 4, 0), torch.tensor([2.0, -1.0]))
    assert out.gaussians.batch_shape == (1, 2)
    torch.testing.assert_close(out.at(0).means, gaussians.means + offsets[2])
    torch.testing.assert_close(out.at(1).means, gaussians.means + offsets[0])
    for name in ("quats", "scales", "opacities", "features"):
        assert torch.equal(getattr(out.at(0), name), getattr(gaussians, name))
    assert torch.equal(out.rigid_mask, torch.zeros(1, 4))
    assert torch.equal(out.deltas.means[0], offsets[[2, 0]])
    assert module.fixed_mask == 0.0 and isinstance(module.offsets, torch.nn.Parameter)
    fixed = FrameOffsets(times, offsets, trainable=False)
    assert not isinstance(fixed.offsets, torch.nn.Parameter) and "offsets" in dict(
        fixed.named_buffers()
    )


def test_frame_offsets_reject_bad_input() -> None:
    times = torch.tensor([-1.0, 0.0])
    with pytest.raises(ValueError, match="offsets: expected shape"):
        FrameOffsets(times, torch.zeros(3, 4, 3))
    with pytest.raises(ValueError, match="offsets: expected shape"):
        FrameOffsets(times, torch.zeros(2, 4, 2))
    module = FrameOffsets(times, torch.zeros(2, 4, 3))
    with pytest.raises(ValueError, match="times: expected"):
        module(canonical(4), torch.zeros(1, 4, 0), torch.tensor([0.5]))
    with pytest.raises(ValueError, match="gaussians: expected batch shape"):
        module(canonical(5), torch.zeros(1, 5, 0), torch.tensor([0.0]))


@pytest.mark.slow
def test_free_offsets_have_no_regulariser_and_learn(clip: DemoClip) -> None:
    module = free_offsets(clip, 6)
    assert module.offsets.shape == (clip.num_frames, 6, 3) and not module.offsets.any()
    model = GaussianSceneModel.from_clip(clip, 6, generator=torch.Generator().manual_seed(0))
    other = 0 if clip.reference != 0 else 1
    gaussians, terms = gaussians_at(model, module, clip, other)
    assert terms is not None and terms["total"].item() == 0.0
    gaussians.means.sum().backward()
    assert module.offsets.grad is not None and module.offsets.grad[other].abs().sum() > 0


def test_free_velocities_move_each_gaussian_by_t_times_v() -> None:
    times = torch.tensor([-2.0, -1.0, 0.0, 1.0])
    velocities = torch.randn(4, 3)
    module = FrameVelocities(times, velocities)
    gaussians = canonical(4)
    out = module(gaussians, torch.zeros(1, 4, 0), torch.tensor([-2.0, 1.0, 0.0]))
    torch.testing.assert_close(out.at(0).means, gaussians.means - 2 * velocities)
    torch.testing.assert_close(out.at(1).means, gaussians.means + velocities)
    torch.testing.assert_close(out.at(2).means, gaussians.means)
    assert list(dict(module.named_parameters())) == ["offsets"]
    assert module.velocities.shape == (4, 3) and module.fixed_mask == 0.0
    # every frame's gradient lands on the one velocity, weighted by its offset
    out.gaussians.means.sum().backward()
    assert module.offsets.grad is not None
    torch.testing.assert_close(module.offsets.grad[0], torch.full((4, 3), -2.0 + 1.0 + 0.0))
    with pytest.raises(ValueError, match="velocities: expected shape"):
        FrameVelocities(times, torch.zeros(4, 2))
    with pytest.raises(ValueError, match="gaussians: expected batch shape"):
        module(canonical(5), torch.zeros(1, 5, 0), torch.tensor([0.0]))


def test_free_velocities_start_still_and_fit_through_the_demo(clip: DemoClip) -> None:
    module = free_velocities(clip, 6)
    assert isinstance(module, FrameVelocities) and not module.velocities.any()
    built = build_deformation("free-velocities", FitConfig(num_gaussians=6), clip)
    assert isinstance(built, FrameVelocities) and built.velocities.shape == (6, 3)
    result = fit_scene(clip, "free-velocities", FitConfig(iterations=3, num_gaussians=40))
    assert isinstance(result.deformation, FrameVelocities)
    assert result.model.deform_classes == MOVABLE_CLASSES  # the same gating as the networks
    assert all(math.isfinite(v) for v in result.history["total"])


def test_the_velocity_variant_fits_a_constant_velocity_network(clip: DemoClip) -> None:
    built = build_deformation("velocity", FitConfig(num_gaussians=6), clip)
    assert isinstance(built, DecoupledDeformation) and built.rigid_motion == "velocity"
    assert built.fixed_mask is None  # the learned mask, as decoupled
    result = fit_scene(clip, "velocity", FitConfig(iterations=3, num_gaussians=40))
    assert result.model.deform_classes == MOVABLE_CLASSES
    assert all(math.isfinite(v) for v in result.history["total"])
    assert "velocity" in EXTENSION_VARIANTS and "velocity" not in VARIANTS


# -- the oracle ---------------------------------------------------------------------------


def test_true_motion_moves_gaussians_with_their_agent(
    scene: SyntheticScene, clip: DemoClip
) -> None:
    moving = [a for a in scene.agents if a.moving]
    parked = [a for a in scene.agents if not a.moving]
    assert moving
    centres = torch.tensor(
        [[*a.position, 0.8] for a in [*moving, *parked]] + [[0.0, 0.0, 30.0]],
        dtype=torch.float32,
    )
    module = true_motion(scene, clip, centres)
    ids = agent_under(centres, clip)
    assert ids[-1] == 0  # high above the grid: no agent
    for k, agent in enumerate([*moving, *parked]):
        if ids[k] != agent.instance_id:
            continue  # the centre's voxel belongs to another solid; nothing to check
        for f, offset in enumerate(scene.offsets):
            distance = agent.speed * offset * scene.frame_dt
            expected = torch.tensor(
                [distance * math.cos(agent.heading), distance * math.sin(agent.heading), 0.0]
            )
            torch.testing.assert_close(module.offsets[f, k], expected, rtol=1e-5, atol=1e-5)
    assert torch.equal(module.offsets[:, -1], torch.zeros(clip.num_frames, 3))
    assert torch.equal(module.offsets[clip.reference], torch.zeros_like(module.offsets[0]))
    assert (ids[: len(moving)] > 0).any()


def test_true_motion_needs_the_synthetic_scene(scene: SyntheticScene, clip: DemoClip) -> None:
    means = torch.zeros(3, 3)
    with pytest.raises(ValueError, match="scene: the true-motion oracle needs the SyntheticScene"):
        true_motion(object(), clip, means)  # type: ignore[arg-type]
    other = SyntheticScene(0, num_frames=5, frame_dt=0.2, image_size=(32, 88))
    with pytest.raises(ValueError, match="scene: expected the SyntheticScene that clip"):
        true_motion(other, clip, means)
    with pytest.raises(ValueError, match="scene: the true-motion oracle needs"):
        build_deformation("true-motion", FitConfig(), clip)
    with pytest.raises(ValueError, match="scene"):
        fit_scene(clip, "true-motion", FitConfig(iterations=1, num_gaussians=50))


# -- variants -----------------------------------------------------------------------------


@pytest.mark.slow
def test_reference_variants_fit_and_single_frame_sees_only_the_reference(
    scene: SyntheticScene, clip: DemoClip, monkeypatch: pytest.MonkeyPatch
) -> None:
    import dego.demo.fit as fit

    seen: list[int] = []
    original = fit._frame_losses

    def spy(model, deformation, clip, index, *args):  # type: ignore[no-untyped-def]
        seen.append(index)
        return original(model, deformation, clip, index, *args)

    monkeypatch.setattr(fit, "_frame_losses", spy)
    config = FitConfig(iterations=7, num_gaussians=120)
    single = fit_scene(clip, "single-frame", config)
    assert set(seen) == {clip.reference} and len(seen) == round(7 / clip.num_frames)
    assert len(single.history["total"]) == len(seen) and single.deformation is None
    seen.clear()
    for variant in REFERENCE_VARIANTS[1:]:
        result = fit_scene(clip, variant, config, scene=scene)
        assert isinstance(result.deformation, FrameOffsets)
        assert all(math.isfinite(v) for v in result.history["total"])
    assert set(seen) == set(range(clip.num_frames))


@pytest.mark.parametrize("deform", ["movable", "all"])
def test_class_gating_leaves_static_classes_in_place(clip: DemoClip, deform: str) -> None:
    config = FitConfig(num_gaussians=200, deform=deform)  # type: ignore[arg-type]
    model = GaussianSceneModel.from_clip(clip, 200, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():  # half the Gaussians movable (car), half static (road)
        model.semantic_logits.zero_()
        model.semantic_logits[:100, 4] = 5
        model.semantic_logits[100:, 11] = 5
    model.deform_classes = MOVABLE_CLASSES if deform == "movable" else None
    offsets = torch.ones(clip.num_frames, 200, 3)
    module = FrameOffsets(clip.times, offsets)
    other = 0 if clip.reference != 0 else 1
    gaussians, _ = gaussians_at(model, module, clip, other)
    moved = (gaussians.means - model.means[None]).norm(dim=-1)[0]
    assert torch.allclose(moved[:100], torch.full((100,), math.sqrt(3)))
    if deform == "movable":
        assert torch.equal(moved[100:], torch.zeros(100))
        assert deformable(model).tolist() == [[True] * 100 + [False] * 100]
    else:
        assert torch.allclose(moved[100:], torch.full((100,), math.sqrt(3)))
        assert deformable(model) is None
    assert config.deform == deform


def test_fit_scene_gates_the_networks_by_default(clip: DemoClip) -> None:
    result = fit_scene(clip, "rigid", FitConfig(iterations=1, num_gaussians=100))
    assert result.model.deform_classes == MOVABLE_CLASSES
    ungated = fit_scene(clip, "rigid", FitConfig(iterations=1, num_gaussians=100, deform="all"))
    assert ungated.model.deform_classes is None
    static = fit_scene(clip, "static", FitConfig(iterations=1, num_gaussians=100))
    assert static.model.deform_classes is None


def test_protection_is_off_by_default_and_still_available() -> None:
    config = FitConfig()
    assert (config.freeze_movable, config.warmup) == (False, 0.0)
    assert FitConfig(freeze_movable=True, warmup=0.5).freeze_movable


def test_regulariser_and_position_scale_reach_the_network(clip: DemoClip) -> None:
    network = build_deformation("decoupled", FitConfig(regulariser="sum", pos_scale=4.0), clip)
    assert network.loss_weights.reduction == "sum" and network.pos_scale == 4.0
    assert build_deformation("rigid", FitConfig(), clip).loss_weights.reduction == "mean"


# -- segments ------------------------------------------------------------------------------


def brute_force_components(points: torch.Tensor, labels: torch.Tensor, radius: float, k: int):
    n = points.shape[0]
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    distances = torch.cdist(points, points)
    for i in range(n):
        order = distances[i].topk(min(k, n - 1) + 1, largest=False)
        for d, j in zip(order.values.tolist(), order.indices.tolist(), strict=True):
            if d < radius and labels[i] == labels[j]:
                parent[find(i)] = find(j)
    roots = [find(i) for i in range(n)]
    smallest = {}
    for i, r in enumerate(roots):
        smallest.setdefault(r, i)
    return torch.tensor([smallest[r] for r in roots])


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 40), st.integers(1, 3), st.floats(0.1, 2.0), st.integers(0, 1000))
def test_segment_ids_are_the_connected_components(
    n: int, classes: int, radius: float, seed: int
) -> None:
    g = torch.Generator().manual_seed(seed)
    points = 3 * torch.rand(n, 3, generator=g)
    labels = torch.randint(0, classes, (n,), generator=g)
    got = segment_ids(points, labels, radius, k=4, chunk=7)
    assert torch.equal(got, brute_force_components(points, labels, radius, 4))


def test_segment_latents_are_shared_within_a_segment(clip: DemoClip) -> None:
    model = GaussianSceneModel.from_clip(
        clip, 300, latent_init="segments", generator=torch.Generator().manual_seed(0)
    )
    plain = GaussianSceneModel.from_clip(clip, 300, generator=torch.Generator().manual_seed(0))
    assert plain.latent.std() < 0.2 < model.latent.std()
    # two Gaussians of one segment differ by the small per-Gaussian noise only
    distances = torch.cdist(model.means, model.means)
    labels = model.semantic_logits.argmax(-1)
    pairs = (distances < 0.2) & (labels[:, None] == labels[None]) & ~torch.eye(300, dtype=bool)
    i, j = pairs.nonzero()[0]
    assert (model.latent[i] - model.latent[j]).abs().max() < 0.6  # noise: std 0.1 each


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("deform", "some"),
        ("regulariser", "weighted"),
        ("pos_scale", 0.0),
        ("latent_init", "zeros"),
        ("lr", {"velocity": 0.1}),
    ],
)
def test_fit_config_rejects_bad_motion_options(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        FitConfig(**{field: value})  # type: ignore[arg-type]


def test_partial_learning_rates_keep_the_defaults() -> None:
    config = FitConfig(lr={"deformation": 0.003})
    assert config.lr["deformation"] == 0.003 and config.lr["offsets"] == 0.05


# -- balanced offset gradients -------------------------------------------------------------


@settings(max_examples=20, deadline=None)
@given(st.integers(1, 12), st.integers(0, 1000))
def test_balanced_gradients_equalise_what_reaches_the_deformation(n: int, seed: int) -> None:
    from dego.demo import balance_deformation_gradients

    g = torch.Generator().manual_seed(seed)
    f64 = {"dtype": torch.float64}
    canonical_means = torch.randn(1, n, 3, generator=g, **f64).requires_grad_(True)
    offsets = torch.randn(1, n, 3, generator=g, **f64).requires_grad_(True)
    quats = torch.zeros(1, n, 4, **f64)
    quats[..., 0] = 1

    def gaussians(means: torch.Tensor) -> GaussianSet:
        return GaussianSet(
            means=means,
            quats=quats,
            scales=torch.ones(1, n, 3, **f64),
            opacities=torch.full((1, n), 0.5, **f64),
        )

    keep = torch.rand(1, n, generator=g) < 0.7
    spread = 10 ** (4 * torch.rand(1, n, 1, generator=g, **f64) - 2)  # 0.01 .. 100
    weights = torch.randn(1, n, 3, generator=g, **f64) * spread
    deformed = gaussians(canonical_means + offsets)
    out = balance_deformation_gradients(deformed, gaussians(canonical_means), keep)
    assert torch.equal(out.means, deformed.means)  # values unchanged
    (out.means * weights).sum().backward()
    # the canonical parameters get exactly the raw gradient
    torch.testing.assert_close(canonical_means.grad, weights, rtol=1e-12, atol=1e-12)
    norms, raw = offsets.grad.norm(dim=-1)[0], weights.norm(dim=-1)[0]
    k = keep[0]
    if k.any():  # every kept Gaussian: its direction, at the mean kept norm
        torch.testing.assert_close(norms[k], raw[k].mean().expand(int(k.sum())))
        cos = torch.nn.functional.cosine_similarity(offsets.grad[0, k], weights[0, k], dim=-1)
        torch.testing.assert_close(cos, torch.ones_like(cos))
    torch.testing.assert_close(offsets.grad[0, ~k], weights[0, ~k])  # others: raw


def test_balanced_gradients_change_no_value_of_a_fit(clip: DemoClip) -> None:
    model = GaussianSceneModel.from_clip(clip, 100, generator=torch.Generator().manual_seed(0))
    network = build_deformation("rigid", FitConfig(), clip)
    other = 0 if clip.reference != 0 else 1
    raw, _ = gaussians_at(model, network, clip, other)
    balanced, _ = gaussians_at(model, network, clip, other, offset_gradients="balanced")
    assert torch.equal(raw.means, balanced.means)
    with pytest.raises(ValueError, match="offset_gradients"):
        FitConfig(offset_gradients="clipped")  # type: ignore[arg-type]
