"""Per-frame position offsets: the demo's ``free offsets``, ``free velocities`` and
``true motion (oracle)`` rows.

Both stand in for a deformation network where :func:`~dego.demo.gaussians_at` expects
one: called like :class:`~dego.DecoupledDeformation` they return a
:class:`~dego.DeformationOutput` whose Gaussians are the canonical ones moved by an
offset of their own at each frame (no rotation, scale or opacity change, mask 0).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from jaxtyping import Float, Int
from torch import Tensor, nn

from dego.data.synthetic import SyntheticScene
from dego.deformation import DeformationDeltas, DeformationLossWeights, DeformationOutput
from dego.demo.clip import DemoClip
from dego.gaussians import GaussianSet

NO_REGULARISER = DeformationLossWeights(reg=0.0, mask=0.0)
"""Offsets are fitted (or held) as they are: no ``L_reg``, no mask loss."""


class FrameOffsets(nn.Module):
    """A position offset per (frame, Gaussian), looked up by the frame's time offset.

    Args:
        times: ``(T,)`` the clip's frame offsets (:attr:`DemoClip.times`).
        offsets: ``(T, N, 3)`` initial offsets in metres.
        trainable: ``True``: the offsets are a parameter (``free offsets``); ``False``: a
            fixed buffer (``true motion (oracle)``).
    """

    fixed_mask = 0.0  # no rigidity mask to learn (what gaussians_at checks)
    times: Tensor  # a buffer

    def __init__(
        self,
        times: Float[Tensor, " T"],
        offsets: Float[Tensor, "T N 3"],
        *,
        trainable: bool = True,
    ) -> None:
        super().__init__()
        if times.ndim != 1 or offsets.ndim != 3 or offsets.shape[::2] != (times.shape[0], 3):
            raise ValueError(
                f"offsets: expected shape (T, N, 3) with T = {times.shape[0]} frame times, got "
                f"{tuple(offsets.shape)}"
            )
        self.register_buffer("times", times.detach().clone())
        if trainable:
            self.offsets = nn.Parameter(offsets.detach().clone())
        else:
            self.register_buffer("offsets", offsets.detach().clone())

    def forward(
        self,
        gaussians: GaussianSet,
        features: Tensor,
        times: Float[Tensor, " T"],
    ) -> DeformationOutput:
        """The ``(1, N)`` canonical set moved to each of ``times`` (frame offsets of the
        clip); ``features`` (the latent) is unused."""
        del features
        index = _frame_index(self.times, times)
        n = self.num_gaussians
        if tuple(gaussians.batch_shape) != (1,) or gaussians.num_gaussians != n:
            raise ValueError(
                f"gaussians: expected batch shape (1,) with N = {n}, got "
                f"{tuple(gaussians.batch_shape)} with N = {gaussians.num_gaussians}"
            )
        d_means = self.frame_offsets(index)[None]  # (1, T, N, 3)
        t, n = d_means.shape[1], d_means.shape[2]
        identity = torch.zeros(1, t, n, 4, dtype=d_means.dtype, device=d_means.device)
        deformed = gaussians.map(lambda _, value: value[:, None].expand(-1, t, *value.shape[1:]))
        deformed = deformed.replace(means=deformed.means + d_means)
        return DeformationOutput(
            gaussians=deformed,
            rigid_mask=d_means.new_zeros(1, n),
            deltas=DeformationDeltas(
                d_means, identity, torch.zeros_like(d_means), d_means.new_zeros(1, t, n)
            ),
            rigid_offsets=d_means,
            nonrigid_offsets=d_means,
            preset="paper",
            loss_weights=NO_REGULARISER,
        )

    @property
    def num_gaussians(self) -> int:
        return self.offsets.shape[1]

    def frame_offsets(self, index: Int[Tensor, " T"]) -> Float[Tensor, "T N 3"]:
        """The ``(T, N, 3)`` offsets of the frames at ``index`` into :attr:`times`."""
        return self.offsets[index]


class FrameVelocities(FrameOffsets):
    """One trainable velocity per Gaussian: the offset at frame offset t is ``t * v``
    (metres per frame), so every frame's labels pull on the same few numbers (the
    ``free velocities`` reference: constant-velocity motion, no network, no regulariser).

    Args:
        times: ``(T,)`` the clip's frame offsets. velocities: ``(N, 3)`` initial velocities.
    """

    def __init__(self, times: Float[Tensor, " T"], velocities: Float[Tensor, "N 3"]) -> None:
        if velocities.ndim != 2 or velocities.shape[1] != 3:
            raise ValueError(f"velocities: expected shape (N, 3), got {tuple(velocities.shape)}")
        nn.Module.__init__(self)  # (1, N, 3), not FrameOffsets' (T, N, 3)
        self.register_buffer("times", times.detach().clone())
        self.offsets = nn.Parameter(velocities.detach().clone()[None])

    @property
    def velocities(self) -> Tensor:
        return self.offsets[0]

    def frame_offsets(self, index: Int[Tensor, " T"]) -> Float[Tensor, "T N 3"]:
        return self.times[index][:, None, None] * self.offsets  # (T, 1, 1) * (1, N, 3)


def _frame_index(frame_times: Tensor, times: Tensor) -> Tensor:
    match = times.to(frame_times)[:, None] == frame_times[None]
    if times.ndim != 1 or not bool(match.any(1).all()):
        raise ValueError(
            f"times: expected (T,) frame offsets among {frame_times.tolist()}, got {times.tolist()}"
        )
    return match.float().argmax(1)


def free_offsets(clip: DemoClip, num_gaussians: int) -> FrameOffsets:
    """Zero-initialised trainable offsets for every frame and Gaussian."""
    zeros = torch.zeros(clip.num_frames, num_gaussians, 3, device=clip.depth.device)
    return FrameOffsets(clip.times, zeros, trainable=True)


def free_velocities(clip: DemoClip, num_gaussians: int) -> FrameVelocities:
    """Zero-initialised trainable velocities, one per Gaussian."""
    zeros = torch.zeros(num_gaussians, 3, device=clip.depth.device)
    return FrameVelocities(clip.times, zeros)


def agent_under(means: Float[Tensor, "N 3"], clip: DemoClip) -> Int[Tensor, " N"]:
    """Ground-truth agent instance id under each point at the reference frame (0: none),
    looked up in the instance grid grown by one voxel. Scoring and the oracle only."""
    reference = clip.instances[clip.reference]
    grown = F.max_pool3d(reference[None, None].float(), 3, stride=1, padding=1)[0, 0].long()
    ids = torch.where(reference > 0, reference, grown)
    index = clip.grid.world_to_index(means.detach())
    inside = clip.grid.contains_index(index)
    shape = torch.tensor(clip.grid.shape, device=index.device)
    index = index.clamp(torch.zeros_like(shape), shape - 1)
    found = ids[index[:, 0], index[:, 1], index[:, 2]]
    return torch.where(inside, found, torch.zeros_like(found))


def true_motion(scene: SyntheticScene, clip: DemoClip, means: Float[Tensor, "N 3"]) -> FrameOffsets:
    """The oracle: each Gaussian near a ground-truth agent at the reference frame moves with
    that agent (its pose at frame t relative to t = 0), the others stay. Uses the scene's
    ground truth, so it is a ceiling for what a position offset can buy, never a
    competitor. Synthetic agents keep their heading, so the motion is a translation.

    Raises:
        ValueError: ``scene`` is not the :class:`~dego.data.SyntheticScene` of ``clip``.
    """
    if not isinstance(scene, SyntheticScene):
        raise ValueError(
            "scene: the true-motion oracle needs the SyntheticScene the clip was made from "
            f"(ground-truth agent poses), got {type(scene).__name__}"
        )
    if (
        tuple(float(o) for o in scene.offsets) != tuple(clip.times.tolist())
        or len(scene.agents) != clip.agent_labels.shape[0]
    ):
        raise ValueError("scene: expected the SyntheticScene that clip was made from")
    agent = agent_under(means, clip)  # (N,), 1-based
    offsets = agent_offsets(agent_translations(scene).to(means), agent.to(means.device))
    return FrameOffsets(clip.times.to(means.device), offsets, trainable=False)


def agent_translations(scene: SyntheticScene) -> Float[Tensor, "T A 3"]:
    """``(T, A, 3)`` float64: how far each agent of ``scene`` moves from the reference
    frame to each frame (synthetic agents keep their heading: a translation)."""
    return torch.stack(
        [
            torch.stack(
                [(a.pose(offset * scene.frame_dt) - a.pose(0.0))[:3, 3] for a in scene.agents]
            )
            if scene.agents
            else torch.zeros(0, 3, dtype=torch.float64)
            for offset in scene.offsets
        ]
    )


def agent_offsets(
    translations: Float[Tensor, "T A 3"], agent: Int[Tensor, "*batch N"]
) -> Float[Tensor, "T *batch N 3"]:
    """Each point's offset at every frame: the translation of the agent it belongs to
    (``agent``: 1-based ids as :func:`agent_under` gives them, 0: no agent, no motion)."""
    padded = torch.cat([translations.new_zeros(translations.shape[0], 1, 3), translations], 1)
    return padded[:, agent]
