"""distillation_loss and StudentProjector: analytic values, invariances, masks, gradients, errors."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from jaxtyping import TypeCheckError

from dego.teacher.loss import DistillationLoss, cosine_distance_map, distillation_loss
from dego.teacher.student import StudentProjector


def _maps(*shape: int, dtype: torch.dtype = torch.float64, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, generator=generator, dtype=dtype)


# -- analytic cases -------------------------------------------------------------------
def test_identical_orthogonal_opposite(dtype: torch.dtype, device: torch.device) -> None:
    x = _maps(2, 3, 4, 5, 6, dtype=dtype).to(device)
    tol = {"rtol": 0, "atol": 1e-6 if dtype == torch.float32 else 1e-14}
    zero = torch.zeros((), dtype=dtype, device=device)
    torch.testing.assert_close(distillation_loss(x, x), zero, **tol)
    torch.testing.assert_close(distillation_loss(x, -x), zero + 2, **tol)
    # e_0 vs e_1 at every pixel: orthogonal.
    a = torch.zeros(1, 2, 3, 4, 5, dtype=dtype, device=device)
    b = torch.zeros_like(a)
    a[:, :, 0] = 1.0
    b[:, :, 1] = 3.0
    torch.testing.assert_close(distillation_loss(a, b), zero + 1, **tol)
    out = distillation_loss(a, b)
    assert out.shape == () and out.dtype == dtype and out.device.type == device.type


def test_hand_computed_mean_of_mixed_pixels() -> None:
    # Two pixels with 1 - cos = 0 and 1 - cos(60 degrees) = 0.5, one opposite pixel (2).
    s = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    t = torch.tensor([[2.0, 0.0], [0.5, 0.75**0.5], [0.0, -1.0]], dtype=torch.float64)
    student = s.T.reshape(1, 1, 2, 1, 3)
    teacher = t.T.reshape(1, 1, 2, 1, 3)
    expected = torch.tensor([0.0, 0.5, 2.0], dtype=torch.float64)
    torch.testing.assert_close(
        cosine_distance_map(student, teacher).flatten(), expected, rtol=0, atol=1e-15
    )
    torch.testing.assert_close(
        distillation_loss(student, teacher), expected.mean(), rtol=0, atol=1e-15
    )


def test_zero_vectors_give_cosine_zero_and_finite_gradients() -> None:
    student = torch.zeros(1, 1, 3, 2, 2, dtype=torch.float64, requires_grad=True)
    teacher = _maps(1, 1, 3, 2, 2)
    loss = distillation_loss(student, teacher)
    assert loss.item() == 1.0
    loss.backward()
    assert student.grad is not None and torch.isfinite(student.grad).all()
    both_zero = distillation_loss(torch.zeros(1, 1, 3, 2, 2), torch.zeros(1, 1, 3, 2, 2))
    assert float(both_zero) == 1.0


@given(
    st.integers(0, 2**31 - 1),
    st.floats(-3.0, 3.0),
    st.booleans(),
)
def test_invariant_to_positive_per_pixel_scaling(
    seed: int, log_scale: float, on_teacher: bool
) -> None:
    student = _maps(2, 2, 4, 3, 3, seed=seed)
    teacher = _maps(2, 2, 4, 3, 3, seed=seed + 1)
    generator = torch.Generator().manual_seed(seed)
    # Per-pixel positive factors spanning 10^-3 .. 10^3 around exp(log_scale).
    factors = torch.exp(
        log_scale + 3 * torch.rand(2, 2, 1, 3, 3, generator=generator, dtype=torch.float64)
    )
    scaled = (student, teacher * factors) if on_teacher else (student * factors, teacher)
    torch.testing.assert_close(
        distillation_loss(*scaled), distillation_loss(student, teacher), rtol=0, atol=1e-12
    )


# -- masks ----------------------------------------------------------------------------
def test_masked_out_pixels_do_not_matter_and_mean_is_over_valid(
    dtype: torch.dtype, device: torch.device
) -> None:
    student = _maps(2, 3, 4, 5, 6, dtype=dtype).to(device)
    teacher = _maps(2, 3, 4, 5, 6, dtype=dtype, seed=1).to(device)
    mask = _maps(2, 3, 5, 6, seed=2).to(device) > 0.3
    loss = distillation_loss(student, teacher, mask)
    # Changing the masked-out pixels arbitrarily changes nothing.
    noise = 100 * _maps(2, 3, 4, 5, 6, dtype=dtype, seed=3).to(device)
    other = torch.where(mask.unsqueeze(2), teacher, noise)
    torch.testing.assert_close(distillation_loss(student, other, mask), loss)
    # Hand computation: 1 - cos at the valid pixels, averaged over their number.
    s = student.movedim(2, -1)[mask]
    t = teacher.movedim(2, -1)[mask]
    cos = (s * t).sum(-1) / (s.norm(dim=-1) * t.norm(dim=-1))
    torch.testing.assert_close(loss, (1 - cos).sum() / mask.sum())
    # A uint8 0/1 mask means the same as the bool mask; an all-True mask is the plain mean.
    torch.testing.assert_close(distillation_loss(student, teacher, mask.to(torch.uint8)), loss)
    torch.testing.assert_close(
        distillation_loss(student, teacher, torch.ones_like(mask)),
        distillation_loss(student, teacher),
    )


def test_masked_out_nonfinite_pixels_do_not_leak() -> None:
    student = _maps(1, 1, 2, 2, 2)
    teacher = _maps(1, 1, 2, 2, 2, seed=1)
    mask = torch.tensor([[[[True, False], [True, True]]]])
    expected = distillation_loss(student, teacher, mask)
    teacher[0, 0, :, 0, 1] = float("inf")
    assert torch.equal(distillation_loss(student, teacher, mask), expected)


def test_all_false_mask_gives_exact_zero_and_zero_gradient(device: torch.device) -> None:
    student = _maps(1, 2, 3, 4, 4).to(device).requires_grad_(True)
    teacher = _maps(1, 2, 3, 4, 4, seed=1).to(device).requires_grad_(True)
    mask = torch.zeros(1, 2, 4, 4, dtype=torch.bool, device=device)
    loss = distillation_loss(student, teacher, mask)
    assert loss.item() == 0.0
    loss.backward()
    for grad in (student.grad, teacher.grad):
        assert grad is not None and torch.equal(grad, torch.zeros_like(grad))


def test_empty_maps_give_zero() -> None:
    empty = torch.zeros(1, 2, 3, 0, 4)
    assert float(distillation_loss(empty, empty)) == 0.0


# -- gradients ------------------------------------------------------------------------
def test_gradcheck_with_and_without_mask() -> None:
    student = _maps(1, 2, 3, 2, 3).requires_grad_(True)
    teacher = _maps(1, 2, 3, 2, 3, seed=1).requires_grad_(True)
    mask = torch.tensor([[[[True, False, True], [False, True, True]]] * 2]).reshape(1, 2, 2, 3)
    assert torch.autograd.gradcheck(distillation_loss, (student, teacher))
    assert torch.autograd.gradcheck(lambda s, t: distillation_loss(s, t, mask), (student, teacher))


def test_module_wrapper_matches_function() -> None:
    student = _maps(1, 2, 3, 2, 3)
    teacher = _maps(1, 2, 3, 2, 3, seed=1)
    module = DistillationLoss(eps=1e-6)
    assert torch.equal(module(student, teacher), distillation_loss(student, teacher, eps=1e-6))
    assert "eps=1e-06" in repr(module)
    assert len(module.state_dict()) == 0


# -- bad inputs -----------------------------------------------------------------------
def test_bad_inputs() -> None:
    s = torch.randn(2, 3, 4, 5, 6)
    t = torch.randn(2, 3, 4, 5, 6)
    with pytest.raises(TypeCheckError, match="parameter 'teacher'"):
        distillation_loss(s, t[:, :2])
    with pytest.raises(TypeCheckError, match="parameter 'teacher'"):
        distillation_loss(s, t[..., :5])
    with pytest.raises(TypeCheckError, match="parameter 'student'"):
        distillation_loss(s[0], t)
    with pytest.raises(TypeCheckError, match="parameter 'student'"):
        distillation_loss(s.long(), t)
    with pytest.raises(TypeError, match=r"teacher: dtype torch.float64"):
        distillation_loss(s, t.double())
    with pytest.raises(TypeCheckError, match="parameter 'mask'"):
        distillation_loss(s, t, torch.ones(2, 3, 5, 5, dtype=torch.bool))
    with pytest.raises(TypeCheckError, match="parameter 'mask'"):
        distillation_loss(s, t, torch.ones(2, 3, 5, 6))
    with pytest.raises(ValueError, match="mask: a uint8 mask must hold only 0 and 1, found 2"):
        distillation_loss(s, t, torch.full((2, 3, 5, 6), 2, dtype=torch.uint8))
    with pytest.raises(ValueError, match="student: expected at least one feature channel"):
        distillation_loss(s[:, :, :0], t[:, :, :0])
    for eps in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="eps: expected a float > 0"):
            distillation_loss(s, t, eps=eps)
    with pytest.raises(TypeCheckError, match="parameter 'eps'"):
        distillation_loss(s, t, eps=True)
    with pytest.raises(ValueError, match="eps"):
        DistillationLoss(eps=0.0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
def test_device_mismatch() -> None:
    s = torch.randn(1, 1, 2, 2, 2)
    with pytest.raises(ValueError, match="teacher: on device"):
        distillation_loss(s, s.cuda())
    with pytest.raises(ValueError, match="mask: on device"):
        distillation_loss(s, s, torch.ones(1, 1, 2, 2, dtype=torch.bool, device="cuda"))


# -- StudentProjector -----------------------------------------------------------------
def test_projector_shapes_and_layers(dtype: torch.dtype, device: torch.device) -> None:
    linear = StudentProjector(16).to(device=device, dtype=dtype)
    x = torch.randn(2, 7, 16, dtype=dtype, device=device)
    out = linear(x)
    assert out.shape == (2, 7, 32) and out.dtype == dtype and out.device.type == device.type
    assert isinstance(linear.net, torch.nn.Linear)
    assert linear(torch.randn(3, 2, 5, 16, dtype=dtype, device=device)).shape == (3, 2, 5, 32)
    assert linear(torch.randn(16, dtype=dtype, device=device)).shape == (32,)
    mlp = StudentProjector(16, 8, hidden_dim=24).to(device=device, dtype=dtype)
    assert mlp(x).shape == (2, 7, 8)
    layers = list(mlp.net)
    assert [type(m) for m in layers] == [torch.nn.Linear, torch.nn.LeakyReLU, torch.nn.Linear]
    assert (layers[0].in_features, layers[0].out_features, layers[2].out_features) == (16, 24, 8)
    assert "hidden_dim=24" in repr(mlp)


def test_projector_is_differentiable_and_matches_linear() -> None:
    proj = StudentProjector(4, 3).double()
    x = torch.randn(5, 4, dtype=torch.float64, requires_grad=True)
    torch.testing.assert_close(proj(x), x @ proj.net.weight.T + proj.net.bias)
    assert torch.autograd.gradcheck(proj, (x,))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"in_dim": 0}, "in_dim: expected an int >= 1"),
        ({"in_dim": 4.0}, "in_dim: expected an int >= 1"),
        ({"in_dim": True}, "in_dim: expected an int >= 1"),
        ({"in_dim": 4, "out_dim": 0}, "out_dim: expected an int >= 1"),
        ({"in_dim": 4, "hidden_dim": -2}, "hidden_dim: expected an int >= 1"),
        ({"in_dim": 4, "hidden_dim": 8, "negative_slope": "x"}, "negative_slope"),
    ],
)
def test_projector_bad_configuration(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        StudentProjector(**kwargs)


def test_projector_bad_input() -> None:
    proj = StudentProjector(4)
    with pytest.raises(ValueError, match=r"features: expected 4 channels.*\(2, 3\)"):
        proj(torch.randn(2, 3))
    with pytest.raises(TypeError, match=r"features: dtype torch.float64"):
        proj(torch.randn(2, 4, dtype=torch.float64))
    with pytest.raises(TypeCheckError, match="parameter 'features'"):
        proj(torch.ones(2, 4, dtype=torch.long))


# -- NaN containment, empty masks, dtypes (issue 17) ----------------------------------
_BAD = st.sampled_from([float("nan"), float("inf"), float("-inf")])


def _loss_and_grads(
    student: torch.Tensor, teacher: torch.Tensor, mask: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    s = student.detach().clone().requires_grad_(True)
    t = teacher.detach().clone().requires_grad_(True)
    loss = distillation_loss(s, t, mask)
    loss.backward()
    assert s.grad is not None and t.grad is not None
    return loss.detach(), s.grad, t.grad


@given(
    shape=st.tuples(
        st.integers(1, 2),
        st.integers(1, 2),
        st.integers(1, 4),
        st.integers(1, 3),
        st.integers(1, 3),
    ),
    seed=st.integers(0, 2**31 - 1),
    valid_fraction=st.floats(0.0, 1.0),
    bad=_BAD,
    where=st.sampled_from(["student", "teacher", "both"]),
    uint8=st.booleans(),
)
def test_nonfinite_values_in_masked_out_pixels_change_neither_loss_nor_gradients(
    shape: tuple[int, ...], seed: int, valid_fraction: float, bad: float, where: str, uint8: bool
) -> None:
    b, v, _, h, w = shape
    student, teacher = _maps(*shape, seed=seed), _maps(*shape, seed=seed + 1)
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(b, v, h, w, generator=g, dtype=torch.float64) < valid_fraction
    # Poison a random subset of the channels of every masked-out pixel.
    plant = (torch.rand(*shape, generator=g) < 0.5) & ~mask.unsqueeze(2)
    poisoned_s = torch.where(plant, bad, student) if where != "teacher" else student
    poisoned_t = torch.where(plant, bad, teacher) if where != "student" else teacher
    m = mask.to(torch.uint8) if uint8 else mask
    clean = _loss_and_grads(student, teacher, m)
    dirty = _loss_and_grads(poisoned_s, poisoned_t, m)
    for expected, got in zip(clean, dirty, strict=True):
        assert torch.equal(got, expected)
    assert torch.isfinite(dirty[0])
    # Masked-out pixels receive exactly zero gradient.
    for grad in dirty[1:]:
        assert torch.equal(grad * ~mask.unsqueeze(2), torch.zeros_like(grad))
    if not mask.any():
        assert dirty[0].item() == 0.0


@given(seed=st.integers(0, 2**31 - 1), bad=_BAD)
def test_all_masked_out_poisoned_batch_is_zero_with_zero_gradient(seed: int, bad: float) -> None:
    student = torch.full((1, 2, 3, 2, 2), bad, dtype=torch.float64)
    teacher = _maps(1, 2, 3, 2, 2, seed=seed)
    teacher[0, 1] = bad
    loss, gs, gt = _loss_and_grads(student, teacher, torch.zeros(1, 2, 2, 2, dtype=torch.bool))
    assert loss.item() == 0.0
    assert torch.equal(gs, torch.zeros_like(gs)) and torch.equal(gt, torch.zeros_like(gt))


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
@pytest.mark.parametrize("masked", [False, True])
def test_nonfinite_values_in_valid_pixels_propagate(bad: float, masked: bool) -> None:
    student, teacher = _maps(1, 1, 3, 2, 2), _maps(1, 1, 3, 2, 2, seed=1)
    student[0, 0, 1, 0, 0] = bad
    mask = torch.ones(1, 1, 2, 2, dtype=torch.bool) if masked else None
    loss, grad, _ = _loss_and_grads(student, teacher, mask)
    assert torch.isnan(loss)
    assert not torch.isfinite(grad).all()


@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([1e-3, 1.0, 300.0, 3e4]))
def test_half_inputs_are_computed_in_float32(half: torch.dtype, seed: int, scale: float) -> None:
    # |x| = 300: x^2 overflows float16 (65504), so a native float16 norm would give inf.
    student = (scale * _maps(2, 2, 8, 3, 3, seed=seed)).clamp(-6e4, 6e4).to(half)
    teacher = (scale * _maps(2, 2, 8, 3, 3, seed=seed + 1)).clamp(-6e4, 6e4).to(half)
    mask = _maps(2, 2, 3, 3, seed=seed + 2) > 0
    for m in (None, mask):
        loss = distillation_loss(student, teacher, m)
        assert loss.dtype == half and torch.isfinite(loss)
        reference = distillation_loss(student.float(), teacher.float(), m)
        torch.testing.assert_close(loss.float(), reference.to(half).float(), rtol=0, atol=0)
    distance = cosine_distance_map(student, teacher)
    assert distance.dtype == half
    torch.testing.assert_close(
        distance, cosine_distance_map(student.float(), teacher.float()).to(half), rtol=0, atol=0
    )


@pytest.mark.parametrize(
    ("student_dtype", "teacher_dtype"),
    [
        (torch.float32, torch.float64),
        (torch.float16, torch.float32),
        (torch.bfloat16, torch.float16),
        (torch.float64, torch.bfloat16),
    ],
)
def test_mixed_dtypes_are_a_type_error_naming_teacher(
    student_dtype: torch.dtype, teacher_dtype: torch.dtype
) -> None:
    s = torch.randn(1, 1, 2, 2, 2, dtype=student_dtype)
    t = torch.randn(1, 1, 2, 2, 2, dtype=teacher_dtype)
    message = rf"teacher: dtype {teacher_dtype} differs from student's {student_dtype}"
    for call in (distillation_loss, cosine_distance_map, DistillationLoss()):
        with pytest.raises(TypeError, match=message):
            call(s, t)


@pytest.mark.parametrize("b, v, h, w", [(0, 2, 3, 3), (1, 0, 3, 3), (1, 2, 0, 3), (2, 1, 3, 0)])
def test_empty_axes_give_zero_with_zero_gradient(b: int, v: int, h: int, w: int) -> None:
    student, teacher = _maps(b, v, 4, h, w), _maps(b, v, 4, h, w, seed=1)
    for mask in (None, torch.ones(b, v, h, w, dtype=torch.bool)):
        loss, gs, gt = _loss_and_grads(student, teacher, mask)
        assert loss.item() == 0.0 and gs.shape == student.shape and gt.shape == teacher.shape
    assert cosine_distance_map(student, teacher).shape == (b, v, h, w)


@given(shape=st.tuples(st.integers(0, 2), st.integers(0, 3), st.integers(1, 4)))
def test_projector_handles_empty_leading_axes(shape: tuple[int, int, int]) -> None:
    proj = StudentProjector(shape[-1], 5, hidden_dim=3).double()
    x = torch.randn(*shape, dtype=torch.float64)
    out = proj(x)
    assert out.shape == (*shape[:-1], 5) and out.dtype == torch.float64


def test_the_masked_out_guarantee_ends_at_the_loss_inputs() -> None:
    """docs/validation.md: masked-out NaN/inf in ``student`` / ``teacher`` gives exactly zero
    gradient to those two tensors there; a layer *upstream* whose own input is inf at those
    pixels still computes 0 * inf = NaN in its weight gradient (autograd, not the loss)."""
    torch.manual_seed(0)
    mask = torch.ones(1, 1, 3, 4, dtype=torch.bool)
    mask[0, 0, 1, 2] = False
    teacher = torch.randn(1, 1, 5, 3, 4)
    teacher[0, 0, :, 1, 2] = float("nan")
    inputs = torch.randn(1, 1, 3, 3, 4)
    inputs[0, 0, :, 1, 2] = float("inf")
    layer = torch.nn.Conv2d(3, 5, 1)
    student = layer(inputs.flatten(0, 1)).unflatten(0, (1, 1))
    student.retain_grad()
    loss = distillation_loss(student, teacher, mask)
    loss.backward()
    assert torch.isfinite(loss)
    assert torch.equal(student.grad[0, 0, :, 1, 2], torch.zeros(5))
    assert torch.isfinite(student.grad).all()
    assert torch.isnan(layer.weight.grad).any()  # the documented limit, not a promise
    clean = torch.where(mask.unsqueeze(2), inputs, torch.zeros(()))  # what the docs advise
    layer.zero_grad()
    student = layer(clean.flatten(0, 1)).unflatten(0, (1, 1))
    distillation_loss(student, teacher, mask).backward()
    assert torch.isfinite(layer.weight.grad).all()
