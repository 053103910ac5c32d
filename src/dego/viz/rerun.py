"""Log occupancy grids, Gaussians, cameras and deformations into a rerun recording.

`rerun <https://rerun.io>`_ records to a ``.rrd`` file that its viewer opens anywhere
(locally, over SSH with ``rerun --web-viewer``, in a notebook), with time lines. Every
function here logs one thing into a :class:`rerun.RecordingStream` (``recording=None``:
rerun's global recording, as ``rr.log`` uses) and can be called alone from a user's own
code; :func:`recording_file` opens a recording that is written to a file atomically.

A training loop, in three lines::

    with dego.viz.rerun.recording_file("train.rrd") as rec:
        ...  # each step:
        dego.viz.rerun.log_gaussians("world/gaussians", gaussians, frame=step, recording=rec)
        dego.viz.rerun.log_occupancy("world/occupancy", labels, grid, frame=step, recording=rec)

Needs the optional extra ``dego-occupancy[rerun]`` (rerun-sdk), imported when a function
runs, so ``import dego.viz.rerun`` works without it. Coordinates are dego's (metres, ego /
world frame x forward, y left, z up; cameras with OpenCV axes): rerun's own unit is free,
and its cameras are given the same axes (right, down, forward).

Entities: a grid is one entity per call (all its voxels in one batch), a Gaussian set one
entity, a camera one entity (its pinhole and pose) with child entities for its images.
Time: ``frame=`` (and ``timeline=``) set the recording's time before logging; ``None``
logs at the recording's current time.
"""

from __future__ import annotations

import contextlib
import inspect
import os
import threading
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch
from jaxtyping import Bool, Float, Integer, UInt8
from torch import Tensor

from dego._atomic import check_output_file, temporary_name
from dego._checks import check_int, check_positive
from dego._typing import typechecked
from dego.classes import CLASS_NAMES, FREE_LABEL, NUM_CLASSES, PALETTE
from dego.deformation import DeformationOutput
from dego.gaussians import GaussianSet, normalize_quaternions
from dego.grid import VoxelGrid
from dego.viz._labels import _label_tensor
from dego.viz.colors import bev_labels, colorize_labels

if TYPE_CHECKING:
    from rerun import RecordingStream
    from rerun.blueprint import Blueprint
else:  # rerun is optional and imported inside the functions; the run-time check sees Any
    RecordingStream = Blueprint = Any

FRAME_TIMELINE = "frame"
"""The timeline of a clip's frames (``dego demo``) and of a user's steps."""
SAMPLE_TIMELINE = "sample"
"""The timeline of ``dego eval``'s samples."""

GridStyle = Literal["auto", "voxels", "boxes", "points"]
GaussianStyle = Literal["ellipsoids", "splats"]

GAUSSIAN_GREY: tuple[int, int, int] = (160, 160, 160)
"""The colour of Gaussians whose features are not class scores (no features, or a width
other than 17 or 18)."""
RIGID_RGB: tuple[int, int, int] = (40, 110, 220)
"""Colour of a Gaussian whose rigidity mask m is 0 (rigid); m = 1 (nonrigid) is
:data:`NONRIGID_RGB`, and values between are mixed linearly."""
NONRIGID_RGB: tuple[int, int, int] = (235, 90, 30)
UNSCORED_BEV_STRIPES: tuple[tuple[int, int, int], tuple[int, int, int]] = (
    (40, 40, 40),
    (150, 150, 150),
)
"""The two colours of the diagonal stripes (2 pixels wide) that :func:`log_bev` draws over
columns outside the camera mask: a pattern, so that no class colour (``other_flat`` is a
plain grey) can be mistaken for "not scored"."""

MIN_RERUN = "0.24"
"""The oldest rerun-sdk the extra allows (the tests run the newest in the registry)."""

_INSTALL_HINT = (
    'dego.viz.rerun needs rerun-sdk, an optional dependency: pip install -e ".[rerun]" in your '
    f'dego clone (or pip install "rerun-sdk>={MIN_RERUN}")'
)


