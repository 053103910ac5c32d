"""dego.losses: the rendering losses (L_seg, L_dep), their combination, and the re-exports."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from jaxtyping import TypeCheckError
from torch import Tensor

import dego
import dego.deformation
import dego.losses
import dego.teacher
from dego.losses import (
    DepthLoss,
    RenderingCriterion,
    RenderingLoss,
    RenderingLossWeights,
    SemanticLoss,
    depth_l1_map,
    depth_loss,
    rendering_loss,
    semantic_cross_entropy_map,
    semantic_loss,
)

DTYPES = (torch.float32, torch.float64)


def old_weak_losses(
    features: Tensor,
    alpha: Tensor,
    rendered_depth: Tensor,
    depth: Tensor,
    semantics: Tensor,
    supervised: Tensor,
) -> dict[str, Tensor]:
    """A copy of the formula of ``dego.demo.weak_losses`` (removed), on one frame ``(V, ...)``."""
    probabilities = torch.cat([features, (1 - alpha)[:, None]], 1)  # (V, C + 1, H, W)
    picked = probabilities.gather(1, semantics[:, None]).squeeze(1)
    semantic = -picked.clamp_min(1e-6).log()[supervised].mean()
    with_depth = supervised & (depth > 0)
    depth_error = (rendered_depth - depth).abs()[with_depth]
    return {
        "semantics": semantic,
        "depth": depth_error.mean() if depth_error.numel() else depth.new_zeros(()),
    }


def render_like(
    b: int, v: int, c: int, h: int, w: int, dtype: torch.dtype = torch.float32, seed: int = 0
) -> dict[str, Tensor]:
    """Random renders and pseudo labels shaped as the demo's: scores sum to alpha."""
    g = torch.Generator().manual_seed(seed)
    raw = torch.rand(b, v, c, h, w, generator=g, dtype=dtype) + 0.05
    alpha = torch.rand(b, v, h, w, generator=g, dtype=dtype)
    scores = raw / raw.sum(2, keepdim=True) * alpha[:, :, None]
    depth = torch.rand(b, v, h, w, generator=g, dtype=dtype) * 40 + 0.5
    target = torch.rand(b, v, h, w, generator=g, dtype=dtype) * 40 + 0.5
    target = torch.where(torch.rand(b, v, h, w, generator=g) < 0.3, 0.0, target).to(dtype)
    labels = torch.randint(0, c + 1, (b, v, h, w), generator=g)
    mask = torch.rand(b, v, h, w, generator=g) < 0.7
    return {
        "scores": scores,
        "alpha": alpha,
        "depth": depth,
        "labels": labels,
        "target_depth": target,
        "mask": mask,
    }


def leaves(inputs: dict[str, Tensor]) -> dict[str, Tensor]:
    return {
        k: x.clone().requires_grad_(x.is_floating_point() and k != "target_depth")
        for k, x in inputs.items()
    }


