"""The preset table and update rules, the DeformationLoss result (and its deprecated dict
access), and the checkpoint key mapping kept free of the deformation module."""

from __future__ import annotations

import ast
import dataclasses
import warnings
from pathlib import Path

import pytest
import torch

import dego
from dego.deformation import (
    PARAMETERS,
    DecoupledDeformation,
    DeformationLoss,
    checkpoint,
    deformation_loss,
    presets,
    shift_opacity_logit,
)
from dego.deformation.presets import PRESETS, official_update, paper_update
from tests.helpers.deformation import (
    literal_output,
    make_inputs,
    make_module,
    randomize_last_layers,
    times_tensor,
)

PACKAGE = Path(dego.__file__).resolve().parent / "deformation"
DEFORMATION_MODULES = ("module", "checkpoint", "presets", "loss", "results")


def _imports(module: str) -> set[str]:
    """Every module that ``dego.deformation.<module>`` imports anywhere (lazy and
    TYPE_CHECKING too)."""
    tree = ast.parse((PACKAGE / f"{module}.py").read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, "relative import"
            names.add(node.module or "")
            names |= {f"{node.module}.{alias.name}" for alias in node.names}
    return names


# -- module structure ---------------------------------------------------------------------


def test_checkpoint_mapping_does_not_import_the_deformation_module() -> None:
    for module in ("checkpoint", "presets", "loss"):
        imported = _imports(module)
        assert not any(
            name == "dego.deformation" or name.startswith("dego.deformation.") for name in imported
        ), module
    text = (PACKAGE / "checkpoint.py").read_text()
    assert "from dego.deformation import" not in text and "TYPE_CHECKING" not in text


def test_no_import_cycle_among_the_deformation_modules() -> None:
    graph = {
        m: {
            other
            for other in DEFORMATION_MODULES
            if other != m
            and any(
                n == f"dego.deformation.{other}" or n.startswith(f"dego.deformation.{other}.")
                for n in _imports(m)
            )
        }
        for m in DEFORMATION_MODULES
    }
    assert graph["module"] == {"checkpoint", "presets", "loss", "results"}
    assert graph["results"] == {"presets", "loss"}
    assert graph["checkpoint"] == graph["presets"] == graph["loss"] == set()
    # none goes through the package's face, which imports them all
    assert not any("dego.deformation" in _imports(m) for m in DEFORMATION_MODULES)


def test_update_rules_are_written_once() -> None:
    """The clamps, the tanh bound and the quaternion composition appear in the presets
    module only."""
    text = (PACKAGE / "module.py").read_text()
    for fragment in ("quaternion_product", "unit_quaternions", "torch.tanh", ".clamp(-"):
        assert fragment not in text, fragment
    assert {spec.name for spec in PRESETS.values()} == set(PRESETS) == {"paper", "official"}
    assert PRESETS["paper"].update is paper_update
    assert PRESETS["official"].update is official_update
    with pytest.raises(TypeError):
        PRESETS["new"] = PRESETS["paper"]  # type: ignore[index]


@pytest.mark.parametrize("preset", list(PRESETS))
def test_the_module_applies_its_preset_rule(preset: str) -> None:
    module = make_module(preset, depth=2)
    randomize_last_layers(module, std=0.3)
    canonical, features = make_inputs(2, 5)
    spec = PRESETS[preset]
    assert module.spec is spec
    # the raw head outputs, recorded, then the rule applied to them alone
    recorded: dict[str, list[torch.Tensor]] = {}

    def keep(name: str):
        def hook(_module, _inputs, output) -> None:
            recorded.setdefault(name, []).append(output)

        return hook

    handles = [head.register_forward_hook(keep(name)) for name, head in module.heads.items()]
    try:
        out = module(canonical, features, times_tensor([0.5, 1.5]))
    finally:
        for handle in handles:
            handle.remove()
    raw = {name: torch.cat(parts, 2) for name, parts in recorded.items()}
    assert set(raw) == {name for name, _ in spec.heads}
    base = {name: getattr(canonical, name)[:, None] for name in PARAMETERS}
    deformed, deltas = spec.update(base, raw, out.rigid_mask)
    for name in PARAMETERS:
        assert torch.equal(deformed[name], getattr(out.gaussians, name)), name
        assert torch.equal(deltas[name], getattr(out.deltas, name)), name
    assert torch.equal(out.nonrigid_offsets, raw[spec.nonrigid_head])
    assert torch.equal(out.rigid_offsets, raw["rigid_offset"])


def test_zero_outputs_leave_the_canonical_set() -> None:
    canonical, _ = make_inputs(1, 4)
    base = {name: getattr(canonical, name)[:, None] for name in PARAMETERS}
    zeros = {
        name: torch.zeros(1, 2, 4, k, dtype=torch.float64)
        for name, k in [("rigid_offset", 3), ("nonrigid_offset", 3), ("scale", 3), ("opacity", 1)]
    }
    deformed, deltas = paper_update(
        base, {**zeros, "rotation": torch.zeros(1, 2, 4, 4).double()}, torch.rand(1, 4).double()
    )
    for name in PARAMETERS:
        assert torch.allclose(deformed[name], base[name].expand_as(deformed[name])), name
        assert not deltas[name].any(), name
    # official: m = 0 and zero offsets give the canonical set whatever the rotation head says
    deformed, deltas = official_update(
        base, {**zeros, "rotation": torch.randn(1, 2, 4, 4).double()}, torch.zeros(1, 2, 4).double()
    )
    for name in PARAMETERS:
        assert torch.equal(deformed[name], base[name].expand_as(deformed[name])), name


def test_update_rules_and_shift_are_type_checked() -> None:
    canonical, _ = make_inputs(1, 4)
    base = {name: getattr(canonical, name)[:, None] for name in PARAMETERS}
    with pytest.raises(TypeError, match="mask"):
        paper_update(base, {}, torch.zeros(1, 2, 4).double())  # the official (B, T, N) layout
    with pytest.raises(TypeError, match="mask"):
        official_update(base, {}, torch.zeros(1, 4).double())
    with pytest.raises(TypeError, match="opacity"):
        shift_opacity_logit(torch.zeros(3, dtype=torch.long), torch.zeros(3))
    assert shift_opacity_logit is presets.shift_opacity_logit


# -- DeformationLoss ------------------------------------------------------------------------


def test_deformation_loss_is_a_frozen_dataclass() -> None:
    loss = deformation_loss(literal_output("paper"))
    assert isinstance(loss, DeformationLoss)
    assert [f.name for f in dataclasses.fields(loss)] == ["reg", "mask", "total"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        loss.total = loss.reg  # type: ignore[misc]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the attribute form never warns
        as_dict = loss.to_dict()
        assert bool(loss)
    assert list(as_dict) == ["reg", "mask", "total"]
    assert all(as_dict[k] is getattr(loss, k) for k in as_dict)


def test_dict_access_still_works_and_warns() -> None:
    loss = deformation_loss(literal_output("official"))
    with pytest.warns(DeprecationWarning, match=r"loss\['total'\] is deprecated.*use loss\.total"):
        assert loss["total"] is loss.total
    with pytest.warns(DeprecationWarning, match=r"use loss\.reg") as record:
        assert loss.get("reg") is loss.reg
    assert record[0].filename == __file__  # the caller's line, not dego's
    with pytest.warns(DeprecationWarning, match="in loss"):
        assert "mask" in loss and "sparsity" not in loss
    with pytest.warns(DeprecationWarning, match="keys"):
        assert list(loss.keys()) == ["reg", "mask", "total"]
    with pytest.warns(DeprecationWarning, match="items"):
        assert dict(loss.items()) == loss.to_dict()
    with pytest.warns(DeprecationWarning, match="values"):
        assert loss.values() == [loss.reg, loss.mask, loss.total]
    with pytest.warns(DeprecationWarning) as record:  # list() also asks len() for a hint
        assert list(loss) == ["reg", "mask", "total"]
    assert any("iterating" in str(w.message) for w in record)
    with pytest.warns(DeprecationWarning, match="len"):
        assert len(loss) == 3
    with pytest.warns(DeprecationWarning):
        assert dict(loss) == loss.to_dict()
    with pytest.raises(KeyError, match="sparsity"):
        loss["sparsity"]
    with pytest.warns(DeprecationWarning):
        assert loss.get("sparsity", 0) == 0


# -- checkpoint mapping -----------------------------------------------------------------------


def test_key_mapping_round_trips_without_a_module() -> None:
    module = make_module("official", depth=3)
    ours = dict(module.named_parameters())
    official = checkpoint.official_tensors(ours, module.pos_levels, module.time_levels)
    assert list(official) == list(module.to_official_state_dict())
    back = checkpoint.from_official_tensors(official, module.input_static.in_features, depth=3)
    assert set(back) == set(ours)
    for name, value in back.items():
        assert torch.equal(value, ours[name]), name
    assert checkpoint.official_names(3)["feature_net.4.weight"] == "trunk.2.weight"


def test_checkpoint_warnings_point_at_the_caller() -> None:
    module = DecoupledDeformation(
        4, preset="official", hidden_dim=8, head_hidden=8, depth=2, time_dim=4, time_scale=2.0
    )
    with pytest.warns(UserWarning, match="time_scale=2.0") as record:
        state = module.to_official_state_dict()
    assert record[0].filename == __file__
    del state["feature_net.2.bias"]
    with pytest.warns(UserWarning, match="skipped keys") as record:
        DecoupledDeformation.from_official_state_dict(state, strict=False)
    assert record[0].filename == __file__
