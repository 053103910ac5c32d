"""deformation_loss reductions: mean (the paper's), sum and per-Gaussian weighted means."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from dego.deformation import (
    PARAMETERS,
    REDUCTIONS,
    DeformationLossWeights,
    DeformationOutput,
    deformation_loss,
)
from tests.helpers.deformation import (
    PRESETS,
    literal_output,
    make_inputs,
    make_module,
    randomize_last_layers,
    times_tensor,
)


def random_output(preset: str, b: int, n: int, t: int, seed: int) -> DeformationOutput:
    module = make_module(preset, seed=seed)
    randomize_last_layers(module, std=0.3)
    canonical, features = make_inputs(b, n, seed=seed)
    times = times_tensor([0.5 * (k + 1) for k in range(t)])
    return module(canonical, features, times)


def only(name: str) -> DeformationLossWeights:
    """Weights that keep parameter ``name``'s term alone in ``reg``."""
    return DeformationLossWeights(**{p: float(p == name) for p in PARAMETERS})


def per_gaussian_values(output: DeformationOutput, name: str) -> Tensor:
    """(B, T, N) per-Gaussian value the reductions act on, written out independently."""
    squared = getattr(output.deltas, name).square()
    if name == "opacities":
        return squared
    return squared.mean(-1) if output.preset == "official" else squared.sum(-1)


shapes = st.tuples(
    st.sampled_from(PRESETS),
    st.integers(1, 2),
    st.integers(1, 6),
    st.integers(1, 3),
    st.integers(0, 50),
)


@settings(max_examples=25, deadline=None)
@given(shapes)
def test_all_ones_weights_give_the_mean(case: tuple[str, int, int, int, int]) -> None:
    preset, b, n, t, seed = case
    out = random_output(preset, b, n, t, seed)
    mean = deformation_loss(out)
    for weights in (torch.ones(n, dtype=torch.float64), torch.full((b, n), 3.5).double()):
        weighted = deformation_loss(out, reduction="weighted", gaussian_weights=weights)
        for key in ("reg", "mask", "total"):
            torch.testing.assert_close(
                getattr(weighted, key), getattr(mean, key), rtol=1e-12, atol=1e-14
            )


@settings(max_examples=25, deadline=None)
@given(shapes)
def test_sum_is_the_mean_times_the_count(case: tuple[str, int, int, int, int]) -> None:
    preset, b, n, t, seed = case
    out = random_output(preset, b, n, t, seed)
    for name in PARAMETERS:
        mean = deformation_loss(out, only(name)).reg
        total = deformation_loss(out, only(name), reduction="sum").reg
        elements = getattr(out.deltas, name).numel()  # sum: every element
        per_gaussian = b * t * n
        expected = mean * (elements if preset == "official" else per_gaussian)
        torch.testing.assert_close(total, expected, rtol=1e-12, atol=1e-14)


