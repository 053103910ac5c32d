"""Checkpoints: GaussianSet and the result dataclasses through ``torch.save`` /
``torch.load(weights_only=True)``, as objects and as plain ``to_dict`` dicts."""

from __future__ import annotations

import copy
import dataclasses
import io
import math
import subprocess
import sys
import textwrap
from collections.abc import Callable, Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from dego import (
    DecoupledDeformation,
    DeformationOutput,
    FactorizedSpatioTemporalTeacher,
    GaussianSet,
    OccupancyMetrics,
    OccupancyReport,
    RayIoU,
    RayIoUReport,
    SplatOutput,
    TeacherOutput,
    VoxelGrid,
    VoxelOutput,
    _safe_globals,
    splat,
    voxelize,
)
from tests.helpers.strategies import gaussian_sets, make_gaussian_set


def save_load(obj: Any) -> Any:
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    buffer.seek(0)
    return torch.load(buffer, weights_only=True)


def assert_same(a: Any, b: Any, where: str = "") -> None:
    """Equal values, dtypes and container types, recursively (NaN equals NaN)."""
    assert type(a) is type(b), (where, type(a), type(b))
    if isinstance(a, Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape, where
        assert torch.equal(a, b) or torch.allclose(a, b, rtol=0, atol=0, equal_nan=True), where
    elif dataclasses.is_dataclass(a):
        for field in dataclasses.fields(a):
            assert_same(getattr(a, field.name), getattr(b, field.name), f"{where}.{field.name}")
    elif isinstance(a, Mapping):
        assert list(a) == list(b), where
        for key in a:
            assert_same(a[key], b[key], f"{where}[{key!r}]")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and math.isnan(a):
        assert math.isnan(b), where
    else:
        assert a == b, where


# -- one real object of every class, cheap to build ----------------------------------------


def gaussians(dtype: torch.dtype, features: bool = True) -> GaussianSet:
    return make_gaussian_set((2,), 6, seed=1, feature_dim=3 if features else None, dtype=dtype)


def splat_output(dtype: torch.dtype) -> SplatOutput:
    gs = gaussians(dtype).replace(means=torch.rand(2, 6, 3, dtype=dtype) + torch.tensor([0, 0, 3]))
    w2c = torch.eye(4, dtype=dtype).expand(2, 1, 4, 4)
    k = torch.tensor([[8.0, 0, 6], [0, 8.0, 4], [0, 0, 1]], dtype=dtype).expand(2, 1, 3, 3)
    return splat(gs, w2c, k, (8, 12), features=gs.features)


def voxel_output(dtype: torch.dtype) -> VoxelOutput:
    grid = VoxelGrid(-50.0, 50.0, 25.0)
    return voxelize(gaussians(dtype), grid, features=gaussians(dtype).features)


def deformation_output(dtype: torch.dtype, preset: str = "paper") -> DeformationOutput:
    torch.manual_seed(0)
    module = DecoupledDeformation(3, hidden_dim=8, depth=2, head_hidden=8, preset=preset)
    gs = gaussians(dtype)
    return module.to(dtype)(
        gs, torch.randn(2, 6, 3, dtype=dtype), torch.tensor([0.0, 0.5], dtype=dtype)
    )


def teacher_output(dtype: torch.dtype) -> TeacherOutput:
    torch.manual_seed(0)
    teacher = FactorizedSpatioTemporalTeacher(16, depth=2, num_heads=2, patch_size=4)
    return teacher.to(dtype)(torch.rand(1, 2, 2, 3, 8, 4, dtype=dtype))


def occupancy_report(dtype: torch.dtype) -> OccupancyReport:
    g = torch.Generator().manual_seed(0)
    metrics = OccupancyMetrics("weak")
    metrics.update(
        torch.randint(0, 18, (2, 4, 4, 2), generator=g),
        torch.randint(0, 18, (2, 4, 4, 2), generator=g),
        None,  # every voxel
    )
    return metrics.compute()


def rayiou_report(dtype: torch.dtype) -> RayIoUReport:
    grid = VoxelGrid((0.0, 0.0, 0.0), (5.0, 5.0, 1.0), 1.0)
    rays = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])
    gt = torch.full((5, 5, 1), 17)
    gt[4, 2], gt[0, 2], gt[2, 4] = 4, 7, 4
    pred = gt.clone()
    pred[2, 0] = 3
    metric = RayIoU(grid=grid, rays=rays)
    metric.update(pred, gt, torch.tensor([[2.5, 2.5, 0.5]]))
    return metric.compute()


