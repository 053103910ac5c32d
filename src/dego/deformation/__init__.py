"""Decoupled rigid / nonrigid Gaussian deformation over time (DeGO section 4.1).

A canonical Gaussian set at t = 0 is deformed to T time offsets by one MLP pass over all
(Gaussian, time) pairs. Each Gaussian i has a rigidity mask m_i in [0, 1] (1 = nonrigid)
and the update is ``dG = (1 - m) dG_rig + m dG_def`` with ``dG_rig = (d_mu_rig, 0, 0, 0)``
and ``dG_def = (d_mu_def, d_rot, d_scale, d_opacity)``.

Modules: ``module`` (the network, :class:`DecoupledDeformation`), ``presets`` (the
``paper`` / ``official`` table ``PRESETS`` and their update rules), ``loss`` (the loss
weights and terms: :class:`DeformationLossWeights`, :class:`DeformationLoss`),
``results`` (:class:`DeformationOutput`, :class:`DeformationDeltas` and
:func:`deformation_loss`, which reads them) and ``checkpoint`` (official DeGO checkpoints
as a pure key mapping). ``presets``, ``loss`` and ``checkpoint`` import no other module of
the package.
"""

from __future__ import annotations

# The API is __all__. A name imported as ``x as x`` is not part of it: dego.deformation
# carried it when it was one module, and it stays importable from here.
from dego.deformation.checkpoint import OFFICIAL_CHECKPOINT_PREFIX, StateDictMismatchError
from dego.deformation.checkpoint import from_official_tensors as from_official_tensors
from dego.deformation.checkpoint import official_state_dict as official_state_dict
from dego.deformation.checkpoint import read_official_state_dict as read_official_state_dict
from dego.deformation.loss import REDUCTIONS, DeformationLoss, DeformationLossWeights
from dego.deformation.module import RIGID_MOTIONS, DecoupledDeformation, RigidMotion
from dego.deformation.module import canonical_batch as canonical_batch
from dego.deformation.module import check_like_gaussians as check_like_gaussians
from dego.deformation.presets import MAX_LOG_SCALE_CHANGE, PARAMETERS, shift_opacity_logit
from dego.deformation.presets import PRESETS as PRESETS
from dego.deformation.presets import Preset as Preset
from dego.deformation.presets import PresetSpec as PresetSpec
from dego.deformation.results import DeformationDeltas, DeformationOutput, deformation_loss
from dego.gaussians import quaternion_multiply

__all__ = [
    "MAX_LOG_SCALE_CHANGE",
    "OFFICIAL_CHECKPOINT_PREFIX",
    "PARAMETERS",
    "REDUCTIONS",
    "RIGID_MOTIONS",
    "DecoupledDeformation",
    "DeformationDeltas",
    "DeformationLoss",
    "DeformationLossWeights",
    "DeformationOutput",
    "RigidMotion",
    "StateDictMismatchError",
    "deformation_loss",
    "quaternion_multiply",
    "shift_opacity_logit",
]
