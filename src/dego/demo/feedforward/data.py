"""The feed-forward miniature's data: synthetic scenes rendered once and cached on disk.

Each scene is a :class:`~dego.data.SyntheticScene` with ``frames`` frames (offsets ``-1, 0,
+1`` for 3). A network sees the reference frame's six images only (the paper's inference
input: one frame of multi-view images); training renders the pseudo labels of every frame;
scoring uses the reference frame's ground truth. :class:`SceneRecord` holds what those
steps need, compactly (labels as ``uint8``); :func:`load_scenes` renders missing scenes and
reads the others from a cache folder whose name is a digest of the generator's settings, so
a changed setting never reuses a stale file. Every file is written atomically and checked
when read (its settings, its seed, the zip's CRCs, every array's shape); a file that fails
a check is rendered again, with a warning.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from dego._checks import check_int, check_positive
from dego._npz import read_npz, write_npz
from dego._version import __version__
from dego.data.synthetic import SyntheticScene
from dego.demo.clip import DEMO_FRAME_DT, MAX_DEMO_FRAMES, DemoClip
from dego.demo.fit import MAX_SEED
from dego.demo.offsets import agent_translations
from dego.grid import VoxelGrid

CACHE_FORMAT = 1
"""Bumped whenever :class:`SceneRecord`'s file layout changes (part of the cache digest)."""

FEEDFORWARD_FRAME_DT = 0.5
"""Seconds between the frames of ``dego train``'s scenes: nuScenes' keyframe spacing (the
paper's 12 deformed frames span 6 s). At the demo's 0.2 s
(:data:`~dego.demo.DEMO_FRAME_DT`, kept as ``--frame-dt 0.2``) a pedestrian moves less than a
voxel between frames and static supervision has little to get wrong."""