@settings(max_examples=25, deadline=None)
@given(shapes, st.data())
def test_weighted_is_the_weighted_mean_over_gaussians(
    case: tuple[str, int, int, int, int], data: st.DataObject
) -> None:
    preset, b, n, t, seed = case
    out = random_output(preset, b, n, t, seed)
    raw = data.draw(st.lists(st.floats(0, 5), min_size=b * n, max_size=b * n))
    weights = torch.tensor(raw, dtype=torch.float64).reshape(b, n)
    for name in PARAMETERS:
        got = deformation_loss(out, only(name), reduction="weighted", gaussian_weights=weights).reg
        values = per_gaussian_values(out, name)  # (B, T, N)
        # relative to the largest weight: subnormal weights would round the products
        unit = weights / weights.max() if float(weights.max()) > 0 else weights
        denominator = float(unit.sum()) * t
        expected = (unit[:, None] * values).sum() / denominator if denominator else 0.0
        torch.testing.assert_close(got, torch.as_tensor(expected).double(), rtol=1e-10, atol=1e-14)
        # scale-free in the weights
        rescaled = deformation_loss(
            out, only(name), reduction="weighted", gaussian_weights=7 * weights
        ).reg
        torch.testing.assert_close(rescaled, got, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("preset", PRESETS)
def test_binary_weights_select_gaussians(preset: str) -> None:
    out = random_output(preset, 1, 5, 2, seed=3)
    keep = torch.tensor([True, False, True, False, False])
    weighted = deformation_loss(out, reduction="weighted", gaussian_weights=keep).reg
    chosen = out.deltas.__class__(
        *(getattr(out.deltas, name)[:, :, keep] for name in PARAMETERS)  # type: ignore[arg-type]
    )
    import dataclasses

    subset = dataclasses.replace(
        out,
        deltas=chosen,
        rigid_mask=out.rigid_mask[..., keep],
        gaussians=out.gaussians.map(lambda _, v: v[:, :, keep]),
        rigid_offsets=out.rigid_offsets[:, :, keep],
        nonrigid_offsets=out.nonrigid_offsets[:, :, keep],
    )
    torch.testing.assert_close(weighted, deformation_loss(subset).reg, rtol=1e-12, atol=0)


@pytest.mark.parametrize("preset", PRESETS)
def test_zero_weights_give_zero_and_no_gradient(preset: str) -> None:
    module = make_module(preset, seed=1)
    randomize_last_layers(module, std=0.3)
    canonical, features = make_inputs(1, 4, seed=1)
    out = module(canonical, features, times_tensor([1.0]))
    weights = torch.tensor([0.0, 0.0, 2.0, 0.0], dtype=torch.float64)
    loss = deformation_loss(out, reduction="weighted", gaussian_weights=weights).reg
    loss.backward()
    grads = [p.grad for p in module.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    zero = deformation_loss(out, reduction="weighted", gaussian_weights=torch.zeros(4).double())
    assert zero.reg.item() == 0.0 and torch.isfinite(zero.total)


def test_weighted_gradient_only_reaches_weighted_gaussians() -> None:
    out = literal_output("paper")
    deltas = out.deltas.means.clone().requires_grad_(True)
    import dataclasses

    out = dataclasses.replace(out, deltas=dataclasses.replace(out.deltas, means=deltas))
    # one Gaussian only: weight 0 leaves it out entirely
    loss = deformation_loss(
        out, only("means"), reduction="weighted", gaussian_weights=torch.ones(1).double()
    ).reg
    (grad,) = torch.autograd.grad(loss, deltas)
    # mean over T = 2 steps of ||d||^2: gradient 2 d / 2
    torch.testing.assert_close(grad, deltas.detach())


def test_paper_preset_numbers_do_not_change() -> None:
    # the hand-computed values of test_deformation.test_loss_hand_computed, through the
    # explicit default reduction
    for preset, reg in (("paper", 7.5), ("official", 9 / 6 + 1 / 8 + 1 / 6 + 2.0)):
        default = deformation_loss(literal_output(preset))
        explicit = deformation_loss(literal_output(preset), reduction="mean")
        assert default.reg.item() == pytest.approx(reg, rel=1e-14)
        assert torch.equal(default.total, explicit.total)
    assert DeformationLossWeights().reduction == "mean"


def test_the_configured_reduction_is_the_default() -> None:
    out = literal_output("paper")
    summed = deformation_loss(out, DeformationLossWeights(reduction="sum")).reg
    # (B, T, N) = (1, 2, 1): the sum is twice the mean
    assert summed.item() == pytest.approx(2 * 7.5, rel=1e-14)
    overridden = deformation_loss(out, DeformationLossWeights(reduction="sum"), reduction="mean")
    assert overridden.reg.item() == pytest.approx(7.5, rel=1e-14)


def test_canonical_step_is_left_out_of_every_reduction() -> None:
    out = random_output("official", 1, 3, 2, seed=5)
    canonical, _ = make_inputs(1, 3, seed=5)
    extended = out.with_canonical(canonical)
    w = torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
    for reduction, kwargs in (("mean", {}), ("sum", {}), ("weighted", {"gaussian_weights": w})):
        a = deformation_loss(out, reduction=reduction, **kwargs)
        b = deformation_loss(extended, reduction=reduction, **kwargs)
        torch.testing.assert_close(a.reg, b.reg, rtol=1e-12, atol=0)


# -- bad input --------------------------------------------------------------------------


def test_unknown_reduction_lists_the_choices() -> None:
    out = literal_output("paper")
    with pytest.raises(
        ValueError, match=r"reduction: expected one of \('mean', 'sum', 'weighted'\)"
    ):
        deformation_loss(out, reduction="median")
    with pytest.raises(ValueError, match="reduction: expected one of"):
        DeformationLossWeights(reduction="avg")  # type: ignore[arg-type]
    assert REDUCTIONS == ("mean", "sum", "weighted")


@pytest.mark.parametrize(
    ("weights", "match"),
    [
        (torch.ones(2), r"gaussian_weights: expected shape \(1,\) or \(1, 1\)"),
        (torch.ones(1, 1, 1), "gaussian_weights: expected shape"),
        (torch.ones(3, 1), "gaussian_weights: expected shape"),
        (torch.tensor([-1.0]), "gaussian_weights: expected finite weights >= 0"),
        (torch.tensor([float("nan")]), "gaussian_weights: expected finite weights >= 0"),
        (torch.tensor([float("inf")]), "gaussian_weights: expected finite weights >= 0"),
        (torch.ones(1, dtype=torch.complex64), "gaussian_weights: expected real or bool"),
    ],
)
def test_bad_weights_name_the_argument(weights: Tensor, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        deformation_loss(literal_output("paper"), reduction="weighted", gaussian_weights=weights)


def test_weights_and_reduction_must_agree() -> None:
    out = literal_output("paper")
    with pytest.raises(ValueError, match="gaussian_weights: reduction='weighted' needs"):
        deformation_loss(out, reduction="weighted")
    with pytest.raises(ValueError, match="gaussian_weights: only used by reduction='weighted'"):
        deformation_loss(out, gaussian_weights=torch.ones(1))
    with pytest.raises(TypeError):
        deformation_loss(out, reduction="weighted", gaussian_weights=[1.0])  # type: ignore[arg-type]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_weights_on_another_device_are_refused() -> None:
    with pytest.raises(ValueError, match="gaussian_weights: expected device"):
        deformation_loss(
            literal_output("paper"), reduction="weighted", gaussian_weights=torch.ones(1).cuda()
        )


@pytest.mark.parametrize("scale", [2.225073858507e-311, 1e-300, 1.0, 1e300])
def test_weighted_mean_is_exact_for_tiny_and_huge_weights(scale: float) -> None:
    """Tiny (even subnormal) and huge weights give the mean: weights are taken relative to
    the largest (hypothesis found a subnormal weight in CI, where w * v rounds)."""
    out = random_output("paper", 1, 1, 1, 1)
    expected = deformation_loss(out, reduction="mean")
    weights = torch.full((1,), scale, dtype=torch.float64)
    got = deformation_loss(out, reduction="weighted", gaussian_weights=weights)
    for key in ("reg", "mask", "total"):
        torch.testing.assert_close(
            getattr(got, key), getattr(expected, key), rtol=1e-12, atol=1e-14
        )
