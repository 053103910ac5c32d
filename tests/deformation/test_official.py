"""Official DeGO checkpoints, the official return layout, the canonical frame, and
GaussianFlowOcc's temporal module with its class gating.

The reference modules below are written from the published descriptions of the official
networks (parameter names, shapes, input order and update rules), not from their code.
"""

from __future__ import annotations

import warnings
from typing import Any

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor, nn

from dego import GaussianSet, normalize_quaternions
from dego.compat.gaussianflowocc import (
    GAUSSIANFLOWOCC_CHECKPOINT_PREFIX,
    GAUSSIANFLOWOCC_DYNAMIC_CLASSES,
    TemporalOffsetNetwork,
    gate_by_class,
)
from dego.deformation import (
    OFFICIAL_CHECKPOINT_PREFIX,
    DecoupledDeformation,
    DeformationOutput,
    StateDictMismatchError,
    deformation_loss,
)
from tests.helpers.strategies import make_gaussian_set

SIZES = {
    "feature_dim": 5,
    "hidden_dim": 12,
    "depth": 3,
    "time_dim": 6,
    "pos_levels": 2,
    "time_levels": 3,
}
TIMES = [0.0, 3.0, 9.0, 16.0]  # official frame indices (current frame = 8)


def _hamilton(a: Tensor, b: Tensor) -> Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def _encode(x: Tensor, freqs: Tensor) -> Tensor:
    """[x, sin(2^k x_d) ordered d-major, cos(same)]."""
    angles = (x[..., None] * freqs).flatten(-2)
    return torch.cat([x, angles.sin(), angles.cos()], -1)


class OfficialReference(nn.Module):
    """The released ``GaussianDeformationMaskStaticRigid`` (static mask off), from the facts.

    Returns the official layout ``(B, N, T, k)`` plus ``"mask"`` ``(B, N, T)`` (which the
    official module computes but does not return) and its two training losses.
    """

    def __init__(
        self,
        feature_dim: int,
        hidden_dim: int,
        depth: int,
        time_dim: int,
        pos_levels: int,
        time_levels: int,
        use_rigid_mask: bool = True,
    ) -> None:
        super().__init__()
        self.register_buffer("pos_enc_freqs", 2.0 ** torch.arange(pos_levels, dtype=torch.float32))
        self.register_buffer(
            "time_enc_freqs", 2.0 ** torch.arange(time_levels, dtype=torch.float32)
        )
        self.time_embed = nn.Sequential(
            nn.Linear(2 * time_levels + 1, time_dim), nn.ReLU(), nn.Linear(time_dim, time_dim)
        )
        width = feature_dim + 3 * (2 * pos_levels + 1) + time_dim
        layers: list[nn.Module] = []
        for _ in range(depth):
            layers += [nn.Linear(width, hidden_dim), nn.ReLU()]
            width = hidden_dim

        def head(k: int, *tail: nn.Module) -> nn.Sequential:
            return nn.Sequential(
                nn.Linear(hidden_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, k), *tail
            )

        self.feature_net = nn.Sequential(*layers)
        if use_rigid_mask:
            self.rigid_mask_head = head(1, nn.Sigmoid())
        self.position_head = head(3)
        self.rotation_head = head(4)
        self.scale_head = head(3)
        self.opacity_head = head(1)

    def forward(
        self,
        means: Tensor,
        features: Tensor,
        times: Tensor,
        quats: Tensor,
        scales: Tensor,
        opacity: Tensor,
    ) -> dict[str, Tensor]:
        steps: dict[str, list[Tensor]] = {
            k: [] for k in ("means", "rotations", "scales", "opacity", "mask")
        }
        identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=means.dtype)
        for t in range(times.shape[1]):
            e_t = self.time_embed(_encode(times[:, t : t + 1], self.time_enc_freqs))
            e_t = e_t[:, None].expand(-1, means.shape[1], -1)
            h = self.feature_net(torch.cat([features, _encode(means, self.pos_enc_freqs), e_t], -1))
            m = self.rigid_mask_head(h) if hasattr(self, "rigid_mask_head") else h[..., :1] * 0 + 1
            d_rot = nn.functional.normalize(self.rotation_head(h) + 1e-8, dim=-1)
            steps["means"].append(means + self.position_head(h).clamp(-10, 10))
            steps["rotations"].append(_hamilton(quats, m * d_rot + (1 - m) * identity))
            steps["scales"].append(scales + m * self.scale_head(h).clamp(-1, 1))
            steps["opacity"].append((opacity + m * self.opacity_head(h)).clamp(0, 1))
            steps["mask"].append(m[..., 0])
        out = {k: torch.stack(v, 2) for k, v in steps.items()}
        canonical = {"means": means, "rotations": quats, "scales": scales, "opacity": opacity}
        out["deformation_reg_loss"] = sum(
            (out[k] - v[:, :, None]).square().mean() for k, v in canonical.items()
        )
        last = out["mask"][:, :, -1]
        out["rigid_non_rigid_loss"] = (last * (1 - last)).mean()
        return out


