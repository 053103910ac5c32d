"""``dego.compat.dego``: the official temporal render layout and post-processing."""

from __future__ import annotations

import warnings

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dego import GaussianSet, OccupancyMetrics, splat
from dego.classes import FREE_LABEL
from dego.compat.dego import occupancy_to_labels, render_temporal
from dego.compat.gsplat import rasterization
from tests.helpers.splatting import make_cameras, make_scene_gaussians

SIZE = (18, 26)  # (H, W)
B, T, V, N, C = 2, 3, 2, 40, 5


def temporal_inputs(seed: int = 0) -> tuple[GaussianSet, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gaussians ``(B, T)``, cameras ``(B, T, V, ...)`` and per-step features ``(B, T, N, C)``."""
    gs = make_scene_gaussians(B * T, N, SIZE, seed=seed, spread=1.2)
    w2c, k = make_cameras(B * T, V, SIZE, seed=seed)
    g = torch.Generator().manual_seed(seed)
    features = torch.randn(B, T, N, C, generator=g, dtype=torch.float64)
    return gs.reshape_batch(B, T), w2c.view(B, T, V, 4, 4), k.view(B, T, V, 3, 3), features


def per_step_reference(
    gs: GaussianSet, w2c: torch.Tensor, k: torch.Tensor, features: torch.Tensor | None, mode: str
) -> torch.Tensor:
    """The official loop: one gsplat-1.4 call per batch item and time step, time steps'
    cameras concatenated."""
    rows = []
    for b in range(B):
        steps = []
        for t in range(T):
            colors = features[b, t] if features is not None else torch.zeros(N, 1, dtype=w2c.dtype)
            image, _, _ = rasterization(
                gs.means[b, t],
                gs.quats[b, t],
                gs.scales[b, t],
                gs.opacities[b, t],
                colors,
                w2c[b, t],
                k[b, t],
                SIZE[1],
                SIZE[0],
                render_mode=mode,
                gsplat_version="1.4.0",
            )
            steps.append(image)
        rows.append(torch.cat(steps, 0))
    return torch.stack(rows)


@pytest.mark.parametrize("mode", ["RGB", "D", "ED", "RGB+D", "RGB+ED"])
def test_render_temporal_equals_the_per_step_loop(mode: str) -> None:
    gs, w2c, k, features = temporal_inputs()
    ours = render_temporal(gs, w2c, k, SIZE, features=features, mode=mode)
    expected = per_step_reference(gs, w2c, k, features if "RGB" in mode else None, mode)
    assert ours.shape == expected.shape
    channels = (C if "RGB" in mode else 0) + (1 if "D" in mode else 0)
    assert ours.shape == (B, T * V, *SIZE, channels)
    torch.testing.assert_close(ours, expected, rtol=1e-10, atol=1e-10)


def test_render_temporal_matches_splat_with_accumulated_depth() -> None:
    gs, w2c, k, features = temporal_inputs(seed=1)
    ours = render_temporal(gs, w2c, k, SIZE, features=features)  # "RGB+D"
    t = 1
    out = splat(
        gs.map(lambda _, v: v[:, t]),
        w2c[:, t],
        k[:, t],
        SIZE,
        features=features[:, t],
        depth_mode="accumulated",
        radius_rule="gsplat<=1.4",
    )
    block = ours[:, t * V : (t + 1) * V]
    torch.testing.assert_close(block[..., :C], out.features.permute(0, 1, 3, 4, 2))
    assert out.depth is not None
    torch.testing.assert_close(block[..., C], out.depth)


def test_shared_features_equal_features_repeated_over_time() -> None:
    gs, w2c, k, features = temporal_inputs(seed=2)
    shared = features[:, 0]
    ours = render_temporal(gs, w2c, k, SIZE, features=shared)
    repeated = render_temporal(gs, w2c, k, SIZE, features=shared[:, None].expand(B, T, N, C))
    torch.testing.assert_close(ours, repeated, rtol=0, atol=0)
    own = render_temporal(gs.replace(features=shared[:, None].expand(B, T, N, C)), w2c, k, SIZE)
    torch.testing.assert_close(own, ours, rtol=0, atol=0)


def test_render_temporal_gradients_reach_every_time_step() -> None:
    gs, w2c, k, features = temporal_inputs(seed=3)
    means = gs.means.clone().requires_grad_(True)
    image = render_temporal(gs.replace(means=means), w2c, k, SIZE, features=features)
    image.sum().backward()
    assert means.grad is not None
    per_step = means.grad.abs().sum(dim=(0, 2, 3))
    assert bool((per_step > 0).all()), per_step


def test_render_temporal_bad_inputs() -> None:
    gs, w2c, k, features = temporal_inputs()
    with pytest.raises(ValueError, match=r"gaussians: expected batch shape \(B, T\)"):
        render_temporal(gs.reshape_batch(B * T), w2c, k, SIZE, features=features)
    # shape mismatches are caught by the annotations (TypeError) or the checks (ValueError)
    with pytest.raises((TypeError, ValueError), match="intrinsics"):
        render_temporal(gs, w2c, k[:, :2], SIZE, features=features)
    with pytest.raises((TypeError, ValueError), match="features"):
        render_temporal(gs, w2c, k, SIZE, features=features[:, :2])
    with pytest.raises(ValueError, match="features: expected"):
        render_temporal(gs, w2c, k, SIZE, features=features[:1, 0].expand(B, N, C)[:, :-1])
    with pytest.raises(ValueError, match="features: mode 'RGB\\+D'"):
        render_temporal(gs, w2c, k, SIZE)
    with pytest.raises((TypeError, ValueError), match="mode"):
        render_temporal(gs, w2c, k, SIZE, features=features, mode="RGBD")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="world_to_cam"):
        render_temporal(gs, w2c.flatten(1, 2), k, SIZE, features=features)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="gsplat_version"):
        render_temporal(gs, w2c, k, SIZE, features=features, gsplat_version="2.0")


def test_render_temporal_depth_only_needs_no_features() -> None:
    gs, w2c, k, _ = temporal_inputs()
    depth = render_temporal(gs, w2c, k, SIZE, mode="D")
    assert depth.shape == (B, T * V, *SIZE, 1)
    assert bool((depth >= 0).all())


# -- occupancy_to_labels ------------------------------------------------------------------


def test_free_space_overlay_threshold_and_roof() -> None:
    density = torch.tensor([0.0, 5e-4, 0.04999, 0.05, 0.3, 1.0]).view(1, 6, 1, 1)
    density = density.expand(1, 6, 1, 13).contiguous()
    semantics = torch.zeros(1, 6, 1, 13, 16)
    semantics[..., 3] = 1.0  # class 4 (car) everywhere
    labels = occupancy_to_labels(density, semantics)
    assert labels.dtype == torch.int64 and labels.shape == density.shape
    below = labels[0, :3]
    assert bool((below == FREE_LABEL).all())  # under the 0.05 threshold: free
    kept = labels[0, 3:, 0]
    assert bool((kept[:, :11] == 4).all())  # at or above the threshold: the class
    assert bool((kept[:, 11:] == FREE_LABEL).all())  # the roof: z index >= 11 is free


def test_min_density_and_knobs() -> None:
    density = torch.full((2, 2, 12), 2e-3)
    semantics = torch.zeros(2, 2, 12, 16)
    # with a threshold below the floor the floor decides: 2e-3 survives a 1e-3 floor ...
    labels = occupancy_to_labels(density, semantics, threshold=1e-3, max_z_index=None)
    assert bool((labels == 1).all())
    # ... and not a 3e-3 one
    labels = occupancy_to_labels(density, semantics, threshold=1e-3, min_density=3e-3)
    assert bool((labels == FREE_LABEL).all())
    # the official roof at z index 11; without it every z keeps its class
    full = occupancy_to_labels(torch.ones(2, 2, 16), torch.zeros(2, 2, 16, 16))
    assert bool((full[..., :11] == 1).all()) and bool((full[..., 11:] == FREE_LABEL).all())
    none = occupancy_to_labels(
        torch.ones(2, 2, 16), torch.zeros(2, 2, 16, 16), max_z_index=None, label_offset=1
    )
    assert bool((none == 1).all())


@pytest.mark.slow
@settings(max_examples=40, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.integers(1, 2),
    st.floats(0.0, 1.0),
)
def test_labels_agree_with_the_written_out_rule(seed: int, batch: int, threshold: float) -> None:
    g = torch.Generator().manual_seed(seed)
    density = torch.rand(batch, 3, 4, 16, generator=g) ** 3
    semantics = torch.randn(batch, 3, 4, 16, 16, generator=g)
    labels = occupancy_to_labels(density, semantics, threshold=threshold)
    d = torch.where(density < 1e-3, torch.zeros_like(density), density)
    expected = semantics.argmax(-1) + 1
    free = (d < threshold) | (torch.arange(16) >= 11)
    expected[free] = FREE_LABEL
    assert torch.equal(labels, expected)
    # unbatched grids give the same labels
    assert torch.equal(
        occupancy_to_labels(density[0], semantics[0], threshold=threshold), labels[0]
    )


def test_occupancy_to_labels_bad_inputs() -> None:
    density = torch.rand(2, 3, 16)
    with pytest.raises(TypeError, match="semantics"):
        occupancy_to_labels(density, torch.rand(2, 3, 15, 16))
    with pytest.raises(ValueError, match="include free_label=17"):
        occupancy_to_labels(density, torch.rand(2, 3, 16, 17))
    with pytest.raises(ValueError, match="C = 0"):
        occupancy_to_labels(density, torch.rand(2, 3, 16, 0))
    with pytest.raises(ValueError, match="threshold"):
        occupancy_to_labels(density, torch.rand(2, 3, 16, 16), threshold=float("nan"))
    with pytest.raises(ValueError, match="max_z_index"):
        occupancy_to_labels(density, torch.rand(2, 3, 16, 16), max_z_index=-1)
    with pytest.raises(TypeError, match="density"):
        occupancy_to_labels(torch.ones(2, 3, 16, dtype=torch.long), torch.rand(2, 3, 16, 16))  # type: ignore[arg-type]


def test_metrics_warn_when_no_voxel_is_predicted_free() -> None:
    g = torch.Generator().manual_seed(0)
    gt = torch.randint(0, 18, (4, 4, 16), generator=g)
    gt[..., 8:] = FREE_LABEL
    density = torch.rand(4, 4, 16, generator=g)
    semantics = torch.randn(4, 4, 16, 16, generator=g)
    forgotten = semantics.argmax(-1) + 1  # no free-space overlay: every voxel has a class
    metrics = OccupancyMetrics("weak")
    metrics.update(forgotten, gt, None)
    with pytest.warns(UserWarning, match="occupancy_to_labels"):
        metrics.compute()
    metrics = OccupancyMetrics("weak")
    metrics.update(occupancy_to_labels(density, semantics), gt, None)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        metrics.compute()
