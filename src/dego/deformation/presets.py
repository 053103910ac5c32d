"""The ``paper`` and ``official`` presets of :class:`dego.DecoupledDeformation`.

One table, :data:`PRESETS`, selected by name: per preset, its update rule (how the MLP
outputs become the deformed means, quaternions, scales and opacities, and the applied
deltas that :func:`dego.deformation_loss` regularises) and the structural choices of the
network and of the losses. :mod:`dego.deformation.module` reads everything
preset-specific from here; nothing here imports another module of the package.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Literal

import torch
from jaxtyping import Float
from torch import Tensor

from dego._geometry import quaternion_product, unit_quaternions
from dego._typing import typechecked

Preset = Literal["paper", "official"]

PARAMETERS = ("means", "quats", "scales", "opacities")
"""The deformed Gaussian parameters, in the order of the paper's ``{mu, r, s, alpha}``."""

MAX_LOG_SCALE_CHANGE = 5.0
"""``paper`` preset: log-scale deltas are soft-bounded to +-5 (a factor e^5 ~ 148) by
``5 tanh(d / 5)``, so deformed scales stay positive and finite whatever the network says."""

_MAX_LOGIT_SHIFT = 50.0  # beyond this the shifted opacity equals 0 or 1 in float32 anyway

# The official code's constants (vggt-and-deformation-facts.md section 4).
_OFFICIAL_OFFSET_CLAMP = 10.0  # metres
_OFFICIAL_SCALE_CLAMP = 1.0  # metres, added to a linear scale
_OFFICIAL_QUAT_EPS = 1e-8

UpdateRule = Callable[
    [Mapping[str, Tensor], Mapping[str, Tensor], Tensor],
    tuple[dict[str, Tensor], dict[str, Tensor]],
]
"""``rule(canonical, raw, mask) -> (deformed, deltas)``: see :func:`paper_update`."""


def _shift_opacity_logit(opacity: Tensor, shift: Tensor) -> Tensor:
    d = shift.clamp(-_MAX_LOGIT_SHIFT, _MAX_LOGIT_SHIFT)
    # each branch sees only its own half of d, so neither can produce NaN gradients
    u = torch.expm1(d.clamp_min(0))
    raised = opacity + (1 - opacity) * (opacity * u / (1 + opacity * u))
    scaled = opacity * torch.exp(d.clamp_max(0))
    lowered = scaled / ((1 - opacity) + scaled)
    return torch.where(d >= 0, raised.clamp_max(1), lowered)


@typechecked
def shift_opacity_logit(
    opacity: Float[Tensor, "*obatch"], shift: Float[Tensor, "*sbatch"]
) -> Float[Tensor, "*batch"]:
    """``sigmoid(logit(o) + d)`` for o in [0, 1], exact where ``d`` is 0, always in [0, 1].

    Raising (d >= 0): ``o + (1 - o) o u / (1 + o u)`` with ``u = expm1(d)``, which is o
    itself at d = 0. Lowering (d < 0): ``o e^d / ((1 - o) + o e^d)``, a ratio of positive
    terms. No logit of 0 or 1 is taken and nothing cancels, so o = 0 (padding) and o = 1
    stay fixed with finite gradients; |d| is clamped to 50, where the result is 0 or 1.
    ``opacity`` and ``shift`` broadcast against each other.
    """
    return _shift_opacity_logit(opacity, shift)


def _identity_quaternions(like: Tensor) -> Tensor:
    identity = torch.zeros_like(like)
    identity[..., 0] = 1
    return identity


@typechecked
def paper_update(
    canonical: Mapping[str, Tensor], raw: Mapping[str, Tensor], mask: Float[Tensor, "B N"]
) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """The ``paper`` update rule: the deformed parameters and the applied deltas.

    ``mu' = mu + (1 - m) d_mu_rig + m d_mu_def``, ``q' = q (x) normalize(1 + m d_rot)``,
    ``s' = s exp(m d_s)`` with ``d_s`` soft-bounded to +-:data:`MAX_LOG_SCALE_CHANGE`,
    ``o' = sigmoid(logit(o) + m d_o)`` (:func:`shift_opacity_logit`).

    Args:
        canonical: :data:`PARAMETERS` -> the canonical values with a time axis,
            ``(B, 1, N, k)`` (opacities ``(B, 1, N)``).
        raw: the head outputs ``rigid_offset``, ``nonrigid_offset`` ``(B, T, N, 3)``,
            ``rotation`` ``(B, T, N, 4)``, ``scale`` ``(B, T, N, 3)``, ``opacity``
            ``(B, T, N, 1)``.
        mask: m, ``(B, N)``, one per Gaussian (1 = nonrigid).

    Returns:
        ``(deformed, deltas)``, both keyed by :data:`PARAMETERS`, ``(B, T, N, k)``
        (opacities ``(B, T, N)``). The deltas are in each parameter's own space, after the
        mask: position offset, the quaternion increment's offset from the identity, the
        log-scale change, the opacity-logit change.
    """
    m = mask[:, None, :, None]  # (B, 1, N, 1)
    d_means = (1 - m) * raw["rigid_offset"] + m * raw["nonrigid_offset"]
    d_quats = m * raw["rotation"]
    d_scales = m * (MAX_LOG_SCALE_CHANGE * torch.tanh(raw["scale"] / MAX_LOG_SCALE_CHANGE))
    d_opacities = (m * raw["opacity"]).squeeze(-1)
    identity = _identity_quaternions(d_quats)
    increment = unit_quaternions(identity + d_quats)
    deformed = {
        "means": canonical["means"] + d_means,
        "quats": quaternion_product(canonical["quats"], increment),
        "scales": canonical["scales"] * torch.exp(d_scales),
        "opacities": _shift_opacity_logit(canonical["opacities"], d_opacities),
    }
    deltas = {
        "means": d_means,
        "quats": increment - identity,
        "scales": d_scales,
        "opacities": d_opacities,
    }
    return deformed, deltas


