"""The voxelizer's options have one source, :class:`VoxelizerConfig`: ``voxelize``'s keywords,
``GaussianVoxelizer``'s ``config`` / ``**overrides`` and ``VoxelizerOptions`` all agree with it,
unknown names are refused with the closest valid one, and every bad value names its option."""

from __future__ import annotations

import dataclasses
import inspect
import math
import pickle
import typing
from typing import Any

import pytest
import torch

import dego
import dego.voxelizer
from dego import GaussianVoxelizer, VoxelGrid, voxelize
from dego._options import field_names, keyword_mismatches
from dego.voxelizer import VoxelizerConfig, VoxelizerOptions, VoxelOutput, api
from tests.helpers.options import assert_overrides_typed_as_config
from tests.helpers.strategies import make_gaussian_set

GRID = VoxelGrid((-2.0, -2.0, -1.0), (2.0, 2.0, 1.0), 0.25)  # (16, 16, 8)

# (options, the option the error names): each is refused by the config, the module and
# the function (where beartype may refuse a wrong type first, still naming it)
BAD_OPTIONS = [
    ({"mode": "max"}, "mode"),
    ({"neighborhood": "sphere"}, "neighborhood"),
    ({"cutoff_sigma": 0.0}, "cutoff_sigma"),
    ({"cutoff_sigma": math.nan}, "cutoff_sigma"),
    ({"neighborhood": "cube"}, "nbh"),
    ({"neighborhood": "cube", "nbh": -1}, "nbh"),
    ({"chunk_size": 0}, "chunk_size"),
    ({"chunk_size": True}, "chunk_size"),
    ({"neighborhood": "scale_cube"}, "scale_multiplier"),
    ({"neighborhood": "scale_cube", "scale_multiplier": -2}, "scale_multiplier"),
    ({"scale_multiplier": 3}, "scale_multiplier"),
    ({"feature_weight": "opacity"}, "feature_weight"),
    ({"opacity_in_density": 1}, "opacity_in_density"),
    ({"empty_value": math.inf}, "empty_value"),
    ({"empty_threshold": -1.0}, "empty_threshold"),
]


def gaussians() -> dego.GaussianSet:
    return make_gaussian_set((1,), 4, seed=0, feature_dim=2, extent=1.5, scale_range=(0.1, 0.4))


def test_voxelize_keywords_are_the_config_fields() -> None:
    assert keyword_mismatches(voxelize, VoxelizerConfig) == []


def test_the_overrides_typed_dict_is_the_config() -> None:
    assert_overrides_typed_as_config(VoxelizerOptions, VoxelizerConfig, GaussianVoxelizer)


def test_defaults_agree_everywhere() -> None:
    defaults = VoxelizerConfig()
    assert GaussianVoxelizer(GRID).config == defaults
    keywords = inspect.signature(voxelize).parameters
    assert {name: keywords[name].default for name in field_names(VoxelizerConfig)} == {
        f.name: getattr(defaults, f.name) for f in dataclasses.fields(defaults)
    }


