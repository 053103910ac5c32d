"""Backend selection of the splatter: "auto" falls back to torch, "gsplat" says why it cannot run."""

from __future__ import annotations

import importlib.util

import pytest
import torch

from dego import splat
from tests.helpers.strategies import make_gaussian_set


def scene(device: str = "cpu"):
    gs = make_gaussian_set(
        (1,), 20, feature_dim=3, dtype=torch.float32, seed=2, scale_range=(0.05, 0.5), extent=1.0
    )
    gs = gs.replace(means=gs.means + torch.tensor([0.0, 0.0, 4.0]))
    w2c = torch.eye(4).expand(1, 2, 4, 4).clone()
    w2c[:, 1, 0, 3] = 0.3
    k = torch.tensor([[40.0, 0, 24], [0, 40.0, 16], [0, 0, 1]]).expand(1, 2, 3, 3).contiguous()
    return gs.to(device), w2c.to(device), k.to(device)


def test_auto_on_cpu_is_the_torch_path() -> None:
    gs, w2c, k = scene()
    torch_out = splat(gs, w2c, k, (32, 48))
    auto_out = splat(gs, w2c, k, (32, 48), backend="auto")
    for name in ("features", "depth", "alpha", "radii"):
        assert torch.equal(getattr(torch_out, name), getattr(auto_out, name)), name


def test_gsplat_backend_explains_why_it_cannot_run() -> None:
    gs, w2c, k = scene()
    with pytest.raises(ValueError, match=r"backend: cannot use 'gsplat'.*CUDA"):
        splat(gs, w2c, k, (32, 48), backend="gsplat")


@pytest.mark.parametrize(
    ("version", "wrong", "fixed"),
    [((1, 4), 0.99, 0.999), ((1, 5), 0.99, 0.999), ((1, 6), 0.999, 0.99)],
)
def test_the_alpha_cap_is_that_of_the_installed_release(
    monkeypatch: pytest.MonkeyPatch, version: tuple[int, int], wrong: float, fixed: float
) -> None:
    """gsplat 1.6 compiles max alpha 0.99, 1.4 and 1.5 0.999: ``auto`` must not pick a
    release whose constant differs from the requested one."""
    from dego.splatting import gsplat_backend

    monkeypatch.setattr(gsplat_backend, "installed_version", lambda: version)
    gs, w2c, k = scene()
    with pytest.raises(
        ValueError, match=rf"max_alpha={wrong} differs from the installed gsplat .*fixed {fixed}"
    ):
        splat(gs, w2c, k, (32, 48), backend="gsplat", max_alpha=wrong)
    with pytest.raises(ValueError, match="CUDA") as info:
        splat(gs, w2c, k, (32, 48), backend="gsplat", max_alpha=fixed)
    assert "max_alpha" not in str(info.value)


@pytest.mark.skipif(
    not torch.cuda.is_available() or importlib.util.find_spec("gsplat") is None,
    reason="needs CUDA and gsplat",
)
@pytest.mark.parametrize(
    "options",
    [{}, {"rasterize_mode": "antialiased", "radius_clip": 1.0}, {"depth_mode": "accumulated"}],
)
def test_gsplat_backend_matches_torch_path_on_cuda(options: dict) -> None:
    from dego.splatting import gsplat_backend

    gs, w2c, k = scene("cuda")
    rule = gsplat_backend.rule_of(gsplat_backend.installed_version())
    ours = splat(gs, w2c, k, (32, 48), radius_rule=rule, **options)
    theirs = splat(gs, w2c, k, (32, 48), backend="gsplat", **options)
    torch.testing.assert_close(theirs.features, ours.features, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(theirs.alpha, ours.alpha, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(theirs.depth, ours.depth, rtol=1e-4, atol=1e-3)
    assert torch.equal(theirs.radii, ours.radii)
    assert torch.equal(theirs.projection.radii_xy, ours.projection.radii_xy)
    per_camera = torch.rand(1, 2, gs.num_gaussians, 3, device="cuda")
    theirs = splat(gs, w2c, k, (32, 48), backend="gsplat", features=per_camera, **options)
    ours = splat(gs, w2c, k, (32, 48), radius_rule=rule, features=per_camera, **options)
    torch.testing.assert_close(theirs.features, ours.features, rtol=1e-4, atol=1e-4)


def test_release_constants_are_gsplat_s() -> None:
    """gsplat's compiled constants (gsplat/cuda/include/Common.h): 1.4 and 1.5 equal
    SplatConfig's defaults; 1.6 differs in max alpha only."""
    from dego.splatting import gsplat_backend
    from dego.splatting.splatter import SplatConfig

    defaults = SplatConfig()
    for version in ((1, 4), (1, 5)):
        constants = gsplat_backend.constants_of(version)
        assert constants == {"max_alpha": 0.999, "alpha_min": 1 / 255, "transmittance_min": 1e-4}
        assert all(getattr(defaults, name) == value for name, value in constants.items())
    assert gsplat_backend.constants_of((1, 6)) == {**constants, "max_alpha": 0.99}