BUILDERS: dict[str, Callable[[torch.dtype], Any]] = {
    "GaussianSet": gaussians,
    "GaussianSet-no-features": lambda dtype: gaussians(dtype, features=False),
    "SplatOutput": splat_output,
    "VoxelOutput": voxel_output,
    "DeformationOutput": deformation_output,
    "DeformationOutput-official": lambda dtype: deformation_output(dtype, "official"),
    "DeformationDeltas": lambda dtype: deformation_output(dtype).deltas,
    "TeacherOutput": teacher_output,
    "OccupancyReport": occupancy_report,
    "RayIoUReport": rayiou_report,
}
DTYPES = [torch.float32, torch.float64]
needs_safe_globals = pytest.mark.skipif(
    not hasattr(torch.serialization, "add_safe_globals"),
    reason="torch < 2.4 cannot allowlist classes for weights_only loading",
)


@pytest.fixture(scope="module")
def objects() -> dict[tuple[str, torch.dtype], Any]:
    with torch.no_grad():
        return {(name, dtype): build(dtype) for name, build in BUILDERS.items() for dtype in DTYPES}


@needs_safe_globals
@pytest.mark.parametrize("dtype", DTYPES, ids=["float32", "float64"])
@pytest.mark.parametrize("name", BUILDERS)
def test_object_and_dict_round_trip_through_weights_only_load(
    objects: dict, name: str, dtype: torch.dtype
) -> None:
    obj = objects[name, dtype]
    assert_same(save_load(obj), obj)
    plain = save_load(obj.to_dict())
    assert_same(plain, obj.to_dict())  # the dict form is only plain values
    assert_same(type(obj).from_dict(plain), obj)
    assert_same(copy.deepcopy(obj), obj)


def test_float_tensors_keep_their_dtype(objects: dict) -> None:
    for (name, dtype), obj in objects.items():
        if name.startswith(("GaussianSet", "Splat", "Voxel", "Deformation", "Teacher")):
            floats = [t for t in _tensors(obj.to_dict()) if t.is_floating_point()]
            assert floats and all(t.dtype == dtype for t in floats), name


def _tensors(value: Any) -> list[Tensor]:
    if isinstance(value, Tensor):
        return [value]
    if isinstance(value, Mapping):
        return [t for v in value.values() for t in _tensors(v)]
    if isinstance(value, list | tuple):
        return [t for v in value for t in _tensors(v)]
    return []


def test_optional_and_nested_fields(objects: dict) -> None:
    assert "features" not in objects["GaussianSet-no-features", torch.float32].to_dict()
    out = objects["SplatOutput", torch.float32]
    assert set(out.to_dict()["projection"]) >= {"means2d", "conics", "radii_xy"}
    no_projection = dataclasses.replace(out, projection=None, depth=None)
    plain = no_projection.to_dict()
    assert "projection" not in plain and plain["depth"] is None  # depth has no default
    assert_same(SplatOutput.from_dict(save_load(plain)), no_projection)
    deformed = objects["DeformationOutput", torch.float64].to_dict()
    assert set(deformed["gaussians"]) == {"means", "quats", "scales", "opacities", "features"}
    assert deformed["preset"] == "paper" and isinstance(deformed["loss_weights"], dict)
    report = OccupancyReport.from_dict(
        save_load(objects["OccupancyReport", torch.float64].to_dict())
    )
    assert isinstance(report.groups, MappingProxyType) and isinstance(report.groups["hcm"], tuple)
    assert report.table() == objects["OccupancyReport", torch.float64].table()


@needs_safe_globals
def test_official_shared_offsets_stay_one_tensor(objects: dict) -> None:
    out = objects["DeformationOutput-official", torch.float32]
    assert out.nonrigid_offsets is out.rigid_offsets
    for loaded in (save_load(out), DeformationOutput.from_dict(save_load(out.to_dict()))):
        assert loaded.nonrigid_offsets is loaded.rigid_offsets


