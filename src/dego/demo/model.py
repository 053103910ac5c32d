"""Learnable canonical Gaussians of a scene, initialised from pseudo depth."""

from __future__ import annotations

from typing import Literal

import torch
from jaxtyping import Float
from torch import Tensor, nn

from dego._checks import check_int
from dego.classes import FREE_LABEL, HUMAN_CENTRIC_CLASSES
from dego.demo.clip import DemoClip, backproject
from dego.gaussians import GaussianSet

NUM_OCCUPIED = FREE_LABEL  # labels 0..16 are occupied classes, 17 is free space
_MIN_SCALE, _MAX_SCALE = 0.05, 1.0  # metres: bounds of the initial nearest-neighbour scales
VEHICLE_CLASSES = (3, 4, 5, 9, 10)
"""Bus, car, construction vehicle, trailer, truck: rigid agents that may move."""
MOVABLE_CLASSES = tuple(sorted(VEHICLE_CLASSES + HUMAN_CENTRIC_CLASSES))
"""Classes that may move (the vehicles and the human-centric bicycle, motorcycle,
pedestrian): where they are depends on the time of the frame."""
Allocation = Literal["area", "class_balanced"]
ALLOCATIONS: tuple[Allocation, ...] = ("area", "class_balanced")
LatentInit = Literal["random", "segments"]
LATENT_INITS: tuple[LatentInit, ...] = ("random", "segments")
SEGMENT_RADIUS = 1.0
"""Metres: Gaussians of one pseudo class closer than this are linked into one segment."""


