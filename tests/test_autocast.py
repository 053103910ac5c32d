"""dego under torch.autocast (CPU bfloat16 and float16): every op runs, the geometry is
computed and returned in float32, learned layers run in the autocast dtype, gradients flow,
and bad input still gets the eager errors."""

from __future__ import annotations

import pytest
import torch

from dego import splat, voxelize
from tests.helpers import triton
from tests.helpers.compile_step import (
    GRID,
    HEIGHT,
    WIDTH,
    adapter,
    deform,
    gaussian_set,
    make_inputs,
    make_modules,
    render,
    targets,
    training_step,
)
from tests.helpers.op_contract import CUDA

HALF = [torch.bfloat16, torch.float16]


@pytest.mark.parametrize(
    ("dtype", "device", "backend"),
    [
        pytest.param(torch.bfloat16, "cpu", "torch", id="bfloat16"),
        pytest.param(torch.float16, "cpu", "torch", id="float16"),
        pytest.param(torch.bfloat16, "cuda", "torch", marks=CUDA, id="cuda-bf16"),
        pytest.param(
            torch.bfloat16, "cuda", "triton", marks=triton.on("cuda"), id="cuda-bf16-triton"
        ),
    ],
)
def test_the_training_step_runs_under_autocast_with_gradients(
    dtype: torch.dtype, device: str, backend: str
) -> None:
    inputs = make_inputs(device=device, backend=backend)
    modules = make_modules(device=device)
    with torch.autocast(device, dtype=dtype):
        loss, values = training_step(inputs, modules)
    loss.backward()
    assert loss.dtype == torch.float32 and torch.isfinite(loss)
    for grad in (inputs.means.grad, inputs.features.grad):
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0
    assert values["rendered"].dtype == torch.float32
    assert values["density"].dtype == torch.float32
    assert values["teacher"].dtype == dtype  # the teacher's layers run in the autocast dtype


@pytest.mark.parametrize("dtype", HALF, ids=["bfloat16", "float16"])
def test_geometry_is_computed_in_float32_under_autocast(dtype: torch.dtype) -> None:
    inputs = make_inputs(n=80)
    gaussians = gaussian_set(inputs)
    eager = (render(gaussians, inputs), voxelize(gaussians, GRID).density)
    eager_adapter = adapter(gaussians, inputs)
    with torch.autocast("cpu", dtype=dtype):
        mixed = (render(gaussians, inputs), voxelize(gaussians, GRID).density)
        mixed_adapter = adapter(gaussians, inputs)
    for a, b in zip(eager, mixed, strict=True):
        assert b.dtype == torch.float32
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    torch.testing.assert_close(eager_adapter, mixed_adapter, rtol=0, atol=0)


def test_the_deformation_runs_its_layers_in_bfloat16_and_returns_float32() -> None:
    inputs, modules = make_inputs(n=80), make_modules()
    gaussians = gaussian_set(inputs)
    reference = deform(gaussians, modules)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = deform(gaussians, modules)
    for name in ("means", "quats", "scales", "opacities"):
        value = getattr(mixed.gaussians, name)
        assert value.dtype == torch.float32, name
        offsets = getattr(reference.gaussians, name) - getattr(gaussians, name).unsqueeze(1)
        error = (value - getattr(reference.gaussians, name)).abs().max()
        assert error <= 0.05 * offsets.abs().max() + 1e-6, name  # bf16 layers: ~1% error
    assert mixed.rigid_mask.dtype == torch.float32
    assert not torch.equal(mixed.gaussians.means, reference.gaussians.means)  # it did run bf16


def test_mixed_half_and_float32_inputs_are_accepted_under_autocast() -> None:
    # A network under autocast hands bf16 features to float32 Gaussians: splat casts them.
    inputs = make_inputs(n=40)
    gaussians = gaussian_set(inputs)
    features = inputs.features.detach().to(torch.bfloat16).requires_grad_(True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = splat(
            gaussians, inputs.world_to_cam, inputs.intrinsics, (HEIGHT, WIDTH), features=features
        )
    out.features.sum().backward()
    assert out.features.dtype == torch.float32
    assert features.grad is not None and features.grad.dtype == torch.bfloat16
    with pytest.raises(TypeError, match=r"features: dtype torch\.bfloat16"):
        splat(gaussians, inputs.world_to_cam, inputs.intrinsics, (HEIGHT, WIDTH), features=features)


@pytest.mark.parametrize("dtype", HALF)
def test_a_gaussian_set_takes_a_networks_features_under_autocast(dtype: torch.dtype) -> None:
    # docs/training.md's pattern: GaussianSet(..., features=net(x)) inside autocast
    inputs = make_inputs(n=40)
    net = torch.nn.Linear(3, inputs.features.shape[-1])
    with torch.autocast("cpu", dtype=dtype):
        features = net(inputs.means.detach())
        assert features.dtype == dtype
        gaussians = gaussian_set(inputs).replace(features=features)
        assert gaussians.dtype == torch.float32  # the geometry's dtype
        out = splat(gaussians, inputs.world_to_cam, inputs.intrinsics, (HEIGHT, WIDTH))
        voxels = voxelize(gaussians, GRID)
    assert out.features.dtype == voxels.features.dtype == torch.float32
    (out.features.sum() + voxels.features.sum()).backward()
    assert net.weight.grad is not None and bool(net.weight.grad.abs().sum() > 0)
    # outside autocast one floating dtype per set, and the message says when it is allowed
    with pytest.raises(TypeError, match=r"features: dtype .* accepted under torch\.autocast"):
        gaussian_set(inputs).replace(features=features.detach())
    with torch.autocast("cpu", dtype=dtype), pytest.raises(TypeError, match="quats: dtype"):
        gaussian_set(inputs).replace(quats=inputs.quats.to(dtype))  # geometry stays float32


def test_bad_input_under_autocast_gets_the_eager_errors() -> None:
    inputs = make_inputs(n=20)
    gaussians = gaussian_set(inputs)
    bad = inputs.means.detach().clone()
    bad[0, 0, 0] = float("inf")
    with torch.autocast("cpu", dtype=torch.bfloat16):
        with pytest.raises(ValueError, match=r"world_to_cam: expected shape \(B, V, 4, 4\)"):
            splat(gaussians, inputs.world_to_cam[..., :3, :], inputs.intrinsics, (HEIGHT, WIDTH))
        with pytest.raises(ValueError, match="means: 1 of 60 values are not finite"):
            voxelize(gaussians.replace(means=bad), GRID)


def test_teacher_targets_follow_the_autocast_dtype() -> None:
    inputs, modules = make_inputs(), make_modules()
    reference = targets(inputs, modules)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = targets(inputs, modules)
    assert mixed.dtype == torch.bfloat16
    error = (mixed.float() - reference).abs().max() / reference.abs().max()
    assert error < 0.05