def make_reference(
    seed: int = 0, dtype: torch.dtype = torch.float64, **sizes: Any
) -> OfficialReference:
    """Random weights large enough that the clamps and the mask are exercised."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        ref = OfficialReference(**{**SIZES, **sizes})
        for module in ref.modules():
            if isinstance(module, nn.Linear):
                nn.init.normal_(module.weight, std=1.5 / module.in_features**0.5)
                nn.init.normal_(module.bias, std=0.3)
    return ref.to(dtype)


def make_inputs(
    b: int = 2,
    n: int = 9,
    *,
    feature_dim: int = 5,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
) -> tuple[GaussianSet, Tensor]:
    canonical = make_gaussian_set(
        (b,), n, seed=seed, feature_dim=3, extent=30.0, scale_range=(0.05, 1.0)
    )
    canonical = canonical.replace(quats=normalize_quaternions(canonical.quats))
    g = torch.Generator().manual_seed(seed + 1)
    features = torch.randn(b, n, feature_dim, generator=g, dtype=torch.float64)
    return canonical.to(dtype), features.to(dtype)


def run_reference(
    ref: OfficialReference, canonical: GaussianSet, features: Tensor, times: Tensor
) -> dict[str, Tensor]:
    return ref(
        canonical.means,
        features,
        times,
        canonical.quats,
        canonical.scales,
        canonical.opacities[..., None],
    )


def times_for(b: int, dtype: torch.dtype = torch.float64) -> Tensor:
    return torch.tensor(TIMES, dtype=dtype).expand(b, -1)


# ---------------------------------------------------------------------------------------
# from_official_state_dict: equivalence


@pytest.mark.parametrize(("dtype", "tol"), [(torch.float64, 1e-6), (torch.float32, 1e-4)])
def test_loaded_module_matches_the_official_forward(dtype: torch.dtype, tol: float) -> None:
    ref = make_reference(dtype=dtype)
    module = DecoupledDeformation.from_official_state_dict(ref.state_dict())
    assert module.preset == "official" and module.input_static.weight.dtype == dtype
    canonical, features = make_inputs(dtype=dtype)
    times = times_for(2, dtype)
    expected = run_reference(ref, canonical, features, times)
    out = module(canonical, features, times)
    official = out.to_official_dict(losses=True)
    for key in (
        "means",
        "rotations",
        "scales",
        "opacity",
        "deformation_reg_loss",
        "rigid_non_rigid_loss",
    ):
        torch.testing.assert_close(official[key], expected[key], atol=tol, rtol=tol, msg=key)
    torch.testing.assert_close(out.rigid_mask, expected["mask"].transpose(1, 2), atol=tol, rtol=tol)
    # the clamps and both mask regimes were exercised
    clamped = (out.rigid_offsets.abs() > 10).any() or (out.gaussians.scales <= 0).any()
    assert clamped or (out.gaussians.opacities == 0).any() or (out.gaussians.opacities == 1).any()


def test_released_sizes_are_inferred() -> None:
    released = {
        "feature_dim": 256,
        "hidden_dim": 256,
        "depth": 6,
        "time_dim": 32,
        "pos_levels": 6,
        "time_levels": 4,
    }
    ref = OfficialReference(**released)
    assert ref.feature_net[0].in_features == 327  # 256 + 39 + 32
    module = DecoupledDeformation.from_official_state_dict(ref.state_dict())
    assert module.feature_dim == 256 and module.pos_levels == 6 and module.time_levels == 4
    assert module.input_static.in_features == 256 + 39 and module.input_time.in_features == 32
    assert module.trunk is not None and len(module.trunk) == 9  # 5 Linear layers
    assert module.mask_head[0].out_features == 256


# ---------------------------------------------------------------------------------------
# round trip


def test_round_trip_is_exact_and_keeps_the_official_order() -> None:
    ref = make_reference()
    state = ref.state_dict()
    back = DecoupledDeformation.from_official_state_dict(state).to_official_state_dict()
    assert list(back) == list(state)
    for key, value in state.items():
        assert back[key].dtype == value.dtype and torch.equal(back[key], value), key
    fresh = make_reference(seed=1)
    fresh.load_state_dict(back)  # the official module itself loads it, strictly


@settings(max_examples=15, deadline=None)
@given(
    feature_dim=st.integers(0, 6),
    hidden_dim=st.integers(1, 8),
    depth=st.integers(1, 4),
    time_dim=st.integers(1, 5),
    pos_levels=st.integers(0, 3),
    time_levels=st.integers(0, 3),
)
def test_round_trip_over_sizes(**sizes: int) -> None:
    module = DecoupledDeformation(preset="official", head_hidden=sizes["hidden_dim"], **sizes)
    state = module.to_official_state_dict()
    loaded = DecoupledDeformation.from_official_state_dict(state)
    assert {
        name: getattr(loaded, name) for name in ("feature_dim", "pos_levels", "time_levels")
    } == {name: sizes[name] for name in ("feature_dim", "pos_levels", "time_levels")}
    for (name, a), (_, b) in zip(
        module.state_dict().items(), loaded.state_dict().items(), strict=True
    ):
        assert torch.equal(a, b), name
    again = loaded.to_official_state_dict()
    assert list(again) == list(state) and all(torch.equal(again[k], state[k]) for k in state)


def test_to_official_rejects_what_the_official_module_cannot_hold() -> None:
    with pytest.raises(ValueError, match="preset: only an 'official'"):
        DecoupledDeformation(4).to_official_state_dict()
    with pytest.raises(ValueError, match="head_hidden"):
        DecoupledDeformation(
            4, preset="official", hidden_dim=8, head_hidden=6
        ).to_official_state_dict()
    module = DecoupledDeformation(
        4, preset="official", hidden_dim=8, head_hidden=8, pos_scale=40.0, fixed_mask=0.0
    )
    with pytest.warns(UserWarning, match=r"pos_scale=40.0, fixed_mask=0.0"):
        module.to_official_state_dict()


# ---------------------------------------------------------------------------------------
# prefixes and checkpoints


def test_prefix_selects_the_detector_keys() -> None:
    ref = make_reference()
    detector = {
        "img_backbone.conv1.weight": torch.zeros(3),
        "gaussian_decoder.layers.0.w": torch.zeros(2),
    }
    detector |= {OFFICIAL_CHECKPOINT_PREFIX + k: v for k, v in ref.state_dict().items()}
    canonical, features = make_inputs()
    expected = DecoupledDeformation.from_official_state_dict(ref.state_dict())(
        canonical, features, times_for(2)
    )
    for source in (detector, {"meta": {"epoch": 30}, "state_dict": detector}):
        for prefix in (OFFICIAL_CHECKPOINT_PREFIX, OFFICIAL_CHECKPOINT_PREFIX.rstrip(".")):
            module = DecoupledDeformation.from_official_state_dict(source, prefix=prefix)
            out = module(canonical, features, times_for(2))
            assert torch.equal(out.gaussians.means, expected.gaussians.means)
    exported = module.to_official_state_dict(prefix=OFFICIAL_CHECKPOINT_PREFIX)
    assert set(exported) == {k for k in detector if k.startswith(OFFICIAL_CHECKPOINT_PREFIX)}
    with pytest.raises(StateDictMismatchError) as info:
        DecoupledDeformation.from_official_state_dict(detector)  # no prefix: other modules' keys
    assert "img_backbone.conv1.weight" in str(info.value)
    with pytest.raises(
        KeyError, match=r"did you mean prefix='gaussian_decoder\.deformation_module\.'"
    ):
        DecoupledDeformation.from_official_state_dict(detector, prefix="deformation_module.")


# ---------------------------------------------------------------------------------------
# errors


def test_every_bad_key_is_listed() -> None:
    state = dict(make_reference().state_dict())
    del state["position_head.2.bias"], state["time_embed.0.weight"]
    state["static_mask_head.0.weight"] = torch.zeros(12, 12, dtype=torch.float64)
    state["extra.bias"] = torch.zeros(1)
    state["scale_head.2.weight"] = torch.zeros(2, 12, dtype=torch.float64)
    state["opacity_head.0.bias"] = torch.zeros(12, dtype=torch.int64)
    with pytest.raises(StateDictMismatchError) as info:
        DecoupledDeformation.from_official_state_dict(state)
    message = str(info.value)
    assert isinstance(info.value, KeyError) and isinstance(info.value, ValueError)
    for expected in [
        "missing (2): time_embed.0.weight, position_head.2.bias",
        "unexpected (2): static_mask_head.0.weight (from use_static_mask=True, not modelled",
        "extra.bias",
        "scale_head.2.weight: shape (2, 12), expected (3, 12)",
        "opacity_head.0.bias: expected a floating-point tensor, got torch.int64",
        "feature_dim=5, hidden_dim=12, depth=3, time_dim=6, pos_levels=2, time_levels=3",
    ]:
        assert expected in message, (expected, message)


@pytest.mark.parametrize("strict", [True, False])
def test_bogus_layer_index_is_refused_before_building(strict: bool) -> None:
    """One key ``feature_net.200000.weight`` once built a 100,001-layer module and a
    5-million-character message (issue 26): the inferred depth is bounded first."""
    state = dict(make_reference().state_dict())
    state["feature_net.200000.weight"] = torch.zeros(12, 12, dtype=torch.float64)
    with pytest.raises(StateDictMismatchError) as info:
        DecoupledDeformation.from_official_state_dict(state, strict=strict)
    message = str(info.value)
    assert len(message) < 2000, len(message)
    assert "feature_net.200000.weight" in message and "100001" in message, message
    assert "depth=" in message, message


def test_mismatch_lists_are_bounded() -> None:
    state = dict(make_reference().state_dict())
    state |= {f"extra.{i}.weight": torch.zeros(1) for i in range(500)}
    for key in [k for k in state if k.startswith(("position_head", "rotation_head"))]:
        state[key] = torch.zeros(1, dtype=torch.float64)  # 8 mis-shaped keys
    with pytest.raises(StateDictMismatchError) as info:
        DecoupledDeformation.from_official_state_dict(state)
    message = str(info.value)
    assert len(message) < 3000, len(message)
    assert "unexpected (500): extra.0.weight, extra.1.weight" in message, message
    assert "... and 480 more" in message and "extra.499.weight" not in message, message
    assert "mis-shaped or invalid (8)" in message and "rotation_head.2.bias" in message


@pytest.mark.parametrize("strict", [True, False])
def test_gaps_in_the_inferred_layers_are_refused(strict: bool) -> None:
    state = dict(make_reference().state_dict())  # depth 3: feature_net.0, .2, .4
    del state["feature_net.2.weight"], state["feature_net.2.bias"]
    with pytest.raises(StateDictMismatchError, match=r"feature_net: .*\[0, 4\].*depth=") as info:
        DecoupledDeformation.from_official_state_dict(state, strict=strict)
    assert len(str(info.value)) < 2000
    state["feature_net.3.weight"] = torch.zeros(12, 12, dtype=torch.float64)  # a ReLU slot
    with pytest.raises(StateDictMismatchError, match=r"feature_net: .*\[0, 3, 4\]"):
        DecoupledDeformation.from_official_state_dict(state, strict=strict)
    # Given explicitly, the depth is not inferred: the gap is missing keys again.
    del state["feature_net.3.weight"]
    with pytest.raises(StateDictMismatchError, match=r"missing \(2\): feature_net\.2\.weight"):
        DecoupledDeformation.from_official_state_dict(state, depth=3)
    with pytest.warns(UserWarning, match="feature_net.2.weight"):
        module = DecoupledDeformation.from_official_state_dict(state, depth=3, strict=False)
    assert module.trunk is not None and len(module.trunk) == 3


def test_inferred_depth_is_bounded_but_an_explicit_one_is_not() -> None:
    deep = make_reference(hidden_dim=2, depth=65).state_dict()
    with pytest.raises(StateDictMismatchError, match=r"feature_net\.128\.bias.*65.*above 64"):
        DecoupledDeformation.from_official_state_dict(deep)
    module = DecoupledDeformation.from_official_state_dict(deep, depth=65)
    assert module.trunk is not None and len(module.trunk) == 2 * 64 - 1


def test_expected_official_shapes_match_the_module() -> None:
    from dego.deformation.checkpoint import _official_shapes

    for sizes in [SIZES, {**SIZES, "depth": 1, "pos_levels": 0, "feature_dim": 0}]:
        module = DecoupledDeformation(preset="official", head_hidden=sizes["hidden_dim"], **sizes)
        shapes = {k: tuple(v.shape) for k, v in module.to_official_state_dict().items()}
        assert list(
            _official_shapes({**sizes, "head_hidden": sizes["hidden_dim"]}).items()
        ) == list(shapes.items())


def test_frequency_buffers_must_be_powers_of_two() -> None:
    state = dict(make_reference().state_dict())
    state["pos_enc_freqs"] = torch.tensor([1.0, 3.0])
    with pytest.raises(
        ValueError, match=r"pos_enc_freqs: expected the frequencies 2\^k = \[1.0, 2.0\]"
    ):
        DecoupledDeformation.from_official_state_dict(state)


def test_first_layer_too_narrow_and_bad_arguments() -> None:
    state = dict(make_reference().state_dict())
    state["feature_net.0.weight"] = torch.zeros(12, 20, dtype=torch.float64)  # < 15 + 6 columns
    with pytest.raises(StateDictMismatchError, match="no room for the features"):
        DecoupledDeformation.from_official_state_dict(state)
    good = make_reference().state_dict()
    with pytest.raises(ValueError, match="preset"):
        DecoupledDeformation.from_official_state_dict(good, preset="paper")
    with pytest.raises(ValueError, match="head_hidden"):
        DecoupledDeformation.from_official_state_dict(good, head_hidden=7)
    with pytest.raises(TypeError, match="state_dict"):
        DecoupledDeformation.from_official_state_dict([("a", 1)])  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="prefix"):
        DecoupledDeformation.from_official_state_dict(good, prefix=3)  # type: ignore[arg-type]


def test_explicit_sizes_are_checked_against_the_shapes() -> None:
    state = make_reference().state_dict()
    with pytest.raises(StateDictMismatchError) as info:
        DecoupledDeformation.from_official_state_dict(state, hidden_dim=10)
    assert "hidden_dim=10" in str(
        info.value
    ) and "feature_net.0.weight: shape (12, 26), expected (10, 26)" in str(info.value)
    module = DecoupledDeformation.from_official_state_dict(state, time_scale=2.0, chunk_rows=3)
    assert module.time_scale == 2.0 and module.chunk_rows == 3


def test_strict_false_loads_the_rest_and_warns() -> None:
    ref = make_reference()
    state = dict(ref.state_dict())
    del state["position_head.2.weight"]
    state["static_mask_head.2.bias"] = torch.zeros(1, dtype=torch.float64)
    with pytest.warns(
        UserWarning, match=r"(?s)skipped keys.*position_head\.2\.weight.*static_mask_head\.2\.bias"
    ):
        module = DecoupledDeformation.from_official_state_dict(state, strict=False)
    loaded = module.to_official_state_dict()
    for key, value in state.items():
        if key in loaded:
            assert torch.equal(loaded[key], value), key
    assert not torch.equal(loaded["position_head.2.weight"], ref.position_head[2].weight)
    # sizes that cannot be read off the shapes must then be given
    del state["feature_net.0.weight"]
    with pytest.raises(StateDictMismatchError, match="cannot infer feature_dim"):
        DecoupledDeformation.from_official_state_dict(state, strict=False)
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        module = DecoupledDeformation.from_official_state_dict(state, strict=False, feature_dim=5)
    assert module.feature_dim == 5


def test_without_rigid_mask_head_fixed_mask_one_reproduces_it() -> None:
    ref = make_reference(use_rigid_mask=False)  # the official m = 1 everywhere
    with pytest.warns(UserWarning, match=r"missing \(4\): rigid_mask_head\.0\.weight"):
        module = DecoupledDeformation.from_official_state_dict(
            ref.state_dict(), strict=False, fixed_mask=1.0
        )
    canonical, features = make_inputs()
    expected = run_reference(ref, canonical, features, times_for(2))
    got = module(canonical, features, times_for(2)).to_official_dict()
    for key in ("means", "rotations", "scales", "opacity"):
        torch.testing.assert_close(got[key], expected[key], atol=1e-6, rtol=1e-6, msg=key)


# ---------------------------------------------------------------------------------------
# DeformationOutput: official layout, canonical frame


def official_output(
    b: int = 2, n: int = 9
) -> tuple[DeformationOutput, GaussianSet, OfficialReference]:
    ref = make_reference()
    module = DecoupledDeformation.from_official_state_dict(ref.state_dict())
    canonical, features = make_inputs(b, n)
    return module(canonical, features, times_for(b)), canonical, ref


def test_to_official_dict_layout() -> None:
    out, _, _ = official_output()
    d = out.to_official_dict()
    assert list(d) == ["means", "rotations", "scales", "opacity"]
    assert d["means"].shape == (2, 9, 4, 3) and d["rotations"].shape == (2, 9, 4, 4)
    assert d["scales"].shape == (2, 9, 4, 3) and d["opacity"].shape == (2, 9, 4, 1)
    assert torch.equal(d["means"][:, 3, 2], out.gaussians.means[:, 2, 3])
    assert torch.equal(d["opacity"][..., 0], out.gaussians.opacities.transpose(1, 2))
    assert all(v.is_contiguous() for v in d.values())
    paper = DecoupledDeformation(5, hidden_dim=8, head_hidden=8, depth=1, time_dim=4).double()
    canonical, features = make_inputs()
    paper_out = paper(canonical, features, times_for(2))
    assert paper_out.to_official_dict()["rotations"].shape == (2, 9, 4, 4)
    with pytest.raises(ValueError, match="losses: the official losses need"):
        paper_out.to_official_dict(losses=True)


def test_with_canonical_appends_the_official_current_frame() -> None:
    out, canonical, ref = official_output()
    full = out.with_canonical(canonical)
    assert full.num_times == 5 and full.canonical_last
    last = full.at(-1)
    for name, value in canonical.items():
        assert torch.equal(getattr(last, name), value), name
    for name in ("means", "quats", "scales", "opacities"):
        assert torch.equal(getattr(full.gaussians, name)[:, :4], getattr(out.gaussians, name))
        assert not getattr(full.deltas, name)[:, -1].any()
    assert full.rigid_mask.shape == (2, 5, 9) and not full.rigid_mask[:, -1].any()
    assert full.rigid_offsets is full.nonrigid_offsets and not full.rigid_offsets[:, -1].any()
    # losses are those of the deformed steps (as the official module computes them)
    for key, value in deformation_loss(out).to_dict().items():
        assert torch.equal(getattr(deformation_loss(full), key), value), key
    # the detector's 9 render frames: cat([deformed, canonical], time) in the module layout
    detector = run_reference(ref, canonical, make_inputs()[1], times_for(2))
    d = full.to_official_dict(losses=True)
    torch.testing.assert_close(
        d["means"],
        torch.cat([detector["means"], canonical.means[:, :, None]], 2),
        atol=1e-6,
        rtol=1e-6,
    )
    torch.testing.assert_close(
        d["deformation_reg_loss"], detector["deformation_reg_loss"], atol=1e-9, rtol=1e-9
    )
    with pytest.raises(ValueError, match="already ends with its canonical set"):
        full.with_canonical(canonical)


@pytest.mark.slow
@settings(max_examples=10, deadline=None)
@given(
    b=st.integers(1, 3),
    n=st.integers(0, 5),
    t=st.integers(1, 3),
    preset=st.sampled_from(["paper", "official"]),
)
def test_with_canonical_any_shape(b: int, n: int, t: int, preset: str) -> None:
    module = DecoupledDeformation(
        2,
        preset=preset,
        hidden_dim=4,
        head_hidden=4,
        depth=1,
        time_dim=3,
        pos_levels=1,
        time_levels=1,  # type: ignore[arg-type]
    ).double()
    canonical = make_gaussian_set((b,), n, seed=n, feature_dim=2)
    out = module(
        canonical, torch.randn(b, n, 2, dtype=torch.float64), torch.arange(t, dtype=torch.float64)
    )
    full = out.with_canonical(canonical)
    assert full.gaussians.batch_shape == (b, t + 1)
    assert torch.equal(full.at(-1).means, canonical.means) and torch.equal(
        full.at(-1).features, canonical.features
    )
    assert full.rigid_mask.shape == ((b, n) if preset == "paper" else (b, t + 1, n))
    if preset == "paper":
        assert full.rigid_mask is out.rigid_mask
        assert not full.nonrigid_offsets[:, -1].any()


def test_with_canonical_validates_the_set() -> None:
    out, canonical, _ = official_output()
    for value, match in [
        (canonical.map(lambda _, v: v[:, :8]), "N = 8"),
        (canonical.map(lambda _, v: v[:1]), r"batch shape \(1,\)"),
        (canonical.to(torch.float32), "torch.float32"),
        (canonical.replace(features=None), "feature_dim None"),
    ]:
        with pytest.raises(ValueError, match=match):
            out.with_canonical(value)
    with pytest.raises(TypeError):
        out.with_canonical(canonical.means)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------
# gating and GaussianFlowOcc's temporal module


def test_gated_leaves_the_others_undeformed() -> None:
    out, canonical, _ = official_output()
    keep = torch.zeros(2, 9, dtype=torch.bool)
    keep[0, :4] = True
    keep[1, 7] = True
    gated = out.gated(keep, canonical)
    for name in ("means", "quats", "scales", "opacities"):
        value, original = getattr(gated.gaussians, name), getattr(out.gaussians, name)
        canon = getattr(canonical, name)[:, None].expand_as(value)
        assert torch.equal(value[:, :, ~keep[0]][0], canon[:, :, ~keep[0]][0])
        assert torch.equal(value[0, :, keep[0]], original[0, :, keep[0]])
        assert torch.equal(value[1, :, 7], original[1, :, 7])
        assert not getattr(gated.deltas, name).transpose(1, 2)[~keep].any()
    assert not gated.rigid_mask.transpose(1, 2)[~keep].any()
    assert torch.equal(gated.rigid_mask.transpose(1, 2)[keep], out.rigid_mask.transpose(1, 2)[keep])
    with pytest.raises(ValueError, match=r"keep: expected shape \(2, 9\)"):
        out.gated(keep[:, :3], canonical)


def test_gate_by_class_uses_gaussianflowocc_labels() -> None:
    out, canonical, _ = official_output(b=1, n=16)
    logits = torch.eye(16, dtype=torch.float64)[None]  # Gaussian i is label i + 1
    gated = gate_by_class(out, logits, canonical)
    moved = (gated.gaussians.means != canonical.means[:, None]).any(-1).any(1)[0]
    labels = torch.arange(1, 17)
    assert torch.equal(moved, torch.isin(labels, torch.tensor(GAUSSIANFLOWOCC_DYNAMIC_CLASSES)))
    shifted = gate_by_class(out, logits, canonical, first_label=0)  # channel i is label i
    moved0 = (shifted.gaussians.means != canonical.means[:, None]).any(-1).any(1)[0]
    assert torch.equal(
        moved0, torch.isin(labels - 1, torch.tensor(GAUSSIANFLOWOCC_DYNAMIC_CLASSES))
    )
    with pytest.raises(ValueError, match="logits: expected finite"):
        gate_by_class(out, logits * float("nan"), canonical)


class FlowOccReference(nn.Module):
    """GaussianFlowOcc's ``TemporalFeedForwardNetwork``, from the facts: an embedding per
    time index concatenated with the feature, then an MLP with LeakyReLU to 3 offsets."""

    def __init__(self, c: int, num_timesteps: int, num_layers: int) -> None:
        super().__init__()
        self.time_embed = nn.Embedding(num_timesteps, c)
        layers: list[nn.Module] = [nn.Linear(2 * c, 3 * c), nn.LeakyReLU()]
        for _ in range(num_layers):
            layers += [nn.Linear(3 * c, 3 * c), nn.LeakyReLU()]
        self.ffn = nn.Sequential(*layers, nn.Linear(3 * c, 3))

    def forward(self, features: Tensor, indices: Tensor) -> Tensor:  # (B, N, T, 3)
        n, t = features.shape[1], indices.shape[1]
        emb = self.time_embed.weight[indices][:, None].expand(-1, n, -1, -1)
        return self.ffn(torch.cat([features[:, :, None].expand(-1, -1, t, -1), emb], -1))


def test_temporal_offset_network_reproduces_gaussianflowocc() -> None:
    torch.manual_seed(0)
    ref = FlowOccReference(4, 13, 2).double()
    net = TemporalOffsetNetwork(4, num_timesteps=13, num_layers=2).double()
    checkpoint = {GAUSSIANFLOWOCC_CHECKPOINT_PREFIX + k: v for k, v in ref.state_dict().items()}
    torch.nn.modules.utils.consume_prefix_in_state_dict_if_present(
        checkpoint, GAUSSIANFLOWOCC_CHECKPOINT_PREFIX
    )
    net.load_state_dict(checkpoint)  # the original parameter names
    canonical, features = make_inputs(2, 10, feature_dim=4)
    indices = torch.tensor([[0, 5, 7, 12], [3, 3, 9, 1]])
    offsets = ref(features, indices)
    logits = torch.randn(2, 10, 16, dtype=torch.float64)
    out = net(canonical, features, indices, logits)
    # the original move: zero the offsets of non-dynamic argmax classes, add to the means
    dynamic = torch.isin(logits.argmax(-1) + 1, torch.tensor(GAUSSIANFLOWOCC_DYNAMIC_CLASSES))
    expected = canonical.means[:, :, None] + offsets * dynamic[..., None, None]
    torch.testing.assert_close(out.to_official_dict()["means"], expected, atol=1e-10, rtol=1e-10)
    assert 0 < dynamic.sum() < dynamic.numel()
    # only the means move; static classes not at all
    for name in ("quats", "scales", "opacities", "features"):
        assert torch.equal(
            getattr(out.gaussians, name),
            getattr(canonical, name)[:, None].expand_as(getattr(out.gaussians, name)),
        )
    assert torch.equal(
        out.gaussians.means.transpose(1, 2)[~dynamic],
        canonical.means[:, :, None].expand(-1, -1, 4, -1)[~dynamic],
    )
    assert not out.rigid_mask.any() and out.preset == "paper"
    # time dependence: one offset per (Gaussian, time index), equal for equal indices
    free = net(canonical, features, indices)
    assert torch.equal(free.rigid_offsets[1, 0], free.rigid_offsets[1, 1])
    assert not torch.allclose(free.rigid_offsets[0, 0], free.rigid_offsets[0, 1])
    shared = net(canonical, features, torch.tensor([3, 9]))  # (T,) shared by the batch
    torch.testing.assert_close(shared.rigid_offsets[1], free.rigid_offsets[1, 1:3])


def test_temporal_offset_network_errors() -> None:
    net = TemporalOffsetNetwork(4, num_timesteps=5, num_layers=0).double()
    canonical, features = make_inputs(1, 3, feature_dim=4)
    with pytest.raises(ValueError, match=r"time_indices: expected indices in \[0, 5\)"):
        net(canonical, features, torch.tensor([0, 5]))
    with pytest.raises(ValueError, match="features: expected shape"):
        net(canonical, features[..., :3], torch.tensor([0]))
    with pytest.raises(ValueError, match="T = 0"):
        net(canonical, features, torch.zeros(0, dtype=torch.long))
    with pytest.raises(ValueError, match=r"features: expected torch\.float64"):
        net(canonical, features.float(), torch.tensor([0]))
    with pytest.raises(ValueError, match="num_timesteps"):
        TemporalOffsetNetwork(4, num_timesteps=0)


@pytest.mark.parametrize("preset", ["paper", "official"])
def test_fixed_mask_zero_recipe_moves_only_dynamic_means(preset: str) -> None:
    module = DecoupledDeformation(
        5,
        preset=preset,
        fixed_mask=0.0,
        hidden_dim=8,
        head_hidden=8,
        depth=2,
        time_dim=4,  # type: ignore[arg-type]
    ).double()
    for head in module.heads.values():  # paper: zero-initialised, i.e. the identity
        nn.init.normal_(head[-1].weight)
    canonical, features = make_inputs(1, 16)
    logits = torch.eye(16, dtype=torch.float64)[None]
    out = gate_by_class(
        module(canonical, features, torch.tensor([-1.0, 2.0], dtype=torch.float64)),
        logits,
        canonical,
    )
    for name in ("quats", "scales", "opacities"):
        assert torch.equal(
            getattr(out.gaussians, name),
            getattr(canonical, name)[:, None].expand_as(getattr(out.gaussians, name)),
        )
    moved = (out.gaussians.means != canonical.means[:, None]).any(-1).any(1)[0]
    assert torch.equal(
        moved, torch.isin(torch.arange(1, 17), torch.tensor(GAUSSIANFLOWOCC_DYNAMIC_CLASSES))
    )


@pytest.mark.parametrize(("extra", "cut"), [(0, False), (1, True)])
def test_keys_are_cut_beyond_120_characters(extra: int, cut: bool) -> None:
    from dego.deformation import checkpoint

    key = "k" * (checkpoint._KEY_CHARS + extra)
    assert (checkpoint._short(key) != key) == cut
    assert checkpoint._short(key).startswith("k" * checkpoint._KEY_CHARS)


@pytest.mark.parametrize(("count", "more"), [(20, False), (21, True)])
def test_gap_listings_show_twenty_layer_indices(count: int, more: bool) -> None:
    state = dict(make_reference().state_dict())  # depth 3: feature_net.0, .2, .4
    for index in [2 * i for i in range(3, count - 1)] + [2 * count]:  # a gap before the last
        state[f"feature_net.{index}.weight"] = torch.zeros(12, 12, dtype=torch.float64)
    with pytest.raises(StateDictMismatchError, match="layer indices") as info:
        DecoupledDeformation.from_official_state_dict(state)
    assert ("..." in str(info.value).split("layer indices")[1].split("]")[0]) == more
