"""Every exported tensor op against the shared contract of tests/helpers/op_contract.py:
documented output shapes, dtype and device follow the input, empty inputs, and bad inputs
rejected with an error that names the argument (DESIGN.md section 2, "Typing")."""

from __future__ import annotations

import dataclasses
import functools
import math

import pytest
import torch
from torch import Tensor

import dego
import dego.gaussians
import dego.metrics
import dego.splatting
import dego.teacher
from tests.helpers import triton
from tests.helpers.op_contract import (
    FLOATS,
    HALVES,
    BadInput,
    OpCase,
    bad_input_params,
    check_bad_input,
    check_device,
    check_dtype,
    check_empty,
    check_shapes,
    device_params,
    dtype_params,
    empty_params,
    shape_params,
    with_nan,
    with_value,
)

# -- input factories ------------------------------------------------------------------------


def _quats(dtype: torch.dtype, device: torch.device, *shape: int) -> Tensor:
    return torch.randn(*shape, 4, dtype=torch.float64).add(0.1).to(dtype=dtype, device=device)


def _scales(dtype: torch.dtype, device: torch.device, *shape: int) -> Tensor:
    return (0.1 + 0.3 * torch.rand(*shape, 3, dtype=torch.float64)).to(dtype=dtype, device=device)


def _gaussians(
    dtype: torch.dtype, device: torch.device, b: int, n: int, channels: int | None = None
) -> dego.GaussianSet:
    means = torch.rand(b, n, 3, dtype=torch.float64) * 1.6 - 0.8
    means[..., 2] += 4.0  # in front of the identity camera; inside the +-1 m grid below shifted
    return dego.GaussianSet(
        means=means.to(dtype=dtype, device=device),
        quats=_quats(dtype, device, b, n),
        scales=_scales(dtype, device, b, n),
        opacities=(0.2 + 0.6 * torch.rand(b, n, dtype=torch.float64)).to(
            device=device, dtype=dtype
        ),
        features=None
        if channels is None
        else torch.rand(b, n, channels, dtype=torch.float64).to(device=device, dtype=dtype),
    )


def _other_float(t: Tensor) -> Tensor:
    return t.to(torch.float64 if t.dtype != torch.float64 else torch.float32)


def _drop_last(t: Tensor) -> Tensor:
    return t[..., :-1]


H, W, V, C = 12, 16, 2, 4


def _cameras(dtype: torch.dtype, device: torch.device, b: int) -> dict[str, Tensor]:
    world_to_cam = torch.eye(4, dtype=dtype, device=device).repeat(b, V, 1, 1)
    world_to_cam[:, 1, 0, 3] = 0.2  # the second camera shifted
    k = torch.tensor([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]], dtype=dtype, device=device)
    return {"world_to_cam": world_to_cam, "intrinsics": k.repeat(b, V, 1, 1)}


GRID = dego.VoxelGrid((-1.0, -1.0, 3.0), (1.0, 1.0, 5.0), 0.5)  # (4, 4, 4)
LABEL_GRID = dego.VoxelGrid((-2.0, -2.0, -1.0), (2.0, 2.0, 1.0), 0.5)  # (8, 8, 4)


def _labels(device: torch.device) -> Tensor:
    labels = torch.full(LABEL_GRID.shape, dego.FREE_LABEL, dtype=torch.uint8)
    labels[0] = 4
    labels[-1] = 15
    labels[:, 0] = 1
    labels[:, -1] = 13
    return labels.to(device)


def _directions(dtype: torch.dtype, device: torch.device, n: int) -> Tensor:
    angle = torch.linspace(0, 2 * math.pi, n + 1, dtype=torch.float64)[:n]
    return torch.stack([angle.cos(), angle.sin(), 0.1 * angle.cos()], -1).to(
        device=device, dtype=dtype
    )


def _origins(dtype: torch.dtype, device: torch.device, n: int) -> Tensor:
    return (0.2 * torch.rand(n, 3, dtype=torch.float64) - 0.1).to(device=device, dtype=dtype)