# -- the demo's former formula ----------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("seed", range(4))
def test_bit_identical_to_the_old_weak_losses(dtype: torch.dtype, seed: int) -> None:
    """The demo's numbers cannot move: values and gradients equal bit for bit (CPU)."""
    x = leaves(render_like(1, 3, 17, 12, 20, dtype, seed))
    old = old_weak_losses(
        x["scores"][0], x["alpha"][0], x["depth"][0], x["target_depth"][0], x["labels"][0],
        x["mask"][0],
    )  # fmt: skip
    new = rendering_loss(**x)
    assert torch.equal(new.semantic, old["semantics"])
    assert torch.equal(new.depth, old["depth"])
    wrt = [x["scores"], x["alpha"], x["depth"]]
    old_grads = torch.autograd.grad(old["semantics"] + 0.1 * old["depth"], wrt)
    new_grads = torch.autograd.grad(new.total, wrt)
    for a, b in zip(old_grads, new_grads, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", DTYPES)
def test_a_batch_is_the_old_formula_on_the_batch_axis_flattened(dtype: torch.dtype) -> None:
    """B > 1 pools every pixel of the batch: the old formula over (B V) cameras."""
    x = leaves(render_like(2, 3, 5, 6, 7, dtype, seed=9))
    old = old_weak_losses(*(
        x[k].flatten(0, 1)
        for k in ("scores", "alpha", "depth", "target_depth", "labels", "mask")
    ))  # fmt: skip
    new = rendering_loss(**x)
    torch.testing.assert_close(new.semantic, old["semantics"], rtol=1e-6, atol=0)
    torch.testing.assert_close(new.depth, old["depth"], rtol=1e-6, atol=0)
    wrt = [x["scores"], x["alpha"], x["depth"]]
    old_grads = torch.autograd.grad(old["semantics"] + 0.1 * old["depth"], wrt)
    for a, b in zip(old_grads, torch.autograd.grad(new.total, wrt), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-12)


# -- analytic cases ---------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
def test_a_perfect_render_costs_nothing(dtype: torch.dtype) -> None:
    labels = torch.tensor([[[[0, 1, 2], [2, 1, 0]]]])  # (1, 1, 2, 3); 2 = free
    alpha = (labels != 2).to(dtype)
    scores = torch.nn.functional.one_hot(labels.clamp_max(1), 2).permute(0, 1, 4, 2, 3)
    scores = scores.to(dtype) * alpha[:, :, None]
    depth = torch.full_like(alpha, 7.5)
    loss = rendering_loss(scores, alpha, depth, labels, depth)
    assert loss.semantic.dtype == dtype and loss.total.dtype == dtype
    assert float(loss.semantic) == 0.0 and float(loss.depth) == 0.0 and float(loss.total) == 0.0
    assert torch.all(semantic_cross_entropy_map(scores, alpha, labels) == 0)


def test_one_pixel_by_hand() -> None:
    scores = torch.tensor([0.25, 0.5]).reshape(1, 1, 2, 1, 1)
    alpha = torch.tensor(0.75).reshape(1, 1, 1, 1)
    for label, expected in ((0, math.log(4)), (1, math.log(2)), (2, math.log(4))):
        labels = torch.full((1, 1, 1, 1), label)
        assert float(semantic_loss(scores, alpha, labels)) == pytest.approx(expected, rel=1e-6)
    empty = torch.zeros(1, 1, 2, 1, 1)
    labels = torch.zeros(1, 1, 1, 1, dtype=torch.long)
    assert float(semantic_loss(empty, alpha * 0, labels)) == pytest.approx(-math.log(1e-6))
    assert float(semantic_loss(empty, alpha * 0, labels, eps=1e-3)) == pytest.approx(
        -math.log(1e-3)
    )
    depth, target = torch.tensor(3.0).reshape(1, 1, 1, 1), torch.tensor(5.5).reshape(1, 1, 1, 1)
    assert float(depth_loss(depth, target)) == 2.5
    assert float(depth_l1_map(depth, target)) == 2.5
    weights = RenderingLossWeights(semantic=2.0, depth=0.5)
    loss = rendering_loss(scores, alpha, depth, labels, target, weights=weights)
    assert float(loss.total) == pytest.approx(2 * math.log(4) + 0.5 * 2.5)


def test_default_weights_are_the_demos() -> None:
    assert RenderingLossWeights() == RenderingLossWeights(semantic=1.0, depth=0.1)
    from dego.demo import FitConfig

    assert FitConfig().depth_weight == RenderingLossWeights().depth


def test_class_weights_match_torch_weighted_nll() -> None:
    x = render_like(2, 2, 4, 5, 6, torch.float64, seed=3)
    weights = torch.tensor([0.5, 2.0, 1.0, 0.0, 3.0], dtype=torch.float64)
    mask = x["mask"]
    ours = semantic_loss(x["scores"], x["alpha"], x["labels"], mask, class_weights=weights)
    probabilities = torch.cat([x["scores"], (1 - x["alpha"])[:, :, None]], 2)
    log_p = probabilities.clamp_min(1e-6).log().movedim(2, -1)[mask]  # (P, C + 1)
    expected = torch.nn.functional.nll_loss(log_p, x["labels"][mask], weight=weights)
    torch.testing.assert_close(ours, expected)
    per_pixel = semantic_cross_entropy_map(
        x["scores"], x["alpha"], x["labels"], class_weights=weights
    )
    plain = semantic_cross_entropy_map(x["scores"], x["alpha"], x["labels"])
    torch.testing.assert_close(per_pixel, plain * weights[x["labels"]])
    zero = semantic_loss(
        x["scores"], x["alpha"], x["labels"], mask, class_weights=torch.zeros_like(weights)
    )
    assert float(zero) == 0.0


def test_the_maps_reduce_to_the_losses() -> None:
    x = render_like(2, 3, 5, 4, 6, torch.float64, seed=4)
    valid = x["mask"]
    ce = semantic_cross_entropy_map(x["scores"], x["alpha"], x["labels"])
    assert ce.shape == x["alpha"].shape and bool((ce >= 0).all())
    torch.testing.assert_close(
        semantic_loss(x["scores"], x["alpha"], x["labels"], valid), ce[valid].mean()
    )
    l1 = depth_l1_map(x["depth"], x["target_depth"])
    with_depth = valid & (x["target_depth"] > 0)
    torch.testing.assert_close(
        depth_loss(x["depth"], x["target_depth"], valid), l1[with_depth].mean()
    )


# -- masks ------------------------------------------------------------------------------


def test_masked_out_pixels_do_not_count_and_uint8_masks_work() -> None:
    x = render_like(1, 2, 3, 4, 5, seed=5)
    mask = x["mask"]
    full = rendering_loss(**{**x, "mask": mask})
    assert torch.equal(rendering_loss(**{**x, "mask": mask.to(torch.uint8)}).total, full.total)
    none = rendering_loss(**{**x, "mask": None})
    everything = rendering_loss(**{**x, "mask": torch.ones_like(mask)})
    assert torch.equal(none.semantic, everything.semantic)
    assert torch.equal(none.depth, everything.depth)
    with pytest.raises(ValueError, match="mask: a uint8 mask must hold only 0 and 1"):
        depth_loss(x["depth"], x["target_depth"], mask.to(torch.uint8) * 2)


def test_no_valid_pixel_gives_zero_and_a_zero_gradient() -> None:
    x = leaves(render_like(1, 2, 3, 4, 5, seed=6))
    loss = rendering_loss(**{**x, "mask": torch.zeros_like(x["mask"])})
    assert float(loss.semantic.detach()) == 0.0 and float(loss.depth.detach()) == 0.0
    grads = torch.autograd.grad(loss.total, [x["scores"], x["alpha"], x["depth"]])
    assert all(bool((g == 0).all()) for g in grads)
    empty = {k: v[:, :0] for k, v in x.items()}  # V = 0
    assert float(rendering_loss(**empty).total.detach()) == 0.0


def test_nan_and_inf_in_masked_pixels_leak_nowhere() -> None:
    x = render_like(1, 2, 3, 4, 5, seed=7)
    mask = x["mask"]
    dirty = dict(x)
    for name in ("scores", "alpha", "depth", "target_depth"):
        value = dirty[name]
        hole = ~mask[:, :, None] if value.ndim == 5 else ~mask
        dirty[name] = torch.where(hole, torch.tensor(float("nan")), value)
    dirty["depth"] = torch.where(~mask & (x["labels"] == 0), float("inf"), dirty["depth"])
    dirty["labels"] = torch.where(mask, x["labels"], 255)  # an ignore value, out of range
    clean, messy = leaves(x), leaves(dirty)
    a, b = rendering_loss(**clean), rendering_loss(**messy)
    assert torch.equal(a.semantic, b.semantic) and torch.equal(a.depth, b.depth)
    wrt = ("scores", "alpha", "depth")
    grads = torch.autograd.grad(b.total, [messy[k] for k in wrt])
    for name, grad, reference in zip(
        wrt, grads, torch.autograd.grad(a.total, [clean[k] for k in wrt]), strict=True
    ):
        assert bool(torch.isfinite(grad).all()), name
        hole = ~mask[:, :, None].expand_as(grad) if grad.ndim == 5 else ~mask
        assert bool((grad[hole] == 0).all()), name
        assert torch.equal(grad, reference), name


def test_a_nan_in_a_valid_pixel_makes_the_loss_nan() -> None:
    x = render_like(1, 1, 2, 2, 2, seed=8)
    mask = torch.ones_like(x["mask"])
    x["depth"][0, 0, 0, 0] = float("nan")
    x["target_depth"][0, 0, 0, 0] = 3.0
    assert math.isnan(float(depth_loss(x["depth"], x["target_depth"], mask)))


# -- gradients --------------------------------------------------------------------------


def test_gradcheck_float64() -> None:
    x = render_like(1, 2, 3, 2, 3, torch.float64, seed=10)
    mask, labels = x["mask"], x["labels"]
    weights = torch.tensor([1.0, 0.5, 2.0, 1.5], dtype=torch.float64)
    alpha = (0.2 + 0.6 * x["alpha"]).requires_grad_()  # away from the eps floor's kink
    scores = (x["scores"] / x["alpha"][:, :, None] * alpha[:, :, None]).detach().requires_grad_()
    depth = x["depth"].clone().requires_grad_()
    target = x["target_depth"].clone().requires_grad_()
    assert torch.autograd.gradcheck(
        lambda s, a: semantic_loss(s, a, labels, mask, class_weights=weights), (scores, alpha)
    )
    assert torch.autograd.gradcheck(
        lambda s, a: semantic_cross_entropy_map(s, a, labels), (scores, alpha)
    )
    # (target = 0 means "no depth": the loss jumps there, so its gradient is checked at t > 0)
    positive = (target + 1.0).detach().requires_grad_()
    assert torch.autograd.gradcheck(lambda d, t: depth_loss(d, t, mask), (depth, positive))
    assert torch.autograd.gradcheck(lambda d: depth_loss(d, target.detach(), mask), (depth,))
    assert torch.autograd.gradcheck(depth_l1_map, (depth, target))


# -- properties -------------------------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(
    shape=st.tuples(*(st.integers(1, 3) for _ in range(5))),
    seed=st.integers(0, 2**16),
    fill=st.sampled_from([0.0, 1e6, float("nan"), float("inf"), -float("inf")]),
)
def test_nonnegative_and_blind_to_masked_out_values(
    shape: tuple[int, int, int, int, int], seed: int, fill: float
) -> None:
    x = render_like(*shape, seed=seed)
    base = rendering_loss(**x)
    assert float(base.semantic) >= 0 and float(base.depth) >= 0 and float(base.total) >= 0
    hole = ~x["mask"]
    changed = {
        **x,
        "scores": torch.where(hole[:, :, None], fill, x["scores"]),
        "alpha": torch.where(hole, fill, x["alpha"]),
        "depth": torch.where(hole, fill, x["depth"]),
        "target_depth": torch.where(hole, fill, x["target_depth"]),
        "labels": torch.where(hole, -7, x["labels"]),
    }
    other = rendering_loss(**changed)
    assert torch.equal(other.semantic, base.semantic) and torch.equal(other.depth, base.depth)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**16), scale=st.floats(0.01, 100.0))