class GaussianSceneModel(nn.Module):
    """Canonical (reference-time) Gaussians with semantic logits and latent features.

    Parameters are stored unconstrained: ``log_scales``, ``opacity_logits`` and raw
    ``quats`` (normalised when used). :meth:`gaussians` gives the ``(1, N)``
    :class:`~dego.GaussianSet` whose features are the class probabilities over the 17
    occupied Occ3D classes (free space is what the Gaussians leave transparent).

    Args:
        means: ``(N, 3)`` initial positions (world = reference ego frame).
        scales: ``(N, 3)`` initial standard deviations.
        latent_dim: channels of the latent features fed to the deformation network.
        opacity: initial opacity of every Gaussian.
        generator: seeds the small random semantic logits and latent features.

    Attributes:
        deform_classes: ``None`` (default): a deformation may move every Gaussian; a
            tuple of labels: only the Gaussians whose most likely class is one of them
            (class gating, see :func:`~dego.demo.gaussians_at`; :func:`~dego.demo.fit_scene`
            sets :data:`MOVABLE_CLASSES` under ``FitConfig(deform="movable")``).
    """

    def __init__(
        self,
        means: Float[Tensor, "N 3"],
        scales: Float[Tensor, "N 3"],
        *,
        latent_dim: int = 16,
        opacity: float = 0.3,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        check_int("latent_dim", latent_dim, 0)
        if not 0 < opacity < 1:
            raise ValueError(f"opacity: expected a number in (0, 1), got {opacity!r}")
        if means.ndim != 2 or means.shape[-1] != 3 or scales.shape != means.shape:
            raise ValueError(
                f"means, scales: expected two (N, 3) tensors, got {tuple(means.shape)} and "
                f"{tuple(scales.shape)}"
            )
        n, dtype = means.shape[0], means.dtype

        def small_normal(*shape: int) -> Tensor:
            return 0.01 * torch.randn(*shape, generator=generator, dtype=dtype).to(means.device)

        identity = torch.zeros(n, 4, dtype=dtype, device=means.device)
        identity[:, 0] = 1
        self.means = nn.Parameter(means.clone())
        self.quats = nn.Parameter(identity)
        self.log_scales = nn.Parameter(scales.log())
        self.opacity_logits = nn.Parameter(
            torch.full(
                (n,), float(torch.logit(torch.tensor(opacity))), dtype=dtype, device=means.device
            )
        )
        self.semantic_logits = nn.Parameter(small_normal(n, NUM_OCCUPIED))
        self.latent = nn.Parameter(10 * small_normal(n, latent_dim))
        self.deform_classes: tuple[int, ...] | None = None

    @classmethod
    def from_clip(
        cls,
        clip: DemoClip,
        num_gaussians: int,
        *,
        latent_dim: int = 16,
        allocation: Allocation = "class_balanced",
        balance: float = 0.3,
        semantic_prior: float = 0.5,
        latent_init: LatentInit = "random",
        generator: torch.Generator | None = None,
    ) -> GaussianSceneModel:
        """Gaussians on the clip's pseudo-depth surfaces (the only geometry it is given).

        ``num_gaussians`` supervised surface pixels are drawn without replacement and
        lifted to 3D; each Gaussian starts isotropic, its scale the mean distance to its 3
        nearest neighbours. Within a class a pixel is drawn with probability proportional
        to depth^2 (its footprint, so the draw is about uniform over visible surface
        area). ``allocation`` decides how the budget is split between classes:

        - ``"area"``: by visible area, over every frame (a pedestrian gets a few
          Gaussians in thousands);
        - ``"class_balanced"`` (default): each pseudo class gets a share proportional to
          its visible area to the power ``balance`` (0: equal shares; 1: by area; the
          default 0.3 flattens them), and movable classes (vehicles, people,
          cycles) are drawn from the reference frame only, where the canonical
          Gaussians live; static classes from every frame.

        ``semantic_prior`` p: a Gaussian's class probabilities start at
        ``p * onehot(pseudo label of its pixel) + (1 - p) / 17`` (0: near uniform, the
        labels are learnt from scratch).

        ``latent_init``: ``"random"``: small independent latent features (std 0.1);
        ``"segments"``: the Gaussians are split into segments (:func:`segment_ids`:
        linked when of the same pseudo class and closer than :data:`SEGMENT_RADIUS`), and
        each segment's Gaussians start from one shared random code (std 1) plus the small
        per-Gaussian noise, so a deformation network can tell one object from another
        the way a feed-forward model's image features do.

        Everything here uses the pseudo labels only.
        """
        check_int("num_gaussians", num_gaussians, 1)
        check_initialisation(allocation, balance, semantic_prior, latent_init=latent_init)
        labels = clip.semantics
        surface = clip.supervised & (clip.depth > 0) & (labels < NUM_OCCUPIED)
        if allocation == "class_balanced":
            at_reference = torch.zeros_like(surface)
            at_reference[clip.reference] = True
            movable = torch.isin(labels, torch.tensor(MOVABLE_CLASSES, device=labels.device))
            surface = surface & (at_reference | ~movable)
        points = backproject(clip.depth, clip.world_to_cam, clip.intrinsics)[surface]
        if points.shape[0] < num_gaussians:
            raise ValueError(
                f"num_gaussians: the clip has only {points.shape[0]} surface pixels inside "
                f"the grid, got num_gaussians={num_gaussians}"
            )
        pixel_labels = labels[surface]
        weights = clip.depth[surface].square().double()
        if allocation == "class_balanced":
            area = torch.zeros(NUM_OCCUPIED, dtype=weights.dtype, device=weights.device)
            area.index_add_(0, pixel_labels, weights)
            share = torch.where(area > 0, area.clamp_min(1e-12) ** balance, 0)
            share = share / share.sum()
            weights = weights * (share / area.clamp_min(1e-12))[pixel_labels]
        pick = torch.multinomial(weights.cpu(), num_gaussians, generator=generator)
        pick = pick.to(points.device)
        means = points[pick]
        spacing = nearest_neighbour_distance(means, k=3).clamp(_MIN_SCALE, _MAX_SCALE)
        model = cls(
            means,
            spacing[:, None].expand(-1, 3),
            latent_dim=latent_dim,
            generator=generator,
        )
        if latent_init == "segments" and latent_dim > 0:
            segments = segment_ids(means, pixel_labels[pick], SEGMENT_RADIUS)
            codes = torch.randn(num_gaussians, latent_dim, generator=generator, dtype=means.dtype)
            with torch.no_grad():
                model.latent.add_(codes.to(means.device)[segments])
        if semantic_prior > 0:
            prior = torch.full_like(model.semantic_logits, (1 - semantic_prior) / NUM_OCCUPIED)
            prior[torch.arange(num_gaussians), pixel_labels[pick]] += semantic_prior
            with torch.no_grad():
                model.semantic_logits.add_(prior.log())
        return model

    @property
    def num_gaussians(self) -> int:
        return self.means.shape[0]

    def gaussians(self) -> GaussianSet:
        """The canonical set, batch ``(1,)``, features = class probabilities ``(1, N, 17)``."""
        return GaussianSet(
            means=self.means[None],
            quats=self.quats[None],
            scales=self.log_scales.exp()[None],
            opacities=torch.sigmoid(self.opacity_logits)[None],
            features=torch.softmax(self.semantic_logits, -1)[None],
        )


def check_initialisation(
    allocation: str,
    balance: float,
    semantic_prior: float,
    balance_name: str = "balance",
    latent_init: str = "random",
) -> None:
    """The argument checks of :meth:`GaussianSceneModel.from_clip` (``balance_name``: how
    the caller names ``balance``), shared with :class:`~dego.demo.FitConfig`."""
    if allocation not in ALLOCATIONS:
        raise ValueError(f"allocation: expected one of {ALLOCATIONS}, got {allocation!r}")
    if not (isinstance(balance, int | float) and 0 <= balance <= 1):
        raise ValueError(f"{balance_name}: expected a number in [0, 1], got {balance!r}")
    if not 0 <= semantic_prior < 1:
        raise ValueError(f"semantic_prior: expected a number in [0, 1), got {semantic_prior!r}")
    if latent_init not in LATENT_INITS:
        raise ValueError(f"latent_init: expected one of {LATENT_INITS}, got {latent_init!r}")


def nearest_neighbour_distance(
    points: Float[Tensor, "N 3"], k: int = 3, chunk: int = 2048
) -> Float[Tensor, " N"]:
    """Mean distance of each point to its ``k`` nearest other points (chunked ``cdist``)."""
    k = min(k, points.shape[0] - 1)
    if k < 1:
        return points.new_ones(points.shape[0])
    parts = []
    for start in range(0, points.shape[0], chunk):
        distances = torch.cdist(points[start : start + chunk], points)
        parts.append(distances.topk(k + 1, largest=False).values[:, 1:].mean(-1))
    return torch.cat(parts)


def segment_ids(
    points: Float[Tensor, "N 3"],
    labels: Tensor,
    radius: float,
    k: int = 8,
    chunk: int = 2048,
) -> Tensor:
    """``(N,)`` segment index of each point: the connected components of the graph that
    links each point to those of its ``k`` nearest neighbours with the same label closer
    than ``radius`` (a component is numbered by its smallest member). Label propagation,
    one vectorised min-reduction per round, until nothing changes."""
    n = points.shape[0]
    k = min(k, n - 1)
    segment = torch.arange(n, device=points.device)
    if k < 1:
        return segment
    sources, targets = [], []
    for start in range(0, n, chunk):
        distances = torch.cdist(points[start : start + chunk], points)
        nearest = distances.topk(k + 1, largest=False)
        rows = torch.arange(start, start + nearest.indices.shape[0], device=points.device)
        rows = rows[:, None].expand_as(nearest.indices)
        linked = (nearest.values < radius) & (labels[rows] == labels[nearest.indices])
        sources.append(rows[linked])
        targets.append(nearest.indices[linked])
    source = torch.cat(sources + targets)  # both directions
    target = torch.cat(targets + sources)
    for _ in range(n):  # at most the graph's diameter rounds; usually tens
        pulled = segment.scatter_reduce(0, target, segment[source], "amin")
        if torch.equal(pulled, segment):
            break
        segment = pulled
    return segment
