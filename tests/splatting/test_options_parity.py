"""The splatter's options have one source, :class:`SplatConfig`: ``splat``'s keywords,
``DifferentiableSplatter``'s ``config`` / ``**overrides`` and ``SplatOptions`` all agree with
it, unknown names are refused with the closest valid one, every bad value names its option,
and the restructured package keeps its public and pickled names."""

from __future__ import annotations

import dataclasses
import io
import math
import pickle
from typing import Any

import pytest
import torch

import dego.splatting
from dego import DifferentiableSplatter, splat
from dego._options import keyword_mismatches
from dego.splatting import pipeline, splatter
from dego.splatting.types import SplatConfig, SplatOptions, SplatOutput
from tests.helpers.options import assert_overrides_typed_as_config
from tests.helpers.splatting import make_cameras, make_scene_gaussians

SIZE = (16, 24)

# (options, the option the error names): refused by the config, the module and splat
BAD_OPTIONS = [
    ({"near": -1.0}, "near"),
    ({"near": math.nan}, "near"),
    ({"far": 0.001}, "far"),
    ({"eps2d": -0.1}, "eps2d"),
    ({"max_alpha": 0.0}, "max_alpha"),
    ({"max_alpha": 1.5}, "max_alpha"),
    ({"alpha_min": 1.0}, "alpha_min"),
    ({"transmittance_min": -0.5}, "transmittance_min"),
    ({"radius_sigma": 0.0}, "radius_sigma"),
    ({"tile_size": 0}, "tile_size"),
    ({"chunk_size": -3}, "chunk_size"),
    ({"max_pairs": 0}, "max_pairs"),
    ({"radius_clip": -1.0}, "radius_clip"),
    ({"depth_mode": "median"}, "depth_mode"),
    ({"backend": "cuda"}, "backend"),
    ({"rasterize_mode": "mip"}, "rasterize_mode"),
    ({"radius_rule": "gsplat>=2"}, "radius_rule"),
]


def scene() -> tuple[dego.GaussianSet, torch.Tensor, torch.Tensor]:
    gs = make_scene_gaussians(1, 6, SIZE, seed=3, feature_dim=2)
    w2c, k = make_cameras(1, 1, SIZE, seed=3)
    return gs, w2c, k


def test_splat_keywords_are_the_config_fields() -> None:
    assert keyword_mismatches(splat, SplatConfig) == []


def test_the_overrides_typed_dict_is_the_config() -> None:
    assert_overrides_typed_as_config(SplatOptions, SplatConfig, DifferentiableSplatter)


def test_defaults_agree_everywhere() -> None:
    assert DifferentiableSplatter().config == SplatConfig()