def test_voxelize_builds_the_config_by_name(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[VoxelizerConfig] = []
    original = api._voxelize
    monkeypatch.setattr(api, "_voxelize", lambda *args: seen.append(args[-1]) or original(*args))
    options = {
        "mode": "probabilistic",
        "neighborhood": "scale_cube",
        "cutoff_sigma": 2.0,
        "chunk_size": 1000,
        "scale_multiplier": 4,
        "feature_weight": "kernel",
        "opacity_in_density": False,
        "empty_value": 0.5,
        "empty_threshold": 1e-9,
    }
    voxelize(gaussians(), GRID, **options)
    assert seen == [VoxelizerConfig(**options)]


@pytest.mark.parametrize(
    ("name", "close"),
    [("nhb", "nbh"), ("cutoff_sgima", "cutoff_sigma"), ("neighbourhood", "neighborhood")],
)
def test_unknown_option_is_refused_with_the_closest_name(name: str, close: str) -> None:
    message = f"GaussianVoxelizer() got an unknown option {name!r} (did you mean {close!r}?)"
    with pytest.raises(TypeError, match=r"valid options: mode, neighborhood") as err:
        GaussianVoxelizer(GRID, **{name: 1})
    assert str(err.value).startswith(message)
    with pytest.raises(TypeError, match=name):
        voxelize(gaussians(), GRID, **{name: 1})
    with pytest.raises(TypeError, match=name):
        VoxelizerConfig(**{name: 1})


def test_unknown_option_without_a_close_name_lists_the_valid_ones() -> None:
    with pytest.raises(TypeError, match=r"unknown option 'zzz'; valid options: ") as err:
        GaussianVoxelizer(GRID, zzz=1)
    assert "did you mean" not in str(err.value)


def test_config_and_overrides_combine() -> None:
    config = VoxelizerConfig(neighborhood="cube", nbh=4, mode="probabilistic")
    module = GaussianVoxelizer(GRID, config, nbh=2, empty_value=0.25)
    assert module.config == dataclasses.replace(config, nbh=2, empty_value=0.25)
    assert config.nbh == 4  # the given config is not changed
    assert GaussianVoxelizer(GRID, config).config is config
    assert GaussianVoxelizer(config=config).grid == VoxelGrid.occ3d()
    gs = gaussians()
    out = module(gs)
    expected = voxelize(gs, GRID, **{f: getattr(module.config, f) for f in field_names(config)})
    assert torch.equal(out.density, expected.density)
    assert torch.equal(out.features, expected.features)
    # the combination is validated once: an override can make a valid config invalid
    with pytest.raises(ValueError, match=r"^nbh: required with neighborhood='cube'"):
        GaussianVoxelizer(GRID, config, nbh=None)
    with pytest.raises(ValueError, match=r"^scale_multiplier: required"):
        GaussianVoxelizer(GRID, config, neighborhood="scale_cube")


@pytest.mark.parametrize("config", [{"nbh": 4}, "cube", 3, VoxelGrid.occ3d()])
def test_wrong_config_type_is_refused(config: Any) -> None:
    with pytest.raises(TypeError, match="config"):
        GaussianVoxelizer(GRID, config)
    with pytest.raises(TypeError, match="config"):
        GaussianVoxelizer(GRID, config=config)


def test_wrong_grid_type_is_refused_naming_it() -> None:
    with pytest.raises(TypeError, match="grid"):
        GaussianVoxelizer((16, 16, 8))  # type: ignore[arg-type]


@pytest.mark.parametrize(("options", "name"), BAD_OPTIONS, ids=[n for _, n in BAD_OPTIONS])
def test_each_bad_option_value_names_the_option(options: dict[str, Any], name: str) -> None:
    with pytest.raises(ValueError, match=f"^{name}: "):
        VoxelizerConfig(**options)
    with pytest.raises(ValueError, match=f"^{name}: "):
        GaussianVoxelizer(GRID, **options)
    with pytest.raises(ValueError, match=f"^{name}: "):
        GaussianVoxelizer(GRID, VoxelizerConfig(), **options)
    with pytest.raises((ValueError, TypeError), match=name):
        voxelize(gaussians(), GRID, **options)


@pytest.mark.parametrize(
    "options",
    [
        {"neighborhood": "scale_cube", "scale_multiplier": 3},  # int
        {"neighborhood": "scale_cube", "scale_multiplier": 3.5},
        {"empty_value": 1},  # int
        {"empty_value": 1 / 17},
        {"neighborhood": "cube", "nbh": 1},
    ],
)
def test_numbers_accepted_before_are_still_accepted(options: dict[str, Any]) -> None:
    gs = gaussians()
    out = voxelize(gs, GRID, **options)
    module = GaussianVoxelizer(GRID, **options)(gs)
    assert torch.equal(out.density, module.density)


@pytest.mark.parametrize(("name", "value"), [("cutoff_sigma", 3), ("empty_threshold", 0)])
def test_voxelize_type_checks_its_keywords(name: str, value: int) -> None:
    # as before the package split: beartype refuses an int for a float keyword
    with pytest.raises(TypeError, match=f"parameter '{name}'"):
        voxelize(gaussians(), GRID, **{name: value})


def test_labels_is_type_checked() -> None:
    out = voxelize(gaussians(), GRID)
    assert out.labels(threshold=0.1).shape == out.density.shape
    with pytest.raises(TypeError, match="threshold"):
        out.labels(threshold="0.1")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="free_label"):
        out.labels(free_label=1.5)  # type: ignore[arg-type]


def test_voxel_output_keeps_its_public_and_pickled_name() -> None:
    assert VoxelOutput.__module__ == "dego.voxelizer" and VoxelOutput.__qualname__ == "VoxelOutput"
    assert dego.voxelizer.VoxelOutput is dego.VoxelOutput is VoxelOutput
    out = voxelize(gaussians(), GRID)
    data = pickle.dumps(out)
    assert b"dego.voxelizer" in data and b"dego.voxelizer.output" not in data
    again = pickle.loads(data)
    assert torch.equal(again.density, out.density) and torch.equal(again.features, out.features)


def test_the_package_exports() -> None:
    assert sorted(dego.voxelizer.__all__) == sorted(
        [
            "FeatureWeight",
            "GaussianVoxelizer",
            "Mode",
            "Neighborhood",
            "VoxelOutput",
            "VoxelizerConfig",
            "VoxelizerOptions",
            "voxelize",
        ]
    )
    for name in dego.voxelizer.__all__:
        assert getattr(dego.voxelizer, name) is not None
    assert typing.get_args(dego.voxelizer.Mode) == ("additive", "probabilistic")