@needs_safe_globals
def test_checkpoint_dict_with_a_state_dict_and_gaussians() -> None:
    model = torch.nn.Linear(3, 2)
    gs = gaussians(torch.float32)
    checkpoint = {"model": model.state_dict(), "gaussians": gs, "plain": gs.to_dict(), "step": 7}
    loaded = save_load(checkpoint)
    restored = torch.nn.Linear(3, 2)
    restored.load_state_dict(loaded["model"])
    assert torch.equal(restored.weight, model.weight) and loaded["step"] == 7
    assert_same(loaded["gaussians"], gs)
    assert_same(GaussianSet.from_dict(loaded["plain"]), gs)


@needs_safe_globals
def test_tensors_that_require_grad_load_as_leaves_that_require_grad() -> None:
    means = torch.zeros(1, 4, 3, requires_grad=True)  # a leaf, e.g. an optimised parameter
    gs = gaussians(torch.float32).select([0, 1, 2, 3]).replace(means=means.expand(2, 4, 3) * 2)
    assert gs.means.grad_fn is not None  # not a leaf
    for loaded in (save_load(gs), GaussianSet.from_dict(save_load(gs.to_dict()))):
        assert loaded.means.requires_grad and loaded.means.is_leaf  # the graph is not saved
        assert not loaded.quats.requires_grad
        assert torch.equal(loaded.means, gs.means.detach())
    assert not save_load(gs.detach()).means.requires_grad
    parameter = torch.nn.Parameter(torch.ones(2, 4, 3))
    assert isinstance(save_load(gs.replace(means=parameter)).means, torch.nn.Parameter)


@settings(max_examples=30)
@given(gaussian_sets(max_n=6), st.sampled_from(DTYPES))
def test_gaussian_set_dict_round_trip(gs: GaussianSet, dtype: torch.dtype) -> None:
    gs = gs.to(dtype)
    plain = gs.to_dict()
    expected = {"means", "quats", "scales", "opacities"} | (
        {"features"} if gs.feature_dim else set()
    )
    assert set(plain) == expected
    assert all(plain[name] is getattr(gs, name) for name in plain)  # no copies
    assert_same(GaussianSet.from_dict(plain), gs)
    assert_same(GaussianSet.from_dict(save_load(plain)), gs)