@typechecked
def official_update(
    canonical: Mapping[str, Tensor], raw: Mapping[str, Tensor], mask: Float[Tensor, "B T N"]
) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """The ``official`` update rule (the released code): the deformed parameters and deltas.

    ``mu' = mu + clamp(d_mu, +-10)`` (one position head, unmasked),
    ``q' = q (x) (m normalize(d_rot + 1e-8) + (1 - m) [1, 0, 0, 0])`` (not renormalised),
    ``s' = s + m clamp(d_s, +-1)``, ``o' = clamp(o + m d_o, 0, 1)``.

    Args:
        canonical: as for :func:`paper_update`.
        raw: the head outputs ``rigid_offset`` (the one position head), ``rotation``,
            ``scale``, ``opacity``, each ``(B, T, N, k)``.
        mask: m, ``(B, T, N)``, per time step (1 = nonrigid).

    Returns:
        ``(deformed, deltas)`` as for :func:`paper_update`; the deltas are deformed minus
        canonical values (the official ``L_reg`` terms).
    """
    m = mask[..., None]  # (B, T, N, 1)
    identity = _identity_quaternions(raw["rotation"])
    blended = m * unit_quaternions(raw["rotation"] + _OFFICIAL_QUAT_EPS) + (1 - m) * identity
    deformed = {
        "means": canonical["means"]
        + raw["rigid_offset"].clamp(-_OFFICIAL_OFFSET_CLAMP, _OFFICIAL_OFFSET_CLAMP),
        "quats": quaternion_product(canonical["quats"], blended),
        "scales": canonical["scales"]
        + m * raw["scale"].clamp(-_OFFICIAL_SCALE_CLAMP, _OFFICIAL_SCALE_CLAMP),
        "opacities": (canonical["opacities"] + mask * raw["opacity"].squeeze(-1)).clamp(0, 1),
    }
    deltas = {name: deformed[name] - canonical[name] for name in PARAMETERS}
    return deformed, deltas


@dataclasses.dataclass(frozen=True)
class PresetSpec:
    """Everything preset-specific of :class:`dego.DecoupledDeformation` and its losses.

    Attributes:
        name: the preset's name.
        update: the update rule (:func:`paper_update`, :func:`official_update`).
        heads: the delta heads and their output widths (the mask head apart).
        nonrigid_head: the head whose output is ``d_mu_def`` (``"rigid_offset"``: the one
            position head is both).
        mask_per_time: the mask is ``sigmoid(mask_head(h(t)))`` per time step, ``(B, T, N)``
            (else ``sigmoid(mask_net([f, PE_p(mu)]))`` per Gaussian, ``(B, N)``).
        scaled_positions: ``pos_scale`` defaults to the Occ3D grid's largest absolute
            bound (else 1: raw positions).
        xavier_init: every Linear is xavier-uniform with zero bias (else PyTorch's default
            with the last layer of every head zeroed: the initial deformation is exact).
        reg_element_mean: ``L_reg`` takes a parameter delta's mean over its elements
            (else the squared norm) before the (B, T, N) reduction, except under ``"sum"``.
        mask_loss_last_step: ``L_mask`` uses the last time step's mask only.
    """

    name: Preset
    update: UpdateRule
    heads: tuple[tuple[str, int], ...]
    nonrigid_head: str
    mask_per_time: bool
    scaled_positions: bool
    xavier_init: bool
    reg_element_mean: bool
    mask_loss_last_step: bool


PRESETS: Mapping[str, PresetSpec] = MappingProxyType(
    {
        "paper": PresetSpec(
            name="paper",
            update=paper_update,
            heads=(
                ("rigid_offset", 3),
                ("nonrigid_offset", 3),
                ("rotation", 4),
                ("scale", 3),
                ("opacity", 1),
            ),
            nonrigid_head="nonrigid_offset",
            mask_per_time=False,
            scaled_positions=True,
            xavier_init=False,
            reg_element_mean=False,
            mask_loss_last_step=False,
        ),
        "official": PresetSpec(
            name="official",
            update=official_update,
            heads=(("rigid_offset", 3), ("rotation", 4), ("scale", 3), ("opacity", 1)),
            nonrigid_head="rigid_offset",
            mask_per_time=True,
            scaled_positions=False,
            xavier_init=True,
            reg_element_mean=True,
            mask_loss_last_step=True,
        ),
    }
)
"""Preset name -> :class:`PresetSpec`."""


__all__ = [
    "MAX_LOG_SCALE_CHANGE",
    "PARAMETERS",
    "PRESETS",
    "Preset",
    "PresetSpec",
    "official_update",
    "paper_update",
    "shift_opacity_logit",
]