def test_depth_l1_scales_with_the_depths(seed: int, scale: float) -> None:
    x = render_like(2, 2, 1, 3, 4, torch.float64, seed=seed)
    d, t, m = x["depth"], x["target_depth"], x["mask"]
    torch.testing.assert_close(depth_loss(scale * d, scale * t, m), scale * depth_loss(d, t, m))
    torch.testing.assert_close(depth_loss(d, t, m), depth_loss(t, d, m & (t > 0)))  # symmetric


# -- modules and results ----------------------------------------------------------------


def test_modules_equal_the_functions() -> None:
    x = render_like(2, 2, 3, 4, 5, seed=11)
    weights = torch.tensor([1.0, 2.0, 0.5, 1.0])
    s, a, lab, m = x["scores"], x["alpha"], x["labels"], x["mask"]
    module = SemanticLoss(class_weights=weights, eps=1e-4)
    assert torch.equal(
        module(s, a, lab, m), semantic_loss(s, a, lab, m, class_weights=weights, eps=1e-4)
    )
    assert torch.equal(SemanticLoss()(s, a, lab), semantic_loss(s, a, lab))
    assert module.state_dict() == {} and "eps=0.0001" in repr(module)
    assert torch.equal(
        DepthLoss()(x["depth"], x["target_depth"], m), depth_loss(x["depth"], x["target_depth"], m)
    )
    lambdas = RenderingLossWeights(semantic=2.0, depth=0.05)
    criterion = RenderingCriterion(lambdas, class_weights=weights)
    got = criterion(**x)
    expected = rendering_loss(**x, weights=lambdas, class_weights=weights)
    assert isinstance(got, RenderingLoss)
    assert all(torch.equal(got.to_dict()[k], v) for k, v in expected.to_dict().items())
    assert list(criterion.parameters()) == [] and criterion.state_dict() == {}
    double = criterion.to(torch.float64)
    x64 = {k: v.double() if v.is_floating_point() else v for k, v in x.items()}
    assert double(**x64).total.dtype == torch.float64