@pytest.mark.slow
def test_dict_form_loads_without_dego(objects: dict, tmp_path: Path) -> None:
    path = tmp_path / "plain.pt"
    forms = {f"{name}-{dtype}": obj.to_dict() for (name, dtype), obj in objects.items()}
    torch.save(forms, path)
    script = textwrap.dedent(
        f"""
        import sys, torch
        forms = torch.load({str(path)!r}, weights_only=True)
        assert "dego" not in sys.modules, "dego was imported"
        print(len(forms), sorted(forms["GaussianSet-torch.float32"]))
        """
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.split()[0] == str(len(forms))


# -- bad input ----------------------------------------------------------------------------


def test_from_dict_rejects_missing_unknown_and_mistyped_keys(objects: dict) -> None:
    plain = gaussians(torch.float32).to_dict()
    with pytest.raises(ValueError, match=r"^scales: missing key"):
        GaussianSet.from_dict({k: v for k, v in plain.items() if k != "scales"})
    with pytest.raises(ValueError, match=r"^colors: unknown key"):
        GaussianSet.from_dict({**plain, "colors": plain["features"]})
    with pytest.raises(TypeError, match=r"^means: expected Float"):
        GaussianSet.from_dict({**plain, "means": plain["means"].tolist()})
    with pytest.raises(TypeError, match=r"^opacities: expected Float.*int64"):
        GaussianSet.from_dict({**plain, "opacities": plain["opacities"].long()})
    with pytest.raises(TypeError, match=r"^quats: expected Float\[Tensor, '\*batch N 4'\]"):
        GaussianSet.from_dict({**plain, "quats": plain["quats"][..., :3]})
    with pytest.raises(ValueError, match=r"^quats: expected shape"):  # the constructor's check
        GaussianSet.from_dict({**plain, "quats": plain["quats"][:, :2]})
    with pytest.raises(TypeError, match=r"^data: expected a dict"):
        GaussianSet.from_dict([plain])  # type: ignore[arg-type]


def test_from_dict_names_nested_keys(objects: dict) -> None:
    deformed = objects["DeformationOutput", torch.float32].to_dict()
    gs = dict(deformed["gaussians"])
    del gs["means"]
    with pytest.raises(ValueError, match=r"^gaussians\.means: missing key"):
        DeformationOutput.from_dict({**deformed, "gaussians": gs})
    with pytest.raises(TypeError, match=r"^preset: expected"):
        DeformationOutput.from_dict({**deformed, "preset": "nonrigid"})
    with pytest.raises(ValueError, match=r"^loss_weights: reg: expected a finite weight"):
        DeformationOutput.from_dict({**deformed, "loss_weights": {"reg": -1.0}})
    teacher = objects["TeacherOutput", torch.float32].to_dict()
    with pytest.raises(TypeError, match=r"^spatial\[1\]: expected Float"):
        TeacherOutput.from_dict({**teacher, "spatial": [teacher["spatial"][0], "x"]})
    with pytest.raises(TypeError, match=r"^patch_grid: expected 2 items, got 3"):
        TeacherOutput.from_dict({**teacher, "patch_grid": [1, 2, 3]})
    report = objects["RayIoUReport", torch.float32].to_dict()
    with pytest.raises(TypeError, match=r"^class_names\[0\]: expected str"):
        RayIoUReport.from_dict({**report, "class_names": [0, *report["class_names"][1:]]})


@needs_safe_globals
def test_a_corrupt_checkpoint_is_refused_on_load() -> None:
    gs = gaussians(torch.float32)
    for scales, error in [(gs.scales[:, :5], ValueError), (gs.scales[..., :2], TypeError)]:
        buffer = io.BytesIO()
        torch.save(GaussianSet._unchecked(**{**gs.to_dict(), "scales": scales}), buffer)
        buffer.seek(0)
        with pytest.raises(error, match=r"GaussianSet.*scales: expected"):
            torch.load(buffer, weights_only=True)


@needs_safe_globals
def test_only_dego_classes_are_allowlisted() -> None:
    """Each class's pickled name resolves to its stand-in (torch >= 2.5), which becomes the
    class only through its checked state; nothing else of dego's is allowlisted."""
    assert _safe_globals.register_safe_globals()
    allowed = torch.serialization.get_safe_globals()
    pairs = [e for e in allowed if isinstance(e, tuple) and e[1].startswith("dego.")]
    ours = [e for e in allowed if getattr(e, "__module__", "").startswith("dego")]
    assert not ours  # no class itself, no function
    targets = {stand_in.target() for stand_in, _ in pairs}
    assert targets == set(_safe_globals.safe_types())
    assert all(dataclasses.is_dataclass(target) for target in targets)
    for stand_in, name in pairs:
        assert issubclass(stand_in, _safe_globals._Unbuilt)
        assert name.rsplit(".", 1)[1] == stand_in.target().__qualname__
    # Named where they are defined: the name each class pickles under.
    pickled = {f"{cls.__module__}.{cls.__qualname__}" for cls in _safe_globals.safe_types()}
    assert pickled == set(_safe_globals._SAFE_NAMES)


def _with_pickle(payload: bytes) -> io.BytesIO:
    """A torch.save zip whose data.pkl is ``payload``."""
    import zipfile

    saved = io.BytesIO()
    torch.save(None, saved)
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(saved.getvalue())) as source, zipfile.ZipFile(out, "w") as z:
        for info in source.infolist():
            data = source.read(info.filename)
            z.writestr(info.filename, payload if info.filename.endswith("data.pkl") else data)
    out.seek(0)
    return out


@needs_safe_globals
@pytest.mark.parametrize("cls", _safe_globals.safe_types(), ids=lambda c: c.__name__)
def test_a_pickle_cannot_make_an_object_without_its_checked_state(cls: type) -> None:
    """Issue 38 (9): ``GLOBAL dego.gaussians GaussianSet; EMPTY_TUPLE; NEWOBJ; STOP`` loaded
    a GaussianSet with no fields (an AttributeError later)."""
    name = f"{cls.__module__}\n{cls.__qualname__}\n".encode()
    loaded = torch.load(_with_pickle(b"\x80\x02c" + name + b")\x81."), weights_only=True)
    assert not isinstance(loaded, cls)
    assert repr(loaded) == f"<{cls.__name__} that its pickle never built>"
    with pytest.raises(AttributeError, match=rf"^{cls.__name__}: the pickle made this object"):
        loaded.to_dict()