def test_splat_builds_the_config_by_name(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[SplatConfig] = []
    original = pipeline.render
    monkeypatch.setattr(pipeline, "render", lambda *a, **k: seen.append(a[6]) or original(*a, **k))
    options: dict[str, Any] = {
        "near": 0.05,
        "far": 50.0,
        "eps2d": 0.2,
        "max_alpha": 0.99,
        "alpha_min": 0.01,
        "transmittance_min": 1e-3,
        "radius_sigma": 2.5,
        "tile_size": 8,
        "depth_mode": "accumulated",
        "chunk_size": 4,
        "max_pairs": 4096,
        "radius_clip": 0.5,
        "rasterize_mode": "antialiased",
        "radius_rule": "gsplat>=1.5",
        "absgrad": True,
    }
    splat(*scene(), SIZE, **options)
    assert seen == [SplatConfig(**options)]


@pytest.mark.parametrize(
    ("name", "close"), [("nera", "near"), ("radius_rul", "radius_rule"), ("tilesize", "tile_size")]
)
def test_unknown_option_is_refused_with_the_closest_name(name: str, close: str) -> None:
    for owner, call in [
        ("DifferentiableSplatter()", lambda: DifferentiableSplatter(**{name: 1})),
        ("splat()", lambda: splat(*scene(), SIZE, **{name: 1})),
    ]:
        with pytest.raises(TypeError, match=r"valid options: near, far") as err:
            call()
        assert str(err.value).startswith(
            f"{owner} got an unknown option {name!r} (did you mean {close!r}?)"
        )


def test_unknown_option_without_a_close_name_lists_the_valid_ones() -> None:
    for call in (lambda: DifferentiableSplatter(zzz=1), lambda: splat(*scene(), SIZE, zzz=1)):
        with pytest.raises(TypeError, match=r"unknown option 'zzz'; valid options: ") as err:
            call()
        assert "did you mean" not in str(err.value)


def test_gsplat_names_say_what_dego_calls_them() -> None:
    for call in (
        lambda: DifferentiableSplatter(near_plane=0.1),
        lambda: splat(*scene(), SIZE, near_plane=0.1),
    ):
        with pytest.raises(TypeError, match=r"keyword 'near_plane': dego calls it near"):
            call()


def test_config_and_overrides_combine() -> None:
    config = SplatConfig(tile_size=8, depth_mode="accumulated")
    module = DifferentiableSplatter(config, chunk_size=4, near=0.05)
    assert module.config == dataclasses.replace(config, chunk_size=4, near=0.05)
    assert config.chunk_size == 32  # the given config is not changed
    assert DifferentiableSplatter(config).config is config
    assert DifferentiableSplatter(config=config).config is config
    gs, w2c, k = scene()
    a = module(gs, w2c, k, SIZE)
    b = splat(gs, w2c, k, SIZE, tile_size=8, depth_mode="accumulated", chunk_size=4, near=0.05)
    assert torch.equal(a.features, b.features) and torch.equal(a.depth, b.depth)


@pytest.mark.parametrize("config", [{"tile_size": 8}, "default", 3])
def test_wrong_config_type_is_refused(config: Any) -> None:
    with pytest.raises(
        TypeError, match=r"DifferentiableSplatter\(\): config must be a SplatConfig"
    ):
        DifferentiableSplatter(config)


@pytest.mark.parametrize(("options", "name"), BAD_OPTIONS)
def test_each_bad_option_value_names_the_option(options: dict[str, Any], name: str) -> None:
    for call in (
        lambda: SplatConfig(**options),
        lambda: DifferentiableSplatter(**options),
        lambda: DifferentiableSplatter(SplatConfig(), **options),
    ):
        with pytest.raises(ValueError, match=rf"^{name}: "):
            call()
    # splat: beartype may refuse a wrong type first, still naming the option
    with pytest.raises((ValueError, TypeError), match=name):
        splat(*scene(), SIZE, **options)


def test_old_names_stay_importable_and_pickled_alike() -> None:
    assert splatter.SplatOutput is SplatOutput is dego.splatting.SplatOutput
    assert splatter.SplatConfig is SplatConfig is dego.splatting.SplatConfig
    assert SplatOutput.__module__ == "dego.splatting.splatter"
    assert b"dego.splatting.splatter" in pickle.dumps(splat(*scene(), SIZE))
    buffer = io.BytesIO()
    torch.save(splat(*scene(), SIZE), buffer)
    buffer.seek(0)
    loaded = torch.load(buffer, weights_only=True)
    assert isinstance(loaded, SplatOutput)


def test_channels_last_layout_matches_channels_first() -> None:
    gs, w2c, k = scene()
    background = torch.rand(2, dtype=gs.dtype)
    config = SplatConfig(tile_size=8)
    first = pipeline.render(gs, w2c, k, SIZE, None, background, config)
    last = pipeline.render(gs, w2c, k, SIZE, None, background, config, layout="channels_last")
    assert torch.equal(last.image[..., :2], first.features.permute(0, 1, 3, 4, 2))
    assert torch.equal(last.image[..., 2], first.depth)
    assert torch.equal(last.alpha, first.alpha)
    with pytest.raises((TypeError, ValueError), match="layout"):
        pipeline.render(gs, w2c, k, SIZE, None, None, config, layout="hwc")  # type: ignore[call-overload]
    with pytest.raises(ValueError, match=r"^backend: 'gsplat' renders the channels_first"):
        pipeline.render(
            gs, w2c, k, SIZE, None, None, SplatConfig(backend="gsplat"), layout="channels_last"
        )


def test_project_gaussians_is_type_checked() -> None:
    gs, w2c, k = scene()
    with pytest.raises(TypeError, match="means"):
        dego.splatting.project_gaussians(
            gs.means[0], gs.quats, gs.scales, w2c, k, SIZE, near=0.01, far=100.0, eps2d=0.3
        )
