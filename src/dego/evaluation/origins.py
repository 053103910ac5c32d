"""RayIoU ray origins: where they come from (an infos file, the nuScenes tables or a folder
of ``<token>.npy``) and the per-sample ``(K, 3)`` origins of each source.

With several sources given, the first of ``infos``, ``nuscenes``, ``origins`` is used (the
others are reported as ignored). Poses become origins with SparseOcc's rule
(``dego.data.SceneOrigins``: every keyframe of the sample's scene, |x|, |y| < 39 m, at most
8); a sample's scene is the GT folder it sits in (``gts/<scene>/<token>``), as in SparseOcc.
There is never a silent fall-back to a single origin.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from dego.evaluation.errors import EvaluationSetupError, list_tokens

NO_ORIGINS_MESSAGE = (
    "RayIoU needs ray origins: pass --infos FILE (mmdet3d nuscenes_infos_val.pkl), "
    "--nuscenes ROOT [--nuscenes-version v1.0-trainval] or --origins DIR (<token>.npy), "
    "or --no-rayiou to skip RayIoU"
)

OriginsFn = Callable[[str], Tensor]


@dataclasses.dataclass(frozen=True)
class OriginSource:
    """Where the origins come from (plain data, so that worker processes can reopen it).

    Attributes:
        kind: ``"infos"``, ``"nuscenes"`` or ``"origins"``.
        path: the infos file, the nuScenes root or the folder of ``<token>.npy``.
        version: the nuScenes version (``"nuscenes"`` only).
    """

    kind: str
    path: str
    version: str | None = None

    @property
    def description(self) -> str:
        """``"infos: <path>"``, ``"nuscenes: <root> (<version>)"`` or ``"origins: <dir>"``."""
        if self.kind == "nuscenes":
            return f"nuscenes: {self.path} ({self.version})"
        return f"{self.kind}: {self.path}"


def choose_source(
    infos: str | os.PathLike[str] | None,
    nuscenes: str | os.PathLike[str] | None,
    version: str,
    origins: str | os.PathLike[str] | None,
) -> tuple[OriginSource | None, tuple[str, ...]]:
    """The preferred source among those given, and the descriptions of those ignored."""
    given = []
    if infos is not None:
        given.append(OriginSource("infos", str(infos)))
    if nuscenes is not None:
        given.append(OriginSource("nuscenes", str(nuscenes), version))
    if origins is not None:
        given.append(OriginSource("origins", str(origins)))
    if not given:
        return None, ()
    return given[0], tuple(s.description for s in given[1:])


def _data_api() -> Any:
    try:
        import dego.data as data

        for name in ("SceneOrigins", "load_infos", "load_nuscenes_keyframes"):
            getattr(data, name)
    except (ImportError, AttributeError) as exc:
        raise EvaluationSetupError(
            "reading infos files and nuScenes tables needs dego.data.load_infos / "
            "load_nuscenes_keyframes / SceneOrigins, which this version of dego lacks; "
            "pass --origins DIR instead"
        ) from exc
    return data


def load_keyframes(source: OriginSource) -> tuple[Any, ...]:
    """The keyframes of an ``infos`` or ``nuscenes`` source (errors as setup errors)."""
    data = _data_api()
    path = Path(source.path)
    if not path.exists():
        what = "infos file" if source.kind == "infos" else "nuScenes root"
        raise EvaluationSetupError(f"--{source.kind}: no such {what} {path}")
    try:
        if source.kind == "infos":
            return tuple(data.load_infos(path))
        return tuple(data.load_nuscenes_keyframes(path, source.version))
    except (OSError, ValueError, TypeError, KeyError) as exc:
        raise EvaluationSetupError(f"--{source.kind} {path}: {exc}") from exc


class DirectoryOrigins:
    """Origins read from ``<root>/<token>.npy``: ``(K, 3)`` finite metres, K >= 1."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    def path(self, token: str) -> Path:
        return self.root / f"{token}.npy"

    def missing(self, tokens: Sequence[str]) -> list[str]:
        """The tokens without a file."""
        return [t for t in tokens if not self.path(t).is_file()]

    def __call__(self, token: str) -> Tensor:
        path = self.path(token)
        try:
            array = np.load(path, allow_pickle=False, mmap_mode="r")
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: not a readable .npy array of origins ({exc})") from exc
        if array.dtype.kind not in "iuf" or array.ndim != 2 or array.shape[1] != 3:
            raise ValueError(
                f"{path}: expected (K, 3) real origins, got shape {array.shape} of {array.dtype}"
            )
        if array.shape[0] == 0 or array.shape[0] > 4096:
            raise ValueError(f"{path}: expected 1..4096 origins, got K = {array.shape[0]}")
        origins = torch.from_numpy(np.array(array, dtype=np.float64))
        if not bool(torch.isfinite(origins).all()):
            raise ValueError(f"{path}: origins hold NaN or infinite values")
        return origins


def open_origins(
    source: OriginSource,
    scene_of: Mapping[str, str],
    tokens: Sequence[str],
    keyframes: tuple[Any, ...] | None = None,
) -> OriginsFn:
    """``token -> (K, 3)`` float64 origins for every token in ``tokens``.

    Checked up front (setup errors naming the tokens): with ``"origins"`` every
    ``<token>.npy`` exists, with ``"infos"`` / ``"nuscenes"`` every token is a keyframe.
    """
    if source.kind == "origins":
        reader = DirectoryOrigins(source.path)
        if not reader.root.is_dir():
            raise EvaluationSetupError(f"--origins: {reader.root} is not a directory")
        missing = reader.missing(tokens)
        if missing:
            raise EvaluationSetupError(
                f"--origins: no origins file for {len(missing)} sample(s): "
                f"{list_tokens(missing)} (expected {reader.path(missing[0])})"
            )
        return reader
    data = _data_api()
    if keyframes is None:
        keyframes = load_keyframes(source)
    scene_origins = data.SceneOrigins(keyframes, scene_of=dict(scene_of))
    missing = [t for t in tokens if t not in scene_origins]
    if missing:
        raise EvaluationSetupError(
            f"--{source.kind} {source.path}: {len(missing)} sample(s) of the ground truth are "
            f"not keyframes there: {list_tokens(missing)}"
        )

    def origins(token: str) -> Tensor:
        return torch.as_tensor(scene_origins(token), dtype=torch.float64)

    return origins


__all__ = [
    "NO_ORIGINS_MESSAGE",
    "DirectoryOrigins",
    "OriginSource",
    "choose_source",
    "load_keyframes",
    "open_origins",
]