def require_rerun() -> ModuleType:
    """Import rerun, or raise an ImportError that names the extra to install."""
    try:
        import rerun
    except ImportError as error:
        raise ImportError(_INSTALL_HINT, name="rerun") from error
    return rerun


def has_voxel_grid_map() -> bool:
    """Whether the installed rerun has ``VoxelGridMap`` (sparse voxels, unstable in 0.41)."""
    return hasattr(require_rerun(), "VoxelGridMap")


def has_gaussian_splats() -> bool:
    """Whether the installed rerun has ``GaussianSplats3D`` (unstable in 0.41)."""
    return hasattr(require_rerun(), "GaussianSplats3D")


def _archetype(name: str, style: str, instead: str) -> Any:
    """rerun's archetype class ``name`` for ``style=``, or ``RuntimeError`` saying what to
    use instead where the installed rerun does not have it."""
    rr = require_rerun()
    if not hasattr(rr, name):
        raise RuntimeError(
            f"style: {style!r} needs rerun's {name}, which rerun-sdk {rr.__version__} does "
            f"not have; use style={instead!r} or upgrade rerun-sdk"
        )
    return getattr(rr, name)


# --------------------------------------------------------------------------- recordings


FLUSH_TIMEOUT_S = 60.0
"""How long :func:`recording_file` waits, when its block ends, for the rest of the recording
to reach the file before it gives up with an ``OSError`` (a full, stalled or very slow
disk)."""

_CLOSE_GRACE_S = 5.0
"""Beyond :data:`FLUSH_TIMEOUT_S`: time for rerun to close the file (its footer)."""


@contextlib.contextmanager
def recording_file(
    path: str | os.PathLike[str],
    *,
    application_id: str = "dego",
    blueprint: Blueprint | None = None,
) -> Iterator[RecordingStream]:
    """A new recording that streams to a temporary file beside ``path`` and is moved onto
    ``path`` when the block ends without an error (an error removes it and leaves any
    previous ``path`` as it was). Class names and colours are logged first (:func:`log_classes`).

    Raises ``OSError`` (one line naming ``path``) before anything is recorded when ``path``
    cannot be written, and when the block ends if the recording cannot be written whole:
    a write fails (a full disk), or the file does not take the rest within
    :data:`FLUSH_TIMEOUT_S` seconds (a stalled disk). The temporary file is removed then.
    """
    rr = require_rerun()
    path = Path(path)
    check_output_file(path)
    tmp = temporary_name(path)
    recording = rr.RecordingStream(application_id)
    closing = False
    try:
        try:
            recording.save(tmp, default_blueprint=blueprint)
        except RuntimeError as error:  # rerun reports a failed write as a RuntimeError
            raise OSError(f"cannot write the recording {path}: {_one_line(error)}") from None
        log_classes(recording=recording)
        yield recording
        closing = True
        _close(recording, path)
        os.replace(tmp, path)
    finally:
        if not closing:
            with contextlib.suppress(OSError):
                _close(recording, path)
        tmp.unlink(missing_ok=True)


def _one_line(error: BaseException) -> str:
    return " ".join(str(error).split()) or type(error).__name__


def _flush(recording: Any, timeout: float) -> None:
    """``recording.flush``, waiting at most ``timeout`` seconds where rerun can bound it."""
    if "timeout_sec" in inspect.signature(recording.flush).parameters:
        recording.flush(timeout_sec=timeout)
    else:  # pragma: no cover - an older rerun-sdk without a timeout; _close bounds the wait
        recording.flush(blocking=True)