def test_rendering_loss_is_a_frozen_checked_result() -> None:
    x = render_like(1, 1, 2, 2, 2, seed=12)
    loss = rendering_loss(**x)
    assert set(loss.to_dict()) == {"semantic", "depth", "total"}
    assert torch.equal(loss.total, loss.semantic + 0.1 * loss.depth)
    with pytest.raises(dataclasses.FrozenInstanceError):
        loss.total = loss.depth  # type: ignore[misc]
    with pytest.raises(TypeCheckError):
        RenderingLoss(semantic=torch.zeros(2), depth=torch.zeros(()), total=torch.zeros(()))


def test_half_inputs_are_computed_in_float32() -> None:
    x = render_like(1, 2, 3, 4, 5, seed=13)
    reference = rendering_loss(**x)
    half = {k: v.bfloat16() if v.is_floating_point() else v for k, v in x.items()}
    got = rendering_loss(**half)
    assert got.total.dtype == torch.bfloat16
    with torch.autocast("cpu", dtype=torch.bfloat16):
        autocast = rendering_loss(**half)
    assert autocast.total.dtype == torch.float32
    torch.testing.assert_close(autocast.total, reference.total, rtol=0.05, atol=0.05)


def test_compiles_into_one_graph_with_the_eager_values() -> None:
    """No graph break (the valid pixels are pooled with torch.where while tracing), the
    eager values and gradients, and the label check as an in-graph assert."""
    x = leaves(render_like(1, 2, 3, 4, 5, seed=16))
    compiled = torch.compile(
        lambda **kw: rendering_loss(**kw).total, backend="eager", fullgraph=True
    )
    got, expected = compiled(**x), rendering_loss(**x).total
    torch.testing.assert_close(got, expected)
    wrt = [x["scores"], x["alpha"], x["depth"]]
    for a, b in zip(torch.autograd.grad(got, wrt), torch.autograd.grad(expected, wrt), strict=True):
        torch.testing.assert_close(a, b)
    with pytest.raises(RuntimeError, match="labels: a label is out of range"):
        compiled(**{**x, "labels": torch.where(x["mask"], 9, x["labels"])})