def _deformation(dtype: torch.dtype, device: torch.device) -> dego.DecoupledDeformation:
    torch.manual_seed(0)
    module = dego.DecoupledDeformation(
        C, pos_levels=2, time_levels=2, time_dim=8, hidden_dim=16, depth=2, head_hidden=8
    )
    return module.to(dtype=dtype, device=device)


def _projection_inputs(dtype: torch.dtype, device: torch.device, n: int) -> dict:
    g = _gaussians(dtype, device, 1, n)
    return {
        "means": g.means,
        "quats": g.quats,
        "scales": g.scales,
        **_cameras(dtype, device, 1),
        "image_size": (H, W),
        "near": 0.01,
        "far": 1e10,
        "eps2d": 0.3,
        "opacities": g.opacities,
    }


def _pose(dtype: torch.dtype, device: torch.device, frames: int) -> Tensor:
    pose = torch.eye(4, dtype=torch.float64).repeat(frames, 1, 1)
    pose[:, 0, 3] = torch.arange(frames, dtype=torch.float64)
    return pose.to(device=device, dtype=dtype)


# -- the cases ------------------------------------------------------------------------------

quaternion_multiply = getattr(dego.gaussians, "quaternion_multiply")  # noqa: B009 (not in __all__)

CASES = [
    OpCase(
        "normalize_quaternions",
        dego.normalize_quaternions,
        lambda d, dev, n: {"quats": _quats(d, dev, 2, n)},
        lambda n: {"out": (2, n, 4)},
        dtypes=FLOATS + HALVES,
        bad=(BadInput("shape", "quats", with_value("quats", _drop_last)),),
    ),
    OpCase(
        "quaternions_to_rotation_matrices",
        dego.quaternions_to_rotation_matrices,
        lambda d, dev, n: {"quats": _quats(d, dev, n)},
        lambda n: {"out": (n, 3, 3)},
        bad=(
            BadInput("shape", "quats", with_value("quats", _drop_last)),
            BadInput("int-dtype", "quats", with_value("quats", lambda t: t.long())),
        ),
    ),
    OpCase(
        "build_covariances",
        dego.build_covariances,
        lambda d, dev, n: {"quats": _quats(d, dev, n), "scales": _scales(d, dev, n)},
        lambda n: {"out": (n, 3, 3)},
        bad=(
            BadInput("shape", "scales", with_value("scales", _drop_last)),
            BadInput("mixed-dtype", "scales", with_value("scales", _other_float)),
        ),
    ),
    OpCase(
        "build_precisions",
        dego.build_precisions,
        lambda d, dev, n: {"quats": _quats(d, dev, n), "scales": _scales(d, dev, n)},
        lambda n: {"out": (n, 3, 3)},
        bad=(
            BadInput("shape", "scales", with_value("scales", _drop_last)),
            BadInput("mixed-dtype", "scales", with_value("scales", _other_float)),
            BadInput("nan", "scales", with_nan("scales"), ValueError),
            BadInput("negative", "scales", with_value("scales", torch.neg), ValueError),
        ),
    ),
    OpCase(
        "quaternion_multiply",
        quaternion_multiply,
        lambda d, dev, n: {"a": _quats(d, dev, n), "b": _quats(d, dev, 1)},
        lambda n: {"out": (n, 4)},
        bad=(BadInput("shape", "b", with_value("b", _drop_last)),),
    ),
    OpCase(
        "rotation_matrices_to_quaternions",
        dego.rotation_matrices_to_quaternions,
        lambda d, dev, n: {"rotations": dego.quaternions_to_rotation_matrices(_quats(d, dev, n))},
        lambda n: {"out": (n, 4)},
        bad=(BadInput("shape", "rotations", with_value("rotations", _drop_last)),),
    ),
    OpCase(
        "positional_encoding",
        dego.positional_encoding,
        lambda d, dev, n: {"x": torch.rand(n, 3, dtype=d, device=dev), "num_levels": 4},
        lambda n: {"out": (n, 27)},
        dtypes=FLOATS + HALVES,
        bad=(
            BadInput("nan", "x", with_nan("x"), ValueError),
            BadInput("scalar", "x", with_value("x", lambda t: t.sum())),
        ),
    ),
    OpCase(
        "PositionalEncoding",
        lambda module, x: module(x),
        lambda d, dev, n: {
            "module": dego.PositionalEncoding(6),
            "x": torch.rand(2, n, 3, dtype=d, device=dev),
        },
        lambda n: {"out": (2, n, 39)},
        dtypes=FLOATS + HALVES,
        bad=(
            BadInput("nan", "x", with_nan("x"), ValueError),
            BadInput("int-dtype", "x", with_value("x", lambda t: t.long())),
        ),
    ),
    OpCase(
        "resize_crop_intrinsics",
        lambda **kw: dego.resize_crop_intrinsics(kw["intrinsics"], 0.5, (2, 1)),
        lambda d, dev, n: {"intrinsics": _cameras(d, dev, n)["intrinsics"]},
        lambda n: {"out": (n, V, 3, 3)},
        bad=(BadInput("shape", "intrinsics", with_value("intrinsics", _drop_last)),),
    ),
    OpCase(
        "split_projection",
        dego.split_projection,
        lambda d, dev, n: {
            "projection": (
                _cameras(d, dev, n)["intrinsics"] @ _cameras(d, dev, n)["world_to_cam"][..., :3, :]
            )
        },
        lambda n: {"0": (n, V, 4, 4), "1": (n, V, 3, 3)},
        bad=(
            BadInput("shape", "projection", with_value("projection", _drop_last)),
            BadInput("nan", "projection", with_nan("projection"), ValueError),
        ),
    ),
    OpCase(
        "apply_image_aug",
        dego.apply_image_aug,
        lambda d, dev, n: {
            "intrinsics": _cameras(d, dev, n)["intrinsics"],
            "post_rot": torch.eye(2, dtype=d, device=dev).mul(0.5).repeat(n, V, 1, 1),
            "post_tran": torch.full((n, V, 2), -3.0, dtype=d, device=dev),
        },
        lambda n: {"out": (n, V, 3, 3)},
        bad=(
            BadInput("shape", "post_tran", with_value("post_tran", lambda t: t[..., :1])),
            BadInput("mixed-dtype", "post_rot", with_value("post_rot", _other_float)),
            BadInput("nan", "post_tran", with_nan("post_tran"), ValueError),
        ),
    ),
    OpCase(
        "confusion_matrix",
        lambda **kw: dego.confusion_matrix(**kw, num_classes=18),
        lambda d, dev, n: {
            "pred": torch.randint(0, 18, (n, 5, 2), device=dev).to(d),
            "gt": torch.randint(0, 18, (n, 5, 2), device=dev).to(d),
            "mask": torch.rand(n, 5, 2, device=dev) > 0.3,
        },
        lambda n: {"out": (18, 18)},
        dtypes=(torch.uint8, torch.int64),
        fixed_dtypes={"out": torch.int64},
        bad=(
            BadInput("float-labels", "pred", with_value("pred", lambda t: t.float())),
            BadInput("out-of-range", "gt", with_value("gt", lambda t: t.fill_(18)), ValueError),
            BadInput("shape", "pred", with_value("pred", lambda t: t[:, :-1]), ValueError),
            BadInput("mask-shape", "mask", with_value("mask", lambda t: t[:, :-1]), ValueError),
            BadInput(
                "mask-uint8-2",
                "mask",
                with_value("mask", lambda t: t.to(torch.uint8) * 2),
                ValueError,
            ),
        ),
    ),
    OpCase(
        "per_class_iou",
        dego.per_class_iou,
        lambda d, dev, n: {"confusion": torch.randint(0, 9, (n, n), device=dev).to(d)},
        lambda n: {"out": (n,)},
        dtypes=(torch.int32, torch.int64),
        fixed_dtypes={"out": torch.float64},
        empty=False,
        bad=(
            BadInput("float", "confusion", with_value("confusion", lambda t: t.double())),
            BadInput("non-square", "confusion", with_value("confusion", _drop_last)),
        ),
    ),
    OpCase(
        "binary_occupancy_confusion",
        lambda **kw: dego.metrics.binary_occupancy_confusion(**kw),
        lambda d, dev, n: {
            "confusion": torch.randint(0, 9, (n + 1, n + 1), device=dev).to(d),
            "free_label": n,
        },
        lambda n: {"out": (2, 2)},
        dtypes=(torch.int64,),
        empty=False,
        bad=(
            BadInput(
                "free-label-out-of-range",
                "free_label",
                lambda kw: {**kw, "free_label": kw["confusion"].shape[0]},
                ValueError,
            ),
            BadInput(
                "float",
                "confusion",
                with_value("confusion", lambda t: t.double()),
            ),
        ),
    ),
    OpCase(
        "lidar_origins",
        lambda **kw: dego.lidar_origins(**kw, reference_index=0),
        lambda d, dev, n: {"ego2global": _pose(d, dev, n), "lidar2ego": _pose(d, dev, n)},
        lambda n: {"out": (n, 3)},
        fixed_dtypes={"out": torch.float64},
        empty=False,
        bad=(
            BadInput(
                "shape",
                "ego2global",
                with_value("ego2global", lambda t: t[:, :3, :3]),
                (TypeError, ValueError),
            ),
            BadInput(
                "nan",
                "ego2global",
                with_nan("ego2global", 3),
                ValueError,
            ),
        ),
    ),
    OpCase(
        "cast_rays",
        lambda **kw: dego.cast_rays(**kw, grid=LABEL_GRID),
        lambda d, dev, n: {
            "labels": _labels(dev),
            "origins": _origins(d, dev, n),
            "directions": _directions(d, dev, 5),
        },
        lambda n: {"0": (n * 5,), "1": (n * 5,)},
        dtypes=FLOATS + HALVES,
        fixed_dtypes={"1": torch.int64},
        bad=(
            BadInput("shape", "origins", with_value("origins", _drop_last)),
            BadInput("float-labels", "labels", with_value("labels", lambda t: t.float())),
            BadInput("grid-shape", "labels", with_value("labels", _drop_last), ValueError),
            BadInput("nan", "origins", with_nan("origins"), ValueError),
            BadInput(
                "zero-direction",
                "directions",
                with_value("directions", torch.zeros_like),
                ValueError,
            ),
        ),
    ),
    OpCase(
        "observed_voxels",
        lambda **kw: dego.observed_voxels(**kw, grid=LABEL_GRID),
        lambda d, dev, n: {
            "labels": _labels(dev),
            "origins": _origins(d, dev, n),
            "directions": _directions(d, dev, n),
        },
        lambda n: {"out": LABEL_GRID.shape},
        fixed_dtypes={"out": torch.bool},
        bad=(
            BadInput("paired", "directions", with_value("directions", lambda t: t[:-1])),
            BadInput("nan", "directions", with_nan("directions"), ValueError),
        ),
    ),
    OpCase(
        "distillation_loss",
        dego.distillation_loss,
        lambda d, dev, n: {
            "student": torch.randn(n, V, C, 3, 5, dtype=d, device=dev),
            "teacher": torch.randn(n, V, C, 3, 5, dtype=d, device=dev),
            "mask": torch.rand(n, V, 3, 5, device=dev) > 0.2,
        },
        lambda n: {"out": ()},
        dtypes=FLOATS + HALVES,
        bad=(
            BadInput("shape", "teacher", with_value("teacher", _drop_last)),
            BadInput("mixed-dtype", "teacher", with_value("teacher", _other_float)),
            BadInput(
                "mask-uint8-2",
                "mask",
                with_value("mask", lambda t: t.to(torch.uint8) * 2),
                ValueError,
            ),
            BadInput("mask-float", "mask", with_value("mask", lambda t: t.float())),
        ),
    ),
    OpCase(
        "cosine_distance_map",
        dego.teacher.cosine_distance_map,
        lambda d, dev, n: {
            "student": torch.randn(n, V, C, 3, 5, dtype=d, device=dev),
            "teacher": torch.randn(n, V, C, 3, 5, dtype=d, device=dev),
        },
        lambda n: {"out": (n, V, 3, 5)},
        dtypes=FLOATS + HALVES,
        bad=(
            BadInput("shape", "teacher", with_value("teacher", lambda t: t[:, :1])),
            BadInput("mixed-dtype", "teacher", with_value("teacher", _other_float)),
        ),
    ),
    OpCase(
        "splat",
        dego.splat,
        lambda d, dev, n: {
            "gaussians": _gaussians(d, dev, 2, n, C),
            **_cameras(d, dev, 2),
            "image_size": (H, W),
        },
        lambda n: {
            "features": (2, V, C, H, W),
            "depth": (2, V, H, W),
            "alpha": (2, V, H, W),
        },
        bad=(
            # camera matrices of the wrong size: one line with what to pass (ValueError, as
            # the other camera-layout errors)
            BadInput("shape", "world_to_cam", with_value("world_to_cam", _drop_last), ValueError),
            BadInput("mixed-dtype", "intrinsics", with_value("intrinsics", _other_float)),
            BadInput("nan-means", "gaussians.means", with_nan("gaussians.means"), ValueError),
            BadInput("nan-cameras", "world_to_cam", with_nan("world_to_cam"), ValueError),
            BadInput(
                "opacity-range",
                "gaussians.opacities",
                with_value("gaussians.opacities", lambda t: t + 2),
                ValueError,
            ),
            BadInput(
                "features-shape",
                "features",
                lambda kw: {**kw, "features": kw["gaussians"].features[:, :1]},
                (TypeError, ValueError),
            ),
        ),
    ),
    OpCase(
        "splat[B]",
        dego.splat,
        lambda d, dev, n: {
            "gaussians": _gaussians(d, dev, n, 3, C),
            **_cameras(d, dev, n),
            "image_size": (H, W),
        },
        lambda n: {"features": (n, V, C, H, W), "depth": (n, V, H, W), "alpha": (n, V, H, W)},
    ),
    OpCase(
        "project_gaussians",
        dego.splatting.project_gaussians,
        _projection_inputs,
        lambda n: {
            "means2d": (1, V, n, 2),
            "conics": (1, V, n, 3),
            "depths": (1, V, n),
            "radii": (1, V, n),
        },
        fixed_dtypes={"radii": torch.int32},
        xfail={},
        bad=(
            BadInput(
                "shape",
                "means",
                with_value("means", _drop_last),
            ),
            BadInput(
                "mixed-dtype",
                "intrinsics",
                with_value("intrinsics", _other_float),
            ),
        ),
    ),
    OpCase(
        "voxelize",
        lambda **kw: dego.voxelize(**kw, grid=GRID),
        lambda d, dev, n: {"gaussians": _gaussians(d, dev, 2, n, C)},
        lambda n: {"density": (2, *GRID.shape), "features": (2, *GRID.shape, C)},
        dtypes=FLOATS + HALVES,
        bad=(
            BadInput(
                "features-shape",
                "features",
                lambda kw: {**kw, "features": kw["gaussians"].features[:, :1]},
                (TypeError, ValueError),
            ),
            BadInput(
                "mixed-dtype",
                "features",
                lambda kw: {**kw, "features": _other_float(kw["gaussians"].features)},
            ),
            BadInput("nan-means", "means", with_nan("gaussians.means"), ValueError),
            BadInput(
                "negative-scales", "scales", with_value("gaussians.scales", torch.neg), ValueError
            ),
            BadInput(
                "opacity-range",
                "opacities",
                with_value("gaussians.opacities", lambda t: t + 2),
                ValueError,
            ),
        ),
    ),
    OpCase(
        "voxelize[B]",
        lambda **kw: dego.voxelize(**kw, grid=GRID),
        lambda d, dev, n: {"gaussians": _gaussians(d, dev, n, 3, C)},
        lambda n: {"density": (n, *GRID.shape), "features": (n, *GRID.shape, C)},
    ),
    OpCase(
        "DecoupledDeformation",
        lambda module, **kw: module(**kw),
        lambda d, dev, n: {
            "module": _deformation(d, dev),
            "gaussians": _gaussians(d, dev, 2, n),
            "features": torch.randn(2, n, C, dtype=d, device=dev),
            "times": torch.tensor([0.0, 0.5, 1.0], dtype=d, device=dev),
        },
        lambda n: {
            "gaussians.means": (2, 3, n, 3),
            "gaussians.quats": (2, 3, n, 4),
            "gaussians.scales": (2, 3, n, 3),
            "gaussians.opacities": (2, 3, n),
            "rigid_mask": (2, n),
            "deltas.means": (2, 3, n, 3),
            "rigid_offsets": (2, 3, n, 3),
        },
        bad=(
            BadInput("features-shape", "features", with_value("features", lambda t: t[..., 0])),
            BadInput(
                "features-channels", "features", with_value("features", _drop_last), ValueError
            ),
            BadInput(
                "mixed-dtype",
                "features",
                with_value("features", _other_float),
                (TypeError, ValueError),
            ),
            BadInput("nan-times", "times", with_nan("times"), ValueError),
            BadInput("nan-means", "gaussians.means", with_nan("gaussians.means"), ValueError),
        ),
    ),
]