def _close(recording: Any, path: Path) -> None:
    """Flush ``recording`` into its file and close it, waiting at most about
    :data:`FLUSH_TIMEOUT_S` seconds; ``OSError`` naming ``path`` when a write fails or the
    file does not take the data in that time.

    The flush and close run on a daemon thread: a file writer that is stuck (a stalled
    disk) cannot hold this thread. Such a recording can never be closed, and rerun's
    exit handler, which flushes every recording, would wait for it forever; that handler is
    unregistered then, so that the process can still end."""
    failures: list[BaseException] = []

    def close() -> None:
        try:
            _flush(recording, FLUSH_TIMEOUT_S)
        except Exception as error:  # rerun: RuntimeError
            failures.append(error)
        finally:
            with contextlib.suppress(Exception):
                recording.disconnect()

    worker = threading.Thread(target=close, name="dego-rerun-close", daemon=True)
    worker.start()
    try:
        worker.join(FLUSH_TIMEOUT_S + _CLOSE_GRACE_S)
    finally:
        if worker.is_alive():  # stuck, or Ctrl-C while closing
            _forget_at_exit()
    if worker.is_alive():
        raise OSError(
            f"cannot write the recording {path}: the file did not take it within "
            f"{FLUSH_TIMEOUT_S:g} s (a full, stalled or very slow disk?)"
        )
    if failures:
        raise OSError(
            f"cannot write the recording {path}: rerun could not write it "
            f"({_one_line(failures[0])}); is the disk full?"
        )


def _forget_at_exit() -> None:
    """Unregister rerun's exit handler (it would wait forever on a stuck recording)."""
    unregister = getattr(require_rerun(), "unregister_shutdown", None)
    if unregister is not None:
        unregister()


def _stream(recording: RecordingStream | None) -> Any:
    """``recording`` or rerun's global recording (what ``rr.log`` logs to)."""
    rr = require_rerun()
    if recording is not None:
        if not isinstance(recording, rr.RecordingStream):
            raise TypeError(
                "recording: expected a rerun.RecordingStream or None, got "
                f"{type(recording).__name__}"
            )
        return recording
    return rr.get_global_data_recording()


def _set_time(stream: Any, frame: int | None, timeline: str) -> None:
    if frame is None:
        return
    check_int("frame", frame)
    if not timeline:
        raise ValueError("timeline: expected a non-empty name")
    if stream is None:
        require_rerun().set_time(timeline, sequence=frame)
    else:
        stream.set_time(timeline, sequence=frame)


def _log(stream: Any, entity: str, *parts: Any) -> None:
    """Log data ``parts`` at ``entity``, which must name an entity below the root."""
    if not isinstance(entity, str) or not entity.strip("/"):
        raise ValueError(
            f"entity: expected an entity path such as 'world/occupancy', got {entity!r}"
        )
    _emit(stream, entity, *parts)


def _emit(stream: Any, entity: str, *parts: Any, static: bool = False) -> None:
    """``stream.log``, or rerun's module-level ``rr.log`` for the global recording."""
    if stream is None:
        require_rerun().log(entity, *parts, static=static)
    else:
        stream.log(entity, *parts, static=static)


@typechecked
def log_classes(entity: str = "/", *, recording: RecordingStream | None = None) -> None:
    """Log the Occ3D class names and palette as a static annotation context at ``entity``:
    every entity below it shows class ids by name and colour (grids, Gaussians,
    segmentation images)."""
    rr = require_rerun()
    context = rr.AnnotationContext(
        [
            rr.ClassDescription(info=rr.AnnotationInfo(id=i, label=name, color=PALETTE[i]))
            for i, name in enumerate(CLASS_NAMES)
        ]
    )
    _emit(_stream(recording), entity, context, static=True)


# --------------------------------------------------------------------------- grids


def _cpu_mask(mask: Tensor | np.ndarray) -> Tensor:
    """``mask`` (shape checked against ``labels`` by the annotations) as a CPU bool tensor."""
    return torch.as_tensor(mask).cpu()


