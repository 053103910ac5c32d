"""The deformation network, :class:`DecoupledDeformation` (DeGO section 4.1), and the
input checks it shares with the porting adapters (:func:`canonical_batch`,
:func:`check_like_gaussians`).

The preset-specific parts come from :mod:`dego.deformation.presets`, the official
checkpoint key mapping from :mod:`dego.deformation.checkpoint`, the result and loss types
from :mod:`dego.deformation.results` and :mod:`dego.deformation.loss`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from typing import Any, Literal

import torch
from jaxtyping import Float
from torch import Tensor, nn

from dego._checks import check_int, check_positive
from dego._policy import finite_check, float32_under_autocast, run_checks
from dego._typing import typechecked
from dego.deformation.checkpoint import (
    from_official_tensors,
    official_state_dict,
    read_official_state_dict,
)
from dego.deformation.loss import DeformationLossWeights
from dego.deformation.presets import PARAMETERS, PRESETS, Preset, PresetSpec
from dego.deformation.results import DeformationDeltas, DeformationOutput
from dego.encoding import positional_encoding
from dego.gaussians import GaussianSet
from dego.grid import VoxelGrid

_CPU_CHUNK_ROWS = 4096  # (Gaussian, time) rows per feature-net chunk on CPU: cache-sized

RigidMotion = Literal["time", "velocity"]
RIGID_MOTIONS: tuple[RigidMotion, ...] = ("time", "velocity")
"""How :class:`DecoupledDeformation`'s rigid branch moves a Gaussian. ``"time"`` (the
paper's): ``d_mu_rig = rigid_offset(h(t))``, a function of the time-conditioned features;
``"velocity"`` (ours, beyond the paper): one velocity per Gaussian from ``[f, PE(mu)]``,
``d_mu_rig = t v``, so the rigid offset is exactly linear in time and 0 at t = 0."""


def canonical_batch(gaussians: GaussianSet) -> tuple[int, int]:
    """``(B, N)`` of a canonical set; ``ValueError`` unless its batch shape is ``(B,)``."""
    if len(gaussians.batch_shape) != 1:
        raise ValueError(
            f"gaussians: expected batch shape (B,), got {tuple(gaussians.batch_shape)}"
        )
    return gaussians.batch_shape[0], gaussians.num_gaussians


def check_like_gaussians(
    gaussians: GaussianSet, weight: Tensor, features: Tensor, *others: tuple[str, Tensor]
) -> None:
    """The input checks of the deformation networks: ``features`` and ``others`` in the
    Gaussians' dtype and device, the module's parameters (``weight``) too, and finite
    Gaussians and features (one host sync)."""
    for name, value in [("features", features), *others]:
        if value.dtype != gaussians.dtype or value.device != gaussians.device:
            raise ValueError(
                f"{name}: expected {gaussians.dtype} on {gaussians.device} like gaussians, "
                f"got {value.dtype} on {value.device}"
            )
    if gaussians.dtype != weight.dtype or gaussians.device != weight.device:
        raise ValueError(
            f"gaussians: {gaussians.dtype} on {gaussians.device}, but the module's "
            f"parameters are {weight.dtype} on {weight.device}; move one with .to()"
        )
    named = [*((f"gaussians.{name}", t) for name, t in gaussians.items()), ("features", features)]
    run_checks([finite_check(name, t) for name, t in named])


def _last_linear(mlp: nn.Module) -> nn.Linear:
    """The output layer of an :func:`_mlp`."""
    assert isinstance(mlp, nn.Sequential)
    last = mlp[-1]
    assert isinstance(last, nn.Linear)
    return last


def _mlp(in_dim: int, hidden: int, out_dim: int, layers: int) -> nn.Sequential:
    """``layers`` Linear layers with ReLU between them (none after the last)."""
    dims = [in_dim] + [hidden] * (layers - 1) + [out_dim]
    modules: list[nn.Module] = []
    for i in range(layers):
        modules.append(nn.Linear(dims[i], dims[i + 1]))
        if i < layers - 1:
            modules.append(nn.ReLU())
    return nn.Sequential(*modules)


class DecoupledDeformation(nn.Module):
    """DeGO's decoupled Gaussian deformation network.

    Architecture (paper section 4.1 and its hyperparameter table):

    - time embedding ``e_t = MLP(PE_t(t))``: Linear(2 L_t + 1, time_dim), ReLU,
      Linear(time_dim, time_dim);
    - feature net: ``depth`` Linear + ReLU layers of width ``hidden_dim`` on
      ``[f_i, PE_p(mu_i), e_t]``; its first layer is split into a per-Gaussian part and a
      per-time part, so the ``[f_i, PE_p(mu_i)]`` projection is computed once for all T;
    - 2-layer heads (Linear(hidden_dim, head_hidden), ReLU, Linear(head_hidden, k)):
      ``rigid_offset`` (3), ``nonrigid_offset`` (3), ``rotation`` (4), ``scale`` (3),
      ``opacity`` (1) and the mask logit (1).

    Presets (one :class:`~dego.deformation.presets.PresetSpec` each, in
    :data:`dego.deformation.presets.PRESETS`; the update rules are
    :func:`~dego.deformation.presets.paper_update` and
    :func:`~dego.deformation.presets.official_update`):

    ``"paper"`` (default), the method as written, with positivity-preserving updates:
        - m is per Gaussian and time-independent: ``sigmoid(mask_net([f, PE_p(mu)]))``;
        - ``mu' = mu + (1 - m) d_mu_rig + m d_mu_def``;
        - ``q' = q (x) normalize(1 + m d_rot)``: composing a unit increment keeps the
          canonical norm, so unit quaternions stay unit;
        - ``s' = s exp(m d_s)`` with ``d_s`` soft-bounded to +-:data:`MAX_LOG_SCALE_CHANGE`;
        - ``o' = sigmoid(logit(o) + m d_o)`` (:func:`shift_opacity_logit`);
        - times divided by ``time_scale``; positions divided by ``pos_scale`` (default:
          the Occ3D grid's largest absolute bound, 40 m) before PE_p;
        - PyTorch's default init, except the last layer of every delta head, zero-initialised
          so the initial deformation is exactly the identity (and m = 0.5);
        - :func:`deformation_loss`: ``mean ||d_p||^2`` over (B, T, N) of the applied
          deltas, L_mask over the per-Gaussian masks.

    ``"official"``, the released code's behaviour; differences from ``paper``:
        1. one position head: ``d_mu_rig`` and ``d_mu_def`` are the same tensor, added to
           every Gaussian unmasked, clamped to +-10 m (there is no ``nonrigid_offset`` head);
        2. m depends on time: ``sigmoid(mask_head(h(t)))``, shape ``(B, T, N)``;
        3. ``q' = q (x) (m normalize(d_rot + 1e-8) + (1 - m) [1, 0, 0, 0])``: the blended
           increment is not renormalised, so q' is not unit;
        4. ``s' = s + m clamp(d_s, +-1)``: linear, may become <= 0;
        5. ``o' = clamp(o + m d_o, 0, 1)``;
        6. times and positions are used raw (``pos_scale`` defaults to 1; the official
           time is the frame index 0..16, current = 8);
        7. every Linear is xavier-uniform initialised with zero bias (the initial
           deformation is not the identity; m starts near 0.5);
        8. :func:`deformation_loss`: ``mean((p' - p)^2)`` over all elements, L_mask on the
           last time step's mask only.

        Released weights load with :meth:`from_official_state_dict`.

    Args:
        feature_dim: C_g, channels of the per-Gaussian latent features.
        pos_levels: L_p (6), frequency levels of the position encoding.
        time_levels: L_t (4), frequency levels of the time encoding.
        time_dim: C_t (32), the time-embedding width.
        hidden_dim: D_h (256), the feature-net width.
        depth: feature-net layers (6).
        head_hidden: hidden width of the 2-layer heads (256).
        preset: ``"paper"`` or ``"official"``.
        time_scale: times are divided by it (e.g. the clip's largest offset).
        pos_scale: positions are divided by it before encoding (``None``: preset default).
        loss_weights: default :class:`DeformationLossWeights` of :func:`deformation_loss`.
        fixed_mask: ``None`` (default): m is learned. A number in [0, 1]: m is that constant
            for every Gaussian and time and the mask head is unused; ``0.0`` gives the
            rigid-only baseline (position offsets only, as in GaussianFlowOcc; add its class
            gating with :func:`gate_by_class`, or use :class:`TemporalOffsetNetwork`),
            ``1.0`` a nonrigid-only model.
        rigid_motion: ``"time"`` (default, the paper's rigid branch) or ``"velocity"``:
            the rigid offset is ``t v`` with one velocity ``v`` per Gaussian predicted
            from ``[f_i, PE_p(mu_i)]`` by a 2-layer head (zero-initialised), ``t`` the
            time divided by ``time_scale``; the nonrigid branch stays time-conditioned.
            Motion over a clip is one vector to learn per Gaussian instead of one per
            (Gaussian, time). ``"paper"`` preset only.
        chunk_rows: about how many (Gaussian, time) rows the feature net and heads process
            at a time (Gaussians are chunked, every chunk covers all T); a speed knob
            only: results agree to floating-point rounding. ``None``: 4096 on CPU, where
            cache-sized chunks are about 1.5-2x faster, all rows at once elsewhere.
    """

    def __init__(
        self,
        feature_dim: int,
        *,
        pos_levels: int = 6,
        time_levels: int = 4,
        time_dim: int = 32,
        hidden_dim: int = 256,
        depth: int = 6,
        head_hidden: int = 256,
        preset: Preset = "paper",
        time_scale: float = 1.0,
        pos_scale: float | None = None,
        loss_weights: DeformationLossWeights | None = None,
        fixed_mask: float | None = None,
        rigid_motion: RigidMotion = "time",
        chunk_rows: int | None = None,
    ) -> None:
        super().__init__()
        for name, value, low in [
            ("feature_dim", feature_dim, 0),
            ("pos_levels", pos_levels, 0),
            ("time_levels", time_levels, 0),
            ("time_dim", time_dim, 1),
            ("hidden_dim", hidden_dim, 1),
            ("depth", depth, 1),
            ("head_hidden", head_hidden, 1),
            ("chunk_rows", 1 if chunk_rows is None else chunk_rows, 1),
        ]:
            check_int(name, value, low)
        if preset not in PRESETS:
            raise ValueError(f"preset: expected 'paper' or 'official', got {preset!r}")
        spec = PRESETS[preset]
        if pos_scale is None:
            grid = VoxelGrid.occ3d()
            pos_scale = max(map(abs, (*grid.lower, *grid.upper))) if spec.scaled_positions else 1.0
        check_positive("time_scale", time_scale)
        check_positive("pos_scale", pos_scale)
        if fixed_mask is not None and (
            isinstance(fixed_mask, bool)
            or not isinstance(fixed_mask, int | float)
            or not 0 <= fixed_mask <= 1
        ):
            raise ValueError(f"fixed_mask: expected None or a number in [0, 1], got {fixed_mask!r}")
        if rigid_motion not in RIGID_MOTIONS:
            raise ValueError(f"rigid_motion: expected one of {RIGID_MOTIONS}, got {rigid_motion!r}")
        if rigid_motion == "velocity" and preset != "paper":
            raise ValueError(
                f"rigid_motion: 'velocity' needs the 'paper' preset (the official network has "
                f"one position head for both branches), got preset {preset!r}"
            )
        if loss_weights is not None and not isinstance(loss_weights, DeformationLossWeights):
            raise TypeError(
                f"loss_weights: expected DeformationLossWeights, got {type(loss_weights).__name__}"
            )
        self.feature_dim = feature_dim
        self.pos_levels, self.time_levels = pos_levels, time_levels
        self.preset: Preset = preset
        self.time_scale, self.pos_scale = float(time_scale), float(pos_scale)
        self.loss_weights = loss_weights or DeformationLossWeights()
        self.chunk_rows = chunk_rows
        self.fixed_mask = None if fixed_mask is None else float(fixed_mask)
        self.rigid_motion: RigidMotion = rigid_motion

        static_dim = feature_dim + 3 * (2 * pos_levels + 1)
        self.time_embedding = _mlp(2 * time_levels + 1, time_dim, time_dim, 2)
        # The first feature-net layer on [f, PE(mu), e_t], split by input block.
        self.input_static = nn.Linear(static_dim, hidden_dim)
        self.input_time = nn.Linear(time_dim, hidden_dim, bias=False)
        self.trunk = _mlp(hidden_dim, hidden_dim, hidden_dim, depth - 1) if depth > 1 else None
        velocity = rigid_motion == "velocity"
        self.heads = nn.ModuleDict(
            {
                name: _mlp(hidden_dim, head_hidden, k, 2)
                for name, k in spec.heads
                if not (velocity and name == "rigid_offset")
            }
        )
        # per Gaussian, on [f, PE(mu)] like the paper's mask: d_mu_rig = t v
        self.velocity_head = _mlp(static_dim, head_hidden, 3, 2) if velocity else None
        # per time step: on the feature net's h(t); per Gaussian: on [f, PE(mu)]
        mask_in = hidden_dim if spec.mask_per_time else static_dim
        self.mask_head = _mlp(mask_in, head_hidden, 1, 2)
        self.reset_parameters()

    @property
    def spec(self) -> PresetSpec:
        """The preset's :class:`~dego.deformation.presets.PresetSpec`."""
        return PRESETS[self.preset]

    @typechecked
    def reset_parameters(self) -> None:
        """Re-initialise per the preset (see the class docstring)."""
        for module in self.modules():
            if isinstance(module, nn.Linear):
                module.reset_parameters()
        if self.spec.xavier_init:
            for module in self.modules():
                if isinstance(module, nn.Linear):
                    nn.init.xavier_uniform_(module.weight)
                    if module.bias is not None:
                        nn.init.zeros_(module.bias)
            # xavier of the split first layer as the one (D_h, fan_in) matrix it stands for
            fan_out, static_in = self.input_static.weight.shape
            fan_in = static_in + self.input_time.weight.shape[1]
            bound = math.sqrt(6.0 / (fan_in + fan_out))
            for part in (self.input_static.weight, self.input_time.weight):
                nn.init.uniform_(part, -bound, bound)
        else:
            velocity = [] if self.velocity_head is None else [self.velocity_head]
            for head in [*self.heads.values(), self.mask_head, *velocity]:
                last = _last_linear(head)
                nn.init.zeros_(last.weight)
                nn.init.zeros_(last.bias)

    def _normalized_times(self, times: Tensor, batch: int) -> Tensor:
        message = "times: expected finite values, got NaN or inf"
        run_checks([(torch.isfinite(times).all(), message, lambda: ValueError(message))])
        if times.shape[-1] == 0:
            raise ValueError("times: expected at least one time step, got T = 0")
        if times.ndim == 1:
            times = times.expand(batch, -1)
        elif times.shape[0] != batch:
            raise ValueError(
                f"times: expected shape (T,) or (B, T) with B = {batch}, got {tuple(times.shape)}"
            )
        return times / self.time_scale

    @float32_under_autocast(keep_autocast=True)
    @typechecked
    def forward(
        self,
        gaussians: GaussianSet,
        features: Float[Tensor, "B N C"],
        times: Float[Tensor, " T"] | Float[Tensor, "B T"],
    ) -> DeformationOutput:
        """Deform the canonical ``(B, N)`` set to every time in ``times``.

        Args:
            gaussians: canonical Gaussians at t = 0, batch shape ``(B,)``.
            features: ``(B, N, C_g)`` per-Gaussian latent features.
            times: ``(T,)`` offsets shared by the batch or ``(B, T)`` per sample, in the
                unit of ``time_scale`` (frames or seconds).

        Returns:
            :class:`DeformationOutput` with ``gaussians`` of batch shape ``(B, T)``.
        """
        b, n = canonical_batch(gaussians)
        if features.shape[:2] != (b, n):
            raise ValueError(
                f"features: expected shape ({b}, {n}, C_g) to match gaussians, got "
                f"{tuple(features.shape)}"
            )
        if features.shape[-1] != self.feature_dim:
            raise ValueError(
                f"features: expected C_g = {self.feature_dim} channels, got {features.shape[-1]}"
            )
        check_like_gaussians(gaussians, self.input_static.weight, features, ("times", times))
        times = self._normalized_times(times, b)  # (B, T)

        static = torch.cat(
            [features, positional_encoding(gaussians.means / self.pos_scale, self.pos_levels)], -1
        )  # (B, N, C_static)
        embedding = self.time_embedding(positional_encoding(times[..., None], self.time_levels))
        static_part = self.input_static(static)[:, None]  # (B, 1, N, D_h)
        time_part = self.input_time(embedding)[:, :, None]  # (B, T, 1, D_h)
        t = times.shape[1]
        spec = self.spec
        heads = {name: head for name, head in self.heads.items()}
        if spec.mask_per_time and self.fixed_mask is None:
            heads["mask"] = self.mask_head
        # All T at once, over bounded chunks of Gaussians: the arithmetic of one pass,
        # but on a CPU each chunk's activations stay in cache (1.5-2x faster fwd + bwd).
        chunk_rows = self.chunk_rows or (_CPU_CHUNK_ROWS if static.device.type == "cpu" else 0)
        per_chunk = max(1, chunk_rows // (b * t)) if chunk_rows and b * t else max(n, 1)
        outputs: dict[str, list[Tensor]] = {name: [] for name in heads}
        for start in range(0, n, per_chunk):
            hidden = torch.relu(static_part[:, :, start : start + per_chunk] + time_part)
            if self.trunk is not None:
                hidden = torch.relu(self.trunk(hidden))
            for name, head in heads.items():
                outputs[name].append(head(hidden))  # (B, T, chunk, k)
        # Under autocast the layers run in its dtype; the deltas return in the Gaussians'.
        raw = {
            name: torch.cat(parts, 2).to(static.dtype)
            if parts
            else static.new_zeros(b, t, n, _last_linear(heads[name]).out_features)
            for name, parts in outputs.items()
        }
        mask_shape = (b, t, n) if spec.mask_per_time else (b, n)
        if self.fixed_mask is not None:
            mask = static.new_full(mask_shape, self.fixed_mask)
        elif spec.mask_per_time:
            mask = torch.sigmoid(raw.pop("mask")).squeeze(-1)  # (B, T, N)
        else:
            mask = torch.sigmoid(self.mask_head(static).to(static.dtype)).squeeze(-1)  # (B, N)
        if self.velocity_head is not None:
            velocities = self.velocity_head(static).to(static.dtype)  # (B, N, 3)
            raw["rigid_offset"] = times[:, :, None, None] * velocities[:, None]
        canonical = {name: getattr(gaussians, name)[:, None] for name in PARAMETERS}
        deformed, deltas = spec.update(canonical, raw, mask)
        if gaussians.features is not None:
            deformed["features"] = gaussians.features[:, None].expand(-1, t, -1, -1)
        return DeformationOutput(
            gaussians=GaussianSet(**deformed),
            rigid_mask=mask,
            deltas=DeformationDeltas(**deltas),
            rigid_offsets=raw["rigid_offset"],
            nonrigid_offsets=raw[spec.nonrigid_head],
            preset=self.preset,
            loss_weights=self.loss_weights,
        )

    @typechecked
    def to_official_state_dict(self, prefix: str = "") -> dict[str, Tensor]:
        """This module's weights as a state dict of the official DeGO deformation module.

        The official ``GaussianDeformationMaskStaticRigid`` (``use_static_mask=False``, the
        released configuration) with ``in_channels=feature_dim``, ``hidden_dim``,
        ``depth``, ``time_channels=time_dim``, ``pos_enc_levels=pos_levels``,
        ``time_enc_levels=time_levels`` loads it with ``load_state_dict`` and then computes
        what this module computes. The exact inverse of :meth:`from_official_state_dict`;
        the tensors are detached (the first layer's weight is a new concatenation).

        Args:
            prefix: prepended to every key, e.g. :data:`OFFICIAL_CHECKPOINT_PREFIX` to
                splice the result into a detector checkpoint (a missing trailing ``"."`` is
                added).

        Raises:
            ValueError: the ``paper`` preset (a different network) or ``head_hidden`` other
                than ``hidden_dim`` (the official heads are ``hidden_dim`` wide).

        Warns:
            UserWarning: ``time_scale``, ``pos_scale`` other than 1 or a ``fixed_mask``: the
                official module has no such setting and will compute something else.
        """
        if self.preset != "official":
            raise ValueError(
                f"preset: only an 'official' preset module has an official state dict, this one "
                f"is {self.preset!r} (a different network: separate nonrigid head, "
                "per-Gaussian mask)"
            )
        params = dict(self.named_parameters())
        state = official_state_dict(params, self.pos_levels, self.time_levels, prefix)
        head_hidden = self.mask_head[0].out_features
        hidden = self.input_static.out_features
        if head_hidden != hidden:
            raise ValueError(
                f"head_hidden: the official heads are hidden_dim = {hidden} wide, this module's "
                f"are {head_hidden}"
            )
        differences = [
            f"{name}={value}"
            for name, value, default in [
                ("time_scale", self.time_scale, 1.0),
                ("pos_scale", self.pos_scale, 1.0),
                ("fixed_mask", self.fixed_mask, None),
            ]
            if value != default
        ]
        if differences:
            warnings.warn(
                f"to_official_state_dict: the official module has no {', '.join(differences)}; "
                "it will load these weights but compute something else",
                stacklevel=3,  # past the run-time type check, at the caller
            )
        return state

    @classmethod
    @typechecked
    def from_official_state_dict(
        cls,
        state_dict: Mapping[str, Any],
        *,
        prefix: str = "",
        strict: bool = True,
        **kwargs: Any,
    ) -> DecoupledDeformation:
        """An ``official`` preset module with the official DeGO deformation network's weights.

        Reads the state dict of ``GaussianDeformationMaskStaticRigid`` (DeGO's
        ``deformation_mask_static_rigid_new_fully_spv.py``, as released:
        ``use_static_mask=False``, ``use_rigid_mask=True``, every ``deform_*`` on); the
        module returned computes the official forward's deformed means, rotations, scales,
        opacities and mask for the same inputs (times as the official frame indices).

        ``feature_dim``, ``hidden_dim``, ``depth``, ``time_dim``, ``pos_levels`` and
        ``time_levels`` are read from the shapes (``head_hidden`` = ``hidden_dim``, as in the
        official heads); any of them given in ``kwargs`` is used instead, and the state
        dict is checked against it. The official first layer ``feature_net.0`` (on
        ``[f, PE(mu), e_t]``) is split column-wise into ``input_static`` and
        ``input_time``; ``rigid_mask_head`` -> ``mask_head``, ``position_head`` ->
        ``heads.rigid_offset``, ``rotation_head``/``scale_head``/``opacity_head`` ->
        ``heads.rotation``/``scale``/``opacity``, ``time_embed`` -> ``time_embedding``,
        ``feature_net.{2j}`` -> ``trunk.{2j - 2}``. The buffers ``pos_enc_freqs`` and
        ``time_enc_freqs`` must hold ``2^k`` (they fix the levels; nothing is loaded).

        Args:
            state_dict: the official module's ``state_dict()``, a detector's (select it with
                ``prefix``), or a whole checkpoint dict whose ``"state_dict"`` entry is one.
            prefix: only keys starting with it are read, with it removed; the released
                detector's is :data:`OFFICIAL_CHECKPOINT_PREFIX`
                (``"gaussian_decoder.deformation_module."``). A missing trailing ``"."`` is
                added. With the default ``""`` every key must belong to the module.
            strict: ``True``: any missing, unexpected or mis-shaped key (or a frequency
                buffer that is not ``2^k``) raises :class:`StateDictMismatchError` listing
                them (up to 20 of each kind, then a count). ``False``: load the keys that
                fit and warn (``UserWarning``) with the list of the others; parameters not
                loaded keep their initialisation. Whatever ``strict`` is, the key set is
                checked before anything is built: when ``depth`` is inferred, the
                ``feature_net`` layer indices must have no gaps and give a depth of at
                most 64 (pass ``depth=`` to load a deeper network).
            kwargs: other :class:`DecoupledDeformation` arguments (``time_scale``,
                ``pos_scale``, ``fixed_mask``, ``loss_weights``, ``chunk_rows``, the sizes
                above); ``preset`` may only be ``"official"``. The defaults reproduce the
                official module; other ``time_scale``, ``pos_scale`` or ``fixed_mask``
                values change what it computes.

        Returns:
            The module, on the device and in the dtype of the state dict's
            ``feature_net.0.weight``.

        Raises:
            StateDictMismatchError: (a ``KeyError`` and ``ValueError``) keys do not match in
                strict mode, or the sizes cannot be inferred.
            TypeError: ``state_dict`` is not a mapping, ``prefix`` not a str.
        """
        found = read_official_state_dict(state_dict, prefix, strict, kwargs)
        if found.skipped is not None:
            warnings.warn(
                f"from_official_state_dict(strict=False) skipped keys; the parameters they "
                f"would fill keep their initialisation. {found.skipped}",
                stacklevel=3,  # past the run-time type check, at the caller
            )
        module = cls(**found.sizes, preset="official", **kwargs)  # type: ignore[arg-type]
        # dtype and device from the first layer (else any floating tensor that fits)
        tensors = found.tensors
        reference = tensors.get("feature_net.0.weight", next(iter(tensors.values()), None))
        if reference is not None:
            module = module.to(dtype=reference.dtype, device=reference.device)
        params = dict(module.named_parameters())
        ours = from_official_tensors(tensors, module.input_static.in_features, found.sizes["depth"])
        with torch.no_grad():
            for name, value in ours.items():
                params[name].copy_(value)
        return module

    def extra_repr(self) -> str:
        return (
            f"feature_dim={self.feature_dim}, preset={self.preset!r}, "
            f"time_scale={self.time_scale}, pos_scale={self.pos_scale}"
            + ("" if self.fixed_mask is None else f", fixed_mask={self.fixed_mask}")
            + ("" if self.rigid_motion == "time" else f", rigid_motion={self.rigid_motion!r}")
        )


__all__ = [
    "RIGID_MOTIONS",
    "DecoupledDeformation",
    "RigidMotion",
    "canonical_batch",
    "check_like_gaussians",
]