MAX_CLIP_SECONDS = (MAX_DEMO_FRAMES // 2) * DEMO_FRAME_DT
"""The largest time from the reference to a clip's outermost frame the synthetic world
covers: the ego drives 5 m/s, the Occ3D grid reaches 40 m ahead and its ground ends at
80 m (:data:`~dego.demo.MAX_DEMO_FRAMES`)."""

TRAIN_SPLIT, HELDOUT_SPLIT = 0, 1


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Which scenes a feed-forward run uses and how they are rendered.

    Attributes:
        train_scenes, heldout_scenes: scenes per split (training / held-out evaluation).
        frames: frames per scene, odd and >= 3, centred on the reference: offsets
            ``-(frames // 2) .. frames // 2`` (3: ``-1, 0, +1``).
        image_size: ``(H, W)`` of the six cameras.
        frame_dt: seconds between frames (:data:`FEEDFORWARD_FRAME_DT`); the outermost
            frame may be at most :data:`MAX_CLIP_SECONDS` from the reference.
        depth_noise: the pseudo depth's noise, :class:`~dego.data.SyntheticScene`'s
            ``depth_noise`` (0: exact depth).
    """

    train_scenes: int = 64
    heldout_scenes: int = 16
    frames: int = 3
    image_size: tuple[int, int] = (64, 176)
    frame_dt: float = FEEDFORWARD_FRAME_DT
    depth_noise: float = 0.0

    def __post_init__(self) -> None:
        check_int("train_scenes", self.train_scenes, 1)
        check_int("heldout_scenes", self.heldout_scenes, 1)
        check_int("frames", self.frames, 3)
        if self.frames % 2 == 0:
            raise ValueError(
                f"frames: expected an odd number (the reference in the middle), got {self.frames}"
            )
        if len(self.image_size) != 2:
            raise ValueError(f"image_size: expected (H, W), got {self.image_size!r}")
        for value in self.image_size:
            check_int("image_size", value, 8)
        check_positive("frame_dt", self.frame_dt)
        span = self.frames // 2 * self.frame_dt
        if span > MAX_CLIP_SECONDS + 1e-9:
            raise ValueError(
                f"frame_dt: {self.frames} frames {self.frame_dt} s apart reach {span:g} s from "
                f"the reference; the synthetic world covers at most {MAX_CLIP_SECONDS:g} s"
            )
        if not 0 <= self.depth_noise < 1:
            raise ValueError(f"depth_noise: expected a number in [0, 1), got {self.depth_noise!r}")

    def render_settings(self) -> dict[str, object]:
        """What a cached scene depends on besides its seed (the cache digest's input)."""
        return {
            "format": CACHE_FORMAT,
            "dego": __version__,
            "frames": self.frames,
            "image_size": list(self.image_size),
            "frame_dt": self.frame_dt,
            "depth_noise": self.depth_noise,
        }

    def digest(self) -> str:
        """16 hex digits naming the cache folder of these render settings."""
        text = json.dumps(self.render_settings(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def scene_seeds(seed: int, split: int, count: int) -> list[int]:
    """The :class:`~dego.data.SyntheticScene` seeds of ``split`` (0: training, 1: held-out)
    for run seed ``seed``: ``count`` draws of numpy's ``SeedSequence([seed, split])``, so
    every run seed has its own scenes and the two splits never share one by construction of
    the stream (a repeat across the two streams has odds of about ``count^2 / 2^32``)."""
    if not 0 <= seed <= MAX_SEED:
        raise ValueError(f"seed: expected an int in [0, {MAX_SEED}], got {seed!r}")
    drawn = np.random.SeedSequence([seed, split]).generate_state(count, dtype=np.uint32)
    return [int(s) for s in drawn]


@dataclasses.dataclass(frozen=True)
class SceneRecord:
    """One cached scene. World coordinates are the reference frame's ego frame.

    Attributes:
        seed: the scene's :class:`~dego.data.SyntheticScene` seed.
        times: ``(T,)`` frame offsets (0 = reference). reference: the index of offset 0.
        world_to_cam: ``(T, V, 4, 4)``. intrinsics: ``(T, V, 3, 3)``.
        images: ``(V, 3, H, W)`` RGB in [0, 1] of the reference frame (the network's input).
        depth, semantics, supervised: ``(T, V, H, W)`` pseudo labels of every frame
            (:class:`~dego.demo.DemoClip`'s meaning).
        occupancy, mask_camera, instances: ``(X, Y, Z)`` ground truth of the reference frame
            (scoring and the oracle only).
        agent_labels, agent_articulated, agent_moving: ``(A,)`` per agent.
        agent_translations: ``(T, A, 3)`` each agent's move from t = 0 to every frame (the
            oracle only).
        ray_origins: ``(K, 3)`` RayIoU origins. grid: the voxel grid of ``occupancy``.
    """

    seed: int
    times: Float[Tensor, " T"]
    reference: int
    world_to_cam: Float[Tensor, "T V 4 4"]
    intrinsics: Float[Tensor, "T V 3 3"]
    images: Float[Tensor, "V 3 H W"]
    depth: Float[Tensor, "T V H W"]
    semantics: Int[Tensor, "T V H W"]
    supervised: Bool[Tensor, "T V H W"]
    occupancy: Int[Tensor, "X Y Z"]
    mask_camera: Bool[Tensor, "X Y Z"]
    instances: Int[Tensor, "X Y Z"]
    agent_labels: Int[Tensor, " A"]
    agent_articulated: Bool[Tensor, " A"]
    agent_moving: Bool[Tensor, " A"]
    agent_translations: Float[Tensor, "T A 3"]
    ray_origins: Float[Tensor, "K 3"]
    grid: VoxelGrid

    @classmethod
    def from_scene(cls, scene: SyntheticScene) -> SceneRecord:
        """Render ``scene`` (about 0.6 s a frame on a CPU at the default image size)."""
        clip = DemoClip.from_scene(scene)
        ref = clip.reference
        return cls(
            seed=scene.seed,
            times=clip.times,
            reference=ref,
            world_to_cam=clip.world_to_cam,
            intrinsics=clip.intrinsics,
            images=clip.images[ref],
            depth=clip.depth,
            semantics=clip.semantics,
            supervised=clip.supervised,
            occupancy=clip.occupancy[ref],
            mask_camera=clip.mask_camera[ref],
            instances=clip.instances[ref],
            agent_labels=clip.agent_labels,
            agent_articulated=clip.agent_articulated,
            agent_moving=clip.agent_moving,
            agent_translations=agent_translations(scene).float(),
            ray_origins=clip.ray_origins,
            grid=clip.grid,
        )

    @property
    def num_frames(self) -> int:
        return self.times.shape[0]

    @property
    def image_size(self) -> tuple[int, int]:
        return (self.depth.shape[-2], self.depth.shape[-1])

    def reference_clip(self) -> DemoClip:
        """A one-frame :class:`~dego.demo.DemoClip` of the reference frame, for the demo's
        scoring functions (:func:`~dego.demo.score_labels`, :func:`~dego.demo.dynamic_counts`,
        :func:`~dego.demo.agent_under`, :func:`~dego.demo.pictures.bev_figure`)."""
        r = slice(self.reference, self.reference + 1)
        v, h, w = self.depth.shape[1:]
        return DemoClip(
            times=self.times[r] * 0,
            reference=0,
            world_to_cam=self.world_to_cam[r],
            intrinsics=self.intrinsics[r],
            ego_poses=torch.eye(4, device=self.depth.device)[None],
            images=self.images[None],
            depth=self.depth[r],
            semantics=self.semantics[r],
            supervised=self.supervised[r],
            occupancy=self.occupancy[None],
            mask_camera=self.mask_camera[None],
            instances=self.instances[None],
            instance_pixels=torch.zeros(1, v, h, w, dtype=torch.long, device=self.depth.device),
            agent_labels=self.agent_labels,
            agent_articulated=self.agent_articulated,
            agent_moving=self.agent_moving,
            ray_origins=self.ray_origins,
            grid=self.grid,
        )

    def to(self, device: torch.device | str) -> SceneRecord:
        """The record with every tensor on ``device``."""
        return dataclasses.replace(
            self,
            **{
                f.name: getattr(self, f.name).to(device)
                for f in dataclasses.fields(self)
                if isinstance(getattr(self, f.name), Tensor)
            },
        )

    def arrays(self, settings: dict[str, object]) -> dict[str, np.ndarray]:
        """The record as compact numpy arrays for the cache, with its ``settings``."""
        as_uint8 = {"semantics", "occupancy"}
        out: dict[str, np.ndarray] = {
            "settings": np.frombuffer(json.dumps(settings, sort_keys=True).encode(), np.uint8),
            "seed": np.array(self.seed, np.int64),
            "reference": np.array(self.reference, np.int64),
            "images": (self.images * 255).round().to(torch.uint8).numpy(),
            "instances": self.instances.to(torch.int16).numpy(),
        }
        for name in _TENSOR_FIELDS:
            if name not in out:
                value = getattr(self, name)
                out[name] = (value.to(torch.uint8) if name in as_uint8 else value).numpy()
        return out

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], grid: VoxelGrid) -> SceneRecord:
        """Inverse of :meth:`arrays` (labels back to ``int64``, images to float)."""
        tensors = {name: torch.from_numpy(np.array(arrays[name])) for name in _TENSOR_FIELDS}
        for name in ("semantics", "occupancy", "instances", "agent_labels"):
            tensors[name] = tensors[name].long()
        tensors["images"] = tensors["images"].float() / 255
        return cls(
            seed=int(arrays["seed"]), reference=int(arrays["reference"]), grid=grid, **tensors
        )


_TENSOR_FIELDS = tuple(
    f.name for f in dataclasses.fields(SceneRecord) if f.name not in ("seed", "reference", "grid")
)


def load_scenes(
    seeds: Sequence[int],
    config: DataConfig,
    cache: Path | None,
    *,
    progress: Callable[[int, int], None] | None = None,
) -> list[SceneRecord]:
    """The scenes of ``seeds``, read from ``cache`` where a valid file is there, else
    rendered (and written there, atomically; ``cache=None``: nothing is cached).

    A file is used only if it holds these render settings and this seed and every array
    reads back whole; otherwise it is rendered again, with a ``UserWarning`` naming the
    file and what was wrong. A scene that cannot be written to the cache (a full disk, a
    read-only folder, a file where the folder should be, a directory where the file should
    be) is a ``UserWarning`` naming the file and why, and nothing more is written to the
    cache in this call: the scenes are still returned. ``progress(done, total)`` is called
    after each scene.
    """
    folder = None if cache is None else cache / f"scenes-{config.digest()}"
    settings = config.render_settings()
    records = []
    writing = folder is not None
    for done, seed in enumerate(seeds, 1):
        path = None if folder is None else folder / f"scene-{seed}.npz"
        record = None
        if path is not None and os.path.lexists(path):
            try:
                record = _read(path, seed, settings)
            except (ValueError, OSError) as error:
                warnings.warn(
                    f"{path}: unusable cached scene ({error}); rendering it again",
                    stacklevel=2,
                )
        if record is None:
            scene = SyntheticScene(
                seed,
                num_frames=config.frames,
                frame_dt=config.frame_dt,
                image_size=config.image_size,
                depth_noise=config.depth_noise,
            )
            record = SceneRecord.from_scene(scene)
            if path is not None and writing:
                try:
                    write_npz(path, record.arrays(settings), compressed=True)
                except OSError as error:
                    writing = False
                    warnings.warn(
                        f"{path}: cannot cache the scene ({_reason(error, path)}); going on "
                        "without caching",
                        stacklevel=2,
                    )
        records.append(record)
        if progress is not None:
            progress(done, len(seeds))
    return records


def _read(path: Path, seed: int, settings: dict[str, object]) -> SceneRecord:
    arrays = read_npz(path, holds="a cached feed-forward scene")
    missing = sorted({"settings", "seed", "reference", *_TENSOR_FIELDS} - set(arrays))
    if missing:
        raise ValueError(f"missing arrays {missing}")
    stored = bytes(arrays["settings"].astype(np.uint8)).decode("utf-8", "replace")
    if stored != json.dumps(settings, sort_keys=True):
        raise ValueError(f"made with other settings ({stored})")
    stored_seed = _one_int(arrays, "seed")
    if stored_seed != seed:
        raise ValueError(f"holds scene {stored_seed}, not {seed}")
    _one_int(arrays, "reference")
    grid = VoxelGrid.occ3d()
    try:
        record = SceneRecord.from_arrays(arrays, grid)
    except (TypeError, OverflowError) as error:  # an array of a type no tensor takes
        raise ValueError(f"arrays of the wrong type ({error})") from None
    _check_shapes(record)
    return record


def _reason(error: OSError, path: Path) -> str:
    """An ``OSError`` of writing ``path`` in a few words: its reason, and the file it is
    about where that is neither ``path`` nor its temporary file (a folder on the way)."""
    reason = error.strerror or str(error)
    named = None if error.filename is None else Path(os.fspath(error.filename))
    if named is not None and named != path and not named.name.startswith(f".{path.name}."):
        reason += f": {named}"
    return reason


def _one_int(arrays: dict[str, np.ndarray], name: str) -> int:
    """The integer scalar array ``name`` of a cached scene (``ValueError`` for any other
    shape or dtype: a float such as inf, two values)."""
    value = arrays[name]
    if value.shape != () or value.dtype.kind not in "iu":
        raise ValueError(f"{name}: expected one integer, got shape {value.shape} of {value.dtype}")
    return int(value)


def _check_shapes(record: SceneRecord) -> None:
    """Every array's shape agrees with the others (a file edited by hand, or one whose
    arrays were swapped, is refused rather than trained on)."""
    t, v, h, w = record.depth.shape
    a = record.agent_labels.shape[0]
    grid = tuple(record.grid.shape)
    expected = {
        "times": (t,),
        "world_to_cam": (t, v, 4, 4),
        "intrinsics": (t, v, 3, 3),
        "images": (v, 3, h, w),
        "semantics": (t, v, h, w),
        "supervised": (t, v, h, w),
        "occupancy": grid,
        "mask_camera": grid,
        "instances": grid,
        "agent_articulated": (a,),
        "agent_moving": (a,),
        "agent_translations": (t, a, 3),
    }
    for name, shape in expected.items():
        got = tuple(getattr(record, name).shape)
        if got != shape:
            raise ValueError(f"{name}: shape {got}, expected {shape}")
    if not 0 <= record.reference < t or record.times[record.reference] != 0:
        raise ValueError(f"reference: {record.reference} is not the frame at offset 0")
    if record.ray_origins.ndim != 2 or record.ray_origins.shape[-1] != 3:
        raise ValueError(f"ray_origins: shape {tuple(record.ray_origins.shape)}, expected (K, 3)")


def default_cache() -> Path:
    """``$XDG_CACHE_HOME/dego`` (``~/.cache/dego`` when unset): where ``dego train`` keeps
    its rendered scenes unless told otherwise (``--cache``)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "dego"