CASES.append(
    OpCase(
        "DecoupledDeformation[B]",
        lambda module, **kw: module(**kw),
        lambda d, dev, n: {
            "module": _deformation(d, dev),
            "gaussians": _gaussians(d, dev, n, 3),
            "features": torch.randn(n, 3, C, dtype=d, device=dev),
            "times": torch.tensor([[0.0, 1.0]], dtype=d, device=dev).expand(n, 2),
        },
        lambda n: {"gaussians.means": (n, 2, 3, 3), "rigid_mask": (n, 3)},
    )
)


def _triton_skips() -> dict[str, str]:
    """Where ``backend="triton"`` cannot run: without triton nowhere, on the CPU only through
    Triton's interpreter (:mod:`tests.helpers.triton`)."""
    if not triton.INSTALLED:
        return {"*": triton.NOT_INSTALLED}
    reason = triton.why_not("cpu")
    return {} if reason is None else {"cpu": reason}


# The Triton backend keeps the torch path's contract: the same outputs, dtypes, devices,
# empty inputs and errors (the checks run before the backend is chosen, and must stay so).
CASES.extend(
    dataclasses.replace(
        case,
        name=case.name + "[triton]",
        fn=functools.partial(dego.splat, backend="triton"),
        skip=_triton_skips(),
    )
    for case in list(CASES)
    if case.fn is dego.splat
)


@pytest.mark.parametrize("case", shape_params(CASES))
def test_output_shapes(case: OpCase) -> None:
    check_shapes(case)


@pytest.mark.parametrize(("case", "dtype"), dtype_params(CASES))
def test_output_dtype_follows_input(case: OpCase, dtype: torch.dtype) -> None:
    check_dtype(case, dtype)


@pytest.mark.parametrize(("case", "device"), device_params(CASES))
def test_output_device_follows_input(case: OpCase, device: str) -> None:
    check_device(case, device)


@pytest.mark.parametrize("case", empty_params(CASES))
def test_empty_input(case: OpCase) -> None:
    check_empty(case)


@pytest.mark.parametrize(("case", "bad"), bad_input_params(CASES))
def test_bad_input_names_the_argument(case: OpCase, bad: BadInput) -> None:
    check_bad_input(case, bad)
