"""RayIoU ray origins of every sample: SparseOcc's ``EgoPoseDataset``.

For a reference keyframe, every keyframe of its scene (past, future and itself) gives a
LiDAR origin in the reference ego frame; :func:`dego.lidar_origins` holds the rule
(``|x|, |y| < 39`` m, at most 8 evenly picked). Scenes are grouped as SparseOcc does:
by scene name (SparseOcc takes it from the ground-truth folder ``gts/<scene>/<token>``),
frames in the order given (SparseOcc does not sort).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from jaxtyping import Float64
from torch import Tensor

from dego._checks import check_int, check_positive
from dego._typing import typechecked
from dego.data.keyframes import Keyframe
from dego.metrics.rayiou import lidar_origins

__all__ = ["SceneOrigins"]


class SceneOrigins:
    """SparseOcc's EgoPoseDataset: the RayIoU ray origins of every sample.

    Args:
        keyframes: the evaluated keyframes, in SparseOcc's frame order (the infos file
            order); tokens must be unique.
        scene_of: ``{token: scene}``, the scene of each sample as SparseOcc reads it from
            ``gts/<scene>/<token>``; ``None`` groups by :attr:`Keyframe.scene`. A keyframe
            whose token it lacks is left out of every scene (and of :attr:`tokens`);
            SparseOcc would fail there, so callers check coverage themselves.
        max_origins: at most this many origins per sample (8).
        xy_limit: origins need ``|x| < xy_limit`` and ``|y| < xy_limit`` (39 m).

    ``origins(token)`` gives ``(K, 3)`` float64 origins in that sample's ego frame,
    ``1 <= K <= max_origins`` when its own LiDAR is inside the limit (always for nuScenes).

    Raises:
        ValueError: duplicate tokens; a keyframe with an empty scene when ``scene_of`` is
            None (every scene-less sample would fall into one scene); bad options.
    """

    @typechecked
    def __init__(
        self,
        keyframes: Sequence[Keyframe],
        scene_of: Mapping[str, str] | None = None,
        max_origins: int = 8,
        xy_limit: float = 39.0,
    ) -> None:
        self.max_origins = check_int("max_origins", max_origins, low=1)
        self.xy_limit = check_positive("xy_limit", xy_limit)
        frames: dict[str, list[Keyframe]] = {}
        where: dict[str, tuple[str, int]] = {}
        seen: set[str] = set()
        tokens = []
        for i, keyframe in enumerate(keyframes):
            if not isinstance(keyframe, Keyframe):
                raise TypeError(
                    f"keyframes[{i}]: expected a Keyframe, got {type(keyframe).__name__}"
                )
            token = keyframe.token
            if token in seen:
                raise ValueError(f"keyframes[{i}]: duplicate token {token!r}")
            seen.add(token)
            if scene_of is None:
                scene = keyframe.scene
                if not scene:
                    raise ValueError(
                        f"keyframes[{i}] ({token!r}): no scene; pass scene_of "
                        "(e.g. from gts/<scene>/<token>)"
                    )
            elif token in scene_of:
                scene = scene_of[token]
            else:
                continue
            group = frames.setdefault(scene, [])
            where[token] = (scene, len(group))
            group.append(keyframe)
            tokens.append(token)
        self.tokens: tuple[str, ...] = tuple(tokens)
        self._where = where
        # per scene: (F, 4, 4) ego2global and lidar2ego stacks in frame order
        self._poses: dict[str, tuple[Tensor, Tensor]] = {
            scene: (
                torch.stack([k.ego2global.cpu() for k in group]),
                torch.stack([k.lidar2ego.cpu() for k in group]),
            )
            for scene, group in frames.items()
        }

    @property
    def scenes(self) -> tuple[str, ...]:
        """The scene names, in order of first appearance."""
        return tuple(self._poses)

    def scene(self, token: str) -> str:
        """The scene a sample was grouped into (``KeyError`` naming an unknown token)."""
        return self._locate(token)[0]

    def __contains__(self, token: object) -> bool:
        return token in self._where

    def __len__(self) -> int:
        return len(self.tokens)

    def __repr__(self) -> str:
        return (
            f"SceneOrigins({len(self.tokens)} samples, {len(self._poses)} scenes, "
            f"max_origins={self.max_origins}, xy_limit={self.xy_limit:g})"
        )

    @typechecked
    def __call__(self, token: str) -> Float64[Tensor, "K 3"]:
        """``(K, 3)`` float64 ray origins of sample ``token`` in its ego frame, K <= max_origins.

        O(frames of the scene). ``KeyError`` naming ``token`` if it is not a sample here.
        """
        scene, index = self._locate(token)
        ego2global, lidar2ego = self._poses[scene]
        return lidar_origins(ego2global, lidar2ego, index, self.max_origins, self.xy_limit)

    def _locate(self, token: str) -> tuple[str, int]:
        try:
            return self._where[token]
        except KeyError:
            raise KeyError(
                f"token {token!r}: not a sample of these SceneOrigins ({len(self.tokens)} samples)"
            ) from None