@typechecked
def log_occupancy(
    entity: str,
    labels: Integer[Tensor, "X Y Z"] | Integer[np.ndarray, "X Y Z"],
    grid: VoxelGrid | None = None,
    *,
    mask: Bool[Tensor, "X Y Z"] | Bool[np.ndarray, "X Y Z"] | None = None,
    free_label: int = FREE_LABEL,
    style: GridStyle = "auto",
    frame: int | None = None,
    timeline: str = FRAME_TIMELINE,
    recording: RecordingStream | None = None,
) -> int:
    """Log the non-free voxels of a label grid as one entity, in the paper's palette.

    Args:
        entity: the entity path, e.g. ``"world/occupancy/prediction"``.
        labels: ``(X, Y, Z)`` Occ3D labels in [0, 17] (any integer dtype).
        grid: the grid ``labels`` lies on (default :meth:`VoxelGrid.occ3d`); its shape
            must be ``labels``' shape.
        mask: optional ``(X, Y, Z)`` camera mask: only voxels inside it are logged.
        free_label: the empty label, not drawn (Occ3D: 17).
        style: ``"voxels"`` (rerun's ``VoxelGridMap``), ``"boxes"`` (``Boxes3D`` one per
            voxel), ``"points"`` (``Points3D`` of half a voxel's radius), or ``"auto"``:
            voxels where the installed rerun has them, else boxes.
        frame: the time to log at on ``timeline`` (``None``: the recording's current time).
        timeline: the timeline of ``frame`` (default :data:`FRAME_TIMELINE`).
        recording: the recording (``None``: rerun's global one).

    The voxels' class ids ride along as the component ``class_id`` (and, for boxes and
    points, as their ``class_ids``, named by :func:`log_classes`). Returns the number of
    voxels logged.

    Raises:
        ValueError: labels outside [0, 17], a shape that is not ``grid.shape``, a mask of
            another shape, an empty entity path; ``ImportError`` without rerun-sdk.
    """
    rr = require_rerun()
    grid = VoxelGrid.occ3d() if grid is None else grid
    index = _label_tensor("labels", labels).cpu()
    if tuple(index.shape) != grid.shape:
        raise ValueError(
            f"labels: shape {tuple(index.shape)} does not match grid.shape {grid.shape}"
        )
    check_int("free_label", free_label)
    occupied = index != free_label
    if mask is not None:
        occupied &= _cpu_mask(mask)
    ijk = occupied.nonzero().to(torch.int32).numpy()
    classes = index[occupied].to(torch.uint8).numpy()
    colors = np.asarray(PALETTE, dtype=np.uint8)[classes]
    size = np.asarray(grid.voxel_size, dtype=np.float32)
    lower = np.asarray(grid.lower, dtype=np.float32)
    if style == "auto":
        style = "voxels" if has_voxel_grid_map() else "boxes"
    if style == "voxels":
        voxel_grid_map = _archetype("VoxelGridMap", style, "boxes")
        archetype = voxel_grid_map(ijk, voxel_size=size, colors=colors, translation=lower)
    else:
        centers = lower + (ijk.astype(np.float32) + 0.5) * size
        if style == "boxes":
            half = np.broadcast_to(size / 2, centers.shape)
            archetype = rr.Boxes3D(
                centers=centers,
                half_sizes=half,
                colors=colors,
                class_ids=classes,
                fill_mode="solid",
            )
        else:
            archetype = rr.Points3D(
                centers, radii=float(size.min()) / 2, colors=colors, class_ids=classes
            )
    stream = _stream(recording)
    _set_time(stream, frame, timeline)
    _log(stream, entity, archetype, rr.AnyValues(class_id=classes))
    return int(classes.shape[0])