# -- bad input --------------------------------------------------------------------------


def test_bad_shapes_and_dtypes_name_the_argument() -> None:
    x = render_like(1, 2, 3, 4, 5, seed=14)
    s, a, lab, m = x["scores"], x["alpha"], x["labels"], x["mask"]
    with pytest.raises(TypeCheckError, match="parameter 'mask'"):
        semantic_loss(s, a, lab, m[..., :3])
    with pytest.raises(TypeCheckError, match="parameter 'alpha'"):
        semantic_loss(s, a[:, :1], lab)
    with pytest.raises(TypeCheckError, match="parameter 'labels'"):
        semantic_loss(s, a, lab.float())
    with pytest.raises(TypeCheckError, match="parameter 'mask'"):
        depth_loss(x["depth"], x["target_depth"], m.float())
    with pytest.raises(TypeCheckError, match="parameter 'target'"):
        depth_l1_map(x["depth"], x["target_depth"][..., :2])
    with pytest.raises(TypeError, match=r"alpha: dtype torch.float64 differs from scores'"):
        semantic_loss(s, a.double(), lab)
    with pytest.raises(TypeError, match=r"target: dtype torch.float64 differs from depth's"):
        depth_loss(x["depth"], x["target_depth"].double())


def test_bad_values_raise_value_errors_naming_the_argument() -> None:
    x = render_like(1, 2, 3, 4, 5, seed=15)
    s, a, lab, m = x["scores"], x["alpha"], x["labels"], x["mask"]
    with pytest.raises(ValueError, match=r"labels: label 4 is out of range; expected 0\.\.3"):
        semantic_loss(s, a, torch.where(m, 4, lab), m)
    with pytest.raises(ValueError, match="labels: label -1 is out of range"):
        semantic_cross_entropy_map(s, a, torch.where(m, lab, -1))
    with pytest.raises(ValueError, match=r"class_weights: expected shape \(4,\)"):
        semantic_loss(s, a, lab, class_weights=torch.ones(3))
    with pytest.raises(ValueError, match="class_weights: expected finite weights >= 0"):
        semantic_loss(s, a, lab, class_weights=torch.tensor([1.0, -1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="class_weights: expected finite weights >= 0"):
        SemanticLoss(class_weights=torch.tensor([1.0, float("nan")]))
    for eps in (0.0, -1.0, 1.0):
        with pytest.raises(ValueError, match="eps: expected a float in"):
            semantic_loss(s, a, lab, eps=eps)
    with pytest.raises(ValueError, match="depth: expected a finite weight >= 0"):
        RenderingLossWeights(depth=-0.1)
    with pytest.raises(ValueError, match="semantic: expected a finite weight >= 0"):
        RenderingLossWeights(semantic=float("inf"))


# -- the module's face ------------------------------------------------------------------


def test_the_face_lists_every_term_of_the_objective() -> None:
    names = dego.losses.__all__
    assert list(names) == sorted(names) and len(set(names)) == len(names)
    for name in ("deformation_loss", "DeformationLoss", "DeformationLossWeights"):
        assert getattr(dego.losses, name) is getattr(dego.deformation, name)
    for name in ("distillation_loss", "DistillationLoss", "cosine_distance_map"):
        assert getattr(dego.losses, name) is getattr(dego.teacher, name)
    for name in names:
        assert hasattr(dego.losses, name), name
    assert dego.losses is __import__("dego").losses