def test_checkpoints_naming_classes_where_they_lived_before_a_split_still_load() -> None:
    """Deformation results moved out of dego.deformation (one module then); old files name
    dego.deformation."""
    from dego import DeformationLossWeights

    weights = DeformationLossWeights(reg=0.5)
    moved = DeformationLossWeights.__module__
    DeformationLossWeights.__module__ = "dego.deformation"  # as saved before the split
    try:
        buffer = io.BytesIO()
        torch.save(weights, buffer)
    finally:
        DeformationLossWeights.__module__ = moved
    assert b"dego.deformation.loss" not in buffer.getvalue()  # only the name it had then
    buffer.seek(0)
    assert torch.load(buffer, weights_only=True) == weights


@needs_safe_globals
@pytest.mark.parametrize("former", ["dego.deformation", "dego.deformation_results"])
def test_deformation_checkpoints_saved_before_the_package_still_load(
    former: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """dego.deformation became a package (its classes in dego.deformation.results and
    .loss); files saved before name them in dego.deformation_results (or, older still,
    dego.deformation) and load with weights_only=True as equal objects."""
    import types

    from dego.deformation import DeformationDeltas, DeformationLoss, DeformationLossWeights

    output = deformation_output(torch.float64, "official")
    loss = DeformationLoss(torch.tensor(0.5), torch.tensor(0.25), torch.tensor(0.75))
    saved: dict[str, Any] = {"output": output}
    classes: list[type] = [DeformationOutput, DeformationDeltas, DeformationLossWeights]
    if former == "dego.deformation_results":  # DeformationLoss was never saved in the other
        saved["loss"] = loss
        classes.append(DeformationLoss)
    # as saved before the move: pickle names each class by __module__, and checks that
    # importing it finds the class (dego.deformation_results no longer exists)
    old_module = types.ModuleType(former)
    for cls in classes:
        monkeypatch.setattr(cls, "__module__", former)
        setattr(old_module, cls.__qualname__, cls)
    if former not in sys.modules:
        monkeypatch.setitem(sys.modules, former, old_module)
    buffer = io.BytesIO()
    torch.save(saved, buffer)
    monkeypatch.undo()
    pickled = buffer.getvalue()
    for cls in classes:
        assert f"{former}\n{cls.__qualname__}\n".encode() in pickled, cls
    assert b"dego.deformation.results" not in pickled and b"dego.deformation.loss" not in pickled
    buffer.seek(0)
    loaded = torch.load(buffer, weights_only=True)
    assert type(loaded["output"]) is DeformationOutput
    assert_same(loaded["output"], output)
    assert loaded["output"].nonrigid_offsets is loaded["output"].rigid_offsets  # still shared
    if "loss" in saved:
        assert type(loaded["loss"]) is DeformationLoss
        terms = ("reg", "mask", "total")
        assert all(torch.equal(getattr(loaded["loss"], t), getattr(loss, t)) for t in terms)


@needs_safe_globals
def test_grids_and_deformation_losses_load_with_weights_only() -> None:
    """Issue 41 (8): VoxelGrid and DeformationLoss load like the other dataclasses; a
    pickled grid whose state breaks the constructor's checks is refused by them."""
    from dego import VoxelGrid
    from dego.deformation import DeformationLoss

    grid = VoxelGrid(lower=(-2.0, -1.0, 0.0), upper=(2.0, 1.0, 1.0), voxel_size=0.25)
    assert save_load(grid) == grid
    loss = DeformationLoss(torch.tensor(0.5), torch.tensor(0.25), torch.tensor(0.75))
    loaded = save_load(loss)
    assert isinstance(loaded, DeformationLoss)
    assert all(torch.equal(getattr(loaded, f), getattr(loss, f)) for f in ("reg", "mask", "total"))
    object.__setattr__(grid, "upper", (-3.0, 1.0, 1.0))  # upper below lower on x
    with pytest.raises(ValueError, match="upper"):
        save_load(grid)