@typechecked
def log_bev(
    entity: str,
    labels: Integer[Tensor, "X Y Z"] | Integer[np.ndarray, "X Y Z"],
    *,
    mask: Bool[Tensor, "X Y Z"] | Bool[np.ndarray, "X Y Z"] | None = None,
    free_label: int = FREE_LABEL,
    frame: int | None = None,
    timeline: str = FRAME_TIMELINE,
    recording: RecordingStream | None = None,
) -> None:
    """Log the bird's-eye view of a label grid (:func:`dego.viz.bev_labels`) as an RGB
    image, oriented as dego's BEV pictures: +x (forward) up, +y (left) to the left. Columns
    with no voxel inside ``mask`` are striped (:data:`UNSCORED_BEV_STRIPES`)."""
    rr = require_rerun()
    index = _label_tensor("labels", labels).cpu()
    bev = bev_labels(index, free_label=free_label)
    rgb = colorize_labels(bev, free_label=free_label).numpy()
    if mask is not None:
        unscored = ~_cpu_mask(mask).any(dim=-1).numpy()
        x, y = np.indices(unscored.shape)
        stripes = np.asarray(UNSCORED_BEV_STRIPES, dtype=np.uint8)[((x + y) // 2) % 2]
        rgb[unscored] = stripes[unscored]
    stream = _stream(recording)
    _set_time(stream, frame, timeline)
    _log(stream, entity, rr.Image(np.ascontiguousarray(rgb[::-1, ::-1])))


# --------------------------------------------------------------------------- Gaussians


def _single_set(gaussians: GaussianSet) -> GaussianSet:
    batch = tuple(gaussians.batch_shape)
    if any(size != 1 for size in batch):
        raise ValueError(
            f"gaussians: expected one set (batch shape () or all ones), got batch shape {batch}; "
            "log each set of the batch on its own"
        )
    return gaussians.reshape_batch() if batch else gaussians


def _class_colors(gaussians: GaussianSet) -> tuple[np.ndarray, np.ndarray | None]:
    """RGB ``(N, 3)`` and class ids ``(N,)`` (or ``None``) from the features' argmax."""
    features = gaussians.features
    n = gaussians.num_gaussians
    if features is None or features.shape[-1] not in (NUM_CLASSES - 1, NUM_CLASSES):
        return np.broadcast_to(np.asarray(GAUSSIAN_GREY, np.uint8), (n, 3)), None
    classes = features.detach().float().argmax(dim=-1).to(torch.uint8).cpu().numpy()
    return np.asarray(PALETTE, dtype=np.uint8)[classes], classes


@typechecked
def log_gaussians(
    entity: str,
    gaussians: GaussianSet,
    *,
    sigma: float = 1.0,
    colors: UInt8[Tensor, "N 3"] | UInt8[np.ndarray, "N 3"] | None = None,
    min_opacity: float = 0.0,
    style: GaussianStyle = "ellipsoids",
    frame: int | None = None,
    timeline: str = FRAME_TIMELINE,
    recording: RecordingStream | None = None,
) -> int:
    """Log a set of Gaussians as one entity.

    Args:
        entity: the entity path, e.g. ``"world/gaussians"``.
        gaussians: one set, ``(N,)`` or a batch of one; values are checked
            (:meth:`GaussianSet.check_values`: NaN, scales <= 0, opacities outside [0, 1]).
        sigma: ellipsoid half-sizes are ``sigma * scales`` (1: the one-sigma ellipsoid).
        colors: ``(N, 3)`` RGB; default: the class colour of each Gaussian's feature argmax
            when the features are 17 or 18 class scores, else :data:`GAUSSIAN_GREY`.
        min_opacity: Gaussians with opacity <= this are left out (0: the padding of
            ragged batches, which contributes nothing).
        style: ``"ellipsoids"`` (``Ellipsoids3D``, solid, alpha = opacity) or ``"splats"``
            (``GaussianSplats3D``, scales as standard deviations; needs a rerun that has it).
        frame: as :func:`log_occupancy`.
        timeline: as :func:`log_occupancy`.
        recording: as :func:`log_occupancy`.

    Returns the number of Gaussians logged.
    """
    rr = require_rerun()
    gaussians = _single_set(gaussians).check_values()
    check_positive("sigma", sigma)
    if not 0.0 <= min_opacity < 1.0:
        raise ValueError(f"min_opacity: expected a number in [0, 1), got {min_opacity!r}")
    if colors is not None and colors.shape[0] != gaussians.num_gaussians:
        raise ValueError(
            f"colors: expected ({gaussians.num_gaussians}, 3) for {gaussians.num_gaussians} "
            f"Gaussians, got {tuple(colors.shape)}"
        )
    rgb, classes = _class_colors(gaussians)
    if colors is not None:
        rgb = colors.cpu().numpy() if isinstance(colors, Tensor) else np.asarray(colors)
    opacities = gaussians.opacities.detach().float().cpu().numpy()
    keep = opacities > min_opacity
    centers = gaussians.means.detach().float().cpu().numpy()[keep]
    scales = gaussians.scales.detach().float().cpu().numpy()[keep]
    xyzw = normalize_quaternions(gaussians.quats.detach().float())[..., [1, 2, 3, 0]]
    quats = xyzw.cpu().numpy()[keep]
    rgba = np.concatenate(
        [rgb[keep], np.round(opacities[keep] * 255).astype(np.uint8)[:, None]], axis=-1
    )
    if style == "splats":
        splats = _archetype("GaussianSplats3D", style, "ellipsoids")
        archetype = splats(centers, scales=scales, quaternions=quats, colors=rgba)
    else:
        archetype = rr.Ellipsoids3D(
            centers=centers,
            half_sizes=sigma * scales,
            quaternions=quats,
            colors=rgba,
            class_ids=None if classes is None else classes[keep],
            fill_mode="solid",
        )
    stream = _stream(recording)
    _set_time(stream, frame, timeline)
    _log(stream, entity, archetype)
    return int(keep.sum())


@typechecked
def mask_colors(mask: Float[Tensor, " N"]) -> UInt8[np.ndarray, "N 3"]:
    """``(N,)`` rigidity mask m in [0, 1] -> ``(N, 3)`` RGB: :data:`RIGID_RGB` at 0,
    :data:`NONRIGID_RGB` at 1, mixed linearly between (values outside [0, 1] are clamped)."""
    m = mask.detach().float().clamp(0, 1).cpu().numpy()[:, None]
    mixed = (1 - m) * np.asarray(RIGID_RGB) + m * np.asarray(NONRIGID_RGB)
    return np.round(mixed).astype(np.uint8)


@typechecked
def log_deformation(
    entity: str,
    output: DeformationOutput,
    frames: Sequence[int] | None = None,
    *,
    batch_index: int = 0,
    sigma: float = 1.0,
    timeline: str = FRAME_TIMELINE,
    recording: RecordingStream | None = None,
) -> None:
    """Log a :class:`~dego.DeformationOutput`: at each of its T times, the deformed
    Gaussians of batch item ``batch_index`` as ``<entity>/classes`` (class colours) and
    ``<entity>/rigidity`` (coloured by the rigidity mask m: :data:`RIGID_RGB` at 0,
    :data:`NONRIGID_RGB` at 1), on ``timeline`` at ``frames[t]`` (default ``t``)."""
    t_count = output.num_times
    batch = output.gaussians.batch_shape[0]
    check_int("batch_index", batch_index)
    if not 0 <= batch_index < batch:
        raise ValueError(f"batch_index: expected an int in [0, {batch - 1}], got {batch_index}")
    frames = list(range(t_count)) if frames is None else list(frames)
    if len(frames) != t_count:
        raise ValueError(f"frames: expected {t_count} frames (one per time), got {len(frames)}")
    stream = _stream(recording)
    for t, frame in enumerate(frames):

        def pick(name: str, x: Tensor, t: int = t) -> Tensor:
            return x[batch_index, t]

        gaussians = output.gaussians.map(pick)
        mask = output.rigid_mask[batch_index]
        mask = mask[t] if mask.ndim == 2 else mask
        _set_time(stream, frame, timeline)
        log_gaussians(f"{entity}/classes", gaussians, sigma=sigma, recording=recording)
        log_gaussians(
            f"{entity}/rigidity",
            gaussians,
            sigma=sigma,
            colors=mask_colors(mask),
            recording=recording,
        )


# --------------------------------------------------------------------------- cameras


def _to_numpy_image(name: str, image: Tensor) -> np.ndarray:
    """``(C, H, W)`` float in [0, 1] or uint8 -> ``(H, W, C)`` uint8."""
    if image.dtype == torch.uint8:
        return image.permute(1, 2, 0).cpu().numpy()
    if not bool(torch.isfinite(image).all()):
        raise ValueError(f"{name}: expected finite values")
    return (
        (image.detach().float().clamp(0, 1) * 255)
        .round()
        .to(torch.uint8)
        .permute(1, 2, 0)
        .cpu()
        .numpy()
    )


@typechecked
def log_cameras(
    entity: str,
    world_to_cam: Float[Tensor, "V 4 4"],
    intrinsics: Float[Tensor, "V 3 3"],
    image_size: tuple[int, int],
    *,
    names: Sequence[str] | None = None,
    images: Float[Tensor, "V 3 H W"] | UInt8[Tensor, "V 3 H W"] | None = None,
    depth: Float[Tensor, "V H W"] | None = None,
    semantics: Integer[Tensor, "V H W"] | Float[Tensor, "V C H W"] | None = None,
    frame: int | None = None,
    timeline: str = FRAME_TIMELINE,
    recording: RecordingStream | None = None,
) -> list[str]:
    """Log V pinhole cameras, each as ``<entity>/<name>`` (its pose as a ``Transform3D``
    camera -> world, its ``Pinhole`` with OpenCV axes), with optional images below it:
    ``image`` (RGB), ``depth`` (metres; 0 = nothing hit) and ``semantics`` (labels, or class
    scores ``(V, C, H, W)`` shown as their argmax, e.g. rendered features).

    Args:
        world_to_cam: ``(V, 4, 4)`` extrinsics (dego's convention, gsplat's ``viewmats``).
        intrinsics: ``(V, 3, 3)`` pinhole matrices K.
        image_size: ``(height, width)`` in pixels, as :func:`dego.splat` takes it.
        names: V entity names (default ``cam0 .. cam{V-1}``).

    Returns the cameras' entity paths.
    """
    rr = require_rerun()
    views = world_to_cam.shape[0]
    if intrinsics.shape[0] != views:
        raise ValueError(
            f"intrinsics: expected {views} matrices (one per camera), got {intrinsics.shape[0]}"
        )
    height, width = (check_int("image_size", v, 1) for v in image_size)
    names = [f"cam{v}" for v in range(views)] if names is None else list(names)
    if len(names) != views or len(set(names)) != views:
        raise ValueError(f"names: expected {views} distinct names, got {names}")
    for name, value in (("world_to_cam", world_to_cam), ("intrinsics", intrinsics)):
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"{name}: expected finite values")
    for name, image in (("images", images), ("depth", depth), ("semantics", semantics)):
        if image is not None and (
            image.shape[0] != views or tuple(image.shape[-2:]) != (height, width)
        ):
            raise ValueError(
                f"{name}: expected {views} images of image_size {(height, width)}, "
                f"got shape {tuple(image.shape)}"
            )
    cam_to_world = torch.linalg.inv(world_to_cam.detach().double().cpu()).numpy()
    k = intrinsics.detach().double().cpu().numpy()
    labels: np.ndarray | None = None
    if semantics is not None:
        ids = semantics.detach().argmax(dim=1) if semantics.is_floating_point() else semantics
        labels = _label_tensor("semantics", ids).to(torch.uint8).cpu().numpy()
    if depth is not None and not bool(torch.isfinite(depth).all()):
        raise ValueError("depth: expected finite values")
    stream = _stream(recording)
    _set_time(stream, frame, timeline)
    paths = []
    for v, name in enumerate(names):  # one entity per camera: V is a handful
        path = f"{entity}/{name}"
        _log(
            stream,
            path,
            rr.Transform3D(translation=cam_to_world[v, :3, 3], mat3x3=cam_to_world[v, :3, :3]),
            rr.Pinhole(
                image_from_camera=k[v],
                resolution=[width, height],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=1.0,
            ),
        )
        if images is not None:
            _log(stream, f"{path}/image", rr.Image(_to_numpy_image("images", images[v])))
        if depth is not None:
            _log(
                stream,
                f"{path}/depth",
                rr.DepthImage(depth[v].detach().float().cpu().numpy(), meter=1.0),
            )
        if labels is not None:
            _log(stream, f"{path}/semantics", rr.SegmentationImage(labels[v], opacity=0.5))
        paths.append(path)
    return paths


@typechecked
def log_pose(
    entity: str,
    pose: Float[Tensor, "4 4"],
    *,
    frame: int | None = None,
    timeline: str = FRAME_TIMELINE,
    recording: RecordingStream | None = None,
) -> None:
    """Log a rigid ``(4, 4)`` child -> parent pose (e.g. ego -> world) as a ``Transform3D``:
    everything logged below ``entity`` is drawn in the parent's coordinates."""
    rr = require_rerun()
    if not bool(torch.isfinite(pose).all()):
        raise ValueError("pose: expected finite values")
    matrix = pose.detach().double().cpu().numpy()
    stream = _stream(recording)
    _set_time(stream, frame, timeline)
    _log(stream, entity, rr.Transform3D(translation=matrix[:3, 3], mat3x3=matrix[:3, :3]))


# --------------------------------------------------------------------------- layout


@typechecked
def blueprint(
    world: str = "world",
    *,
    tabs: Mapping[str, Sequence[str]] | None = None,
    bev: Sequence[str] = (),
    cameras: Sequence[str] = (),
) -> Blueprint:
    """A viewer layout: 3-D views of ``world`` on the left, and on the right the BEV images
    ``bev`` (entity paths) above the ``cameras`` (camera entity paths).

    ``tabs``: one 3-D view per entry, ``name: contents`` in rerun's query syntax (lines
    such as ``"+ /world/occupancy/prediction"``, ``"- /world/cameras/**"``); default: one
    view of everything under ``world``.
    """
    require_rerun()
    import rerun.blueprint as rrb

    def grid(paths: Sequence[str]) -> Any:
        return rrb.Grid(*[rrb.Spatial2DView(origin=p, name=p.rsplit("/", 1)[-1]) for p in paths])

    main: Any
    if tabs:
        main = rrb.Tabs(
            *[
                rrb.Spatial3DView(origin=world, name=name, contents=list(query))
                for name, query in tabs.items()
            ]
        )
    else:
        main = rrb.Spatial3DView(origin=world, name="3-D")
    panels = [grid(paths) for paths in (bev, cameras) if paths]
    body = rrb.Horizontal(main, rrb.Vertical(*panels), column_shares=[3, 2]) if panels else main
    # the time panel stays open (the frame timeline); the side panels start folded
    return rrb.Blueprint(
        body,
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="expanded"),
    )


def send_blueprint(layout: Blueprint, *, recording: RecordingStream | None = None) -> None:
    """Make ``layout`` the recording's default and active layout."""
    stream = _stream(recording)
    if stream is None:
        require_rerun().send_blueprint(layout)
    else:
        stream.send_blueprint(layout)


__all__ = [
    "FLUSH_TIMEOUT_S",
    "FRAME_TIMELINE",
    "GAUSSIAN_GREY",
    "MIN_RERUN",
    "NONRIGID_RGB",
    "RIGID_RGB",
    "SAMPLE_TIMELINE",
    "UNSCORED_BEV_STRIPES",
    "blueprint",
    "has_gaussian_splats",
    "has_voxel_grid_map",
    "log_bev",
    "log_cameras",
    "log_classes",
    "log_deformation",
    "log_gaussians",
    "log_occupancy",
    "log_pose",
    "mask_colors",
    "recording_file",
    "require_rerun",
    "send_blueprint",
]
